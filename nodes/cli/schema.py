"""`derl schema [TYPE]`: a message type's JSON schema, the list of types, or a reference document
generated from the code (`nodes.tools.reference`)."""

from __future__ import annotations

import argparse
import json

from derl.messages import MESSAGE_TYPES, SCHEMA_VERSION
from derl.nodes.cli.options import fail
from derl.nodes.tools.reference import DOCUMENTS, summary

USAGE = 2  # exit status for an unknown type, as argparse's for bad arguments


def register(commands: argparse._SubParsersAction) -> None:
    schema = commands.add_parser(
        "schema",
        help="a message type's JSON schema, or the list of types",
        description="Print the JSON schema of message type TYPE; without TYPE, list the types "
        "and the schema version. With --markdown, print a reference document generated from "
        "the code (docs/protocol.md, docs/configuration.md).",
    )
    schema.add_argument("type", nargs="?", metavar="TYPE", help="a message type, e.g. Birth")
    schema.add_argument(
        "--markdown", choices=list(DOCUMENTS), help="print docs/NAME.md as the code writes it"
    )
    schema.set_defaults(handler=_schema)


def _schema(args: argparse.Namespace) -> int:
    if args.markdown:
        if args.type:
            fail("give a TYPE or --markdown, not both", USAGE)
        print(DOCUMENTS[args.markdown](), end="")
    elif args.type is None:
        print(f"schema version {SCHEMA_VERSION}")
        width = max(map(len, MESSAGE_TYPES))
        for name, model in MESSAGE_TYPES.items():
            print(f"{name:<{width}}  {summary(model)}")
    elif args.type in MESSAGE_TYPES:
        print(json.dumps(MESSAGE_TYPES[args.type].model_json_schema(), indent=2))
    else:
        fail(f"unknown message type {args.type!r}; valid: {', '.join(MESSAGE_TYPES)}", USAGE)
    return 0
