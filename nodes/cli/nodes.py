"""`derl coordinator|trainer|evaluator|router`: start one node of a run on this host."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
from pathlib import Path

from nodes.cli.options import add_bus_arguments, add_profile_arguments, options_from, profile_from
from nodes.runtime.bus import node_name


def register(commands: argparse._SubParsersAction) -> None:
    coordinator = commands.add_parser("coordinator", help="start the coordinator of a run")
    add_profile_arguments(coordinator)
    coordinator.add_argument("--run-dir", type=Path, required=True, help="journal and results")
    add_bus_arguments(coordinator)
    coordinator.set_defaults(handler=_coordinator)

    for role in ("trainer", "evaluator"):
        worker = commands.add_parser(role, help=f"start {role} nodes (one training per process)")
        worker.add_argument("--workers", type=int, default=1, help="processes on this host")
        worker.add_argument("--threads", type=int, default=1, help="simulation threads each")
        worker.add_argument("--name", help="node id (default: role-host-pid-index)")
        add_bus_arguments(worker)
        worker.set_defaults(handler=_worker, role=role)

    router = commands.add_parser("router", help="run a Zenoh router for star topologies")
    add_bus_arguments(router, run_required=False)
    router.set_defaults(handler=_router)


def _coordinator(args: argparse.Namespace) -> int:
    from nodes.coordinator.node import serve

    serve(args.run, args.run_dir, profile_from(args), options_from(args))
    return 0


def _worker(args: argparse.Namespace) -> int:
    if args.workers > 1:
        return _fan_out(args)
    from nodes.worker.node import serve

    name = args.name or node_name(args.role)
    serve(args.run, name, args.role, options_from(args), nthread=args.threads)
    return 0


def _fan_out(args: argparse.Namespace) -> int:
    """`--workers K`: K single-worker processes, stopped together."""
    from nodes.runtime.processes import spawn_derl, stop_all

    rest = [a for a in sys.argv[1:] if a not in ("--workers", str(args.workers))]
    children = [spawn_derl([*rest, "--workers", "1"]) for _ in range(args.workers)]
    signal.signal(signal.SIGTERM, lambda *_: stop_all(children))
    try:
        for child in children:
            child.wait()
    except KeyboardInterrupt:
        pass
    finally:
        stop_all(children)
    return 0


def _router(args: argparse.Namespace) -> int:
    from nodes.runtime.bus import open_session

    options = options_from(args, mode="router")
    if not options.listen and not options.config_file:
        options = options.model_copy(update={"listen": ("tcp/0.0.0.0:7447",)})
    with open_session(options):
        logging.getLogger("derl.router").info("router listening on %s", ", ".join(options.listen))
        signal.sigwait([signal.SIGTERM, signal.SIGINT])
    return 0
