"""Every measurement of a report, computed once from the runs' records (no files, no plots).

`analyse` gives per run: the tree, lineages, Muller abundances, morphology, learning speed and
the run's own time and generation series; per world (its runs pooled, as the paper pools its 3
runs an environment): the top agents, the series of figs. 2a, 3 and 5a-c and the numbers of
fig. 5d; across runs: the fig. 6 correlations (a world's top agents, and all bodies) and the
fig. 4 test-suite statistics.

A world's top agents follow appendix D where its runs carry retrainings: the `top` (100) best
bodies by mean fitness over the world's retrainings (`rank_by_mean`: only bodies with every
seed's result); without them, the fittest bodies of each run in evolution, pooled.

What counts once: the population (figs. 2a left, 3, 5b, the Muller diagrams) holds every birth,
repeats included, as the population did; whatever is about bodies (the top agents, the
selection, fig. 6's bodies, the test suite, the beneficial mutations, the pictures) counts each
body once per world, as its first birth (`WorldBodies`); the quarters of births count each body
once per quarter, the top agents' ancestors each once per generation. Censored values (never
reaching the learning criterion, no positive reward) are counted, never dropped (`statistics`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from derl.analysis.config import PAPER_TOP, AnalysisConfig
from derl.analysis.learning import (
    GainSummary,
    LineageGain,
    by_generation,
    cost_of_work,
    criterion,
    generations,
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
    new_mutations,
    shared_grid,
    time_grid,
    window,
)
from derl.analysis.morphology import DESCRIPTORS, Morphology, column, measure, over_time
from derl.analysis.progress import Quarters, Replicates, quarters, replicates
from derl.analysis.records import Record, RunLog
from derl.analysis.selection import rank_by_mean
from derl.analysis.statistics import (
    Correlation,
    Estimate,
    Measure,
    Point,
    censored_median,
    estimate,
    pearson,
    point,
    spearman,
)
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
    """Births."""
    distinct_bodies: int
    repeats: int
    """Births of a body born before in the run (`body_hash`): counted once, as its first birth,
    wherever bodies are counted (bodies - distinct_bodies)."""
    population: int
    generations: int
    top_of_population: int
    """k of fig. 2a's left panel: the fittest k of the population at each time."""
    top_agents: int
    """The run's bodies among its world's top agents (figs. 2a right, 5a, 5c, 6)."""
    beneficial_threshold: float
    beneficial_mutations: int
    """Mutations made for the first time (`lineage.new_mutations`) with a gain >= threshold."""
    gain_p75: float | None
    """75th percentile of the positive fitness gains of all mutations (each once: how the paper
    set its thresholds), None without any."""
    criterion: float
    """Fitness criterion of learning speed: percentile of the initial population's fitness."""
    criterion_reached: int
    criterion_censored: int
    """Distinct bodies whose curve never reached the criterion within their budget: censored,
    counted in figs. 5a and 6b (Kaplan-Meier medians, Spearman's rank correlation)."""
    no_positive_reward: int
    """Distinct bodies whose fitness is not positive: their cost of work is censored (beyond
    every measured one), counted in figs. 5c and 6."""
    stability_simulated: int
    surviving_lineages: int
    quarters: Quarters | None
    """The median fitness of the distinct bodies of the first and last quarter of births and its
    difference (lineages resampled)."""
    fingerprint: str | None
    """A hash of its births (`derl.evolution.fingerprint`), where it was read from a journal."""
    audited: int
    """Births from two trainings by two trainer identities that agreed (an audit)."""
    quarantined: tuple[str, ...]
    """Trainer identities caught lying by an audit (their unchecked births trained again)."""


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
    """Retraining results counted: one per body and seed."""
    retrainings_repeated: int
    """Results of a body's retraining with a seed counted already (a repeat, or the same body
    selected in another run, retrained again): the same training, left out."""
    partially_retrained: int
    """Retrained bodies without a result for every seed: not ranked."""
    shared_bodies: int
    """Bodies born in an earlier run of the world too: counted once, in the first run."""
    top_of_population: int
    """n of fig. 2a left at each time: the k fittest of each run's population, pooled."""
    births: int
    """The pooled time axis ends where the shortest of the runs ends."""
    illustrative: LineageGain
    """Fig. 5d: the top agent with the longest ancestry against its founder."""
    gains: GainSummary
    """Fig. 5d pooled: every top agent against its founder, medians."""
    replicates: Replicates | None = None
    """Its runs as replicates (seeds): each run's last quarter against its first, compared
    across runs (`derl.analysis.progress`); None below two runs."""


