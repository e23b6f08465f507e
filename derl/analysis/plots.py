"""The report's figures as PNG files, drawn with matplotlib (object API, Agg, no pyplot state).

One function per paper figure; each takes computed results (`derl.analysis.compute`) and writes
one PNG. The curves of figs. 2a, 3 and 5a-c are one per world, its runs pooled; the trees, Muller
diagrams and lineages are drawn run by run. A panel without enough data still appears, with a
note saying what is missing.
"""

from __future__ import annotations

from itertools import cycle
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib import colormaps
from matplotlib.axes import Axes
from matplotlib.collections import LineCollection, PolyCollection
from matplotlib.colors import to_rgba
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from derl.analysis.compute import Analysis, RunAnalysis, WorldAnalysis, pooled
from derl.analysis.learning import LineageGain
from derl.analysis.morphology import DESCRIPTORS
from derl.analysis.statistics import Correlation, Estimate, Point
from derl.analysis.testsuite import budget_label, budgets, tasks_and_worlds
from derl.unimal import Genome
from derl.unimal.render import GRID_GAP, render_grid

DPI = 110
WORLD_COLORS = {"ft": "tab:blue", "vt": "tab:orange", "mvt": "tab:green"}
OTHER_COLORS = ("tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan")
LINESTYLES = ("-", "--", ":", "-.")
LINEAGE_COLORS = tuple(f"C{k}" for k in range(10))
UNITS = {
    "length": "length (m)",
    "width": "width (m)",
    "height": "height (m)",
    "coverage": "coverage",
    "mass": "mass (kg)",
    "dof": "DoF",
}
MAX_CURVES = 8


def world_colors(worlds: list[str]) -> dict[str, str]:
    others = cycle(OTHER_COLORS)
    return {w: WORLD_COLORS.get(w) or next(others) for w in dict.fromkeys(worlds)}


def run_styles(runs: list[RunAnalysis]) -> dict[str, dict[str, str]]:
    """Colour by world, line style by run within its world."""
    colors = world_colors([r.run.world for r in runs])
    seen: dict[str, int] = {}
    styles = {}
    for r in runs:
        k = seen[r.run.world] = seen.get(r.run.world, -1) + 1
        styles[r.run.name] = {
            "color": colors[r.run.world],
            "linestyle": LINESTYLES[k % len(LINESTYLES)],
            "label": f"{r.run.name} ({r.run.world.upper()})",
        }
    return styles


def world_label(world: WorldAnalysis) -> str:
    """The world and its runs: 'FT: r1' for one run, 'FT (3 runs)' for more."""
    runs = world.summary.runs
    name = world.summary.world.upper()
    return f"{name}: {runs[0]}" if len(runs) == 1 else f"{name} ({len(runs)} runs)"


def _save(figure: Figure, path: Path) -> Path:
    figure.savefig(path, dpi=DPI)
    return path


def _note(axis: Axes, text: str, y: float = 0.5) -> None:
    """`text` across the panel, at height `y` (axes fraction: 0.5 its middle)."""
    axis.text(
        0.5, y, text, transform=axis.transAxes, ha="center", va="center", color="0.35", wrap=True
    )


def _band(axis: Axes, points: list[Point], style: dict[str, Any]) -> bool:
    """Mean (or median) line and CI band of `points` (no band where a limit is unknown or
    unbounded); False (and nothing drawn) when none has a value."""
    shown = [p for p in points if p.value is not None]
    if not shown:
        return False
    x = np.array([p.x for p in shown])
    axis.plot(x, _values(shown), marker="o" if len(shown) < 12 else None, ms=3, **style)
    ci = [p for p in shown if p.low is not None and p.high is not None]
    if ci:
        axis.fill_between(
            [p.x for p in ci],
            np.array([p.low for p in ci], float),
            np.array([p.high for p in ci], float),
            color=style["color"],
            alpha=0.2,
            linewidth=0,
        )
    return True


