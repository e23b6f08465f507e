"""The test-task suite across worlds (the paper's fig. 4): per world and task, the median reward
and cost of work with bootstrapped CIs, and two-tailed Mann-Whitney U tests between worlds.

Runs of the same world are pooled: every evaluation (agent, task, seed) is one sample.
"""

from __future__ import annotations

from itertools import combinations

import numpy as np

from derl.analysis.records import Record, RunLog
from derl.analysis.statistics import BootstrapConfig, Comparison, Estimate, estimate, mann_whitney

METRICS = ("reward", "cost_of_work")


class TestResult(Record):
    """One evaluation (a row of tests.csv)."""

    __test__ = False  # not a pytest class
    run: str
    world: str
    agent: str
    task: str
    seed: int
    reward: float
    cost_of_work: float


class TaskSummary(Record):
    """Medians of one world on one task (a row of test_summary.csv)."""

    world: str
    task: str
    reward: Estimate
    cost_of_work: Estimate


class WorldComparison(Record):
    """Mann-Whitney U test of two worlds on one task and metric."""

    task: str
    metric: str
    world_a: str
    world_b: str
    test: Comparison


def results(runs: list[RunLog]) -> list[TestResult]:
    return [
        TestResult(run=run.name, world=run.world, **evaluation.model_dump())
        for run in runs
        for evaluation in run.evaluations
    ]


def _values(rows: list[TestResult], world: str, task: str, metric: str) -> np.ndarray:
    return np.array(
        [getattr(r, metric) for r in rows if r.world == world and r.task == task], dtype=float
    )


def tasks_and_worlds(rows: list[TestResult]) -> tuple[list[str], list[str]]:
    """The tasks and worlds present, in order of first appearance."""
    return list(dict.fromkeys(r.task for r in rows)), list(dict.fromkeys(r.world for r in rows))


def summarize(rows: list[TestResult], config: BootstrapConfig) -> list[TaskSummary]:
    tasks, worlds = tasks_and_worlds(rows)
    return [
        TaskSummary(
            world=world,
            task=task,
            **{m: estimate(_values(rows, world, task, m), config, "median") for m in METRICS},
        )
        for task in tasks
        for world in worlds
        if any(r.world == world and r.task == task for r in rows)
    ]


def compare(rows: list[TestResult]) -> list[WorldComparison]:
    """Every pair of worlds on every task both were tested on, for reward and cost of work."""
    tasks, worlds = tasks_and_worlds(rows)
    return [
        WorldComparison(
            task=task,
            metric=metric,
            world_a=a,
            world_b=b,
            test=mann_whitney(_values(rows, a, task, metric), _values(rows, b, task, metric)),
        )
        for task in tasks
        for metric in METRICS
        for a, b in combinations(worlds, 2)
        if _values(rows, a, task, metric).size and _values(rows, b, task, metric).size
    ]
