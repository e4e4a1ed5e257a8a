"""Uncertainty across seeds: the percentile bootstrap over seeds, and the claim verdict rule.

The seed is the unit of replication (SPEC §6). A statistic of two arms (a relative difference of
their seed means, the worst one over a range of iterations, a ratio of training steps) gets a 95%
interval by resampling each arm's seeds with replacement, independently per arm
(:func:`bootstrap`, ``B`` resamples from a fixed generator: the same runs give the same
interval). With n seeds per arm there are at most C(2n-1, n) distinct resamples, so at 3 seeds
the interval is coarse and too narrow: a comparison with fewer than :data:`MIN_SEEDS` seeds per
arm is never given a verdict other than ``inconclusive``.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable

import numpy as np

MIN_SEEDS = 3
BOOTSTRAP_RESAMPLES = 10_000
LEVEL = 0.95


def bootstrap(
    stat: Callable[[np.ndarray, np.ndarray], np.ndarray],
    a: np.ndarray,
    b: np.ndarray,
    resamples: int = BOOTSTRAP_RESAMPLES,
    seed: int = 0,
    level: float = LEVEL,
) -> tuple[float, float, float]:
    """(point, ci_low, ci_high) of ``stat`` over per-seed data ``a`` (n_a, ...) and ``b``
    (n_b, ...). ``stat(A, B)`` takes stacks of resampled arms, A (R, n_a, ...) and B (R, n_b,
    ...), and returns (R,) values; the point estimate is ``stat`` of the data itself. The
    interval is the (1 - level)/2 and (1 + level)/2 percentiles of the finite resampled
    values (NaN when fewer than half of them are finite)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    point = float(stat(a[None], b[None])[0])
    if len(a) == 0 or len(b) == 0:
        return point, math.nan, math.nan
    rng = np.random.default_rng(seed)
    ia = rng.integers(0, len(a), size=(resamples, len(a)))
    ib = rng.integers(0, len(b), size=(resamples, len(b)))
    values = np.asarray(stat(a[ia], b[ib]), dtype=float)
    ok = values[~np.isnan(values)]
    if ok.size < resamples / 2:
        return point, math.nan, math.nan
    tail = (1.0 - level) / 2.0
    lo, hi = np.quantile(ok, [tail, 1.0 - tail], method="inverted_cdf")
    return point, float(lo), float(hi)


def rel_of_means(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(mean_a - mean_b) / |mean_b| per resample, means over the seed axis (axis 1)."""
    with warnings.catch_warnings(), np.errstate(divide="ignore", invalid="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)
        ma, mb = np.nanmean(a, axis=1), np.nanmean(b, axis=1)
        return (ma - mb) / np.abs(mb)


def worst_rel_over_iterations(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The largest (least favourable to arm a) relative difference of seed means over the
    iteration axis (axis 2): "a is at least X% below b at every iteration" <=> this <= -X."""
    rel = rel_of_means(a, b)
    if rel.ndim == 1:
        return rel
    with warnings.catch_warnings():  # an all-NaN resample is NaN, and dropped
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmax(rel, axis=1)


def verdict(
    ci_low: float, ci_high: float, claimed: float, direction: str, n_a: int, n_b: int
) -> str:
    """``reproduced`` when the whole 95% interval satisfies the claim (``direction`` ``le``:
    value <= claimed; ``ge``: value >= claimed), ``not reproduced`` when the whole interval
    violates it, else ``inconclusive``; always ``inconclusive`` with fewer than
    :data:`MIN_SEEDS` seeds in an arm or no interval."""
    if min(n_a, n_b) < MIN_SEEDS or math.isnan(ci_low) or math.isnan(ci_high):
        return "inconclusive"
    if direction == "le":
        if ci_high <= claimed:
            return "reproduced"
        if ci_low > claimed:
            return "not reproduced"
    else:
        if ci_low >= claimed:
            return "reproduced"
        if ci_high < claimed:
            return "not reproduced"
    return "inconclusive"