def _curves(axis: Axes, analysis: Analysis, name: str, xlabel: str, ylabel: str) -> None:
    """The world-pooled curve `name` of every world, in its world's colour."""
    colors = world_colors([w.summary.world for w in analysis.worlds])
    drawn = [
        _band(axis, w.series[name], {"color": colors[w.summary.world], "label": world_label(w)})
        for w in analysis.worlds
    ]
    axis.set(xlabel=xlabel, ylabel=ylabel)
    axis.xaxis.set_major_locator(MaxNLocator(integer=True))
    axis.grid(alpha=0.3)
    if not any(drawn):
        _note(axis, "no values to show")
        return
    axis.legend(fontsize=7)
    points = max(sum(p.value is not None for p in w.series[name]) for w in analysis.worlds)
    if points == 1:  # e.g. a smoke run: the top agents' ancestors with a value in one generation
        _note(axis, "a single point: too few bodies for a curve", y=0.9)


def _sizes(analysis: Analysis, field: str) -> str:
    """A world summary's count, world by world: '300' or 'FT 300, VT 200'."""
    sizes = {w.summary.world: getattr(w.summary, field) for w in analysis.worlds}
    if len(set(sizes.values())) == 1:
        return str(next(iter(sizes.values())))
    return ", ".join(f"{world.upper()} {n}" for world, n in sizes.items())


def fitness(path: Path, analysis: Analysis) -> Path:
    """Fig. 2a: the top of the population over time, and the top agents' ancestors, each
    world's runs pooled."""
    figure = Figure(figsize=(11, 4), layout="constrained")
    left, right = figure.subplots(1, 2)
    _curves(left, analysis, "fitness_top", "bodies born", "fitness")
    confidence = analysis.config.bootstrap.confidence
    left.set_title(
        f"top of each run's population (n={_sizes(analysis, 'top_of_population')}): mean, "
        f"{confidence:.0%} CI",
        fontsize=10,
    )
    _curves(right, analysis, "fitness_by_generation", "generation", "fitness")
    colors = world_colors([w.summary.world for w in analysis.worlds])
    for w in analysis.worlds:
        shown = [p for p in w.series["fitness_by_generation"] if p.value is not None]
        _counts(right, shown, _values(shown), colors[w.summary.world])
    right.set_title(
        f"ancestors of the top agents (n={_sizes(analysis, 'top_agents')}), each once: n at each "
        "point",
        fontsize=10,
    )
    return _save(figure, path)


def _values(points: list[Point]) -> list[float]:
    """The values of `points`, each of which has one."""
    return [p.value for p in points if p.value is not None]


def _counts(axis: Axes, points: list[Point], heights: list[float], color: str) -> None:
    """Each point's n, written just above it at its height."""
    for p, height in zip(points, heights, strict=True):
        axis.annotate(
            str(p.n),
            (p.x, height),
            xytext=(0, 3),
            textcoords="offset points",
            ha="center",
            fontsize=7,
            color=color,
        )


def lineage_scatter(path: Path, analysis: Analysis) -> Path:
    """Fig. 2b: each surviving lineage by its founder's initial rank and its final abundance;
    dot size = beneficial mutations it accrued."""
    styles = run_styles(analysis.runs)
    figure = Figure(figsize=(6.5, 4.5), layout="constrained")
    axis = figure.subplots()
    for r in analysis.runs:
        rows = [row for row in r.lineages if row.surviving]
        axis.scatter(
            [row.founder_rank for row in rows],
            [100 * row.final_abundance for row in rows],
            s=[20 + 40 * row.beneficial_mutations for row in rows],
            color=styles[r.run.name]["color"],
            alpha=0.6,
            edgecolors="k",
            linewidths=0.5,
            label=f"{styles[r.run.name]['label']}: {len(rows)} lineages, "
            f"{sum(row.beneficial_mutations for row in rows)} beneficial mutations "
            f"(>= {r.summary.beneficial_threshold:g})",
        )
    axis.set(
        xlabel="founder's fitness rank in the initial population (1 = fittest)",
        ylabel="share of the final population (%)",
        ylim=(0, 105),
    )
    axis.xaxis.set_major_locator(MaxNLocator(integer=True))
    axis.set_title("surviving lineages (dot size: beneficial mutations)", fontsize=10)
    axis.grid(alpha=0.3)
    axis.legend(fontsize=7)
    return _save(figure, path)


