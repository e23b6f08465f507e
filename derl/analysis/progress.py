"""Does evolution improve what it produces? The statistic `derl report` prints first: the median
fitness of a run's first and last quarter of births, and the difference (last minus first) with
its bootstrapped confidence interval.

Every birth counts in its quarter, repeats included: a repeat is a birth of the population (it
takes a place in it and competes in its tournaments like any child), and the statistic is about
what the population was given at the start and at the end. How many births of each quarter are
repeats is reported beside it.
"""

from __future__ import annotations

from derl.analysis.records import Record, RunLog
from derl.analysis.statistics import BootstrapConfig, Estimate, difference_of_medians, estimate


class Quarters(Record):
    """The median fitness of the first and the last quarter of a run's births (bootstrapped CIs)
    and `difference`: the last's median minus the first's, with its bootstrapped CI."""

    births: int
    """Births in each quarter (a quarter of the run's, rounded down)."""
    first: Estimate
    last: Estimate
    difference: Estimate
    first_repeats: int
    last_repeats: int
    """Births of each quarter whose body was born before in the run (counted as births)."""


def quarters(run: RunLog, config: BootstrapConfig) -> Quarters | None:
    """The first and last quarter of `run`'s births compared (None below 4 births)."""
    size = len(run.bodies) // 4
    if size == 0:
        return None
    first, last = slice(0, size), slice(len(run.bodies) - size, len(run.bodies))
    repeats = ~run.distinct
    return Quarters(
        births=size,
        first=estimate(run.fitness[first], config, "median"),
        last=estimate(run.fitness[last], config, "median"),
        difference=difference_of_medians(run.fitness[first], run.fitness[last], config),
        first_repeats=int(repeats[first].sum()),
        last_repeats=int(repeats[last].sum()),
    )


def describe(run: str, result: Quarters, config: BootstrapConfig) -> str:
    """One line: the two medians, their difference and its interval, how it was resampled."""

    def number(value: float | None) -> str:
        return "-" if value is None else f"{value:.4g}"

    d = result.difference
    interval = (
        "no interval (too few births)"
        if d.low is None
        else (f"{config.confidence:.0%} CI [{number(d.low)}, {number(d.high)}]")
    )
    return (
        f"{run}: median fitness of the first {result.births} births {number(result.first.value)}, "
        f"of the last {result.births} {number(result.last.value)}; difference "
        f"{number(d.value)}, {interval} (bootstrap, {config.method}, {config.n_resamples} "
        f"resamples, seed {config.seed}); repeats counted as births: {result.first_repeats} "
        f"in the first quarter, {result.last_repeats} in the last"
    )
