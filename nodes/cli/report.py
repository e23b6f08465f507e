"""`derl report` and `derl select`: the paper's analyses of finished (or running) runs.

Both read a run's journal (a run directory, or one MCAP file such as a journal segment) with
`nodes.journal.segments`, fold its messages into `derl.analysis` records (bodies in birth order with the
parent of their TrainJob and the body, mutation, fitness, curve, energy, cost of work and mass
of their FitnessReport; the EvalResults), and hand those to
`derl.analysis`. The first report of a child is its birth, as in the coordinator's fold.
"""

from __future__ import annotations

import argparse
import logging
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING

from rich.console import Console

if TYPE_CHECKING:
    from derl.analysis import Body, RunLog
    from messages import FitnessReport, TrainJob

console = Console()
log = logging.getLogger("derl.report")

SELECT_FORMAT = """\
output (JSON, one job per selected agent and new seed):
  {"format": "derl-retrain-plan", "version": 1, "per_lineage": 3, "seeds": [S1, ..., S5],
   "jobs": [{"run": RUN, "agent": ID, "lineage": FOUNDER_ID, "fitness": EVOLUTION_FITNESS,
             "task": WORLD, "steps": ENV_STEPS_OR_NULL, "seed": S, "genome": {GENOME}}, ...]}
  run/agent: where the body comes from; lineage: its founder; task: the run's evolution world
  (ft/vt/mvt) and steps its lifetime budget, so retraining repeats evolution's training with a
  new seed (appendix D); genome: the body (derl.unimal.Genome JSON). The same seeds are used for
  every agent and none equals a run's training seed. The file validates as
  `derl.analysis.RetrainPlan`, for a `derl evaluate` to hand each job to an evaluator.
"""


def register(commands: argparse._SubParsersAction) -> None:
    report = commands.add_parser(
        "report",
        help="plots and tables of the paper's analyses of one or more runs",
        description="Write DIR/index.html, one PNG per figure (figs. 2-6 of the paper and the "
        "best bodies), CSV tables (bodies, lineages, series, muller, tests, test_summary) and "
        "stats.json, from the runs' journals alone.",
    )
    report.add_argument(
        "runs", nargs="+", type=Path, metavar="RUN_DIR_OR_LOG", help="run directory or MCAP log"
    )
    report.add_argument("--out", type=Path, required=True, help="output directory")
    report.add_argument(
        "--beneficial",
        type=_thresholds,
        default={},
        metavar="GAIN|WORLD=GAIN,...",
        help="least fitness gain of a beneficial mutation: one number for every world, or per "
        "world, e.g. ft=300,vt=100 (default: the paper's ft=300, vt=100, mvt=100)",
    )
    report.add_argument(
        "--top", type=int, help="top agents (default 100, or a quarter of a smaller group)"
    )
    report.add_argument(
        "--stability-sample",
        type=int,
        metavar="N",
        help="bodies whose passive stability is simulated: all of a run up to N, else N evenly "
        "spaced in birth order (default 500)",
    )
    report.add_argument(
        "--processes",
        type=int,
        default=min(4, os.cpu_count() or 1),
        help="processes for the stability simulations (default: up to 4 cores)",
    )
    report.add_argument("--pictures", type=int, help="best bodies drawn (default 8)")
    report.set_defaults(handler=_report)

    select = commands.add_parser(
        "select",
        help="appendix D: top bodies of the surviving lineages, to retrain with new seeds",
        description=(
            "Pick the top bodies of every surviving lineage (one with a member in its run's final\n"
            "population) across the runs, and pair each with the same new seeds: the paper's\n"
            "reporting method (appendix D). Writes the jobs; starts nothing."
        ),
        epilog=SELECT_FORMAT,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    select.add_argument("runs", nargs="+", type=Path, metavar="RUN_DIR_OR_LOG")
    select.add_argument(
        "--per-lineage", type=int, default=3, help="fittest bodies per lineage (paper: 3)"
    )
    select.add_argument("--seeds", type=int, default=5, help="new seeds per body (paper: 5)")
    select.add_argument("--seed", type=int, default=0, help="draws the new seeds (default 0)")
    select.add_argument("--out", type=Path, required=True, help="JSON file to write")
    select.set_defaults(handler=_select)


def _thresholds(text: str) -> dict[str, float]:
    """``300`` (every world) or ``ft=300,vt=100``, as {world: gain}; "*" stands for every world."""
    try:
        if "=" not in text:
            return {"*": float(text)}
        pairs = (item.split("=", 1) for item in text.split(",") if item.strip())
        return {world.strip().lower(): float(gain) for world, gain in pairs}
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: give a number or WORLD=GAIN pairs, e.g. ft=300,vt=100"
        ) from None


