"""A whole report in a folder: the figures (PNG), the gaits (GIF), the tables (CSV, stats.json)
and index.html.

`write_report(runs, out)` analyses the runs (`compute.analyse`), draws every figure of the paper
that a run's journal supports, films the best bodies' gaits where their checkpoints are at hand,
writes the tables and a page that shows them, and returns what it wrote. Runs of one world are
pooled as the paper pools its 3 runs an environment (figs. 2a, 3, 5, 6); the trees, Muller
diagrams and lineages stay run by run. Captions say what each figure shows, how its top agents
were chosen and how many values each point rests on (n); the notes say what was sampled and
where the data were too few.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict

from derl.analysis import plots
from derl.analysis.compute import Analysis, RunAnalysis, WorldAnalysis, WorldSummary, analyse
from derl.analysis.config import AnalysisConfig
from derl.analysis.gaits import write_gaits
from derl.analysis.page import FigureEntry, write_page
from derl.analysis.progress import describe as describe_quarters
from derl.analysis.progress import describe_replicates
from derl.analysis.records import Body, RunLog
from derl.analysis.tables import write_tables
from derl.analysis.testsuite import budget_label, budgets

log = logging.getLogger("derl.analysis")

PAGE = "index.html"


class ReportFiles(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    page: Path
    figures: list[Path]
    gaits: list[Path]
    tables: list[Path]
    notes: list[str]
    headline: list[str]
    """The numbers `derl report` prints: each run's first and last quarter of births compared,
    what was counted once and what was censored."""


def write_report(
    runs: list[RunLog], out: Path, config: AnalysisConfig | None = None
) -> ReportFiles:
    config = config or AnalysisConfig()
    out.mkdir(parents=True, exist_ok=True)
    log.info("analysing %d run(s): %d bodies", len(runs), sum(len(r.bodies) for r in runs))
    analysis = analyse(runs, config)
    notes = _notes(analysis)
    log.info("drawing figures")
    entries = _figures(analysis, out, notes)
    gaits = write_gaits(_ranked(analysis), config.gaits, out, notes)
    tables = write_tables(analysis, out, notes)
    title = "DERL report: " + ", ".join(f"{r.name} ({r.world.upper()})" for r in runs)
    summaries = [r.summary for r in analysis.runs]
    worlds = [w.summary for w in analysis.worlds]
    lines = headline(analysis)
    page = write_page(out / PAGE, title, lines, entries, summaries, worlds, tables, notes, gaits)
    return ReportFiles(
        page=page,
        figures=[out / e.file for e in entries],
        gaits=[out / g.file for g in gaits],
        tables=tables,
        notes=notes,
        headline=lines,
    )


def headline(analysis: Analysis) -> list[str]:
    """Per run: its first and last quarter of births compared, its repeats and censored bodies;
    per world of a study: how many retrained bodies were ranked."""
    lines = []
    for r in analysis.runs:
        s = r.summary
        if s.quarters is not None:
            lines.append(describe_quarters(s.run, s.quarters, analysis.config.bootstrap))
        lines.append(
            f"{s.run}: {s.bodies} births, {s.distinct_bodies} distinct bodies ({s.repeats} "
            f"repeats, each counted once as its body); of those bodies {s.criterion_censored} "
            f"never reached the learning criterion and {s.no_positive_reward} had no positive "
            "reward: kept as censored values, not dropped"
        )
    for w in analysis.worlds:
        if (replicated := w.summary.replicates) is not None:
            config = analysis.config.bootstrap
            lines.append(describe_replicates(w.summary.world, replicated, config))
        if w.summary.top_rule == "retrained":
            lines.append(f"{w.summary.world.upper()}: top agents are {top_rule(w.summary)}")
    return lines


def _runs_text(analysis: Analysis, what: Callable[[RunAnalysis], str]) -> str:
    """`what` of each run, labelled with the run's name."""
    return "; ".join(f"{r.run.name}: {what(r)}" for r in analysis.runs)


def _worlds_text(analysis: Analysis, what: Callable[[WorldAnalysis], str]) -> str:
    """`what` of each world, labelled with the world and its runs."""
    return "; ".join(
        f"{w.summary.world.upper()} ({', '.join(w.summary.runs)}): {what(w)}"
        for w in analysis.worlds
    )


