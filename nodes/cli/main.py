"""`derl`: one entry point whose subcommands are registered by the modules of `nodes.cli`, and the
one place where what went wrong (`DerlError`) becomes a line on stderr and an exit status."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
from collections.abc import Iterable
from typing import Any, TypeVar, overload

import derl
from derl.nodes.errors import DerlError
from derl.nodes.runtime import ratelimit

N = TypeVar("N")  # a namespace class `Parser.parse_known_args` fills


class Parser(argparse.ArgumentParser):
    """argparse for every subcommand (each parser made by `add_subparsers` is of its parent's
    class) without prefix matching of long options: with it, `derl train --env ft` read as
    `--envs ft` and failed on "'ft' is not an integer". An argument no option takes is refused by
    the subcommand that got it, with that subcommand's usage (argparse's own top level showed
    `usage: derl [-h] COMMAND ...` for `derl unimal sample 3`)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)

    @overload
    def parse_known_args(
        self, args: Iterable[str] | None = None, namespace: None = None
    ) -> tuple[argparse.Namespace, list[str]]: ...

    @overload
    def parse_known_args(self, args: Iterable[str] | None, namespace: N) -> tuple[N, list[str]]: ...

    @overload
    def parse_known_args(self, *, namespace: N) -> tuple[N, list[str]]: ...

    def parse_known_args(
        self, args: Iterable[str] | None = None, namespace: Any = None
    ) -> tuple[Any, list[str]]:
        namespace, extras = super().parse_known_args(args, namespace)
        if extras:
            self.error(f"unrecognized arguments: {' '.join(extras)}")
        return namespace, extras


def build_parser() -> argparse.ArgumentParser:
    from derl.nodes.cli import (  # here: a Ctrl-C while they load is `main`'s
        certs,
        launch,
        nodes,
        report,
        run,
        schema,
        slurm,
        study,
        train,
        unimal,
        watch,
    )

    parser = Parser(
        prog="derl",
        description="Deep Evolutionary Reinforcement Learning: evolve and train UNIMAL bodies.",
    )
    parser.add_argument("--version", action="version", version=f"derl {derl.__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    unimal.register(commands)
    train.register(commands)
    run.register(commands)
    nodes.register(commands)
    launch.register(commands)
    slurm.register(commands)
    certs.register(commands)
    report.register(commands)
    study.register(commands)
    watch.register(commands)
    schema.register(commands)
    return parser


def _interrupted(number: int, _frame: object) -> None:
    """A Ctrl-C before the command began (its modules load for seconds): one line, no
    traceback, exit status 130."""
    print(f"derl: {signal.Signals(number).name} before the command began: nothing done",
          file=sys.stderr)  # fmt: skip
    raise SystemExit(130)


def log_to_stderr() -> None:
    """A node's log lines on stderr, rate-limited (nothing if a handler is there already: a
    test's); not torch's INFO lines at exit."""
    logging.basicConfig(
        level=logging.INFO,
        format="%(asctime)s %(name)s %(levelname)s %(message)s",
        handlers=[ratelimit.install(logging.StreamHandler(sys.stderr))],
    )
    logging.getLogger("torch").setLevel(logging.WARNING)


def main(argv: list[str] | None = None) -> int:
    before = signal.signal(signal.SIGINT, _interrupted)
    try:
        parser = build_parser()
    finally:
        signal.signal(signal.SIGINT, before)
    log_to_stderr()
    args = parser.parse_args(argv)
    try:
        return args.handler(args)
    except DerlError as error:
        print(f"derl: {' '.join(str(error).split())}", file=sys.stderr)
        raise SystemExit(error.code) from None