def lineage_colors(result: RunAnalysis) -> dict[int, tuple[float, ...]]:
    """Founder index -> colour for the Muller lineages (the same in the tree and the diagram)."""
    index = {body.id: i for i, body in enumerate(result.run.bodies)}
    return {
        index[f]: to_rgba(LINEAGE_COLORS[k % len(LINEAGE_COLORS)])
        for k, f in enumerate(result.muller.founders)
    }


def _opacity(values: np.ndarray, low: float, high: float) -> np.ndarray:
    """Fitness as opacity: 0.15 (lowest) to 1 (highest); 0.15 where missing."""
    scaled = (values - low) / (high - low) if high > low else np.ones_like(values)
    return np.where(np.isnan(scaled), 0.15, 0.15 + 0.85 * np.clip(scaled, 0, 1))


def phylogeny(path: Path, analysis: Analysis) -> Path:
    """Fig. 2c-e: every body as a dot at its birth, under its parent; size = descendants,
    opacity = fitness; the Muller diagram's lineages in colour, the rest grey."""
    runs = analysis.runs
    figure = Figure(figsize=(11, 4 * len(runs)), layout="constrained")
    for axis, r in zip(np.atleast_1d(figure.subplots(len(runs), 1)), runs, strict=True):
        tree, n = r.tree, len(r.run.bodies)
        y = np.empty(n)
        y[tree.preorder()] = np.arange(n)
        x = np.arange(n, dtype=float)
        children = np.flatnonzero(tree.parent >= 0)
        parents = tree.parent[children]
        elbows = np.stack(
            [
                np.c_[x[parents], y[parents]],
                np.c_[x[parents], y[children]],
                np.c_[x[children], y[children]],
            ],
            axis=1,
        )
        axis.add_collection(LineCollection(list(elbows), colors="0.75", linewidths=0.5, zorder=1))
        colors = lineage_colors(r)
        rgba = np.array([colors.get(int(f), to_rgba("0.2")) for f in tree.founder])
        fit = r.run.fitness
        rgba[:, 3] = _opacity(fit, fit.min(), fit.max())
        sizes = 6 + 150 * tree.descendants / max(1, tree.descendants.max())
        axis.scatter(x, y, s=sizes, c=rgba, edgecolors="none", zorder=2)
        axis.set_xlim(-1, n)
        axis.set_ylim(n, -1)
        axis.set_yticks([])
        axis.set(xlabel="birth order", ylabel="lineages (each subtree contiguous)")
        axis.set_title(
            f"{r.run.name} ({r.run.world.upper()}): {n} bodies, {int((tree.parent < 0).sum())} "
            "founders; dot size = descendants, opacity = fitness",
            fontsize=10,
        )
    return _save(figure, path)


def muller(path: Path, analysis: Analysis) -> Path:
    """Fig. 2f-h: population share over time of the lineages largest at the end (stacked; white =
    the other lineages), opacity = the lineage's mean fitness; stars = topology changes with many
    descendants."""
    runs = analysis.runs
    figure = Figure(figsize=(11, 3.5 * len(runs)), layout="constrained")
    for axis, r in zip(np.atleast_1d(figure.subplots(len(runs), 1)), runs, strict=True):
        m = r.muller
        times, share, fit = m.times.astype(float), m.abundance, m.fitness
        if times.size == 1:  # one moment: a stacked bar one birth wide
            times, share, fit = times[0] + np.array([-0.5, 0.5]), share[[0, 0]], fit[[0, 0]]
        top = np.cumsum(share, axis=1)
        opacity = _opacity(fit, r.run.fitness.min(), r.run.fitness.max())
        for column, founder in enumerate(m.founders):
            low, high = top[:, column] - share[:, column], top[:, column]
            quads = [
                [
                    (times[i], low[i]),
                    (times[i + 1], low[i + 1]),
                    (times[i + 1], high[i + 1]),
                    (times[i], high[i]),
                ]
                for i in range(times.size - 1)
            ]
            color = to_rgba(LINEAGE_COLORS[column % len(LINEAGE_COLORS)])
            faces = [(*color[:3], a) for a in opacity[:-1, column]]
            axis.add_collection(PolyCollection(quads, facecolors=faces, edgecolors=faces, lw=0.3))
            axis.plot([], [], color=color, lw=6, label=founder)
        for birth, column, _ in m.stars:
            middle = top[:, column] - share[:, column] / 2
            axis.plot(birth, np.interp(birth, times, middle), marker="*", color="k", ms=9)
        axis.set(xlim=(times[0], times[-1]), ylim=(0, 1))
        axis.set(xlabel="bodies born", ylabel="share of the population")
        axis.set_title(
            f"{r.run.name} ({r.run.world.upper()}): the {len(m.founders)} largest surviving "
            f"lineages; {len(m.stars)} stars (limb added/removed, > "
            f"{analysis.config.star_descendants} descendants)",
            fontsize=10,
        )
        axis.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.0, 0.5), title="founder")
    return _save(figure, path)


