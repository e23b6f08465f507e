"""Every measurement of a report, computed once from the runs' records (no files, no plots).

`analyse` gives per run: the tree, lineages, Muller abundances, morphology, learning speed and
the run's own time and generation series; per world (its runs pooled, as the paper pools its 3
runs an environment): the top agents, the series of figs. 2a, 3 and 5a-c and the numbers of
fig. 5d; across runs: the fig. 6 correlations (a world's top agents, and all bodies) and the
fig. 4 test-suite statistics.

A world's top agents follow appendix D where its runs carry retrainings: the `top` (100) best
(run, body) pairs by mean fitness over all the world's retrainings (`by_mean_fitness`); without
them, the fittest bodies of each run in evolution, pooled.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from derl.analysis.config import PAPER_TOP, AnalysisConfig
from derl.analysis.learning import (
    GainSummary,
    LineageGain,
    by_generation,
    criterion,
    learning_speed,
    lineage_gain,
    summarize_gains,
    top_agents,
)
from derl.analysis.lineage import (
    Lineage,
    Muller,
    Tree,
    beneficial,
    fitness_gain,
    lineages,
    muller,
    shared_grid,
    time_grid,
    window,
)
from derl.analysis.morphology import DESCRIPTORS, Morphology, column, measure, over_time
from derl.analysis.records import Record, RunLog
from derl.analysis.selection import by_mean_fitness
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
    """The run's bodies among its world's top agents (figs. 2a right, 5a, 5c, 6)."""
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


TopRule = Literal["retrained", "evolution"]


class WorldSummary(Record):
    """What a world's pooled figures rest on (stats.json "worlds")."""

    world: str
    runs: list[str]
    top_rule: TopRule
    """retrained: the best by mean fitness over the retrainings (appendix D); evolution: the
    fittest of each run in evolution."""
    top_agents: int
    """n of figs. 2a right, 5a, 5c and 6: the world's top agents, its runs pooled."""
    retrained_bodies: int
    retrainings: int
    top_of_population: int
    """n of fig. 2a left at each time: the k fittest of each run's population, pooled."""
    births: int
    """The pooled time axis ends where the shortest of the runs ends."""
    illustrative: LineageGain
    """Fig. 5d: the top agent with the longest ancestry against its founder."""
    gains: GainSummary
    """Fig. 5d pooled: every top agent against its founder, medians."""


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
    """Indices of the run's bodies among its world's top agents, best first."""
    series: dict[str, list[Point]]
    """The run's own curves by name: fitness_top (time), fitness_by_generation, descriptor
    names and passively_stable (time), steps_to_criterion and cost_of_work (by generation)."""

    def values(self, name: Literal["fitness", "cost_of_work", "steps_to_criterion"]) -> np.ndarray:
        """One measurement of every body."""
        if name == "steps_to_criterion":
            return self.speed
        return getattr(self.run, name)


@dataclass(frozen=True)
class TopAgents:
    """A world's top agents, best first: (run name, body index) each, and the rule that chose
    them."""

    rule: TopRule
    agents: list[tuple[str, int]]
    retrained_bodies: int = 0
    retrainings: int = 0

    def of(self, run: str) -> np.ndarray:
        """The body indices of `run`'s top agents, best first."""
        return np.array([i for name, i in self.agents if name == run], dtype=int)


@dataclass(frozen=True)
class WorldAnalysis:
    """A world's runs pooled: the series the figures draw and the fig. 5d numbers."""

    summary: WorldSummary
    runs: list[RunAnalysis]
    series: dict[str, list[Point]]
    """The same curves as `RunAnalysis.series`, every run of the world pooled at each x (a
    world of one run: its run's)."""
    illustrative: tuple[RunAnalysis, int]
    """Fig. 5d's agent: the top agent with the longest ancestry (the best among those)."""


@dataclass(frozen=True)
class Analysis:
    config: AnalysisConfig
    runs: list[RunAnalysis]
    worlds: list[WorldAnalysis]
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
    worlds = list(dict.fromkeys(run.world for run in runs))
    tops = {w: world_top([run for run in runs if run.world == w], config) for w in worlds}
    analysed = [analyse_run(run, config, tops[run.world].of(run.name)) for run in runs]
    tests = results(runs)
    return Analysis(
        config=config,
        runs=analysed,
        worlds=[
            analyse_world([r for r in analysed if r.run.world == w], tops[w], config)
            for w in worlds
        ],
        correlations=correlations(analysed),
        tests=tests,
        test_summary=summarize(tests, config.bootstrap),
        comparisons=compare(tests),
    )


