"""The viewers' JSON-schema parser, twice: a Python port of its rules, and the parser itself.

Lichtblick and open-source Foxglove Studio read a ``jsonschema`` channel with ``parseJsonSchema``
(``packages/mcap-support/src/parseJsonSchema.ts``; the same code in Lichtblick's repository and in
Foxglove Studio's last open-source release). `parse_json_schema` is a line-by-line port of its
rules: the message definitions it makes, and an `Unreadable` error wherever it throws (the viewer
then marks the channel unsupported). `RealParser` runs the original under Node: it takes the
function out of the npm package ``@foxglove/studio-base@1.48.0`` (its webpack chunk keeps the
module's source; the tarball's sha512 is pinned) with ``@protobufjs/base64``, which it imports,
into pytest's cache, and runs ``viewer_parser.js``.
"""

from __future__ import annotations

import base64
import hashlib
import io
import json
import os
import shutil
import subprocess
import tarfile
import tempfile
from pathlib import Path
from typing import Any

PACKAGES = {
    "@foxglove/studio-base@1.48.0": "EY8cYoHUm6VyTSVZBdfn5EJK2bRwTfAjH92H5wgAEcnKyeCUyKkxjgwbqO2jK"
    "wRJGa+7VPaEHHF167BzFh+N4A==",
    "@protobufjs/base64@1.1.2": "AZkcAA5vnN/v4PDqKyMR5lx7hZttPDgClv83E//FMNhR2TMcLUhfRUBHCmSl0oi9z"
    "MgDDqRUJkSxO3wm85+XLg==",
}
"""npm package -> the sha512 of its tarball (the registry's `dist.integrity`)."""
MODULE_START = ";// CONCATENATED MODULE: ../mcap-support/src/parseJsonSchema.ts"
MODULE_END = "// EXTERNAL MODULE:"
DRIVER = Path(__file__).with_name("viewer_parser.js")

Field = dict[str, Any]


class Unreadable(ValueError):
    """Where the viewers' parser throws: the channel would be unsupported."""


def parse_json_schema(root: dict[str, Any], root_type: str) -> dict[str, list[Field]]:
    """The message definitions the viewers make of `root` (type name -> fields), as
    ``parseJsonSchema`` does; `Unreadable` where it throws."""
    datatypes: dict[str, list[Field]] = {}

    def add_fields(schema: Any, type_name: str, key_path: list[str]) -> None:
        if not isinstance(schema, dict) or schema.get("type") != "object":
            kind = schema.get("type") if isinstance(schema, dict) else None
            raise Unreadable(f'Expected "type": "object" for schema {type_name}, got {kind!r}')
        properties = schema.get("properties")
        if not isinstance(properties, dict):  # Object.entries(undefined) throws a TypeError
            raise Unreadable(f"{type_name}: no properties")
        fields: list[Field] = []
        for name, field in properties.items():
            where = ".".join([*key_path, name])
            if not isinstance(field, dict):
                raise Unreadable(f"Unsupported type for {where}")
            one_of = field.get("oneOf")
            if isinstance(one_of, list):
                if not all(_is_number(alternative.get("const")) for alternative in one_of):
                    raise Unreadable(f"Unsupported type for {where}: oneOf alternatives")
                fields += [
                    {
                        "name": a.get("title"),
                        "type": "uint32",
                        "isConstant": True,
                        "value": a["const"],
                    }
                    for a in one_of
                ]
                fields.append({"name": name, "type": "uint32"})
                continue
            kind = field.get("type")
            if kind == "boolean":
                fields.append({"name": name, "type": "bool"})
            elif kind == "string":
                encoding = field.get("contentEncoding")
                if encoding is None:
                    fields.append({"name": name, "type": "string"})
                elif encoding == "base64":
                    fields.append({"name": name, "type": "uint8", "isArray": True})
                else:
                    raise Unreadable(f"Unsupported contentEncoding {encoding!r} in {where}")
            elif kind in ("number", "integer"):
                fields.append({"name": name, "type": "float64"})
            elif kind == "object":
                nested = f"{type_name}.{name}"
                add_fields(field, nested, [*key_path, name])
                fields.append({"name": name, "type": nested, "isComplex": True})
            elif kind == "array":
                items = field.get("items")
                if not isinstance(items, dict):  # itemSchema.type of undefined throws
                    raise Unreadable(f"{where}: an array without one items schema")
                item = items.get("type")
                if item == "boolean":
                    fields.append({"name": name, "type": "bool", "isArray": True})
                elif item == "string":
                    if items.get("contentEncoding") is not None:
                        raise Unreadable(f"Unsupported contentEncoding for array item {where}")
                    fields.append({"name": name, "type": "string", "isArray": True})
                elif item in ("number", "integer"):
                    fields.append({"name": name, "type": "float64", "isArray": True})
                elif item == "object":
                    nested = f"{type_name}.{name}"
                    add_fields(items, nested, [*key_path, name])
                    fields.append(
                        {"name": name, "type": nested, "isComplex": True, "isArray": True}
                    )
                else:
                    raise Unreadable(f"Unsupported type {item!r} for array item {where}")
            else:
                raise Unreadable(f"Unsupported type {kind!r} for {where}")
        datatypes[type_name] = fields

    add_fields(root, root_type, [])
    return datatypes


