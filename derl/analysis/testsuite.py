"""The test-task suite across worlds (the paper's fig. 4): per budget of env steps, world and task,
the median reward and cost of work with bootstrapped CIs, and two-tailed Mann-Whitney U tests
between worlds.

Runs of the same world are pooled: every evaluation (agent, task, seed) is one sample, each body
once (a second evaluation of the same body, as a repeat or from another run of the world, with
the same task, seed and budget is the same training: it is left out and counted). Results with
different budgets are never pooled: the paper trains the same agents for 5M steps (fig. 4b) and
for 1M steps (fig. 4c); results without a known budget form a group of their own. A result whose
reward is not positive has no cost of work: it is counted as beyond every measured one (a
censored value: Kaplan-Meier median, and ranked last by Mann-Whitney's test), never dropped.
"""

from __future__ import annotations

from collections.abc import Iterable
from itertools import combinations

import numpy as np

from derl.analysis.records import Record, RunLog
from derl.analysis.statistics import (
    BootstrapConfig,
    Comparison,
    Estimate,
    Measure,
    censored_median,
    estimate,
    mann_whitney,
)
from derl.envs.registry import TEST_TASKS, WORLDS

METRICS = ("reward", "cost_of_work")


class TestResult(Record):
    """One evaluation (a row of tests.csv)."""

    __test__ = False  # not a pytest class
    run: str
    world: str
    agent: str
    task: str
    seed: int
    steps: int | None
    """Its training budget in env steps (None: unknown)."""
    reward: float
    cost_of_work: float


class TaskSummary(Record):
    """Medians of one world on one task at one budget (a row of test_summary.csv)."""

    steps: int | None
    world: str
    task: str
    reward: Estimate
    cost_of_work: Estimate


class WorldComparison(Record):
    """Mann-Whitney U test of two worlds on one task and metric at one budget."""

    steps: int | None
    task: str
    metric: str
    world_a: str
    world_b: str
    test: Comparison


def results(runs: list[RunLog]) -> tuple[list[TestResult], int]:
    """Every evaluation of the runs, each body's training once; and how many were left out as
    the same body's training again."""
    rows, seen = [], set()
    for run in runs:
        index = {body.id: i for i, body in enumerate(run.bodies)}
        for evaluation in run.evaluations:
            i = index.get(evaluation.agent)
            body = evaluation.agent if i is None else run.body_keys[i]
            training = (run.world, body, evaluation.task, evaluation.seed, evaluation.steps)
            if training not in seen:
                seen.add(training)
                rows.append(TestResult(run=run.name, world=run.world, **evaluation.model_dump()))
    return rows, sum(len(run.evaluations) for run in runs) - len(rows)


def budgets(rows: list[TestResult]) -> list[int | None]:
    """The budgets present, largest first; an unknown budget (None) last."""
    known = sorted({r.steps for r in rows if r.steps is not None}, reverse=True)
    return known + ([None] if any(r.steps is None for r in rows) else [])


def budget_label(steps: int | None) -> str:
    return "budget unknown" if steps is None else f"{steps:,} env steps"


def _measure(rows: list[TestResult], world: str, task: str, metric: str) -> Measure:
    """`metric` of a world's results on a task; a cost of work censored where the reward is not
    positive."""
    mine = [r for r in rows if r.world == world and r.task == task]
    values = np.array([getattr(r, metric) for r in mine], dtype=float)
    if metric == "reward":
        return Measure.exact(values)
    none = np.isnan(values) & np.array([r.reward <= 0 for r in mine], dtype=bool)
    return Measure(np.where(none, np.inf, values), none)


def _estimate(measure: Measure, config: BootstrapConfig) -> Estimate:
    if measure.censored.any():
        return censored_median(measure.values, measure.censored, config.confidence)
    return estimate(measure.values, config, "median")


def tasks_and_worlds(rows: list[TestResult]) -> tuple[list[str], list[str]]:
    """The tasks and worlds present, in the paper's order (tasks as in fig. 4, worlds FT, VT,
    MVT; others after them, as they first appear): the same in every panel and table."""
    return _ordered((r.task for r in rows), TEST_TASKS), _ordered((r.world for r in rows), WORLDS)


def _ordered(names: Iterable[str], order: tuple[str, ...]) -> list[str]:
    present = list(dict.fromkeys(names))
    return sorted(present, key=lambda n: order.index(n) if n in order else len(order))


def _groups(rows: list[TestResult]) -> list[tuple[int | None, list[TestResult]]]:
    """The results of each budget, largest budget first."""
    return [(steps, [r for r in rows if r.steps == steps]) for steps in budgets(rows)]


def summarize(rows: list[TestResult], config: BootstrapConfig) -> list[TaskSummary]:
    return [
        TaskSummary(
            steps=steps,
            world=world,
            task=task,
            **{m: _estimate(_measure(group, world, task, m), config) for m in METRICS},
        )
        for steps, group in _groups(rows)
        for task in tasks_and_worlds(group)[0]
        for world in tasks_and_worlds(group)[1]
        if any(r.world == world and r.task == task for r in group)
    ]


def compare(rows: list[TestResult]) -> list[WorldComparison]:
    """Every pair of worlds on every task both were tested on at a budget, for reward and cost
    of work."""
    return [
        WorldComparison(
            steps=steps,
            task=task,
            metric=metric,
            world_a=a,
            world_b=b,
            test=mann_whitney(
                _measure(group, a, task, metric).values, _measure(group, b, task, metric).values
            ),
        )
        for steps, group in _groups(rows)
        for task in tasks_and_worlds(group)[0]
        for metric in METRICS
        for a, b in combinations(tasks_and_worlds(group)[1], 2)
        if _measure(group, a, task, metric).values.size
        and _measure(group, b, task, metric).values.size
    ]