def load_run(path: Path) -> RunLog:
    """A run's records from its journal: a run directory or one MCAP file."""
    from derl.analysis import Evaluation, RunLog
    from messages import EvalResult, FitnessReport, TrainJob
    from nodes.journal.segments import read_segment, replay, segments

    if path.is_dir():
        if not segments(path):
            raise SystemExit(f"derl: {path} holds no journal (journal/segment-NNNN.mcap)")
        messages = replay(path)
    elif path.is_file():
        messages = read_segment(path)
    else:
        raise SystemExit(f"derl: no run directory or log at {path}")
    run: str | None = None
    jobs: dict[str, TrainJob] = {}
    bodies: list[Body] = []
    born: set[str] = set()
    evaluations: dict[tuple[str, str, int], Evaluation] = {}
    orphans = others = 0
    for msg in messages:
        run = run or msg.run
        if msg.run != run:
            others += 1
            continue
        if isinstance(msg, TrainJob):
            jobs.setdefault(msg.child, msg)
        elif isinstance(msg, FitnessReport):
            job = jobs.get(msg.child)
            if msg.child in born:
                continue
            if job is None or (job.parent is not None and job.parent not in born):
                orphans += 1
                continue
            born.add(msg.child)
            bodies.append(_body(len(bodies), job, msg))
        elif isinstance(msg, EvalResult):
            evaluations.setdefault(
                (msg.agent, msg.task, msg.seed),
                Evaluation(
                    agent=msg.agent,
                    task=msg.task,
                    seed=msg.seed,
                    reward=msg.reward,
                    cost_of_work=msg.cost_of_work,
                ),
            )
    if not bodies:
        raise SystemExit(f"derl: no body was born in {path}")
    if orphans:
        log.warning("%s: %d fitness reports without their job or parent skipped", path, orphans)
    if others:
        log.warning("%s: %d messages of runs other than %s skipped", path, others, run)
    first = next(iter(jobs.values()))
    return RunLog(
        name=run,
        world=first.task,
        bodies=tuple(bodies),
        evaluations=tuple(evaluations.values()),
        train_steps=first.steps,
        training_seed=first.seed,
    )


def _body(birth: int, job: TrainJob, report: FitnessReport) -> Body:
    from derl.analysis import Body

    return Body(
        id=report.child,
        parent=job.parent,
        birth=birth,
        fitness=report.fitness,
        curve_steps=report.curve.env_steps,
        curve_returns=report.curve.returns,
        energy=report.energy,
        cost_of_work=report.cost_of_work,
        mass=report.mass,
        mutation=report.mutation,
        genome=report.genome,
    )


def load_runs(paths: list[Path]) -> list[RunLog]:
    """The runs of `paths`, renamed run-2, run-3... where two carry the same run id."""
    runs, seen = [], set()
    for path in paths:
        run = load_run(path)
        name, k = run.name, 1
        while name in seen:
            k += 1
            name = f"{run.name}-{k}"
        seen.add(name)
        runs.append(run if name == run.name else run.model_copy(update={"name": name}))
    return runs


def _report(args: argparse.Namespace) -> int:
    from derl.analysis import AnalysisConfig, write_report
    from derl.analysis.config import BENEFICIAL

    everywhere = args.beneficial.pop("*", None)
    defaults = {w: everywhere for w in BENEFICIAL} if everywhere is not None else BENEFICIAL
    given = {
        "top": args.top,
        "stability_sample": args.stability_sample,
        "processes": args.processes,
        "pictures": args.pictures,
    }
    try:
        config = AnalysisConfig(
            beneficial={**defaults, **args.beneficial},
            **{name: value for name, value in given.items() if value is not None},
        )
    except ValueError as error:
        raise SystemExit(f"derl: {error}") from None
    start = time.monotonic()
    runs = load_runs(args.runs)
    try:
        files = write_report(runs, args.out, config)
    except ValueError as error:
        raise SystemExit(f"derl: {error}") from None
    for note in files.notes:
        console.print(f"note: {note}", highlight=False)
    console.print(
        f"wrote {files.page} ({len(files.figures)} figures, {len(files.tables)} tables) in "
        f"{time.monotonic() - start:.1f} s",
        highlight=False,
    )
    return 0


def _select(args: argparse.Namespace) -> int:
    from derl.analysis import plan

    if args.per_lineage < 1 or args.seeds < 1:
        raise SystemExit("derl: --per-lineage and --seeds must be at least 1")
    result = plan(load_runs(args.runs), args.per_lineage, args.seeds, args.seed)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(result.model_dump_json(indent=2) + "\n")
    agents = len({(job.run, job.agent) for job in result.jobs})
    console.print(
        f"wrote {args.out}: {len(result.jobs)} jobs ({agents} bodies x {len(result.seeds)} seeds)",
        highlight=False,
    )
    return 0
