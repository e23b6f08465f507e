"""`derl coordinator|trainer|evaluator|router`: start one node of a run on this host.

Exit status (`derl.nodes.errors`): the coordinator 0 only when the run finished (1 when stopped
or failed, so a supervisor restarts it; 78 when it refuses to start: its run directory holds
another run or profile, its journal is damaged, its configuration or study is not valid); a worker
0 when stopped or when the run is over; 2 when a port or the run directory is taken; `--workers
K` the status of the first of its K processes that failed, else 0.
"""

from __future__ import annotations

import argparse
import logging
import signal
import subprocess
import threading
from functools import partial
from pathlib import Path

import zenoh

from derl.nodes.cli.options import (
    add_bus_arguments,
    add_profile_arguments,
    at_least_one,
    fail_on_bus,
    options_from,
    profile_from,
    run_directory,
    study_profile_from,
)
from derl.nodes.errors import DerlError, Refused
from derl.nodes.launch.model import split_endpoint, with_port
from derl.nodes.runtime.bus import node_name


def register(commands: argparse._SubParsersAction) -> None:
    coordinator = commands.add_parser(
        "coordinator", help="start the coordinator of a run (or of a study: --study)"
    )
    add_profile_arguments(coordinator)
    where = coordinator.add_mutually_exclusive_group(required=True)
    where.add_argument("--run-dir", type=Path, help="journal and results")
    where.add_argument(
        "--study", type=Path, metavar="STUDY_DIR", help="coordinate this study (`derl study`)"
    )
    coordinator.add_argument(
        "--study-runs",
        nargs="+",
        type=Path,
        default=[],
        metavar="RUN_DIR",
        help="with --study: the runs to select from when STUDY_DIR is not planned yet (then "
        "--profile names a study profile)",
    )
    add_bus_arguments(coordinator)
    coordinator.set_defaults(handler=_coordinator)

    for role in ("trainer", "evaluator"):
        worker = commands.add_parser(role, help=f"start {role} nodes (one training per process)")
        worker.add_argument("--workers", type=at_least_one, default=1, help="processes here")
        worker.add_argument("--threads", type=at_least_one, default=1, help="simulation threads")
        worker.add_argument(
            "--name", help="node id (default: role-host-pid-index; NAME-k with --workers)"
        )
        if role == "trainer":
            worker.add_argument(
                "--tensorboard",
                type=Path,
                metavar="LOGDIR",
                help="write each training's curves and PPO diagnostics to TensorBoard event "
                "files in LOGDIR/<run>/children/<agent> (pip install 'derl[tensorboard]')",
            )
        add_bus_arguments(worker)
        worker.set_defaults(handler=_worker, role=role, tensorboard=None)  # trainers: a flag

    router = commands.add_parser("router", help="run a Zenoh router for star topologies")
    add_bus_arguments(router, run_required=False)
    router.set_defaults(handler=_router)


def _coordinator(args: argparse.Namespace) -> int:
    from derl.nodes.coordinator.node import serve
    from derl.nodes.coordinator.run.rules import EvolutionRules
    from derl.nodes.coordinator.study.rules import serve_study

    try:  # its directory and settings: a restart would not change them
        if args.study is not None:
            study = study_profile_from(args) if args.study_runs else None
        else:
            run_dir, config = run_directory(args.run_dir), profile_from(args)
    except DerlError as error:
        raise Refused(str(error)) from None
    try:
        if args.study is not None:
            finished = serve_study(args.run, args.study, options_from(args), args.study_runs,
                                   study)  # fmt: skip
        else:
            rules = partial(EvolutionRules, args.run, run_dir, config)
            finished = serve(args.run, run_dir, rules, options_from(args))
    except zenoh.ZError as error:
        fail_on_bus(error)
    return 0 if finished is True else 1


def _worker(args: argparse.Namespace) -> int:
    if args.workers > 1:
        return _fan_out(args)
    from derl.nodes.worker.node import serve

    name = args.name or node_name(args.role)
    board = args.tensorboard
    if board is not None:
        from derl.metrics import NoTensorBoard, require_extra

        try:
            require_extra()
        except NoTensorBoard as error:  # no restart would change that
            raise Refused(f"--tensorboard: {error}") from None
    try:
        serve(args.run, name, args.role, options_from(args), nthread=args.threads,
              tensorboard=board)  # fmt: skip
    except zenoh.ZError as error:
        fail_on_bus(error)
    return 0


def child_args(args: argparse.Namespace, k: int) -> list[str]:
    """The command line of process `k` of `--workers K`: one worker, named NAME-k (when --name is
    given), listening on port + k of each --listen endpoint with a port (port 0 stays 0)."""
    line = [args.role, "--run", args.run, "--threads", str(args.threads), "--mode", args.mode]
    if args.name:
        line += ["--name", f"{args.name}-{k}"]
    for endpoint in args.listen:
        line += ["--listen", _shifted(endpoint, k)]
    for endpoint in args.connect:
        line += ["--connect", endpoint]
    if args.zenoh_config:
        line += ["--zenoh-config", str(args.zenoh_config)]
    if args.multicast:
        line.append("--multicast")
    if args.tensorboard is not None:
        line += ["--tensorboard", str(args.tensorboard)]
    return line


def _shifted(endpoint: str, k: int) -> str:
    try:
        _, _, port = split_endpoint(endpoint)
    except ValueError:  # not PROTO/HOST:PORT (e.g. with Zenoh options): as given
        return endpoint
    return with_port(endpoint, port + k if port else 0)


def _fan_out(args: argparse.Namespace) -> int:
    """`--workers K`: K single-worker processes, all stopped on SIGTERM or SIGINT; the exit
    status of the first that failed, else 0."""
    from derl.nodes.runtime.processes import exit_status, spawn_derl, stop_all

    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    children: list[subprocess.Popen] = []
    try:
        for k in range(args.workers):
            if not stop.is_set():
                children.append(spawn_derl(child_args(args, k)))
        while not stop.wait(0.2) and any(child.poll() is None for child in children):
            pass
    finally:
        stop_all(children)
    failed = [code for code in (exit_status(child) for child in children) if code != 0]
    return failed[0] if failed else 0


def _router(args: argparse.Namespace) -> int:
    from derl.nodes.runtime.bus import open_session

    options = options_from(args, mode="router")
    if not options.listen and not options.config_file:
        options = options.model_copy(update={"listen": ("tcp/0.0.0.0:7447",)})
    try:
        session = open_session(options)
    except zenoh.ZError as error:
        fail_on_bus(error)
    with session:
        logging.getLogger("derl.router").info("router listening on %s", ", ".join(options.listen))
        signal.sigwait([signal.SIGTERM, signal.SIGINT])
    return 0
