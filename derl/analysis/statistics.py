"""The statistics of the paper, from scipy: bootstrapped confidence intervals (95%, of a mean or a
median, or of two medians and their difference resampling clusters of dependent values),
two-tailed Pearson and Spearman correlations, two-tailed Mann-Whitney U tests, and Kaplan-Meier
medians of censored values.

Each wrapper takes plain arrays, drops missing values (NaN) and says when there is too little
data instead of failing: a CI needs two values, a correlation three non-constant pairs, a
Mann-Whitney test one value on each side.

Censored values are kept, never dropped: a body that never reaches the learning criterion within
its budget, or whose reward is not positive (its cost of work is undefined: energy spent for no
work), is only known to lie beyond what was measured. `censored_median` counts them as the
Kaplan-Meier estimator does (`scipy.stats.ecdf` of `CensoredData`); the rank statistics
(Spearman, Mann-Whitney) count a value of +inf as larger than every measured one; Pearson's r,
which needs numbers, leaves them out and says how many.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal, cast

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy import stats

if TYPE_CHECKING:
    from scipy.stats._result_classes import EmpiricalDistributionFunction


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class BootstrapConfig(_Model):
    """How confidence intervals are resampled (scipy.stats.bootstrap, BCa by default)."""

    confidence: float = Field(0.95, gt=0, lt=1)
    n_resamples: int = Field(2000, ge=100)
    method: Literal["BCa", "percentile", "basic"] = "BCa"
    seed: int = 0


class Estimate(_Model):
    """A statistic of `n` values with its CI (None below two values, where a censored CI is
    unbounded, or with too few clusters to resample)."""

    n: int
    value: float | None = None
    low: float | None = None
    high: float | None = None
    censored: int = 0
    """Of the n, values only known to lie beyond what was measured (counted, not dropped)."""


class Point(Estimate):
    """An estimate at one place of an axis (a birth count, a generation)."""

    x: float


class Correlation(_Model):
    """A two-tailed correlation of `n` pairs (`excluded`: pairs left out, with a missing value
    or, for Pearson's r, a censored one; `censored`: pairs counted with a censored value)."""

    n: int
    excluded: int
    r: float | None = None
    p: float | None = None
    censored: int = 0
    note: str = ""


class Comparison(_Model):
    """Two-tailed Mann-Whitney U test of sample a against sample b."""

    n_a: int
    n_b: int
    u: float | None = None
    p: float | None = None
    stars: str = ""


@dataclass(frozen=True)
class Measure:
    """One measurement of some bodies: `values` (NaN: missing; where `censored`, a value only
    known to lie beyond the one given, which may be +inf: beyond every measured value)."""

    values: np.ndarray
    censored: np.ndarray

    @classmethod
    def exact(cls, values: np.ndarray) -> Measure:
        """Values with none censored."""
        values = np.asarray(values, dtype=float)
        return cls(values, np.zeros(values.shape, bool))

    @classmethod
    def concat(cls, parts: list[Measure]) -> Measure:
        return cls(
            np.concatenate([p.values for p in parts]) if parts else np.zeros(0),
            np.concatenate([p.censored for p in parts]) if parts else np.zeros(0, bool),
        )

    def __getitem__(self, index: np.ndarray) -> Measure:
        return Measure(self.values[index], self.censored[index])

    def ranked(self) -> np.ndarray:
        """The values with every censored one at +inf: for rank statistics and Pearson's r
        (which leaves +inf out)."""
        return np.where(self.censored, np.inf, self.values)


STATISTICS: dict[str, Callable[..., Any]] = {"mean": np.mean, "median": np.median}


def present(values: np.ndarray | list[float]) -> np.ndarray:
    """The values that are not missing (NaN), as floats."""
    array = np.asarray(values, dtype=float)
    return array[~np.isnan(array)]


def estimate(
    values: np.ndarray | list[float],
    config: BootstrapConfig,
    statistic: Literal["mean", "median"] = "mean",
) -> Estimate:
    """The statistic of the present values with its bootstrapped confidence interval."""
    data = present(values)
    if data.size == 0:
        return Estimate(n=0)
    function = STATISTICS[statistic]
    value = float(function(data))
    if data.size < 2:
        return Estimate(n=1, value=value)
    if np.ptp(data) == 0:  # every resample is the same: the interval is the value itself
        return Estimate(n=data.size, value=value, low=value, high=value)
    interval = _bootstrap((data,), function, config)
    return Estimate(n=data.size, value=value, low=float(interval[0]), high=float(interval[1]))


def _bootstrap(samples: tuple[np.ndarray, ...], function, config: BootstrapConfig) -> np.ndarray:
    """scipy's bootstrap interval (low, high) of `function` of the samples, by `config.method`,
    or by the percentile method where that is undefined (BCa for some tiny samples)."""
    for method in (config.method, "percentile"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # DegenerateDataWarning: handled here
            result = stats.bootstrap(
                samples,
                function,
                confidence_level=config.confidence,
                n_resamples=config.n_resamples,
                method=method,
                rng=np.random.default_rng(config.seed),
            )
        interval = np.array([result.confidence_interval.low, result.confidence_interval.high])
        if np.all(np.isfinite(interval)):
            break
    return interval


def point(x: float, values: np.ndarray | list[float], config: BootstrapConfig) -> Point:
    """`estimate` (of the mean) placed at `x`."""
    return Point(x=x, **estimate(values, config).model_dump())


def pearson(x: np.ndarray | list[float], y: np.ndarray | list[float]) -> Correlation:
    """Pearson's r and two-tailed p over the pairs where both values are measured numbers (a
    missing or censored value, +inf, excludes its pair)."""
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    return _correlation(x, y, np.isfinite(x) & np.isfinite(y), stats.pearsonr)


def spearman(x: np.ndarray | list[float], y: np.ndarray | list[float]) -> Correlation:
    """Spearman's rank correlation and two-tailed p over the pairs where both values are
    present, a censored value (+inf) ranked above every measured one (ties among them)."""
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    return _correlation(x, y, ~(np.isnan(x) | np.isnan(y)), stats.spearmanr)


def _correlation(x: np.ndarray, y: np.ndarray, counted: np.ndarray, test) -> Correlation:
    n, excluded = int(counted.sum()), int((~counted).sum())
    x, y = x[counted], y[counted]
    censored = int((np.isinf(x) | np.isinf(y)).sum())
    if n < 3:
        return Correlation(n=n, excluded=excluded, censored=censored, note="fewer than 3 pairs")
    if np.ptp(stats.rankdata(x)) == 0 or np.ptp(stats.rankdata(y)) == 0:
        return Correlation(n=n, excluded=excluded, censored=censored, note="a constant variable")
    result = test(x, y)
    return Correlation(n=n, excluded=excluded, censored=censored, r=float(result.statistic),
                       p=float(result.pvalue))  # fmt: skip


def censored_median(
    values: np.ndarray | list[float],
    censored: np.ndarray | list[bool],
    confidence: float,
) -> Estimate:
    """The Kaplan-Meier median of the present values, where a censored one is only known to be
    larger than its value (its budget; +inf: larger than every measured value), with the
    `confidence` interval found where the survival function's confidence band (scipy's
    log-log Greenwood band) crosses 1/2. The median is None when at least half the values are
    censored, a limit None when the band does not cross 1/2 where it is defined (unbounded: it
    is undefined where the curve falls to 0). Without censored values it is the plain median."""
    every = np.asarray(values, dtype=float)
    keep = ~np.isnan(every)
    kept, beyond = every[keep], np.asarray(censored, dtype=bool)[keep]
    n, lost = kept.size, int(beyond.sum())
    measured = kept[~beyond]
    if measured.size == 0:
        return Estimate(n=n, censored=lost)
    bound = np.minimum(kept[beyond], measured.max())  # beyond everything: at the largest
    data = stats.CensoredData(uncensored=measured, right=bound)
    survival = stats.ecdf(data).sf
    value = _halfway(survival.quantiles, survival.probabilities)
    if n < 2:
        return Estimate(n=n, value=value, censored=lost)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # undefined where the curve is 1 or 0: handled below
        band = survival.confidence_interval(confidence, method="log-log")
    # the limits are survival curves too (scipy-stubs calls them floats)
    limits = cast("tuple[EmpiricalDistributionFunction, ...]", (band.low, band.high))
    low, high = (
        _halfway(limit.quantiles, _defined(limit.probabilities, survival.probabilities))
        for limit in limits
    )
    return Estimate(n=n, value=value, low=low, high=high, censored=lost)


def _defined(limit: np.ndarray, survival: np.ndarray) -> np.ndarray:
    """A limit of the log-log band, which is undefined where the survival curve is 1 or 0: 1
    where the curve is 1 (before the first measured value nothing has fallen and Greenwood's
    variance is 0: the band is exactly 1); undefined (NaN: never a crossing) where it is 0 (the
    variance is infinite), so a limit that only the curve's last fall would give is unbounded."""
    return np.where(np.isnan(limit) & (survival == 1), 1.0, limit)


def _halfway(times: np.ndarray, survival: np.ndarray) -> float | None:
    """Where a step survival curve first falls to 1/2 or below (None: never); where it is
    exactly 1/2 from one time until a later drop, the midpoint of the two times (the plain
    median's rule), and None if it stays at 1/2 to the end (half the values are censored)."""
    below = np.flatnonzero(survival <= 0.5 + 1e-12)
    if below.size == 0:
        return None
    k = int(below[0])
    if not np.isclose(survival[k], 0.5):
        return float(times[k])
    later = np.flatnonzero(survival[k:] < 0.5 - 1e-12)
    return float((times[k] + times[k + later[0]]) / 2) if later.size else None


@dataclass(frozen=True)
class Clustered:
    """Values and the cluster of each: values of one cluster are not independent draws (the
    bodies of one lineage), values of different clusters are taken to be."""

    values: np.ndarray
    clusters: np.ndarray

    def present(self) -> Clustered:
        """The values that are not missing (NaN), with their clusters."""
        values = np.asarray(self.values, dtype=float)
        keep = ~np.isnan(values)
        return Clustered(values[keep], np.asarray(self.clusters)[keep])


def compare_medians(
    first: Clustered, last: Clustered, config: BootstrapConfig
) -> tuple[Estimate, Estimate, Estimate]:
    """The median of `first`, of `last`, and median(last) - median(first), each with its
    confidence interval from one stratified cluster bootstrap (`cluster_interval`); n: the
    present values of each sample, and of both for the difference."""
    first, last = first.present(), last.present()
    a, b = (float(np.median(s.values)) if s.values.size else None for s in (first, last))
    difference = None if a is None or b is None else b - a
    values = (a, b, difference)
    sizes = (first.values.size, last.values.size, first.values.size + last.values.size)
    interval = None if difference is None else cluster_interval(first, last, config)

    def at(k: int) -> Estimate:
        if interval is None:
            return Estimate(n=sizes[k], value=values[k])
        low, high = float(interval[0, k]), float(interval[1, k])
        return Estimate(n=sizes[k], value=values[k], low=low, high=high)

    return at(0), at(1), at(2)


def cluster_interval(
    first: Clustered, last: Clustered, config: BootstrapConfig
) -> np.ndarray | None:
    """Bootstrap intervals, rows (low, high), of median(first), median(last) and their
    difference, resampling clusters rather than values (None: too few clusters).

    Clusters are drawn with replacement within three strata: those with values in `first` only,
    in both, in `last` only; so every resample has as many clusters in each sample as the data
    (as the two-sample bootstrap keeps each sample's size), and a drawn cluster brings all its
    values of both samples (their dependence kept). Every stratum present needs two clusters or
    more: a single one would be in every resample, and the interval would not show how clusters
    vary. With each value its own cluster this is scipy's two-sample bootstrap."""
    labels = np.concatenate([first.clusters, last.clusters])
    names, codes = np.unique(labels, return_inverse=True)
    in_first, in_last = codes[: first.values.size], codes[first.values.size :]
    has_first = np.isin(np.arange(names.size), in_first)
    has_last = np.isin(np.arange(names.size), in_last)
    strata = tuple(
        stratum
        for stratum in (
            np.flatnonzero(has_first & ~has_last),
            np.flatnonzero(has_first & has_last),
            np.flatnonzero(~has_first & has_last),
        )
        if stratum.size
    )
    if any(stratum.size < 2 for stratum in strata):
        return None

    def medians(*drawn: np.ndarray) -> np.ndarray:
        copies = np.bincount(np.concatenate(drawn).astype(int), minlength=names.size)
        a = np.median(np.repeat(first.values, copies[in_first]))
        b = np.median(np.repeat(last.values, copies[in_last]))
        return np.array([a, b, b - a])

    return _bootstrap(strata, medians, config)


def mann_whitney(a: np.ndarray | list[float], b: np.ndarray | list[float]) -> Comparison:
    """Two-tailed Mann-Whitney U test of the present values of a and b."""
    a, b = present(a), present(b)
    if a.size == 0 or b.size == 0:
        return Comparison(n_a=a.size, n_b=b.size)
    result = stats.mannwhitneyu(a, b, alternative="two-sided")
    p = float(result.pvalue)
    return Comparison(n_a=a.size, n_b=b.size, u=float(result.statistic), p=p, stars=stars(p))


def stars(p: float) -> str:
    """The paper's significance marks: * < 0.05, ** < 0.01, *** < 0.001, **** < 0.0001."""
    return "*" * sum(p < level for level in (0.05, 0.01, 0.001, 0.0001)) or "ns"
