"""Does evolution improve what it produces? The statistic `derl report` prints first: the median
fitness of the bodies of a run's first and last quarter of births, and the difference (last minus
first) with its bootstrapped confidence interval.

Each body counts once per quarter: the births of a quarter that are one body (a repeat and its
original, by `RunLog.original`) are one value, the original's. The bodies of one lineage (the
descendants of one initial body) are related: a child is its parent's body but for one mutation.
So the interval resamples lineages, not bodies (`statistics.cluster_interval`), and there is none
where a quarter's bodies come from too few lineages: one run often cannot carry the claim.

The claim rests on replicates: several runs of one world (seeds) are compared as pairs
(`Replicates`), each run's last quarter against its own first, and the mean of those differences
gets a t interval over the runs (the paired comparison: what varies between seeds is the unit).
"""

from __future__ import annotations

import numpy as np
from scipy import stats

from derl.analysis.lineage import Tree
from derl.analysis.records import Record, RunLog
from derl.analysis.statistics import BootstrapConfig, Clustered, Estimate, compare_medians


class Quarters(Record):
    """The median fitness of the distinct bodies of the first and the last quarter of a run's
    births and `difference`: the last's median minus the first's, with bootstrapped CIs
    (lineages resampled); each estimate's n counts distinct bodies."""

    births: int
    """Births in each quarter (a quarter of the run's, rounded down)."""
    first: Estimate
    last: Estimate
    difference: Estimate
    first_lineages: int
    last_lineages: int
    """Lineages (founders) the distinct bodies of each quarter belong to."""


def quarters(run: RunLog, tree: Tree, config: BootstrapConfig) -> Quarters | None:
    """The first and last quarter of `run`'s births compared (None below 4 births)."""
    size = len(run.bodies) // 4
    if size == 0:
        return None
    first = _bodies(run, tree, slice(0, size))
    last = _bodies(run, tree, slice(len(run.bodies) - size, len(run.bodies)))
    early, late, difference = compare_medians(first, last, config)
    return Quarters(
        births=size,
        first=early,
        last=late,
        difference=difference,
        first_lineages=np.unique(first.clusters).size,
        last_lineages=np.unique(last.clusters).size,
    )


def _bodies(run: RunLog, tree: Tree, births: slice) -> Clustered:
    """The distinct bodies of some births, each as its original: fitness and lineage."""
    bodies = np.unique(run.original[births])
    return Clustered(run.fitness[bodies], tree.founder[bodies])


class Replicates(Record):
    """The runs of one world as replicates: each run's `Quarters.difference` (its last quarter's
    median fitness minus its first's), their mean with its t interval over the runs, and the
    p-value of a paired t test (no change on average: mean difference 0)."""

    runs: list[str]
    differences: list[float]
    mean: Estimate
    p_value: float


def replicates(results: list[tuple[str, Quarters]], config: BootstrapConfig) -> Replicates | None:
    """The runs' differences compared across runs (None below two runs with a difference); the
    interval's confidence is `config.confidence`."""
    named = [(run, q.difference.value) for run, q in results if q.difference.value is not None]
    if len(named) < 2:
        return None
    values = np.array([d for _, d in named])
    mean = float(values.mean())
    if np.ptp(values) == 0:  # every run the same: the interval is the value, no test to make
        return Replicates(runs=[r for r, _ in named], differences=values.tolist(),
                          mean=Estimate(n=len(named), value=mean, low=mean, high=mean),
                          p_value=1.0 if mean == 0 else 0.0)  # fmt: skip
    test = stats.ttest_1samp(values, 0.0)
    interval = test.confidence_interval(config.confidence)
    return Replicates(
        runs=[r for r, _ in named],
        differences=values.tolist(),
        mean=Estimate(n=len(named), value=mean, low=float(interval.low), high=float(interval.high)),
        p_value=float(test.pvalue),
    )


def describe_replicates(world: str, result: Replicates, config: BootstrapConfig) -> str:
    """One line: each run's difference, their mean, its interval and the test."""
    each = ", ".join(f"{run} {d:+.4g}" for run, d in zip(result.runs, result.differences,
                                                           strict=True))  # fmt: skip
    m = result.mean
    assert m.value is not None and m.low is not None and m.high is not None
    return (
        f"{world.upper()}, {len(result.runs)} runs as replicates: the last quarter's median "
        f"fitness minus the first's, {each}; mean {m.value:+.4g}, {config.confidence:.0%} CI "
        f"[{m.low:+.4g}, {m.high:+.4g}] (t interval over the runs, each run paired with itself), "
        f"paired t test p = {result.p_value:.3g}"
    )


def describe(run: str, result: Quarters, config: BootstrapConfig) -> str:
    """One line: the two medians (of how many bodies, of how many lineages), their difference and
    its interval, how it was resampled."""

    def number(value: float | None) -> str:
        return "-" if value is None else f"{value:.4g}"

    d = result.difference
    interval = (
        "no interval (too few lineages to resample)"
        if d.low is None
        else f"{config.confidence:.0%} CI [{number(d.low)}, {number(d.high)}]"
    )
    return (
        f"{run}: median fitness of the first {result.births} births {number(result.first.value)}, "
        f"of the last {result.births} {number(result.last.value)}, each body once "
        f"({result.first.n} and {result.last.n} distinct bodies, of {result.first_lineages} "
        f"and {result.last_lineages} lineages); difference {number(d.value)}, {interval} "
        f"(bootstrap of lineages, {config.method}, {config.n_resamples} resamples, "
        f"seed {config.seed})"
    )