def world_top(runs: list[RunLog], config: AnalysisConfig) -> TopAgents:
    """The top agents of one world's runs: by mean retrained fitness where there are
    retrainings (appendix D), else each run's fittest in evolution, pooled."""
    retrained = [((run.name, t.agent), t.fitness) for run in runs for t in run.retrained]
    if not retrained:
        pooled = [
            (run.name, int(i), run.fitness[i])
            for run in runs
            for i in top_agents(run, config.top_of(len(run.bodies)))
        ]
        ranked = sorted(pooled, key=lambda agent: -agent[2])
        return TopAgents("evolution", [(name, i) for name, i, _ in ranked])
    index = {run.name: {body.id: i for i, body in enumerate(run.bodies)} for run in runs}
    means = by_mean_fitness(retrained)
    unknown = [f"{name}/{agent}" for (name, agent), _ in means if agent not in index[name]]
    if unknown:
        raise ValueError(f"retrained bodies that were never born: {', '.join(unknown[:5])}")
    return TopAgents(
        "retrained",
        [(name, index[name][agent]) for (name, agent), _ in means[: config.top or PAPER_TOP]],
        retrained_bodies=len(means),
        retrainings=len(retrained),
    )


def analyse_run(run: RunLog, config: AnalysisConfig, top: np.ndarray) -> RunAnalysis:
    """Everything of one run; `top` are its bodies among its world's top agents."""
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
    flags = beneficial(run, tree, threshold)
    summary = RunSummary(
        run=run.name,
        world=run.world,
        bodies=len(run.bodies),
        repeats=sum(body.repeat_of is not None for body in run.bodies),
        population=run.population,
        generations=int(tree.generation.max()) + 1,
        top_of_population=config.top_of(run.population),
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
    result = RunAnalysis(
        run=run,
        summary=summary,
        tree=tree,
        lineages=rows,
        muller=muller(run, tree, rows, times, config.muller_lineages, config.star_descendants),
        morphology=morphology,
        speed=speed,
        beneficial=flags,
        top=top,
        series={},
    )
    return replace(result, series=pooled_series([result], times, config))


def pooled_series(
    runs: list[RunAnalysis], times: np.ndarray, config: AnalysisConfig
) -> dict[str, list[Point]]:
    """The curves of figs. 2a, 3 and 5a-c over `runs` pooled: at each time, the k fittest of
    each run's population (fig. 2a left) or its every member; at each generation, the ancestors
    of each run's top agents."""
    boot = config.bootstrap

    def ancestors(name: Literal["fitness", "cost_of_work", "steps_to_criterion"]) -> list[Point]:
        return by_generation([(r.tree, r.top, r.values(name)) for r in runs], boot)

    return {
        "fitness_top": [point(int(t), _fittest_of_each(runs, int(t)), boot) for t in times],
        "fitness_by_generation": ancestors("fitness"),
        "steps_to_criterion": ancestors("steps_to_criterion"),
        "cost_of_work": ancestors("cost_of_work"),
        **{
            name: over_time(
                [(column(r.morphology, name), r.run.population) for r in runs], times, boot
            )
            for name in (*DESCRIPTORS, "passively_stable")
        },
    }


def _fittest_of_each(runs: list[RunAnalysis], t: int) -> np.ndarray:
    """The k fittest of each run's population after t births, together (n = runs x k)."""
    return np.concatenate(
        [
            _fittest(r.run.fitness[window(t, r.run.population)], r.summary.top_of_population)
            for r in runs
        ]
    )


def _fittest(values: np.ndarray, k: int) -> np.ndarray:
    """The k largest values."""
    return np.sort(values)[::-1][:k]


def analyse_world(runs: list[RunAnalysis], top: TopAgents, config: AnalysisConfig) -> WorldAnalysis:
    """One world's runs pooled, with its top agents `top`."""
    by_name = {r.run.name: r for r in runs}
    members = [(by_name[name], i) for name, i in top.agents]
    depth = [r.tree.generation[i] for r, i in members]
    deepest = depth.index(max(depth))  # the first of the deepest: the best ranked
    gains = [lineage_gain(r.run, r.tree, i, r.summary.criterion) for r, i in members]
    times = shared_grid([r.run for r in runs], config.time_points)
    summary = WorldSummary(
        world=runs[0].run.world,
        runs=list(by_name),
        top_rule=top.rule,
        top_agents=len(members),
        retrained_bodies=top.retrained_bodies,
        retrainings=top.retrainings,
        top_of_population=sum(r.summary.top_of_population for r in runs),
        births=int(times[-1]),
        illustrative=gains[deepest],
        gains=summarize_gains(gains),
    )
    return WorldAnalysis(
        summary=summary,
        runs=runs,
        series=runs[0].series if len(runs) == 1 else pooled_series(runs, times, config),
        illustrative=members[deepest],
    )


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