def top_rule(summary: WorldSummary) -> str:
    """How a world's top agents were chosen, and how many they are."""
    if summary.top_rule == "retrained":
        ranked = summary.retrained_bodies - summary.partially_retrained
        return (
            f"the {summary.top_agents} best of {ranked} retrained bodies by mean fitness over "
            f"{summary.retrainings} retrainings with new seeds (appendix D), its runs pooled, "
            f"each body once; {summary.partially_retrained} bodies without a result for every "
            f"seed are not ranked, {summary.retrainings_repeated} results of a body's retraining "
            "counted already are left out"
        )
    return (
        f"the {summary.top_agents} fittest in evolution (each run's fittest bodies, each body "
        "once, pooled; no retrainings)"
    )


def _gain_text(w: WorldAnalysis) -> str:
    """Fig. 5d's numbers of one world: its illustrative lineage, then medians over its top
    agents."""
    one, many, n = w.summary.illustrative, w.summary.gains, plots.number
    return (
        f"{one.first} (generation 0) to {one.last} (generation {one.generations}): final return "
        f"{n(one.first_return)} to {n(one.last_return)} (x{n(one.return_ratio)}), env steps to "
        f"the criterion {n(one.first_steps)} to {n(one.last_steps)} (x{n(one.speedup)} sooner), "
        f"the founder's final return reached after {n(one.last_steps_to_first_return)} steps; "
        f"over the {many.agents} top agents with a founder before them: median final return "
        f"x{n(many.return_ratio)}, median steps to the criterion {n(many.first_steps)} to "
        f"{n(many.last_steps)}, median speed-up x{n(many.speedup)} (n={many.speedup_defined} "
        "reaching the criterion both)"
    )


def _population_text(w: WorldAnalysis) -> str:
    """n of a world's population means: every run's population, together."""
    sizes = [r.summary.population for r in w.runs]
    return f"n={sum(sizes)} (P={'/'.join(map(str, sizes))})"


def _tests_text(analysis: Analysis) -> str:
    """Fig. 4's groups: the results of each budget."""
    return "; ".join(
        f"{budget_label(steps)}: {sum(t.steps == steps for t in analysis.tests)} results"
        for steps in budgets(analysis.tests)
    )


