"""The `derl` command line: one entry point whose subcommands live in small modules."""

from __future__ import annotations

import argparse
import logging
import os
import sys

# MuJoCo picks its OpenGL backend when first imported: offscreen EGL unless the user chose one.
os.environ.setdefault("MUJOCO_GL", "egl")

from nodes import (
    bus_cli,
    evaluate_cli,
    launch_cli,
    report_cli,
    run,
    train_cli,
    unimal_cli,
    watch_cli,
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="derl",
        description="Deep Evolutionary Reinforcement Learning: evolve and train UNIMAL bodies.",
    )
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    unimal_cli.register(commands)
    train_cli.register(commands)
    run.register(commands)
    bus_cli.register(commands)
    launch_cli.register(commands)
    report_cli.register(commands)
    evaluate_cli.register(commands)
    watch_cli.register(commands)
    return parser


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(
        level=logging.INFO,
        format="%(asctime)s %(name)s %(levelname)s %(message)s",
        stream=sys.stderr,
    )
    args = build_parser().parse_args(argv)
    return args.handler(args)


if __name__ == "__main__":
    sys.exit(main())