class CorrelationRow(Record):
    """Fig. 6: cost of work (x) against y for a world's top agents or all its bodies, pooled
    over every generation (generation None) or at one: Pearson's r over the measured values
    (the paper's) and Spearman's rank correlation counting the censored ones."""

    world: str
    agents: Literal["top", "all"]
    generation: int | None
    x: str
    y: str
    pearson: Correlation
    spearman: Correlation


@dataclass(frozen=True)
class RunAnalysis:
    run: RunLog
    summary: RunSummary
    tree: Tree
    lineages: list[Lineage]
    muller: Muller
    morphology: list[Morphology]
    measures: dict[str, Measure]
    """Every body's fitness, cost_of_work and steps_to_criterion (censored where never
    reached, or where the reward is not positive)."""
    counted: np.ndarray
    """Which bodies count as bodies: the first birth of each body in its world."""
    beneficial: np.ndarray
    top: np.ndarray
    """Indices of the run's bodies among its world's top agents, best first."""
    series: dict[str, list[Point]]
    """The run's own curves by name: fitness_top (time), fitness_by_generation, descriptor
    names and passively_stable (time), steps_to_criterion and cost_of_work (by generation)."""


@dataclass(frozen=True)
class WorldBodies:
    """Each body of a world's runs once: its first birth, in the runs' order."""

    first: dict[str, tuple[str, int]]
    """Body identity -> (run, index) of its first birth."""
    counted: dict[str, np.ndarray]
    """Per run, which of its births are a body's first."""
    shared: int
    """Bodies new in their run but born in an earlier run too."""

    @classmethod
    def of(cls, runs: list[RunLog]) -> WorldBodies:
        first: dict[str, tuple[str, int]] = {}
        counted = {}
        for run in runs:
            counted[run.name] = np.array(
                [first.setdefault(key, (run.name, i)) == (run.name, i)
                 for i, key in enumerate(run.body_keys)], dtype=bool,
            )  # fmt: skip
        shared = sum(int((r.distinct & ~counted[r.name]).sum()) for r in runs)
        return cls(first, counted, shared)


@dataclass(frozen=True)
class TopAgents:
    """A world's top agents, best first: (run name, body index) each, and the rule that chose
    them."""

    rule: TopRule
    agents: list[tuple[str, int]]
    retrained_bodies: int = 0
    retrainings: int = 0
    retrainings_repeated: int = 0
    partially_retrained: int = 0

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
    tests_repeated: int
    """Evaluations left out as the same body's training again."""
    test_summary: list[TaskSummary]
    comparisons: list[WorldComparison]


