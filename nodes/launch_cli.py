"""`derl launch FILE`: start the nodes of a launch file (see `nodes.launch`)."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(commands: argparse._SubParsersAction) -> None:
    launch = commands.add_parser(
        "launch",
        help="start the nodes of a launch file (this host's, and others' over ssh)",
        description="Start the nodes a launch file places on this host, and those of its ssh "
        "hosts over ssh; restart them by their policy; stop them all on Ctrl-C or SIGTERM.",
    )
    launch.add_argument("file", type=Path, help="launch file (YAML), e.g. launch/local.yaml")
    launch.add_argument(
        "--host",
        action="append",
        default=[],
        metavar="NAME",
        help="start this host's nodes here, never over ssh (repeatable; default: the host "
        "named `local` or after this machine, else every host without ssh, and the ssh "
        "hosts' nodes over ssh)",
    )
    launch.add_argument("--no-ssh", action="store_true", help="do not start ssh hosts' nodes")
    launch.add_argument("--dry-run", action="store_true", help="print every command, start none")
    launch.add_argument("--log-dir", type=Path, help="node logs (default: RUN_DIR/logs)")
    launch.set_defaults(handler=_launch)


def _launch(args: argparse.Namespace) -> int:
    from nodes.launch import main

    return main(args)