def morphology(path: Path, analysis: Analysis) -> Path:
    """Fig. 3: population mean (with CI) of each descriptor over time, each world's runs
    pooled."""
    figure = Figure(figsize=(13, 7), layout="constrained")
    for axis, name in zip(figure.subplots(2, 3).flat, DESCRIPTORS, strict=True):
        _curves(axis, analysis, name, "bodies born", UNITS[name])
        sampled = all(r.summary.stability_simulated == r.summary.bodies for r in analysis.runs)
        suffix = "" if name != "coverage" or sampled else " (simulated sample)"
        axis.set_title(UNITS[name].split(" (")[0] + suffix, fontsize=10)
    return _save(figure, path)


def baldwin(path: Path, analysis: Analysis) -> Path:
    """Fig. 5a-c: learning speed and cost of work of the top agents' ancestors by generation
    (Kaplan-Meier medians, censored values counted, and below each the share censored), and the
    passively stable share of the population over time, each world's runs pooled."""
    figure = Figure(figsize=(14, 6), layout="constrained")
    grid = figure.add_gridspec(2, 3, height_ratios=(3, 1.2))
    a, b, c = (figure.add_subplot(grid[0, k]) for k in range(3))
    _curves(a, analysis, "steps_to_criterion", "generation", "median env steps to the criterion")
    percentile = analysis.config.criterion_percentile
    a.set_title(f"a. steps to the {percentile:g}th percentile of the initial fitness", fontsize=10)
    _curves(b, analysis, "passively_stable", "bodies born", "passively stable share")
    b.set_title("b. passively stable bodies in the population", fontsize=10)
    _curves(c, analysis, "cost_of_work", "generation", "median cost of work")
    c.set_title("c. cost of work of the top agents' ancestors", fontsize=10)
    for column, axis, name, what in ((0, a, "steps_to_criterion", "never reach it"),
                                     (2, c, "cost_of_work", "no positive reward")):  # fmt: skip
        below = figure.add_subplot(grid[1, column], sharex=axis)
        _censored(below, analysis, name, what)
        generations = [p.x for w in analysis.worlds for p in w.series[name]]
        if generations:
            axis.set_xlim(min(generations) - 0.5, max(generations) + 0.5)
    return _save(figure, path)


def _censored(axis: Axes, analysis: Analysis, name: str, what: str) -> None:
    """The share of censored values at each point of the world-pooled curve `name`, with the
    point's n."""
    colors = world_colors([w.summary.world for w in analysis.worlds])
    for w in analysis.worlds:
        shown = [p for p in w.series[name] if p.n]
        shares = [p.censored / p.n for p in shown]
        color = colors[w.summary.world]
        axis.plot(
            [p.x for p in shown],
            shares,
            marker="o" if len(shown) < 12 else None,
            ms=3,
            color=color,
            label=world_label(w),
        )
        _counts(axis, shown, shares, color)
    axis.set(xlabel="generation", ylabel=f"share: {what}", ylim=(-0.05, 1.2))
    axis.set_title("n at each generation above its point", fontsize=8)
    axis.xaxis.set_major_locator(MaxNLocator(integer=True))
    axis.grid(alpha=0.3)


def number(value: float | None) -> str:
    """A ratio or a count of steps, short ('-' when unknown)."""
    return "-" if value is None else f"{value:.3g}"


