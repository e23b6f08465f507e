"""`derl study`: the paper's appendix D over finished runs, on this host or a cluster.

`derl study RUN_DIR... --study-dir DIR` chooses the bodies to retrain from the runs' journals (the
`per_lineage` fittest of every surviving lineage, each with `seeds` new seeds; `plan.json`), then
runs the study's coordinator and `--workers` evaluators here, supervised like `derl run`: every
retraining, then each world's `top` of its `keep` best on the test tasks at every budget. The
coordinator journals every job and result in DIR, so running the command again resumes the study.
With `--plan-only` it only writes DIR's plan. On a cluster, ``derl coordinator --study DIR
--study-runs RUN_DIR...`` plans and coordinates on one host, ``derl evaluator`` nodes work
anywhere; a launch file with ``study: DIR`` and ``study_runs:`` starts them all.
`derl report DIR` draws the study's figures.
"""

from __future__ import annotations

import argparse
import signal
from pathlib import Path

from rich.console import Console

from derl.nodes.cli.options import (
    add_port_argument,
    add_set_argument,
    at_least_one,
    fail,
    run_directory,
    study_profile_from,
)
from derl.nodes.cli.run import listenable, local_run_id, supervise, watch_command
from derl.nodes.errors import USAGE
from derl.nodes.launch.commands import build_commands
from derl.nodes.launch.local import local_launch
from derl.nodes.launch.supervisor import Supervisor
from derl.nodes.runtime.rundir import lock_run_dir

console = Console()


def register(commands: argparse._SubParsersAction) -> None:
    study = commands.add_parser(
        "study",
        help="appendix D: retrain the runs' best bodies with new seeds, test the best",
        description=__doc__.split("\n", 2)[2] if __doc__ else None,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    study.add_argument(
        "runs", nargs="*", type=Path, metavar="RUN_DIR", help="finished runs (not to resume)"
    )
    study.add_argument("--study-dir", type=Path, required=True, help="journal and results")
    study.add_argument("--profile", default="smoke", help="smoke | demo | paper | FILE.yaml")
    add_set_argument(study)
    study.add_argument("--workers", type=at_least_one, default=2, help="evaluator processes (2)")
    add_port_argument(study, "the coordinator's port on 127.0.0.1")
    study.add_argument("--plan-only", action="store_true", help="write the plan, start nothing")
    study.set_defaults(handler=_study)


def _study(args: argparse.Namespace) -> int:
    from derl.nodes.coordinator.study.files import SETUP_FILE, prepare_study, read_plan

    config = study_profile_from(args)
    if not (args.study_dir / SETUP_FILE).exists():  # checked before DIR is made
        if not args.runs:
            fail(f"{args.study_dir} is not a study yet: give the run directories to study")
        for path in args.runs:
            if not path.exists():
                fail(f"no run directory or log at {path}", USAGE)
    study_dir = run_directory(args.study_dir)
    with lock_run_dir(study_dir):
        setup = prepare_study(study_dir, args.runs, config)
    worlds = sorted({job.task for job in read_plan(study_dir).jobs})
    console.print(
        f"study {study_dir}: {len(setup.runs)} runs ({', '.join(worlds)}), "
        f"profile {setup.config.name}; plan in {study_dir / 'plan.json'}",
        highlight=False,
    )
    if args.plan_only:
        return 0
    port = listenable(args.port)
    run = local_run_id(study_dir)
    endpoint = f"tcp/127.0.0.1:{port}"
    graph = local_launch(run, endpoint, {"evaluator": args.workers}, study=study_dir)
    supervisor = Supervisor(build_commands(graph), study_dir / "logs")
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: supervisor.stop.set())
    console.print(
        f"coordinator on {endpoint} ({watch_command(endpoint, run)}); "
        f"{args.workers} evaluators; logs in {supervisor.log_dir}",
        highlight=False,
    )
    code, status = supervise(supervisor, run, endpoint, 1)
    if code != 0:
        console.print(f"stopped; `derl study --study-dir {study_dir}` resumes the study")
        return code
    done = f"{status.evaluated} results" if status is not None else "done"
    console.print(f"done: {done}; `derl report {study_dir} --out DIR` draws its figures")
    return 0
