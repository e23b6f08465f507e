"""The paper's reporting method (appendix D) as data: the top bodies of every surviving lineage
across runs, each to be retrained with several new seeds.

A lineage survives when it has a member in its run's final population; its top bodies are its
fittest members ever born (alive or not), each body once: a repeat is its original, and a body
selected from an earlier run of the same world is not selected again (retraining it again with
the same seeds would give the same results). Every selected body is paired with every one of
the same new seeds, drawn at random but never equal to a training seed of the runs. The plan is
a JSON file (`RetrainPlan`): a `derl study` hands each job to an evaluator node.

Bodies are then ranked by their mean fitness over the new seeds (`rank_by_mean`), each body
once, and only where every seed's retraining has a result: a mean over fewer seeds is not
comparable (a body ranked on 1 of its 5 retrainings could rank first).
"""

from __future__ import annotations

from collections.abc import Hashable, Iterable, Mapping
from dataclasses import dataclass
from typing import Generic, Literal, TypeVar

import numpy as np
from pydantic import Field

from derl.analysis.lineage import Tree, final_members
from derl.analysis.records import Record, RunLog
from derl.unimal import Genome, body_hash

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


def top_of_surviving_lineages(
    run: RunLog, tree: Tree, per_lineage: int, taken: set[str] | None = None
) -> list[int]:
    """The `per_lineage` fittest bodies of each surviving lineage, by lineage then fitness, each
    body once (a repeat is its original, which is born first and as fit); of those, the ones
    whose identity is in `taken` (bodies chosen already) are left out, and the others added
    to it."""
    taken = set() if taken is None else taken
    chosen = []
    for founder in final_members(run, tree):
        members = np.flatnonzero((tree.founder == founder) & run.distinct)
        ranked = members[np.argsort(-run.fitness[members], kind="stable")][:per_lineage]
        mine = [int(i) for i in ranked if run.body_keys[i] not in taken]
        taken.update(run.body_keys[i] for i in mine)
        chosen.extend(mine)
    return chosen


def plan(runs: list[RunLog], per_lineage: int, seeds: int, seed: int = 0) -> RetrainPlan:
    """Retraining jobs for the top bodies of all surviving lineages across `runs`, each body of
    a world once."""
    used = {run.training_seed for run in runs if run.training_seed is not None}
    fresh = new_seeds(seeds, used, seed)
    taken: dict[str, set[str]] = {}
    jobs: list[RetrainJob] = []
    for run in runs:
        tree = Tree.of(run)
        world = taken.setdefault(run.world, set())
        for i in top_of_surviving_lineages(run, tree, per_lineage, world):
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


@dataclass(frozen=True)
class Ranking(Generic[K]):
    """Bodies by mean retrained fitness: `ranked` (body, mean), best first, the bodies with a
    result for every training any of them has; `partial`, the others (not ranked)."""

    ranked: list[tuple[K, float]]
    partial: list[K]
    results: int
    """Results counted: one per body and training."""
    duplicates: int
    """Results of a training of a body counted already (the same training again), left out."""


def rank_by_mean(results: Iterable[tuple[K, Hashable, float]]) -> Ranking[K]:
    """Rank (body, training, fitness) results (a training: what makes it another sample, e.g.
    its seed): each body's mean over its trainings, best first (ties: first seen first), for
    the bodies that have a result for every training that any body has; a second result of
    the same body and training is not counted."""
    trainings: dict[K, dict[Hashable, float]] = {}
    duplicates = 0
    for body, training, fitness in results:
        mine = trainings.setdefault(body, {})
        if training in mine:
            duplicates += 1
        else:
            mine[training] = fitness
    every = set().union(*trainings.values()) if trainings else set()
    complete = [body for body, done in trainings.items() if done.keys() == every]
    means = [(body, float(np.mean(list(trainings[body].values())))) for body in complete]
    return Ranking(
        ranked=sorted(means, key=lambda kv: -kv[1]),
        partial=[body for body, done in trainings.items() if done.keys() != every],
        results=sum(len(done) for done in trainings.values()),
        duplicates=duplicates,
    )


def kept_bodies(
    selected: Mapping[str, RetrainJob], results: Iterable[tuple[str, int, float]], keep: int
) -> dict[str, list[tuple[str, float]]]:
    """A study's kept bodies: per world, the `keep` best selected agents by mean fitness over
    their (agent, seed, fitness) retraining results (`rank_by_mean`: each body once, ranked only
    with every seed's result), each as the first agent the plan names for its body."""
    body = {agent: (job.task, body_hash(job.genome)) for agent, job in selected.items()}
    name: dict[tuple[str, str], str] = {}
    for agent in selected:
        name.setdefault(body[agent], agent)
    done = list(results)
    worlds = dict.fromkeys(job.task for job in selected.values())
    return {
        world: [
            (name[key], mean)
            for key, mean in rank_by_mean(
                (body[agent], seed, fitness)
                for agent, seed, fitness in done
                if selected[agent].task == world
            ).ranked
        ][:keep]
        for world in worlds
    }