def illustrative_curves(path: Path, analysis: Analysis) -> Path:
    """Fig. 5d: learning curves of one top agent's ancestors, one per generation, a panel per
    world."""
    worlds = analysis.worlds
    figure = Figure(figsize=(8, 4 * len(worlds)), layout="constrained")
    for axis, w in zip(np.atleast_1d(figure.subplots(len(worlds), 1)), worlds, strict=True):
        r, agent = w.illustrative
        chain = r.tree.ancestry(agent)
        shown = sorted({chain[int(k)] for k in np.linspace(0, len(chain) - 1, MAX_CURVES)})
        shades = np.linspace(0.15, 0.9, len(chain))
        for body in shown:
            b = r.run.bodies[body]
            generation = int(r.tree.generation[body])
            axis.plot(
                b.curve_steps,
                b.curve_returns,
                color=colormaps["viridis"](shades[generation]),
                label=f"generation {generation}: {b.id} ({b.fitness:.1f})",
            )
        axis.axhline(r.summary.criterion, color="0.4", ls="--", lw=1, label="criterion")
        axis.set(xlabel="env steps", ylabel="mean return")
        gain = w.summary.illustrative
        axis.set_title(
            f"{w.summary.world.upper()}, {r.run.name}: lineage of {gain.last}, {len(chain)} "
            f"generation{'s' if len(chain) != 1 else ''}\n{_gains(gain)}",
            fontsize=10,
        )
        axis.grid(alpha=0.3)
        axis.legend(fontsize=7)
    return _save(figure, path)


def _gains(gain: LineageGain) -> str:
    """What the lineage's last generation gained over its founder, in words, each part as far
    as it is known (a ratio needs a positive founder's value)."""
    if gain.return_ratio is not None:
        returns = f"final return x{number(gain.return_ratio)}"
    elif gain.first_return is not None and gain.last_return is not None:
        returns = f"final return {gain.first_return:.1f} -> {gain.last_return:.1f}"
    else:
        returns = "no final returns to compare"
    if gain.speedup is not None:
        speed = f"criterion reached x{number(gain.speedup)} sooner"
    elif gain.last_steps is not None:
        speed = (
            f"criterion reached by {gain.last} (at {gain.last_steps:,.0f} steps), not its founder"
        )
    elif gain.first_steps is not None:
        speed = f"criterion reached by the founder {gain.first} only"
    else:
        speed = "criterion reached by neither"
    return f"{returns}; {speed}"


def energy(path: Path, analysis: Analysis) -> Path:
    """Fig. 6: fitness and learning speed against cost of work (top agents in colour, every body
    once in grey, censored values as triangles beyond the measured ones; Pearson and Spearman
    per world in the legend); below, both correlations of every body at each generation."""
    runs = analysis.runs
    colors = world_colors([r.run.world for r in runs])
    figure = Figure(figsize=(12, 9), layout="constrained")
    grid = figure.subplots(2, 2)
    for k, y in enumerate(("fitness", "steps_to_criterion")):
        _energy_scatter(grid[0, k], analysis, y, colors)
        _by_generation(grid[1, k], analysis, y, colors)
    return _save(figure, path)


YLABELS = {"fitness": "fitness", "steps_to_criterion": "env steps to the criterion"}


def _edge(values: np.ndarray) -> float:
    """Where censored values (+inf) are drawn: 5% of the range beyond the largest measured one."""
    finite = values[np.isfinite(values)]
    if not finite.size:
        return 1.0
    return float(finite.max() + 0.05 * (np.ptp(finite) or abs(finite.max()) or 1.0))


def _place(values: np.ndarray, edge: float) -> np.ndarray:
    return np.where(np.isposinf(values), edge, values)


