"""JSON schemas that the viewers read: a pydantic model's schema in the form Foxglove and
Lichtblick parse.

Both open-source viewers (Lichtblick, and Foxglove Studio up to its last open-source release)
turn a ``jsonschema`` channel into message definitions with ``parseJsonSchema``
(``packages/mcap-support``): every field needs one ``type`` (object, array, string, number,
integer, boolean), objects their ``properties``, arrays an ``items`` schema of one type, and
bytes are strings with ``contentEncoding: base64``. Any other field fails the whole channel,
which the viewer then marks unsupported. Pydantic writes references into ``$defs``, optional
fields as ``anyOf [X, null]`` and tuples as ``prefixItems``; `viewer_schema` rewrites those:
references inlined, an optional field as its type (its value may still be null), a tuple of one
item type as an array of it. A construct with no such form (a union of two types, a tuple of
mixed types, a recursive model) is refused with `ViewerSchemaError`, so a new message type that
the viewers could not read fails its test rather than a user's viewer.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel

Schema = dict[str, Any]


class ViewerSchemaError(ValueError):
    """A model whose JSON schema the viewers cannot read; the text names the field."""


def viewer_schema(model: type[BaseModel]) -> Schema:
    """The JSON schema of `model` in the form the viewers parse (module docstring)."""
    schema = model.model_json_schema()
    definitions = schema.pop("$defs", {})
    return _rewrite(schema, definitions, model.__name__, ())


def _rewrite(node: Schema, definitions: Schema, where: str, inlined: tuple[str, ...]) -> Schema:
    """`node` with its references inlined and its unions and tuples in the viewers' form."""
    if "$ref" in node:
        name = node["$ref"].removeprefix("#/$defs/")
        if name in inlined or name not in definitions:
            raise ViewerSchemaError(f"{where}: a recursive or unknown reference {node['$ref']}")
        outer = {key: value for key, value in node.items() if key != "$ref"}
        return _rewrite({**definitions[name], **outer}, definitions, where, (*inlined, name))
    if "anyOf" in node:
        kinds = [option for option in node["anyOf"] if option != {"type": "null"}]
        if len(kinds) != 1:
            raise ViewerSchemaError(f"{where}: a union of types ({node['anyOf']})")
        outer = {key: value for key, value in node.items() if key != "anyOf"}
        return _rewrite({**kinds[0], **outer}, definitions, where, inlined)
    for key in ("oneOf", "allOf"):
        if key in node:
            raise ViewerSchemaError(f"{where}: {key} has no form the viewers read")
    node = dict(node)
    if not isinstance(node.get("type"), str):
        raise ViewerSchemaError(f"{where}: no single type ({node.get('type')!r})")
    if node.get("format") == "binary":  # bytes: base64 text, Foxglove's convention
        node = {k: v for k, v in node.items() if k not in ("format", "maxLength")}
        node["contentEncoding"] = "base64"
    if "prefixItems" in node:
        forms = {repr(item) for item in node["prefixItems"]}
        if len(forms) != 1:
            raise ViewerSchemaError(f"{where}: a tuple of mixed types")
        node["items"] = node.pop("prefixItems")[0]
    if "items" in node:
        node["items"] = _rewrite(node["items"], definitions, f"{where}[]", inlined)
    if node["type"] == "object":
        properties = node.get("properties", {})
        node["properties"] = {
            name: _rewrite(field, definitions, f"{where}.{name}", inlined)
            for name, field in properties.items()
        }
        if isinstance(node.get("additionalProperties"), dict):  # a map: the viewers see no fields
            node["additionalProperties"] = _rewrite(
                node["additionalProperties"], definitions, f"{where}{{}}", inlined
            )
    return node
