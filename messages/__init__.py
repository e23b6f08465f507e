"""The wire: pydantic message models, the msgpack codec, key expressions, the schema version."""
