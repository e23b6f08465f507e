"""`derl evaluate PLAN.json`: run the retraining jobs of a `derl select` plan on this host.

Each job trains its body from scratch with its new seed (the paper's appendix D), one job per
process, `--workers` at a time; the results (mean of each agent over its seeds, and every
training) go to a CSV and a JSON, with the best `--keep` agents (the paper keeps 100).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import multiprocessing
from pathlib import Path

from rich.console import Console
from rich.progress import track

console = Console()


def register(commands: argparse._SubParsersAction) -> None:
    evaluate = commands.add_parser("evaluate", help="retrain the bodies of a `derl select` plan")
    evaluate.add_argument("plan", type=Path, help="JSON plan written by `derl select`")
    evaluate.add_argument("--out", type=Path, required=True, help="output directory")
    evaluate.add_argument("--workers", type=int, default=2, help="trainings at a time")
    evaluate.add_argument("--steps", type=int, help="override every job's env steps")
    evaluate.add_argument("--keep", type=int, default=100, help="best agents kept (paper: 100)")
    evaluate.set_defaults(handler=_evaluate)


def _retrain(job: dict[str, object]) -> dict[str, object]:
    from derl.analysis import RetrainJob
    from derl.lifetime import learn, ppo_config

    spec = RetrainJob.model_validate(job)
    summary, _ = learn(spec.genome, spec.task, ppo_config(spec.task, int(spec.steps), spec.seed))
    return {
        "run": spec.run,
        "agent": spec.agent,
        "lineage": spec.lineage,
        "task": spec.task,
        "seed": spec.seed,
        "evolution_fitness": spec.fitness,
        "fitness": summary.fitness,
        "cost_of_work": summary.cost_of_work,
    }


def _evaluate(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from derl.analysis import RetrainPlan

    try:
        plan = RetrainPlan.model_validate_json(args.plan.read_text())
    except (OSError, ValidationError) as error:
        raise SystemExit(f"derl: {args.plan} is not a retraining plan: {error}") from None
    jobs = []
    for job in plan.jobs:
        steps = args.steps or job.steps
        if steps is None:
            raise SystemExit(f"derl: job {job.agent} has no step budget: give --steps")
        jobs.append(job.model_copy(update={"steps": steps}).model_dump(mode="json"))
    args.out.mkdir(parents=True, exist_ok=True)
    with multiprocessing.get_context("spawn").Pool(args.workers) as pool:
        results = list(track(pool.imap(_retrain, jobs), total=len(jobs), description="retraining"))
    agents: dict[tuple[str, str], list[dict[str, object]]] = {}
    for row in results:
        agents.setdefault((str(row["run"]), str(row["agent"])), []).append(row)
    ranked = sorted(
        (
            {**rows[0], "fitness": _mean(r["fitness"] for r in rows), "seeds": len(rows)}
            for rows in agents.values()
        ),
        key=lambda row: row["fitness"],
        reverse=True,
    )
    with (args.out / "retrained.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(results[0]))
        writer.writeheader()
        writer.writerows(results)
    best = [{k: v for k, v in row.items() if k not in ("seed", "cost_of_work")} for row in ranked]
    (args.out / "best.json").write_text(json.dumps(best[: args.keep], indent=2) + "\n")
    console.print(f"{len(results)} trainings of {len(agents)} agents -> {args.out}")
    return 0


def _mean(values) -> float:
    values = [float(v) for v in values if math.isfinite(float(v))]
    return sum(values) / len(values) if values else float("nan")