def _energy_scatter(axis: Axes, analysis: Analysis, y: str, colors: dict[str, str]) -> None:
    """Fig. 6a or b: y against cost of work, every body once in grey, the top agents by world."""

    def values(runs: list[RunAnalysis], name: str, top: bool) -> np.ndarray:
        return pooled(runs, [r.top if top else np.flatnonzero(r.counted) for r in runs], name)

    x_all, y_all = values(analysis.runs, "cost_of_work", False), values(analysis.runs, y, False)
    edges = _edge(x_all), _edge(y_all)
    _points(axis, x_all, y_all, edges, s=8, color="0.75", edgecolors="none")
    lines: list[str] = []
    for world, color in colors.items():
        mine = [r for r in analysis.runs if r.run.world == world]
        top = values(mine, "cost_of_work", True), values(mine, y, True)
        _points(axis, *top, edges, s=18, color=color, edgecolors="k", linewidths=0.4,
                label=f"{world.upper()} top agents")  # fmt: skip
        lines.extend(
            f"{world.upper()} {row.agents}: {_r(row.pearson, 'Pearson')}; "
            f"{_r(row.spearman, 'Spearman')}"
            for row in analysis.correlations
            if row.world == world and row.y == y and row.generation is None
        )
    axis.text(0.01, 0.01, "\n".join(lines), transform=axis.transAxes, fontsize=6, va="bottom",
              bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "0.8"})  # fmt: skip
    axis.set(xlabel="cost of work (>: no positive reward)", ylabel=YLABELS[y])
    axis.set_title(
        "a. fitness vs cost of work"
        if y == "fitness"
        else "b. learning speed vs cost of work (^: never reached)",
        fontsize=10,
    )
    axis.grid(alpha=0.3)
    axis.legend(fontsize=7, loc="upper right")


def _points(
    axis: Axes, x: np.ndarray, y: np.ndarray, edges: tuple[float, float], **style: Any
) -> None:
    """Measured pairs as dots; pairs with a censored y at the top edge (^), with only a censored
    x at the right edge (>)."""
    up, right = np.isinf(y), np.isinf(x) & ~np.isinf(y)
    drawn_x, drawn_y = _place(x, edges[0]), _place(y, edges[1])
    for mask, marker in ((~(up | right), "o"), (up, "^"), (right, ">")):
        if mask.any() or marker == "o":
            axis.scatter(drawn_x[mask], drawn_y[mask], marker=marker, **style)
            style.pop("label", None)


def _r(c: Correlation, name: str) -> str:
    if c.r is None:
        return f"{name} n={c.n} ({c.note})"
    return f"{name} r={c.r:.2f} p={c.p:.2g} n={c.n}"


def _by_generation(axis: Axes, analysis: Analysis, y: str, colors: dict[str, str]) -> None:
    """Pearson (solid) and Spearman (dashed) r of every body at each generation, per world."""
    drawn = False
    for world, color in colors.items():
        rows = [row for row in analysis.correlations if row.world == world and row.y == y
                and row.agents == "all" and row.generation is not None]  # fmt: skip
        for statistic, style in (("pearson", "-"), ("spearman", "--")):
            shown = [(row.generation, getattr(row, statistic).r) for row in rows
                     if getattr(row, statistic).r is not None]  # fmt: skip
            if shown:
                drawn = True
                axis.plot(*zip(*shown, strict=True), ls=style, marker="o", ms=3, color=color,
                          label=f"{world.upper()} {statistic.capitalize()}")  # fmt: skip
    axis.axhline(0, color="0.4", lw=0.8)
    axis.set(xlabel="generation", ylabel="r", ylim=(-1.05, 1.05))
    axis.set_title(
        f"{'c' if y == 'fitness' else 'd'}. cost of work vs {YLABELS[y]}, each generation "
        "(all bodies)",
        fontsize=10,
    )
    axis.xaxis.set_major_locator(MaxNLocator(integer=True))
    axis.grid(alpha=0.3)
    if drawn:
        axis.legend(fontsize=7)
    else:
        _note(axis, "no generation with 3 or more bodies")


def tests(path: Path, analysis: Analysis) -> Path:
    """Fig. 4b-d: median reward per test task and world (with CI) at each budget of env steps,
    side by side, largest first, with the Mann-Whitney marks between worlds; below, the cost
    of work at the largest budget."""
    steps = budgets(analysis.tests)
    figure = Figure(figsize=(max(12, 7 * len(steps)), 7), layout="constrained")
    grid = figure.add_gridspec(2, max(1, len(steps)))
    if not steps:
        for row in range(2):
            _note(figure.add_subplot(grid[row, 0]), "no evaluation results in these runs")
        return _save(figure, path)
    panels = [(budget, "reward", figure.add_subplot(grid[0, k])) for k, budget in enumerate(steps)]
    panels.append((steps[0], "cost_of_work", figure.add_subplot(grid[1, :])))
    for budget, metric, axis in panels:
        _test_bars(axis, analysis, budget, metric)
    return _save(figure, path)