def _is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


class RealParser:
    """``parseJsonSchema`` itself under Node, fetched once into `cache` (see the module)."""

    def __init__(self, cache: Path) -> None:
        self.parser = cache / "parseJsonSchema.js"
        self.base64 = cache / "node_modules" / "@protobufjs" / "base64" / "index.js"
        if not self.parser.exists():
            _provision(cache)

    def parse(self, cases: list[tuple[str, dict[str, Any], list[Any]]]) -> list[dict[str, Any]]:
        """For each (type name, schema, messages): {ok, datatypes, messages} or {ok, error}."""
        with tempfile.NamedTemporaryFile("w", suffix=".json") as f:
            json.dump(
                {
                    "parser": str(self.parser),
                    "base64": str(self.base64),
                    "cases": [
                        {"name": name, "schema": schema, "messages": messages}
                        for name, schema, messages in cases
                    ],
                },
                f,
            )
            f.flush()
            done = subprocess.run(
                ["node", str(DRIVER), f.name], capture_output=True, text=True, timeout=60
            )
        assert done.returncode == 0, done.stderr
        return json.loads(done.stdout)


def _provision(cache: Path) -> None:
    """Fetch the pinned packages with `npm pack`, check their sha512, and write the parser's
    source and @protobufjs/base64 under `cache` (atomically: tests may run in parallel)."""
    with tempfile.TemporaryDirectory(dir=cache.parent) as scratch:
        done = subprocess.run(
            ["npm", "pack", *PACKAGES, "--json", "--pack-destination", scratch],
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert done.returncode == 0, f"npm pack failed: {done.stderr[-2000:]}"
        staged = Path(scratch) / "cache"
        staged.mkdir()
        for package, packed in zip(PACKAGES, json.loads(done.stdout), strict=True):
            data = (Path(scratch) / packed["filename"]).read_bytes()
            digest = base64.b64encode(hashlib.sha512(data).digest()).decode()
            assert digest == PACKAGES[package], f"{package}: sha512 {digest} is not the pinned one"
            with tarfile.open(fileobj=io.BytesIO(data)) as tar:
                if package.startswith("@protobufjs/base64"):
                    target = staged / "node_modules" / "@protobufjs" / "base64" / "index.js"
                    target.parent.mkdir(parents=True)
                    target.write_bytes(tar.extractfile("package/index.js").read())  # type: ignore[union-attr]
                else:
                    (staged / "parseJsonSchema.js").write_text(_parser_source(tar))
        try:
            os.rename(staged, cache)
        except OSError:  # another test process put it there first
            if not (cache / "parseJsonSchema.js").exists():
                raise
            shutil.rmtree(staged, ignore_errors=True)


def _parser_source(tar: tarfile.TarFile) -> str:
    """The parseJsonSchema module's source, out of the package's webpack chunks."""
    for member in tar.getmembers():
        if member.name.startswith("package/assets/") and member.name.endswith(".js"):
            text = tar.extractfile(member).read().decode()  # type: ignore[union-attr]
            start = text.find(MODULE_START)
            if start >= 0:
                end = text.index(MODULE_END, start)
                return text[start + len(MODULE_START) : end]
    raise AssertionError("no parseJsonSchema module in the package")