def analyse(runs: list[RunLog], config: AnalysisConfig) -> Analysis:
    if not runs:
        raise ValueError("no runs to analyse")
    names = [run.name for run in runs]
    if len(set(names)) != len(names):
        raise ValueError(f"runs must have distinct names: {names}")
    first: dict[str, str] = {}
    for run in runs:
        if (
            run.fingerprint is not None
            and (same := first.setdefault(run.fingerprint, run.name)) != run.name
        ):
            raise ValueError(
                f"{same} and {run.name} are the same run (fingerprint {run.fingerprint}: the same "
                "births): pooled, its births would count twice; give it once"
            )
    worlds = list(dict.fromkeys(run.world for run in runs))
    mine = {w: [run for run in runs if run.world == w] for w in worlds}
    bodies = {w: WorldBodies.of(mine[w]) for w in worlds}
    tops = {w: world_top(mine[w], bodies[w], config) for w in worlds}
    analysed = [
        analyse_run(run, config, tops[run.world].of(run.name), bodies[run.world].counted[run.name])
        for run in runs
    ]
    tests, repeated = results(runs)
    return Analysis(
        config=config,
        runs=analysed,
        worlds=[
            analyse_world([r for r in analysed if r.run.world == w], tops[w], bodies[w], config)
            for w in worlds
        ],
        correlations=correlations(analysed),
        tests=tests,
        tests_repeated=repeated,
        test_summary=summarize(tests, config.bootstrap),
        comparisons=compare(tests),
    )


def world_top(runs: list[RunLog], bodies: WorldBodies, config: AnalysisConfig) -> TopAgents:
    """The top agents of one world's runs, each body once (as its first birth): by mean
    retrained fitness where there are retrainings (appendix D), else each run's fittest in
    evolution, pooled."""
    if not any(run.retrained for run in runs):
        fittest = [
            (run.name, int(i), run.fitness[i])
            for run in runs
            for i in top_agents(run, config.top_of(len(run.bodies)), bodies.counted[run.name])
        ]
        ranked = sorted(fittest, key=lambda agent: -agent[2])
        return TopAgents("evolution", [(name, i) for name, i, _ in ranked])
    results, unknown = [], []
    for run in runs:
        index = {body.id: i for i, body in enumerate(run.bodies)}
        for t in run.retrained:
            if t.agent not in index:
                unknown.append(f"{run.name}/{t.agent}")
            else:
                results.append((run.body_keys[index[t.agent]], (t.seed, t.steps), t.fitness))
    if unknown:
        raise ValueError(f"retrained bodies that were never born: {', '.join(unknown[:5])}")
    ranking = rank_by_mean(results)
    return TopAgents(
        "retrained",
        [bodies.first[key] for key, _ in ranking.ranked[: config.top or PAPER_TOP]],
        retrained_bodies=len(ranking.ranked) + len(ranking.partial),
        retrainings=ranking.results,
        retrainings_repeated=ranking.duplicates,
        partially_retrained=len(ranking.partial),
    )