def _figures(analysis: Analysis, out: Path, notes: list[str]) -> list[FigureEntry]:
    config = analysis.config
    ci = (
        f"{config.bootstrap.confidence:.0%} bootstrapped CIs (scipy, {config.bootstrap.method}, "
        f"{config.bootstrap.n_resamples} resamples)"
    )
    entries = [
        FigureEntry(
            file=plots.fitness(out / "fitness.png", analysis).name,
            title="Fig. 2a: fitness of the top agents",
            caption=(
                "Left (the paper's fig. 2a, as its caption says): mean fitness of the k fittest "
                "members of each run's population (the P most recently born, repeats included as "
                f"the population holds them) after each number of births, with {ci}, the runs of "
                "a world pooled (n = runs x k at each point; the axis ends where the world's "
                "shortest run ends). Right: mean fitness, generation by generation, of the "
                "ancestors of the world's top agents, each ancestor once however many top agents "
                "descend from it (a repeat as its original; n at generation g = the distinct "
                "ancestors at that depth, written at each point). "
                + _worlds_text(
                    analysis,
                    lambda w: (
                        f"n={w.summary.top_of_population} "
                        f"(k={'/'.join(str(r.summary.top_of_population) for r in w.runs)}), "
                        f"{w.summary.births} births; top agents: {top_rule(w.summary)}"
                    ),
                )
            ),
        ),
        FigureEntry(
            file=plots.lineage_scatter(out / "lineages.png", analysis).name,
            title="Fig. 2b: surviving lineages",
            caption=(
                "Each dot is a lineage with members in the final population: its founder's "
                "fitness rank among the initial bodies against its share of the final population; "
                "dot size is the number of beneficial mutations in the lineage (child fitness - "
                "parent fitness >= the world's threshold; the same mutation found again, a "
                "repeat of a sibling, counts once). "
                + _runs_text(
                    analysis,
                    lambda r: (
                        f"{r.summary.surviving_lineages} of {r.summary.population} lineages "
                        f"survive, {r.summary.beneficial_mutations} beneficial mutations "
                        f"(threshold {r.summary.beneficial_threshold:g})"
                    ),
                )
            ),
        ),
        FigureEntry(
            file=plots.phylogeny(out / "phylogeny.png", analysis).name,
            title="Fig. 2c-e: phylogenetic trees",
            caption=(
                "Every body is a dot at its birth (x), joined to its parent; each lineage's "
                "subtree occupies contiguous rows. Dot size: number of descendants; opacity: "
                "fitness (darker = fitter). The Muller diagram's lineages have its colours, the "
                "others are grey. " + _runs_text(analysis, lambda r: f"{r.summary.bodies} bodies")
            ),
        ),
        FigureEntry(
            file=plots.muller(out / "muller.png", analysis).name,
            title="Fig. 2f-h: Muller diagrams",
            caption=(
                f"Share of the population over time of the (up to) {config.muller_lineages} "
                "lineages with the largest final share, stacked; white space is all other "
                "lineages. Opacity: the lineage's mean fitness in the population at that time. "
                "Stars: a limb added or removed by a mutation whose sub-lineage has more than "
                f"{config.star_descendants} descendants. "
                + _runs_text(
                    analysis,
                    lambda r: (
                        f"{len(r.muller.founders)} of {r.summary.surviving_lineages} "
                        f"surviving lineages shown, {len(r.muller.times)} times, population "
                        f"{r.summary.population}"
                    ),
                )
            ),
        ),
        FigureEntry(
            file=plots.morphology(out / "morphology.png", analysis).name,
            title="Fig. 3: morphological descriptors",
            caption=(
                f"Population mean with {ci} after each number of births, the populations of a "
                "world's runs pooled (averaged over its runs: n = runs x P at each point): "
                "bounding-box length (forward), width and height at rest, coverage (body volume "
                "/ bounding-box volume), mass and degrees of freedom. "
                + _worlds_text(analysis, _population_text)
                + ". Coverage comes from the stability simulation: "
                + _runs_text(
                    analysis,
                    lambda r: f"{r.summary.stability_simulated} of {r.summary.bodies} bodies",
                )
            ),
        ),
        FigureEntry(
            file=plots.tests(out / "tests.png", analysis).name,
            title="Fig. 4: the test-task suite",
            caption=(
                "Top: median reward per test task and evolution world at each training budget "
                "of env steps, side by side, largest first (the paper's 5M steps, fig. 4b, and "
                "1M, fig. 4c); bottom: median cost of work at the largest budget (fig. 4d). "
                f"With {ci} of the median, over every evaluated (body, seed) of a world's runs, "
                "each body once; a result with no positive reward has no cost of work and counts "
                "as beyond every measured one (Kaplan-Meier median with its 95% CI where there "
                "are such); marks: two-tailed Mann-Whitney U tests between worlds at the same "
                "budget (* p<0.05, ** p<0.01, *** p<0.001, **** p<0.0001, ns). "
                f"{len(analysis.tests)} evaluation results: {_tests_text(analysis) or 'none'}"
                f"; {analysis.tests_repeated} left out as the same body's training again."
            ),
        ),
        FigureEntry(
            file=plots.baldwin(out / "baldwin.png", analysis).name,
            title="Fig. 5a-c: the morphological Baldwin effect, stability and cost of work",
            caption=(
                f"a: median env steps until the learning curve first reaches the "
                f"{config.criterion_percentile:g}th percentile of the initial population's "
                "fitness (each run's own), for the ancestors of the world's top agents by "
                "generation. A body that never reaches it within its budget is censored at its "
                "budget and counted: the median is Kaplan-Meier's (scipy.stats.ecdf), its 95% CI "
                "where Greenwood's log-log band of the survival curve crosses 1/2 (no point where "
                "half or more are censored, no band where a limit is unbounded); "
                "below it, the share censored at each generation. b: share of passively "
                f"stable bodies in the population over time, a world's runs pooled ({ci}; "
                "simulated bodies only: n <= runs x P, as in fig. 3). c: median cost of work of "
                "the same ancestors by generation, a body whose reward is not positive (no work "
                "for its energy) counted as beyond every measured one (Kaplan-Meier as in a); "
                "below it, the share with no positive reward. In a and c, n at generation g = the "
                "distinct ancestors at that depth of the world's top agents, each once however "
                "many top agents descend from it (written at each point of the shares below): "
                + _worlds_text(analysis, lambda w: top_rule(w.summary))
                + ". "
                + _runs_text(
                    analysis,
                    lambda r: (
                        f"criterion {r.summary.criterion:.4g}, {r.summary.criterion_censored} of "
                        f"{r.summary.distinct_bodies} bodies never reach it, "
                        f"{r.summary.no_positive_reward} have no positive reward"
                    ),
                )
            ),
        ),
        FigureEntry(
            file=plots.illustrative_curves(out / "curves.png", analysis).name,
            title="Fig. 5d: learning curves across generations of one lineage",
            caption=(
                "Learning curves (mean return against env steps) of one top agent of each world "
                "(the one with the most generations behind it) and of its ancestors (at most "
                f"{plots.MAX_CURVES} generations, evenly spread), darker to lighter from founder "
                "to descendant; dashed: the learning criterion. How much better and sooner the "
                "last generation learns than the first: " + _worlds_text(analysis, _gain_text)
            ),
        ),
        FigureEntry(
            file=plots.energy(out / "energy.png", analysis).name,
            title="Fig. 6: energy efficiency, fitness and learning speed",
            caption=(
                "a: fitness and b: env steps to the learning criterion against cost of work, for "
                "the top agents of each world (colour; their fitness and cost of work in "
                "evolution) and for every body, each once (grey); bodies whose cost of work or "
                "learning speed is censored (no positive reward; never reaching the criterion) "
                "are drawn as triangles beyond the axis' last measured value. The legends give "
                "two-tailed Pearson r and p over the measured values (the paper's statistic; "
                "censored bodies left out) and Spearman's rank correlation counting the censored "
                "bodies as beyond every measured one. c, d: the same correlations of every body "
                "at each fixed generation (the paper: the relation holds at any generation), "
                "solid Pearson, dashed Spearman, where a generation has at least 3 bodies. "
                + "; ".join(
                    f"{row.world.upper()} {row.agents} {row.y}: n={row.spearman.n} "
                    f"({row.spearman.censored} censored, counted by Spearman, left out by "
                    f"Pearson: n={row.pearson.n})"
                    for row in analysis.correlations
                    if row.generation is None
                )
            ),
        ),
    ]
    entries.append(_pictures(analysis, out, notes))
    return entries


