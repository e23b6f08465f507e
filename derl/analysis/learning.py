"""Learning speed and the morphological Baldwin effect (the paper's fig. 5a, 5c, 5d and 6).

A body's learning speed is the number of env steps at which its learning curve first reaches a
criterion: the 75th percentile of the initial population's fitness. A body that never reaches it
is censored: it needs more than its whole budget (the last step of its curve), and is counted so
(`statistics.censored_median`), never left out nor given a made-up value. The top agents'
ancestors are followed generation by generation (the paper's "as a function of generations"):
at generation g, the top agents' ancestors at depth g, each body once however many top agents
descend from it (the few founders of the fittest lineages would otherwise count up to once per
top agent), pooled over the runs of a world. Fig. 5d's numbers compare a lineage's founder with
its last generation: how much more it reaches at the end of learning and how much sooner it
learns.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from derl.analysis.lineage import Tree
from derl.analysis.records import Body, Record, RunLog
from derl.analysis.statistics import Estimate, Measure, Point


def criterion(run: RunLog, percentile: float) -> float:
    """The given percentile of the initial population's fitness."""
    return criterion_of(run.fitness[[body.parent is None for body in run.bodies]], percentile)


def criterion_of(initial_fitness: Sequence[float] | np.ndarray, percentile: float) -> float:
    """The learning criterion: the given percentile of the initial population's fitness."""
    return float(np.percentile(initial_fitness, percentile))


def steps_to_reach(body: Body, level: float) -> float:
    """Env steps at which the learning curve first reaches `level` (NaN if it never does)."""
    return first_reaching(body.curve_steps, body.curve_returns, level)


def first_reaching(steps: Sequence[int], returns: Sequence[float], level: float) -> float:
    """Env steps at which a learning curve (`returns` after `steps`) first reaches `level`
    (NaN if it never does)."""
    reached = np.flatnonzero(np.asarray(returns, dtype=float) >= level)
    return float(steps[reached[0]]) if reached.size else float("nan")


def learning_speed(run: RunLog, level: float) -> Measure:
    """`steps_to_reach` of every body; censored at its budget (the last step of its curve)
    where it never reaches `level`, missing (NaN) without a curve."""
    steps = np.array([steps_to_reach(body, level) for body in run.bodies])
    budget = np.array([body.curve_steps[-1] if body.curve_steps else np.nan for body in run.bodies])
    never = np.isnan(steps) & ~np.isnan(budget)
    return Measure(np.where(never, budget, steps), never)


def cost_of_work(run: RunLog) -> Measure:
    """Every body's cost of work; where it is undefined because the reward was not positive
    (energy spent for no work), censored beyond every measured value (+inf)."""
    cost = run.cost_of_work
    none = np.isnan(cost) & (run.fitness <= 0)
    return Measure(np.where(none, np.inf, cost), none)


def top_agents(run: RunLog, count: int, counted: np.ndarray) -> np.ndarray:
    """The `count` fittest of the `counted` bodies of the run, fittest first (earlier birth
    first among equals)."""
    order = np.argsort(-run.fitness, kind="stable")
    return order[counted[order]][:count]


def generations(tree: Tree, agents: np.ndarray, original: np.ndarray) -> list[np.ndarray]:
    """Per generation g, the ancestors at depth g of `agents` (an agent of generation g is its
    own), each body once however many agents descend from it (a repeat as its `original`)."""
    layers: list[set[int]] = []
    for agent in agents:
        for g, body in enumerate(tree.ancestry(int(agent))):
            if g == len(layers):
                layers.append(set())
            layers[g].add(int(original[body]))
    return [np.array(sorted(layer), dtype=int) for layer in layers]


def by_generation(
    parts: list[tuple[list[np.ndarray], Measure]], statistic: Callable[[Measure], Estimate]
) -> list[Point]:
    """`statistic` at each generation g of the measure of the bodies at g, over every part
    (`generations` and the measure of one run's bodies)."""
    depth = max((len(layers) for layers, _ in parts), default=0)
    return [
        Point(
            x=g,
            **statistic(
                Measure.concat([values[layers[g]] for layers, values in parts if len(layers) > g])
            ).model_dump(),
        )
        for g in range(depth)
    ]


class LineageGain(Record):
    """Fig. 5d's comparison of a lineage's first generation (its founder) with a descendant."""

    run: str
    first: str
    last: str
    generations: int
    """Generations from the founder to the descendant."""
    first_return: float | None
    last_return: float | None
    """The last point of each learning curve (None without a curve)."""
    return_ratio: float | None
    """last_return / first_return (None unless both are known and the first is positive)."""
    first_steps: float | None
    last_steps: float | None
    """Env steps each needs to reach the learning criterion (None: never)."""
    speedup: float | None
    """first_steps / last_steps: how many times sooner the descendant reaches the criterion."""
    last_steps_to_first_return: float | None
    """Env steps the descendant needs to reach the founder's final return (None: never)."""


def _final(body: Body) -> float | None:
    return float(body.curve_returns[-1]) if body.curve_returns else None


def _known(value: float) -> float | None:
    return None if np.isnan(value) else value


def _ratio(a: float | None, b: float | None) -> float | None:
    return a / b if a is not None and b is not None and b > 0 else None


def lineage_gain(run: RunLog, tree: Tree, agent: int, level: float) -> LineageGain:
    """How `agent` learns compared with its lineage's founder, against the criterion `level`."""
    first, last = run.bodies[int(tree.founder[agent])], run.bodies[agent]
    first_return, last_return = _final(first), _final(last)
    first_steps = _known(steps_to_reach(first, level))
    last_steps = _known(steps_to_reach(last, level))
    catch_up = None if first_return is None else _known(steps_to_reach(last, first_return))
    return LineageGain(
        run=run.name,
        first=first.id,
        last=last.id,
        generations=int(tree.generation[agent]),
        first_return=first_return,
        last_return=last_return,
        return_ratio=_ratio(last_return, first_return),
        first_steps=first_steps,
        last_steps=last_steps,
        speedup=_ratio(first_steps, last_steps),
        last_steps_to_first_return=catch_up,
    )


class GainSummary(Record):
    """Medians of `LineageGain` over the top agents of a world that descend from a founder (the
    founders among them are left out: they have nothing to compare with)."""

    agents: int
    return_ratio: float | None
    speedup: float | None
    first_steps: float | None
    last_steps: float | None
    speedup_defined: int
    """Agents whose founder and themselves both reach the criterion (the speedup's n)."""


def _median(values: list[float | None]) -> float | None:
    known = [v for v in values if v is not None]
    return float(np.median(known)) if known else None


def summarize_gains(gains: list[LineageGain]) -> GainSummary:
    descended = [g for g in gains if g.generations > 0]
    return GainSummary(
        agents=len(descended),
        return_ratio=_median([g.return_ratio for g in descended]),
        speedup=_median([g.speedup for g in descended]),
        first_steps=_median([g.first_steps for g in descended]),
        last_steps=_median([g.last_steps for g in descended]),
        speedup_defined=sum(g.speedup is not None for g in descended),
    )
