"""The paper's reporting method (appendix D) as data: the top bodies of every surviving lineage
across runs, each to be retrained with several new seeds.

A lineage survives when it has a member in its run's final population; its top bodies are its
fittest members ever born (alive or not). Every selected body is paired with every one of the
same new seeds, drawn at random but never equal to a training seed of the runs. The plan is a
JSON file (`RetrainPlan`): a `derl study` hands each job to an evaluator node.
"""

from __future__ import annotations

from collections.abc import Hashable, Iterable
from typing import Literal, TypeVar

import numpy as np
from pydantic import Field

from derl.analysis.lineage import Tree, final_members
from derl.analysis.records import Record, RunLog
from derl.unimal import Genome

SEED_RANGE = 2**31

K = TypeVar("K", bound=Hashable)


class RetrainJob(Record):
    """Train `agent`'s body (from `run`) from scratch in `task` with a new `seed`."""

    run: str
    agent: str
    lineage: str
    """The founder of the agent's lineage."""
    fitness: float
    """Its fitness in the evolution run (with the run's training seed)."""
    task: str
    """The run's evolution world."""
    steps: int | None
    """The run's lifetime-learning budget (env steps), if known."""
    seed: int
    genome: Genome


class RetrainPlan(Record):
    format: Literal["derl-retrain-plan"] = "derl-retrain-plan"
    version: Literal[1] = 1
    per_lineage: int = Field(ge=1)
    seeds: tuple[int, ...]
    jobs: tuple[RetrainJob, ...]


def new_seeds(count: int, exclude: set[int], seed: int) -> list[int]:
    """`count` distinct random seeds, none of them in `exclude`."""
    rng = np.random.default_rng(seed)
    chosen: list[int] = []
    while len(chosen) < count:
        drawn = int(rng.integers(SEED_RANGE))
        if drawn not in exclude and drawn not in chosen:
            chosen.append(drawn)
    return chosen


def top_of_surviving_lineages(run: RunLog, tree: Tree, per_lineage: int) -> list[int]:
    """The `per_lineage` fittest bodies of each surviving lineage, by lineage then fitness."""
    chosen = []
    for founder in final_members(run, tree):
        members = np.flatnonzero(tree.founder == founder)
        ranked = members[np.argsort(-run.fitness[members], kind="stable")]
        chosen.extend(int(i) for i in ranked[:per_lineage])
    return chosen


def plan(runs: list[RunLog], per_lineage: int, seeds: int, seed: int = 0) -> RetrainPlan:
    """Retraining jobs for the top bodies of all surviving lineages across `runs`."""
    used = {run.training_seed for run in runs if run.training_seed is not None}
    fresh = new_seeds(seeds, used, seed)
    jobs = []
    for run in runs:
        tree = Tree.of(run)
        for i in top_of_surviving_lineages(run, tree, per_lineage):
            body = run.bodies[i]
            if body.genome is None:
                raise ValueError(f"{run.name}: no genome for {body.id}")
            jobs.extend(
                RetrainJob(
                    run=run.name,
                    agent=body.id,
                    lineage=run.bodies[tree.founder[i]].id,
                    fitness=body.fitness,
                    task=run.world,
                    steps=run.train_steps,
                    seed=s,
                    genome=body.genome,
                )
                for s in fresh
            )
    return RetrainPlan(per_lineage=per_lineage, seeds=tuple(fresh), jobs=tuple(jobs))


def by_mean_fitness(results: Iterable[tuple[K, float]]) -> list[tuple[K, float]]:
    """Each body's mean fitness over its retrainings, best first (ties: first seen first): the
    order in which appendix D keeps the 100 best of a world and tests the top 10 of those."""
    sums: dict[K, list[float]] = {}
    for key, fitness in results:
        sums.setdefault(key, []).append(fitness)
    means = [(key, float(np.mean(values))) for key, values in sums.items()]
    return sorted(means, key=lambda kv: -kv[1])