def analyse_run(
    run: RunLog, config: AnalysisConfig, top: np.ndarray, counted: np.ndarray
) -> RunAnalysis:
    """Everything of one run; `top` are its bodies among its world's top agents, `counted` its
    births that are the first of their body in the world."""
    if not run.bodies:
        raise ValueError(f"{run.name}: no body was born")
    tree = Tree.of(run)
    threshold = config.threshold(run.world)
    rows = lineages(run, tree, threshold)
    times = time_grid(run, config.time_points)
    morphology = measure(run, config.stability_sample, config.processes)
    level = criterion(run, config.criterion_percentile)
    speed, cost = learning_speed(run, level), cost_of_work(run)
    gains = fitness_gain(run, tree)
    rises = gains[new_mutations(run, tree) & (gains > 0)]
    flags = beneficial(run, tree, threshold)
    new = run.distinct
    summary = RunSummary(
        run=run.name,
        world=run.world,
        bodies=len(run.bodies),
        distinct_bodies=int(new.sum()),
        repeats=int((~new).sum()),
        population=run.population,
        generations=int(tree.generation.max()) + 1,
        top_of_population=config.top_of(run.population),
        top_agents=top.size,
        beneficial_threshold=threshold,
        beneficial_mutations=int(flags.sum()),
        gain_p75=float(np.percentile(rises, 75)) if rises.size else None,
        criterion=level,
        criterion_reached=int((new & ~speed.censored & ~np.isnan(speed.values)).sum()),
        criterion_censored=int((new & speed.censored).sum()),
        no_positive_reward=int((new & cost.censored).sum()),
        stability_simulated=sum(m.passively_stable is not None for m in morphology),
        surviving_lineages=sum(row.surviving for row in rows),
        quarters=quarters(run, tree, config.bootstrap),
        fingerprint=run.fingerprint,
        audited=run.audited,
        quarantined=run.quarantined,
    )
    result = RunAnalysis(
        run=run,
        summary=summary,
        tree=tree,
        lineages=rows,
        muller=muller(run, tree, rows, times, config.muller_lineages, config.star_descendants),
        morphology=morphology,
        measures={
            "fitness": Measure.exact(run.fitness),
            "cost_of_work": cost,
            "steps_to_criterion": speed,
        },
        counted=counted,
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
    of each run's top agents, each once (fitness: mean; steps to the criterion and cost of work:
    their Kaplan-Meier median, censored values counted)."""
    boot = config.bootstrap

    def mean(values: Measure) -> Estimate:
        return estimate(values.values, boot)

    def median(values: Measure) -> Estimate:
        return censored_median(values.values, values.censored, boot.confidence)

    def ancestors(name: str, statistic: Callable[[Measure], Estimate]) -> list[Point]:
        layers = [(generations(r.tree, r.top, r.run.original), r.measures[name]) for r in runs]
        return by_generation(layers, statistic)

    return {
        "fitness_top": [point(int(t), _fittest_of_each(runs, int(t)), boot) for t in times],
        "fitness_by_generation": ancestors("fitness", mean),
        "steps_to_criterion": ancestors("steps_to_criterion", median),
        "cost_of_work": ancestors("cost_of_work", median),
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


def analyse_world(
    runs: list[RunAnalysis], top: TopAgents, bodies: WorldBodies, config: AnalysisConfig
) -> WorldAnalysis:
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
        retrainings_repeated=top.retrainings_repeated,
        partially_retrained=top.partially_retrained,
        shared_bodies=bodies.shared,
        top_of_population=sum(r.summary.top_of_population for r in runs),
        births=int(times[-1]),
        illustrative=gains[deepest],
        gains=summarize_gains(gains),
        replicates=replicates(
            [(r.run.name, r.summary.quarters) for r in runs if r.summary.quarters is not None],
            config.bootstrap,
        ),
    )
    return WorldAnalysis(
        summary=summary,
        runs=runs,
        series=runs[0].series if len(runs) == 1 else pooled_series(runs, times, config),
        illustrative=members[deepest],
    )


def correlations(runs: list[RunAnalysis]) -> list[CorrelationRow]:
    """Fig. 6: cost of work against fitness and against learning speed, per world, for the top
    agents of its runs pooled and for all their bodies (each once), over every generation and
    at each generation."""
    rows = []
    for world in dict.fromkeys(r.run.world for r in runs):
        mine = [r for r in runs if r.run.world == world]
        for agents in ("top", "all"):
            chosen = [r.top if agents == "top" else np.flatnonzero(r.counted) for r in mine]
            generation = np.concatenate(
                [r.tree.generation[c] for r, c in zip(mine, chosen, strict=True)]
            )
            cost = pooled(mine, chosen, "cost_of_work")
            for y in ("fitness", "steps_to_criterion"):
                values = pooled(mine, chosen, y)
                for g in (None, *np.unique(generation).tolist()):
                    at = slice(None) if g is None else generation == g
                    x_at, y_at = cost[at], values[at]
                    rows.append(
                        CorrelationRow(
                            world=world,
                            agents=agents,
                            generation=g,
                            x="cost_of_work",
                            y=y,
                            pearson=pearson(x_at, y_at),
                            spearman=spearman(x_at, y_at),
                        )
                    )
    return rows


def pooled(runs: list[RunAnalysis], chosen: list[np.ndarray], name: str) -> np.ndarray:
    """`name` of the chosen bodies of each run, concatenated, censored values at +inf."""
    return np.concatenate([r.measures[name][c].ranked() for r, c in zip(runs, chosen, strict=True)])