def _ranked(analysis: Analysis) -> list[tuple[RunLog, Body]]:
    """Every body of the runs, each once, with its run, fittest first."""
    return sorted(
        ((r.run, r.run.bodies[i]) for r in analysis.runs for i in np.flatnonzero(r.counted)),
        key=lambda rb: -rb[1].fitness,
    )


def _pictures(analysis: Analysis, out: Path, notes: list[str]) -> FigureEntry:
    ranked = _ranked(analysis)[: analysis.config.pictures]
    path = out / "bodies.png"
    title = "The best bodies"
    if not ranked:
        plots.placeholder(path, "no bodies to draw (pictures = 0)")
        return FigureEntry(file=path.name, title=title, caption="No pictures were asked for.")
    genomes = []
    for _, body in ranked:
        assert body.genome is not None  # every analysed run has them all (`morphology.measure`)
        genomes.append(body.genome)
    try:
        plots.bodies(
            path,
            genomes,
            [f"{run.name}/{body.id}: {body.fitness:.4g}" for run, body in ranked],
        )
    except RuntimeError as error:  # no offscreen OpenGL
        notes.append(f"the bodies could not be drawn: {error}")
        plots.placeholder(path, f"offscreen rendering failed: {error}")
    return FigureEntry(
        file=path.name,
        title=title,
        caption=f"The {len(ranked)} fittest bodies across the runs, at rest, with run/id: fitness.",
    )