def _error_bar(estimate: Estimate) -> tuple[float, float]:
    """The lengths of an estimate's error bar below and above its value; none (0) where the
    value is unknown (a median of mostly censored values) and on the side of a limit that is
    (an unbounded interval)."""
    value, low, high = estimate.value, estimate.low, estimate.high
    if value is None:
        return 0.0, 0.0
    return (0.0 if low is None else value - low), (0.0 if high is None else high - value)


def _test_bars(axis: Axes, analysis: Analysis, budget: int | None, metric: str) -> None:
    """One panel of fig. 4: `metric`'s median per task and world at one budget."""
    tasks, worlds = tasks_and_worlds([t for t in analysis.tests if t.steps == budget])
    colors = world_colors(worlds)
    width = 0.8 / len(worlds)
    summary = [s for s in analysis.test_summary if s.steps == budget]
    for k, world in enumerate(worlds):
        rows = {s.task: getattr(s, metric) for s in summary if s.world == world}
        x = np.array([t for t, task in enumerate(tasks) if task in rows], dtype=float)
        est = [rows[task] for task in tasks if task in rows]
        value = np.array([np.nan if e.value is None else e.value for e in est])
        err = np.array([_error_bar(e) for e in est]).T
        axis.bar(
            x + (k - (len(worlds) - 1) / 2) * width,
            value,
            width,
            yerr=err,
            color=colors[world],
            label=world.upper(),
            capsize=3,
        )
    for t, task in enumerate(tasks):
        marks = [
            f"{c.world_a.upper()}-{c.world_b.upper()} {c.test.stars}"
            for c in analysis.comparisons
            if c.steps == budget and c.task == task and c.metric == metric and c.test.p is not None
        ]
        if marks:
            axis.annotate(
                "\n".join(marks),
                (t, 0.98),
                xycoords=("data", "axes fraction"),
                ha="center",
                va="top",
                fontsize=7,
            )
    axis.margins(y=0.2)  # room for the marks
    axis.set_xlim(-0.5, len(tasks) - 0.5)  # each task's label under its bars, not at an edge
    axis.set_xticks(range(len(tasks)), tasks, rotation=20, fontsize=8)
    why = " (reward <= 0)" if metric == "cost_of_work" else ""
    for t, task in enumerate(tasks):  # a task without a value says so, not an empty slot
        if all(getattr(row, metric).value is None for row in summary if row.task == task):
            axis.annotate(f"no value{why}", (t, 0.5), xycoords=("data", "axes fraction"),
                          ha="center", color="0.35", fontsize=8)  # fmt: skip
    axis.set_ylabel(f"median {metric.replace('_', ' ')}")
    axis.set_title(f"{metric.replace('_', ' ')}, {budget_label(budget)}", fontsize=10)
    axis.grid(alpha=0.3, axis="y")
    axis.legend(fontsize=8)


def bodies(path: Path, genomes: list[Genome], labels: list[str]) -> Path:
    """The given bodies drawn offscreen in a grid, each with its label."""
    width, height, columns = 240, 180, min(4, len(genomes))
    image = render_grid(genomes, width, height, columns=columns)
    figure = Figure(figsize=(image.shape[1] / 80, image.shape[0] / 80 + 0.3), layout="constrained")
    axis = figure.subplots()
    axis.imshow(image)
    axis.set_axis_off()
    for k, label in enumerate(labels):
        row, col = divmod(k, columns)
        axis.text(col * (width + GRID_GAP) + 4, row * (height + GRID_GAP) + 14, label, fontsize=8)
    return _save(figure, path)


def placeholder(path: Path, text: str) -> Path:
    """A figure that only says why the real one could not be drawn."""
    figure = Figure(figsize=(8, 2), layout="constrained")
    axis = figure.subplots()
    axis.set_axis_off()
    _note(axis, text)
    return _save(figure, path)
