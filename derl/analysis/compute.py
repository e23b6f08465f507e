"""Every measurement of a report, computed once from the runs' records (no files, no plots).

`analyse` gives per run: the tree, lineages, Muller abundances, morphology, learning speed and
the time and generation series of figs. 2a, 3 and 5; across runs: the fig. 6 correlations
(top agents of each world's runs pooled, and all bodies) and the fig. 4 test-suite statistics.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from derl.analysis.config import AnalysisConfig
from derl.analysis.learning import by_generation, criterion, learning_speed, top_agents
from derl.analysis.lineage import (
    Lineage,
    Muller,
    Tree,
    beneficial,
    fitness_gain,
    lineages,
    muller,
    time_grid,
    window,
)
from derl.analysis.morphology import DESCRIPTORS, Morphology, column, measure, over_time
from derl.analysis.records import Record, RunLog
from derl.analysis.statistics import Correlation, Point, pearson, point
from derl.analysis.testsuite import (
    TaskSummary,
    TestResult,
    WorldComparison,
    compare,
    results,
    summarize,
)


class RunSummary(Record):
    """The sizes and thresholds a run's figures rest on (stats.json "runs")."""

    run: str
    world: str
    bodies: int
    repeats: int
    """Bodies born as repeats of an earlier equal body, with its result (never trained)."""
    population: int
    generations: int
    top_of_population: int
    """k of fig. 2a's left panel: the fittest k of the population at each time."""
    top_agents: int
    """The run's fittest bodies followed over generations (figs. 2a right, 5a, 5c, 6)."""
    beneficial_threshold: float
    beneficial_mutations: int
    gain_p75: float | None
    """75th percentile of the positive fitness gains of all mutations (how the paper set its
    thresholds), None without any."""
    criterion: float
    """Fitness criterion of learning speed: percentile of the initial population's fitness."""
    learning_speed_defined: int
    learning_speed_undefined: int
    """Bodies whose curve never reached the criterion (left out of figs. 5a and 6b)."""
    stability_simulated: int
    surviving_lineages: int


class CorrelationRow(Record):
    world: str
    agents: Literal["top", "all"]
    x: str
    y: str
    correlation: Correlation


@dataclass(frozen=True)
class RunAnalysis:
    run: RunLog
    summary: RunSummary
    tree: Tree
    lineages: list[Lineage]
    muller: Muller
    morphology: list[Morphology]
    speed: np.ndarray
    """Env steps to reach the criterion, per body (NaN: never)."""
    beneficial: np.ndarray
    top: np.ndarray
    """Indices of the top agents, fittest first."""
    series: dict[str, list[Point]]
    """Curves by name: fitness_top (time), fitness_by_generation, descriptor names and
    passively_stable (time), steps_to_criterion and cost_of_work (by generation)."""

    @property
    def illustrative(self) -> int:
        """The top agent with the longest ancestry (the fittest among those): fig. 5d's."""
        return max(self.top.tolist(), key=lambda i: (self.tree.generation[i], self.run.fitness[i]))

    def values(self, name: Literal["fitness", "cost_of_work", "steps_to_criterion"]) -> np.ndarray:
        """One measurement of every body."""
        if name == "steps_to_criterion":
            return self.speed
        return getattr(self.run, name)


@dataclass(frozen=True)
class Analysis:
    config: AnalysisConfig
    runs: list[RunAnalysis]
    correlations: list[CorrelationRow]
    tests: list[TestResult]
    test_summary: list[TaskSummary]
    comparisons: list[WorldComparison]


def analyse(runs: list[RunLog], config: AnalysisConfig) -> Analysis:
    if not runs:
        raise ValueError("no runs to analyse")
    names = [run.name for run in runs]
    if len(set(names)) != len(names):
        raise ValueError(f"runs must have distinct names: {names}")
    analysed = [analyse_run(run, config) for run in runs]
    tests = results(runs)
    return Analysis(
        config=config,
        runs=analysed,
        correlations=correlations(analysed),
        tests=tests,
        test_summary=summarize(tests, config.bootstrap),
        comparisons=compare(tests),
    )


def analyse_run(run: RunLog, config: AnalysisConfig) -> RunAnalysis:
    if not run.bodies:
        raise ValueError(f"{run.name}: no body was born")
    tree = Tree.of(run)
    threshold = config.threshold(run.world)
    rows = lineages(run, tree, threshold)
    times = time_grid(run, config.time_points)
    morphology = measure(run, config.stability_sample, config.processes)
    level = criterion(run, config.criterion_percentile)
    speed = learning_speed(run, level)
    gains = fitness_gain(run, tree)
    rises = gains[gains > 0]
    k_population = config.top_of(run.population)
    top = top_agents(run, config.top_of(len(run.bodies)))
    boot = config.bootstrap
    series = {
        "fitness_top": [
            point(int(t), _fittest(run.fitness[window(int(t), run.population)], k_population), boot)
            for t in times
        ],
        "fitness_by_generation": by_generation(tree, top, run.fitness, boot),
        "steps_to_criterion": by_generation(tree, top, speed, boot),
        "cost_of_work": by_generation(tree, top, run.cost_of_work, boot),
        **{
            name: over_time(column(morphology, name), times, run.population, boot)
            for name in (*DESCRIPTORS, "passively_stable")
        },
    }
    flags = beneficial(run, tree, threshold)
    summary = RunSummary(
        run=run.name,
        world=run.world,
        bodies=len(run.bodies),
        repeats=sum(body.repeat_of is not None for body in run.bodies),
        population=run.population,
        generations=int(tree.generation.max()) + 1,
        top_of_population=k_population,
        top_agents=top.size,
        beneficial_threshold=threshold,
        beneficial_mutations=int(flags.sum()),
        gain_p75=float(np.percentile(rises, 75)) if rises.size else None,
        criterion=level,
        learning_speed_defined=int(np.isfinite(speed).sum()),
        learning_speed_undefined=int(np.isnan(speed).sum()),
        stability_simulated=sum(m.passively_stable is not None for m in morphology),
        surviving_lineages=sum(row.surviving for row in rows),
    )
    return RunAnalysis(
        run=run,
        summary=summary,
        tree=tree,
        lineages=rows,
        muller=muller(run, tree, rows, times, config.muller_lineages, config.star_descendants),
        morphology=morphology,
        speed=speed,
        beneficial=flags,
        top=top,
        series=series,
    )


def _fittest(values: np.ndarray, k: int) -> np.ndarray:
    """The k largest values."""
    return np.sort(values)[::-1][:k]


def correlations(runs: list[RunAnalysis]) -> list[CorrelationRow]:
    """Fig. 6: cost of work against fitness and against learning speed, per world, for the top
    agents of its runs pooled and for all their bodies."""
    rows = []
    for world in dict.fromkeys(r.run.world for r in runs):
        mine = [r for r in runs if r.run.world == world]
        for agents in ("top", "all"):
            chosen = [r.top if agents == "top" else slice(None) for r in mine]
            cost = _pooled(mine, chosen, "cost_of_work")
            for y in ("fitness", "steps_to_criterion"):
                rows.append(
                    CorrelationRow(
                        world=world,
                        agents=agents,
                        x="cost_of_work",
                        y=y,
                        correlation=pearson(cost, _pooled(mine, chosen, y)),
                    )
                )
    return rows


def _pooled(runs: list[RunAnalysis], chosen: list, name: str) -> np.ndarray:
    """`name` of the chosen bodies of each run, concatenated."""
    return np.concatenate([r.values(name)[c] for r, c in zip(runs, chosen, strict=True)])
