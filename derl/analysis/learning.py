"""Learning speed and the morphological Baldwin effect (the paper's fig. 5a, 5c, 5d and 6).

A body's learning speed is the number of env steps at which its learning curve first reaches a
criterion: the 75th percentile of the initial population's fitness. A body that never reaches it
has no learning speed (NaN): it is counted and left out, never given a made-up value. The top
agents' ancestors are followed generation by generation: at generation g, each top agent
contributes the value of its ancestor at depth g (the paper's "as a function of generations").
"""

from __future__ import annotations

import numpy as np

from derl.analysis.lineage import Tree
from derl.analysis.records import Body, RunLog
from derl.analysis.statistics import BootstrapConfig, Point, point


def criterion(run: RunLog, percentile: float) -> float:
    """The given percentile of the initial population's fitness."""
    initial = run.fitness[[body.parent is None for body in run.bodies]]
    return float(np.percentile(initial, percentile))


def steps_to_reach(body: Body, level: float) -> float:
    """Env steps at which the learning curve first reaches `level` (NaN if it never does)."""
    returns = np.asarray(body.curve_returns, dtype=float)
    reached = np.flatnonzero(returns >= level)
    return float(body.curve_steps[reached[0]]) if reached.size else float("nan")


def learning_speed(run: RunLog, level: float) -> np.ndarray:
    """`steps_to_reach` of every body."""
    return np.array([steps_to_reach(body, level) for body in run.bodies])


def top_agents(run: RunLog, count: int) -> np.ndarray:
    """The `count` fittest bodies of the run, fittest first (earlier birth first among equals)."""
    return np.argsort(-run.fitness, kind="stable")[:count]


def by_generation(
    tree: Tree, agents: np.ndarray, values: np.ndarray, config: BootstrapConfig
) -> list[Point]:
    """Mean (with CI) over `agents` of the value of their ancestor at each generation."""
    chains = [tree.ancestry(int(a)) for a in agents]
    depth = max((len(chain) for chain in chains), default=0)
    return [
        point(g, [values[chain[g]] for chain in chains if len(chain) > g], config)
        for g in range(depth)
    ]
