"""The statistics of the paper, from scipy: bootstrapped confidence intervals (95%, of a mean or a
median), two-tailed Pearson correlation and two-tailed Mann-Whitney U tests.

Each wrapper takes plain arrays, drops missing values (NaN) and says when there is too little
data instead of failing: a CI needs two values, a correlation three non-constant pairs, a
Mann-Whitney test one value on each side.
"""

from __future__ import annotations

import warnings
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy import stats


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class BootstrapConfig(_Model):
    """How confidence intervals are resampled (scipy.stats.bootstrap, BCa by default)."""

    confidence: float = Field(0.95, gt=0, lt=1)
    n_resamples: int = Field(2000, ge=100)
    method: Literal["BCa", "percentile", "basic"] = "BCa"
    seed: int = 0


class Estimate(_Model):
    """A statistic of `n` values with its bootstrapped CI (None below two values)."""

    n: int
    value: float | None = None
    low: float | None = None
    high: float | None = None


class Point(Estimate):
    """An estimate at one place of an axis (a birth count, a generation)."""

    x: float


class Correlation(_Model):
    """Two-tailed Pearson correlation of `n` complete pairs (`excluded` had a missing value)."""

    n: int
    excluded: int
    r: float | None = None
    p: float | None = None
    note: str = ""


class Comparison(_Model):
    """Two-tailed Mann-Whitney U test of sample a against sample b."""

    n_a: int
    n_b: int
    u: float | None = None
    p: float | None = None
    stars: str = ""


STATISTICS = {"mean": np.mean, "median": np.median}


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
    interval = _bootstrap(data, function, config, config.method)
    if not np.all(np.isfinite(interval)):  # BCa is undefined for some tiny samples
        interval = _bootstrap(data, function, config, "percentile")
    return Estimate(n=data.size, value=value, low=float(interval[0]), high=float(interval[1]))


def _bootstrap(data: np.ndarray, function, config: BootstrapConfig, method: str) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # DegenerateDataWarning: handled by the caller
        result = stats.bootstrap(
            (data,),
            function,
            confidence_level=config.confidence,
            n_resamples=config.n_resamples,
            method=method,
            rng=np.random.default_rng(config.seed),
        )
    return np.array([result.confidence_interval.low, result.confidence_interval.high])


def point(x: float, values: np.ndarray | list[float], config: BootstrapConfig) -> Point:
    """`estimate` (of the mean) placed at `x`."""
    return Point(x=x, **estimate(values, config).model_dump())


def pearson(x: np.ndarray | list[float], y: np.ndarray | list[float]) -> Correlation:
    """Pearson's r and two-tailed p over the pairs where both values are present."""
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    complete = ~(np.isnan(x) | np.isnan(y))
    n, excluded = int(complete.sum()), int((~complete).sum())
    if n < 3:
        return Correlation(n=n, excluded=excluded, note="fewer than 3 complete pairs")
    x, y = x[complete], y[complete]
    if np.ptp(x) == 0 or np.ptp(y) == 0:
        return Correlation(n=n, excluded=excluded, note="a constant variable")
    result = stats.pearsonr(x, y)
    return Correlation(n=n, excluded=excluded, r=float(result.statistic), p=float(result.pvalue))


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
