"""The JSON schemas derl gives viewers (`derl foxglove`'s channels, `derl export`'s copy) against
the viewers' own parser: a port of its rules for every schema, and the parser itself under Node
(fetched from npm, tests/viewer_parser.py), which must agree with the port on every schema served
and on probes of the constructs it refuses."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from pydantic import BaseModel
from viewer_parser import RealParser, Unreadable, parse_json_schema

from derl.messages import MESSAGE_TYPES
from derl.messages.examples import examples
from derl.nodes.journal.segments import JournalWriter
from derl.nodes.tools.foxglove import TOPICS, RunSummary
from derl.nodes.tools.logs import base64_text, export_json, json_form, json_schema
from derl.nodes.tools.viewer_schema import ViewerSchemaError, viewer_schema


def _served() -> dict[str, dict[str, Any]]:
    """Every schema derl gives a viewer: each message type's, and the bridge's summary."""
    return {
        **{kind: json_schema(kind) for kind in MESSAGE_TYPES},
        "RunSummary": viewer_schema(RunSummary),
    }


def _exported(tmp_path: Path) -> dict[str, dict[str, Any]]:
    """The schemas of a `derl export` copy of a log holding every message type."""
    log, out = tmp_path / "run.mcap", tmp_path / "run.json.mcap"
    with JournalWriter(log) as writer:
        for message in examples("r1", 0):
            writer.write(message)
    export_json(log, out)
    with out.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    return {schema.name: json.loads(schema.data) for schema in summary.schemas.values()}


class Optional(BaseModel):
    a: int | None = None
    pair: tuple[float, float] = (0.0, 0.0)
    blob: bytes = b""


class Union(BaseModel):
    a: int | str


class Mixed(BaseModel):
    a: tuple[int, str]


class Tree(BaseModel):
    children: list[Tree] = []


def test_every_schema_derl_serves_passes_the_viewers_rules(tmp_path: Path) -> None:
    exported = _exported(tmp_path)
    assert exported.keys() == MESSAGE_TYPES.keys()
    for name, schema in [*_served().items(), *exported.items()]:
        datatypes = parse_json_schema(schema, name)
        assert [f["name"] for f in datatypes[name]] == list(schema["properties"]), name


def test_pydantics_own_schemas_fail_the_viewers_rules() -> None:
    """What `derl foxglove` served before on its five channels (`$ref`, `anyOf [X, null]` and
    `prefixItems`): each one fails."""
    for model in (*(MESSAGE_TYPES[kind] for kind in TOPICS), RunSummary):
        with pytest.raises(Unreadable):
            parse_json_schema(model.model_json_schema(), model.__name__)


def test_optional_fields_are_their_type_tuples_arrays_bytes_base64() -> None:
    schema = viewer_schema(Optional)
    assert schema["properties"]["a"]["type"] == "integer"
    assert schema["properties"]["pair"]["items"] == {"type": "number"}
    assert schema["properties"]["blob"]["contentEncoding"] == "base64"
    assert "$defs" not in json.dumps(viewer_schema(RunSummary))
    assert parse_json_schema(schema, "Optional")["Optional"][1] == {
        "name": "pair",
        "type": "float64",
        "isArray": True,
    }


@pytest.mark.parametrize(
    ("model", "why"),
    [(Union, "a union of types"), (Mixed, "a tuple of mixed types"), (Tree, "recursive")],
)
def test_a_model_the_viewers_cannot_read_is_refused(model: type[BaseModel], why: str) -> None:
    with pytest.raises(ViewerSchemaError, match=why):
        viewer_schema(model)


PROBES: dict[str, dict[str, Any]] = {
    "nullable": {"anyOf": [{"type": "number"}, {"type": "null"}]},
    "reference": {"$ref": "#/$defs/X"},
    "tuple": {"type": "array", "prefixItems": [{"type": "integer"}, {"type": "integer"}]},
    "type list": {"type": ["number", "null"]},
    "map": {"type": "object", "additionalProperties": {"type": "number"}},
    "empty object": {"type": "object", "properties": {}},
    "matrix": {"type": "array", "items": {"type": "array", "items": {"type": "number"}}},
    "base64 items": {"type": "array", "items": {"type": "string", "contentEncoding": "base64"}},
    "hex string": {"type": "string", "contentEncoding": "base16"},
    "enum of numbers": {"oneOf": [{"title": "A", "const": 1}, {"title": "B", "const": 2}]},
    "enum of text": {"oneOf": [{"const": "a"}]},
    "null": {"type": "null"},
    "nested array": {
        "type": "array",
        "items": {"type": "object", "properties": {"x": {"type": "boolean"}}},
    },
}
"""Field schemas, each of which the viewers' parser reads or refuses."""


@pytest.fixture(scope="session")
def real_parser(request: pytest.FixtureRequest) -> RealParser:
    if shutil.which("node") is None or shutil.which("npm") is None:
        pytest.skip("the viewers' own parser needs Node and npm (the port's test still runs)")
    return RealParser(request.config.cache.mkdir("viewer-parser"))


def _defined(datatypes: dict[str, list[dict[str, Any]]]) -> dict[str, list[dict[str, Any]]]:
    """Fields without keys set to None (JSON.stringify leaves out what is undefined)."""
    return {
        name: [{k: v for k, v in field.items() if v is not None} for field in fields]
        for name, fields in datatypes.items()
    }


def test_the_viewers_own_parser_reads_every_schema_like_the_port(
    real_parser: RealParser, tmp_path: Path
) -> None:
    sent = {m.type: m for m in examples("r1", 0)}
    messages = {kind: [json_form(m, base64_text)] for kind, m in sent.items()}
    cases = [(name, schema, messages.get(name, [])) for name, schema in _served().items()]
    cases += [(name, schema, []) for name, schema in _exported(tmp_path).items()]
    results = real_parser.parse(cases)
    for (name, schema, given), result in zip(cases, results, strict=True):
        assert result["ok"], (name, result.get("error"))
        assert result["datatypes"] == _defined(parse_json_schema(schema, name)), name
        assert len(result["messages"]) == len(given)
    report = results[list(_served()).index("FitnessReport")]["messages"][0]
    assert report["checkpoint"] == {"bytes": len(sent["FitnessReport"].checkpoint)}  # decoded


def test_the_port_refuses_what_the_viewers_own_parser_refuses(real_parser: RealParser) -> None:
    cases = [
        (probe, {"type": "object", "properties": {"field": field}}, [])
        for probe, field in PROBES.items()
    ]
    cases += [(kind, MESSAGE_TYPES[kind].model_json_schema(), []) for kind in TOPICS]
    refused = set()
    for (name, schema, _), result in zip(cases, real_parser.parse(cases), strict=True):
        try:
            port: dict[str, list[dict[str, Any]]] | None = _defined(parse_json_schema(schema, name))
        except Unreadable:
            port = None
            refused.add(name)
        assert (result["datatypes"] if result["ok"] else None) == port, (name, result)
    assert refused == {
        "nullable",
        "reference",
        "tuple",
        "type list",
        "map",
        "matrix",
        "base64 items",
        "hex string",
        "enum of text",
        "null",
        *TOPICS,
    }
