"""`derl run`: a whole run on this host: coordinator, K trainers and an evaluator, on loopback.

Each node is its own process (its log in RUN_DIR/logs/), connected through the coordinator's
loopback endpoint with multicast off; this process watches the run's status and shows progress
(bodies born, best fitness, steps/s, time left). Ctrl-C stops every node cleanly; running it
again on the same run directory resumes the run from its journal.
"""

from __future__ import annotations

import argparse
import re
import signal
import socket
import threading
import time
from pathlib import Path

from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from messages import RunStatus
from nodes.cli.options import add_profile_arguments, profile_from
from nodes.runtime.bus import Bus, ZenohOptions, open_session
from nodes.runtime.processes import spawn_derl, stop_all

console = Console()


def register(commands: argparse._SubParsersAction) -> None:
    run = commands.add_parser("run", help="run evolution on this host (all nodes, embedded)")
    add_profile_arguments(run)
    run.add_argument("--workers", type=int, default=2, help="trainer processes (default 2)")
    run.add_argument("--run-dir", type=Path, help="default: runs/<profile>-<world>")
    run.add_argument("--port", type=int, default=0, help="coordinator port (default: a free one)")
    run.set_defaults(handler=_run)


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _run(args: argparse.Namespace) -> int:
    config = profile_from(args)
    run_dir = args.run_dir or Path("runs") / f"{config.name}-{config.world}"
    run = re.sub(r"[^A-Za-z0-9_.-]", "-", run_dir.resolve().name)[:128]
    logs = run_dir / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    endpoint = f"tcp/127.0.0.1:{args.port or _free_port()}"
    bus_args = ["--run", run]
    coordinator = spawn_derl(
        [
            "coordinator",
            "--profile",
            args.profile,
            "--run-dir",
            str(run_dir),
            *(["--env", args.env] if args.env else []),
            *bus_args,
            "--listen",
            endpoint,
        ],
        logs / "coordinator.log",
    )
    workers = [
        spawn_derl(
            ["trainer", *bus_args, "--connect", endpoint, "--name", f"trainer-{k}"],
            logs / f"trainer-{k}.log",
        )
        for k in range(args.workers)
    ]
    if config.eval_top:
        workers.append(
            spawn_derl(
                ["evaluator", *bus_args, "--connect", endpoint, "--name", "evaluator-0"],
                logs / "evaluator-0.log",
            )
        )
    console.print(
        f"run [bold]{run}[/] ({config.name}, {config.world}): {config.total} bodies, "
        f"{args.workers} trainers; logs in {logs}"
    )
    interrupted = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: interrupted.set())
    try:
        status = _watch(run, endpoint, config.total, coordinator, interrupted)
    except KeyboardInterrupt:
        status = None
        interrupted.set()
    finally:
        stop_all([coordinator, *workers])
    if interrupted.is_set() or status is None or not status.done:
        console.print(f"stopped; `derl run --run-dir {run_dir} ...` resumes the run")
        return 130 if interrupted.is_set() else 1
    best = f"{status.best_agent} ({status.best_fitness:.1f})" if status.best_agent else "-"
    console.print(f"done: {status.born} bodies, best {best}; results in {run_dir}")
    return 0


def _watch(
    run: str, endpoint: str, total: int, coordinator, interrupted: threading.Event
) -> RunStatus | None:
    """Show the run's status until the coordinator exits; the last status seen."""
    latest: list[RunStatus] = []
    options = ZenohOptions(connect=(endpoint,))
    columns = (
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TextColumn("{task.completed:.0f}/{task.total:.0f} born"),
        TextColumn("best {task.fields[best]}"),
        TextColumn("{task.fields[sps]:,.0f} steps/s"),
        TextColumn("eval {task.fields[evaluated]}"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
    )
    with open_session(options) as session, Progress(*columns, console=console) as bar:
        bus = Bus(session, run)
        bus.subscribe(bus.keys.status(), latest.append, (RunStatus,))
        task = bar.add_task("evolution", total=total, best="-", sps=0.0, evaluated="-")
        while coordinator.poll() is None and not interrupted.is_set():
            time.sleep(0.5)
            if not latest:
                continue
            s = latest[-1]
            del latest[:-1]
            bar.update(
                task,
                total=s.target,
                completed=s.born,
                best="-" if s.best_fitness is None else f"{s.best_fitness:.1f}",
                sps=s.steps_per_s,
                evaluated=f"{s.evaluated}/{s.eval_target}",
            )
    return latest[-1] if latest else None
