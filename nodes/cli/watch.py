"""`derl monitor|foxglove|tensorboard|topic|record|replay|export|log`: the watch-and-replay tools.

Only argument parsing and printing; the work is done by `nodes.tools.monitor`,
`nodes.tools.foxglove`, `nodes.tools.tensorboard`, `nodes.tools.topic`, `nodes.tools.recorder` and
`nodes.tools.logs`. Every command that joins the bus takes the nodes' connection flags
(`--connect`, `--mode client`, `--zenoh-config`; multicast stays off); given none, it connects to
the local run's endpoint, where `derl run` listens (127.0.0.1 at $DERL_LOCAL_PORT, else 7447),
and a replay listens there when no run does. Each stops cleanly on SIGINT/SIGTERM, and reports
bad input (a damaged log, several runs and no --run, an existing output file, a missing extra)
in one line on stderr with exit status 1, and so does a watcher that heard nothing, naming how
it joined the bus.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import os
import signal
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from derl.messages import InvalidKey
from derl.messages.keys import ARITY
from derl.nodes.cli.options import (
    add_bus_arguments,
    at_least_one,
    fail,
    how_joined,
    output_directory,
    output_file,
    publish_options,
    watch_options,
)
from derl.nodes.errors import USAGE
from derl.nodes.runtime.bus import ZenohOptions

if TYPE_CHECKING:
    from foxglove.websocket import WebSocketServer

REPLAY_KINDS = sorted(kind for kind in ARITY if kind != "alive")


def register(commands: argparse._SubParsersAction) -> None:
    monitor = commands.add_parser("monitor", help="live terminal view of a run")
    monitor.add_argument(
        "--once",
        nargs="?",
        const=3.0,
        type=_seconds,
        metavar="S",
        help="listen S seconds (default 3), print one snapshot and exit (1 if nothing of the "
        "run was heard)",
    )
    add_bus_arguments(monitor, run_required=False)
    monitor.set_defaults(handler=_clearly(_monitor))

    live = commands.add_parser(
        "foxglove",
        help="serve a run live to Foxglove (WebSocket)",
        description="Serve the run's births, status and progress over the Foxglove WebSocket "
        "protocol (JSON with JSON schemas) until Ctrl-C; open docs/foxglove-layout.json in "
        "Foxglove for fitness over births, best fitness, steps/s per worker and the latest births.",
    )
    live.add_argument("--host", default="127.0.0.1", help="address to serve on (127.0.0.1)")
    live.add_argument("--port", type=int, default=8765, help="WebSocket port (8765)")
    add_bus_arguments(live, run_required=False)
    live.set_defaults(handler=_clearly(_foxglove))

    board = commands.add_parser(
        "tensorboard",
        help="write a run's curves live to TensorBoard event files",
        description="Write the run's scalars (per birth: fitness, cost of work, generation, "
        "steps to the learning criterion; the run's births, best fitness, failures, evaluations "
        "and steps/s) into LOGDIR/<run> until the run is done or Ctrl-C; view them with "
        "`tensorboard --logdir LOGDIR`. Needs the extra: pip install 'derl[tensorboard]'.",
    )
    board.add_argument("--logdir", type=Path, required=True, help="TensorBoard's log directory")
    add_bus_arguments(board, run_required=False)
    board.set_defaults(handler=_clearly(_tensorboard))

    topic = commands.add_parser("topic", help="list, echo or time live keys (like ros2 topic)")
    verbs = topic.add_subparsers(dest="topic_verb", required=True, metavar="VERB")
    key_help = "key expression: derl/... as is, else relative to the run (fitness = fitness/**)"
    listing = verbs.add_parser("list", help="keys heard, with message type, count and rate")
    listing.add_argument("key", nargs="?", help=f"{key_help}; default all keys")
    listing.add_argument("--duration", type=_seconds, default=3.0, help="seconds to listen (3)")
    listing.set_defaults(handler=_clearly(_topic_list))
    echo = verbs.add_parser("echo", help="print each message as one JSON line")
    echo.add_argument("key", help=key_help)
    echo.add_argument("--count", type=at_least_one, help="stop after N messages")
    echo.add_argument("--duration", type=_seconds, help="stop after S seconds")
    echo.add_argument("--raw", action="store_true", help="every sample, undecoded, valid or not")
    echo.set_defaults(handler=_clearly(_echo))
    rate = verbs.add_parser("hz", help="rate of samples and min/max/std of their intervals")
    rate.add_argument("key", help=key_help)
    rate.add_argument("--duration", type=_seconds, default=10.0, help="seconds to measure (10)")
    rate.add_argument("--window", type=at_least_one, default=1000, help="intervals kept (1000)")
    rate.set_defaults(handler=_clearly(_hz))
    for verb in (listing, echo, rate):
        add_bus_arguments(verb, run_required=False)

    record = commands.add_parser(
        "record",
        help="record live traffic into an MCAP file",
        description="Record every valid message on the keys (default derl/**, or the run's keys "
        "with --run) until Ctrl-C or --duration; malformed payloads are counted, not kept.",
    )
    record.add_argument("out", type=Path, metavar="OUT.mcap", help="new file")
    record.add_argument("keys", nargs="*", metavar="KEY", help=f"{key_help}; default derl/**")
    record.add_argument("--duration", type=_seconds, help="stop after S seconds (else on Ctrl-C)")
    add_bus_arguments(record, run_required=False)
    record.set_defaults(handler=_clearly(_record))

    replay = commands.add_parser(
        "replay",
        help="publish a log again with its original timing",
        description="Publish the messages of a log on their keys, the original gaps divided by "
        "--rate. --run R replays only run R of a log holding several. A run with live nodes on "
        "the bus is refused (its trainers would take old jobs and acks): use --as-run NEW.",
    )
    replay.add_argument("log", type=Path, metavar="LOG", help="an MCAP file or a run directory")
    replay.add_argument("--rate", type=_non_negative, default=1.0, help="speed; 0: at once")
    replay.add_argument("--loop", action="store_true", help="start again at the end")
    replay.add_argument(
        "--topics",
        type=_kinds,
        default=frozenset(),
        metavar="KINDS",
        help=f"only these key kinds, e.g. fitness,status (of {','.join(REPLAY_KINDS)})",
    )
    replay.add_argument("--start-offset", type=_non_negative, default=0.0, metavar="S")
    replay.add_argument("--as-run", metavar="NEW", help="publish under this run id instead")
    replay.add_argument("--force", action="store_true", help="even into a run that is live")
    replay.add_argument(
        "--skip-damaged",
        action="store_true",
        help="replay what can be read of a damaged log (else refused, exit status 1)",
    )
    add_bus_arguments(replay, run_required=False)
    replay.set_defaults(handler=_clearly(_replay))

    export = commands.add_parser(
        "export",
        help="a log for Foxglove (json+jsonschema) or TensorBoard (event files)",
        description="Write a copy of a log that Foxglove opens (--json: json + jsonschema "
        "channels), or its run's scalars as TensorBoard event files in LOGDIR/<run> "
        "(--tensorboard: the tags `derl tensorboard` writes live), or both.",
    )
    export.add_argument("log", type=Path, metavar="LOG", help="an MCAP file or a run directory")
    export.add_argument("--json", type=Path, metavar="OUT.mcap", dest="out")
    export.add_argument("--tensorboard", type=Path, metavar="LOGDIR")
    export.set_defaults(handler=_clearly(_export))

    logs = commands.add_parser("log", help="inspect or repair MCAP logs")
    log_verbs = logs.add_subparsers(dest="log_verb", required=True, metavar="VERB")
    info = log_verbs.add_parser("info", help="channels, counts, time span, integrity")
    info.add_argument("log", type=Path, metavar="LOG", help="an MCAP file or a run directory")
    info.add_argument("--json", action="store_true", help="print JSON")
    info.set_defaults(handler=_clearly(_log_info))
    repair = log_verbs.add_parser("repair", help="a clean, indexed copy of a damaged file")
    repair.add_argument("source", type=Path, metavar="IN.mcap")
    repair.add_argument("out", type=Path, metavar="OUT.mcap", help="new file")
    repair.set_defaults(handler=_clearly(_log_repair))
    upgrade = log_verbs.add_parser(
        "upgrade",
        help="bring a journal or recording of schema version 4 to this derl's: a run directory "
        "in place (its old segments kept in journal.v4/), a file into OUT.mcap",
    )
    upgrade.add_argument("source", type=Path, metavar="LOG", help="a run directory or an MCAP file")
    upgrade.add_argument("out", type=Path, metavar="OUT.mcap", nargs="?", help="new file (a file)")
    upgrade.set_defaults(handler=_clearly(_log_upgrade))


def _non_negative(text: str) -> float:
    value = _number(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text} is negative")
    return value


def _seconds(text: str) -> float:
    """An argparse type: a duration in seconds, > 0."""
    value = _number(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be more than 0 seconds, not {text}")
    return value


def _number(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if math.isnan(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a number")
    return value


def _kinds(text: str) -> frozenset[str]:
    kinds = frozenset(k.strip() for k in text.split(",") if k.strip())
    unknown = kinds - set(REPLAY_KINDS)
    if unknown:
        raise argparse.ArgumentTypeError(
            f"unknown {', '.join(sorted(unknown))}; kinds: {', '.join(REPLAY_KINDS)}"
        )
    return kinds


def _clearly(handler: Callable[[argparse.Namespace], int]) -> Callable[..., int]:
    """`handler`, with expected failures reported in one line instead of a traceback; when
    nothing was heard, the line says how the tool joined the bus."""

    @functools.wraps(handler)
    def run(args: argparse.Namespace) -> int:
        from derl.nodes.tools.logs import LogError, NoLog
        from derl.nodes.tools.recorder import ReplayRefused
        from derl.nodes.tools.tensorboard import NoTensorBoard
        from derl.nodes.tools.topic import NothingHeard, RunNotFound

        try:
            return handler(args)
        except NothingHeard as error:
            print(f"derl {args.command}: {error} ({how_joined(_joined(args))}); is the run on "
                  "another endpoint? --connect EP (or --mode client, --zenoh-config FILE)",
                  file=sys.stderr)  # fmt: skip
            return 1
        except (LogError, RunNotFound, ReplayRefused, InvalidKey, FileExistsError,
                NoTensorBoard) as error:  # fmt: skip
            print(f"derl {args.command}: {error}", file=sys.stderr)
            return USAGE if isinstance(error, NoLog) else 1
        except BrokenPipeError:  # the reader of our output went away (`| head`)
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            return 1

    return run


def _joined(args: argparse.Namespace) -> ZenohOptions:
    """How the command joins the bus: a replay publishes, every other tool watches."""
    return publish_options(args) if args.command == "replay" else watch_options(args)


def _stop_on_signals() -> threading.Event:
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop


def _monitor(args: argparse.Namespace) -> int:
    from derl.nodes.tools.monitor import monitor
    from derl.nodes.tools.topic import NothingHeard

    view = monitor(watch_options(args), args.run, args.once, _stop_on_signals())
    if args.once is not None and not view.heard:  # a script must tell "no run" from a quiet one
        raise NothingHeard(f"heard nothing of run {view.run} in {args.once:g} s")
    return 0


def _foxglove(args: argparse.Namespace) -> int:
    from derl.nodes.tools.foxglove import CannotServe, serve

    def started(run: str, server: WebSocketServer) -> None:
        print(f"serving run {run} on ws://{args.host}:{server.port} (Ctrl-C stops)", flush=True)

    try:
        serve(watch_options(args), args.run, args.host, args.port, _stop_on_signals(), started)
    except CannotServe as error:
        print(f"derl foxglove: {error}", file=sys.stderr)
        return 1
    return 0


def _topic_list(args: argparse.Namespace) -> int:
    from derl.nodes.tools.topic import NothingHeard, topic_list

    key = args.key or ("**" if args.run else "derl/**")
    if not topic_list(watch_options(args), key, args.run, args.duration, _stop_on_signals()):
        raise NothingHeard(f"nothing heard on {key} in {args.duration:g} s")
    return 0


RUN_QUIET_S = 10.0
"""A run whose status, once heard, has not come for this long (it comes every second) is over."""


def _echo(args: argparse.Namespace) -> int:
    from derl.nodes.tools.topic import NothingHeard, echo

    stop = _stop_on_signals()
    options = watch_options(args)
    with _RunEnd(options, args.run, stop) as end:
        shown = echo(options, args.key, args.run, args.count, args.duration, args.raw, stop)
    if end.why is not None:
        print(f"derl topic echo: {end.why}; {shown} messages shown", file=sys.stderr)
    elif not shown:
        within = f"in {args.duration:g} s" if args.duration else "before it was stopped"
        raise NothingHeard(f"nothing heard on {args.key} {within}")
    return 0


class _RunEnd:
    """Sets `stop` when the run (`run`, or any where None) says it is done, or its status,
    once heard, stops coming for `RUN_QUIET_S` (its coordinator stopped); `why` then says so."""

    def __init__(self, options: ZenohOptions, run: str | None, stop: threading.Event) -> None:
        self.options, self.run, self.stop = options, run, stop
        self.why: str | None = None
        self.heard: float | None = None

    def __enter__(self) -> _RunEnd:
        import time

        from derl.messages import RunStatus
        from derl.nodes.runtime.bus import open_session
        from derl.nodes.tools.topic import Checker

        self.opened = open_session(self.options)
        session = self.opened.__enter__()
        checker = Checker(session)

        def on_status(sample) -> None:  # zenoh.Sample
            status = checker.check(str(sample.key_expr), sample.payload.to_bytes())
            if isinstance(status, RunStatus):
                self.heard = time.monotonic()
                if status.done:
                    self._end(f"run {status.run} is done")

        self.subscriber = session.declare_subscriber(f"derl/{self.run or '*'}/status", on_status)
        self.watching = threading.Thread(target=self._watch, name="run end", daemon=True)
        self.watching.start()
        return self

    def _watch(self) -> None:
        import time

        while not self.stop.wait(1.0):
            if self.heard is not None and time.monotonic() - self.heard > RUN_QUIET_S:
                self._end(f"the run's status stopped coming ({RUN_QUIET_S:g} s): it is over")

    def _end(self, why: str) -> None:
        if not self.stop.is_set():
            self.why = why
            self.stop.set()

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.watching.join()
        self.subscriber.undeclare()
        self.opened.__exit__(*exc)


def _hz(args: argparse.Namespace) -> int:
    from derl.nodes.tools.topic import NothingHeard, hz

    stop = _stop_on_signals()
    if not hz(watch_options(args), args.key, args.run, args.duration, args.window, stop):
        raise NothingHeard(f"nothing heard on {args.key} in {args.duration:g} s")
    return 0


def _record(args: argparse.Namespace) -> int:
    from derl.nodes.tools.recorder import record

    if args.out.exists():
        raise FileExistsError(f"{args.out} exists; choose another name")
    keys = args.keys or (["**"] if args.run else ["derl/**"])
    done = record(watch_options(args), args.out, keys, args.run, args.duration, _stop_on_signals())
    rejected = ", ".join(f"{why} {n}" for why, n in done.rejected.items()) or "none"
    print(
        f"recorded {done.messages} messages in {done.seconds:.1f} s into {args.out}; "
        f"rejected: {rejected}"
    )
    return 0


def _replay(args: argparse.Namespace) -> int:
    from derl.nodes.tools.recorder import UNHEARD_S, replay

    options = publish_options(args)

    def unheard(published: int, ended: bool) -> None:
        when = "" if ended else f" in its first {UNHEARD_S:g} s"
        print(f"derl replay: nobody heard it: no subscriber matched the {published} messages "
              f"published{when} ({how_joined(options)})", file=sys.stderr, flush=True)  # fmt: skip

    done = replay(
        options,
        args.log,
        _stop_on_signals(),
        rate=args.rate,
        loop=args.loop,
        kinds=args.topics,
        start_offset=args.start_offset,
        as_run=args.as_run,
        only_run=args.run,
        force=args.force,
        skip_damaged=args.skip_damaged,
        unheard=unheard,
    )
    speed = done.messages / done.seconds if done.seconds else 0.0
    print(
        f"replayed {done.messages} messages in {done.seconds:.2f} s ({speed:,.0f} msg/s), "
        f"{done.passes} pass{'es' if done.passes != 1 else ''}"
    )
    return 0


def _export(args: argparse.Namespace) -> int:
    from derl.nodes.tools.logs import LogError, export_json
    from derl.nodes.tools.tensorboard import export

    if args.out is None and args.tensorboard is None:
        raise LogError("say what to write: --json OUT.mcap, --tensorboard LOGDIR, or both")
    if args.out is not None:
        output_file(args.out, "--json")
    if args.tensorboard is not None:
        output_directory(args.tensorboard, "--tensorboard")
    if args.out is not None:
        written = export_json(args.log, args.out)
        print(f"exported {written} messages to {args.out} (json + jsonschema)")
    if args.tensorboard is not None:
        directory = export(args.log, args.tensorboard)
        print(f"exported the run's scalars to {directory} (tensorboard --logdir "
              f"{args.tensorboard})")  # fmt: skip
    return 0


def _tensorboard(args: argparse.Namespace) -> int:
    from derl.nodes.tools.tensorboard import watch

    def started(run: str, directory: Path) -> None:
        print(f"writing run {run}'s scalars to {directory} (tensorboard --logdir {args.logdir}; "
              "Ctrl-C stops)", flush=True)  # fmt: skip

    watch(watch_options(args), args.run, args.logdir, _stop_on_signals(), started)
    return 0


def _log_info(args: argparse.Namespace) -> int:
    from derl.nodes.tools.logs import HEALTHY, describe, info

    files = info(args.log)
    if args.json:
        print(json.dumps([dataclasses.asdict(f) for f in files], indent=2))
    else:
        print(describe(files))
    return 0 if all(f.integrity in HEALTHY for f in files) else 3


def _log_upgrade(args: argparse.Namespace) -> int:
    from derl.nodes.journal.upgrade import upgrade, upgrade_run

    if args.source.is_dir():
        if args.out is not None:
            fail("a run directory is upgraded in place: give no OUT.mcap")
        done = upgrade_run(args.source)
    elif args.out is None:
        fail(f"{args.source} is a file: give the new file to write, OUT.mcap")
    else:
        done = [upgrade(args.source, args.out)]
    for file in done:
        dropped = f", {file.dropped} dropped (see the warnings)" if file.dropped else ""
        print(f"{file.source} -> {file.out}: {file.messages} messages{dropped}")
    return 0


def _log_repair(args: argparse.Namespace) -> int:
    from derl.nodes.tools.logs import describe, repair

    print(describe([repair(args.source, args.out)]))
    return 0