def _notes(analysis: Analysis) -> list[str]:
    notes = []
    for r in analysis.runs:
        s = r.summary
        if s.quarantined:
            notes.append(
                f"{s.run}: QUARANTINED as liars by an audit: {', '.join(s.quarantined)} (their "
                "births no audit checked were trained again, and every tournament decided after "
                "a lie was born from was decided again: the births shown are the honest ones)"
            )
        if s.stability_simulated < s.bodies:
            notes.append(
                f"{s.run}: passive stability and coverage were simulated for "
                f"{s.stability_simulated} of {s.bodies} bodies, evenly spaced in birth order; "
                "population shares and means of those use the simulated members only"
            )
        if s.repeats:
            notes.append(
                f"{s.run}: {s.repeats} of {s.bodies} births are a body born before in the run "
                "(repeats): each body counts once, as its first birth, in the top agents, the "
                "selection, the beneficial mutations, fig. 6, the test suite and the pictures; "
                "the population (figs. 2a left, 3, 5b, the Muller diagrams) holds every birth"
            )
        if s.criterion_censored:
            notes.append(
                f"{s.run}: {s.criterion_censored} of {s.distinct_bodies} bodies never reached the "
                f"learning criterion {s.criterion:.4g} within their budget: censored at it, "
                "counted in fig. 5a's Kaplan-Meier medians and fig. 6b's Spearman correlation "
                "(Pearson's r leaves them out)"
            )
        if s.no_positive_reward:
            notes.append(
                f"{s.run}: {s.no_positive_reward} of {s.distinct_bodies} bodies had no positive "
                "reward, so no cost of work: counted as beyond every measured one in fig. 5c's "
                "Kaplan-Meier medians and fig. 6's Spearman correlations (Pearson's r leaves "
                "them out)"
            )
        if not s.beneficial_mutations and s.gain_p75 is not None:
            notes.append(
                f"{s.run}: no mutation gained >= {s.beneficial_threshold:g} fitness; the 75th "
                f"percentile of the positive gains (how the paper chose its thresholds) is "
                f"{s.gain_p75:.4g}: try --beneficial {s.world}={s.gain_p75:.3g}"
            )
    for w in analysis.worlds:
        notes.append(f"{w.summary.world.upper()}: top agents are {top_rule(w.summary)}")
        single = sum(p.n < 2 for points in w.series.values() for p in points)
        if single:
            notes.append(
                f"{w.summary.world.upper()}: {single} plotted points rest on fewer than 2 values "
                "and have no CI (a CI needs >= 2 values)"
            )
        lengths = {r.summary.bodies for r in w.runs}
        if len(lengths) > 1:
            notes.append(
                f"{w.summary.world.upper()}: its runs differ in length ({min(lengths)} to "
                f"{max(lengths)} bodies); the pooled time series end at {w.summary.births} births"
            )
        if w.summary.shared_bodies:
            notes.append(
                f"{w.summary.world.upper()}: {w.summary.shared_bodies} bodies were born in more "
                "than one of its runs; each counts once, in the first run given"
            )
        missing = [r.run.name for r in w.runs if not r.run.retrained]
        if w.summary.top_rule == "retrained" and missing:
            notes.append(
                f"{w.summary.world.upper()}: no retrainings of {', '.join(missing)}; none of "
                "their bodies can be among the world's top agents"
            )
    for row in analysis.correlations:
        if row.generation is None and row.pearson.r is None:
            notes.append(
                f"fig. 6 ({row.world.upper()}, {row.agents} bodies, cost of work vs {row.y}): "
                f"no Pearson correlation: {row.pearson.note}"
            )
    if analysis.tests_repeated:
        notes.append(
            f"fig. 4: {analysis.tests_repeated} evaluation results were the same body's training "
            "again (a repeat or a body of two runs, same task, seed and budget): left out"
        )
    worlds = {t.world for t in analysis.tests}
    if not analysis.tests:
        notes.append("fig. 4: these runs hold no evaluation (test-task) results")
    elif None in budgets(analysis.tests):
        notes.append("fig. 4: some evaluation results have no known budget; they form a group")
    if analysis.tests and len(worlds) < 2:
        notes.append(
            "fig. 4: Mann-Whitney U tests compare worlds; give runs of at least two worlds with "
            "evaluation results (derl report A B C)"
        )
    return notes
