"""Uncertainty across seeds: intervals for the paper's comparisons and the claim verdict rule.

The seed is the unit of replication (SPEC §6); every interval is 95% and across seeds.

* A relative difference of two arms' seed means, (m_a - m_b) / |m_b|: Fieller's interval for a
  ratio of means with Welch's degrees of freedom (:func:`fieller_rel`), a closed form that
  widens as it should at 3-5 seeds (t quantiles), where a percentile bootstrap is too narrow
  (at n seeds it behaves like a normal interval with the SE shrunk by sqrt((n-1)/n)).
* The worst relative difference over a range of iterations ("at least X% at every iteration"):
  Fieller per iteration, combined as [max of lows, max of highs] (:func:`worst_over_iterations`).
* A mean of per-seed paired differences: Student's t (:func:`mean_interval`).
* Statistics with no closed form (the ratio of training steps to a threshold): the percentile
  bootstrap over seeds, each arm resampled independently (:func:`bootstrap`, a fixed generator:
  the same runs give the same interval).

A comparison with fewer than :data:`MIN_SEEDS` seeds per arm is never given a verdict other than
``inconclusive``.
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


def fieller_rel(a, b, level: float = LEVEL) -> tuple[float, float, float]:
    """(point, ci_low, ci_high) of (mean_a - mean_b) / |mean_b| over per-seed values ``a`` and
    ``b`` (independent arms), by Fieller's interval for the ratio of two means with Welch's
    degrees of freedom: the set of ratios r with |m_a - r m_b| <= t sqrt(v_a + r^2 v_b)
    (v = s^2 / n), which, unlike a percentile bootstrap, widens properly at 3-5 seeds. NaN
    bounds when an arm has fewer than 2 seeds or the reference mean is not clearly nonzero
    (the interval is unbounded)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    a, b = a[~np.isnan(a)], b[~np.isnan(b)]
    if a.size == 0 or b.size == 0 or b.mean() == 0:
        return math.nan, math.nan, math.nan
    ma, mb = float(a.mean()), float(b.mean())
    point = (ma - mb) / abs(mb)
    if a.size < 2 or b.size < 2:
        return point, math.nan, math.nan
    va, vb = a.var(ddof=1) / a.size, b.var(ddof=1) / b.size
    r0 = ma / mb
    num = (va + r0**2 * vb) ** 2
    den = (va**2 / (a.size - 1) if va else 0.0) + ((r0**2 * vb) ** 2 / (b.size - 1) if vb else 0.0)
    if den == 0:  # both arms constant: no uncertainty
        return point, point, point
    from scipy.stats import t as student_t

    t = float(student_t.ppf(0.5 + level / 2.0, num / den))
    g = t**2 * vb / mb**2
    if g >= 1.0:
        return point, math.nan, math.nan
    half = (t / abs(mb)) * math.sqrt(va * (1.0 - g) + r0**2 * vb)
    lo_r, hi_r = (r0 - half) / (1.0 - g), (r0 + half) / (1.0 - g)
    if mb > 0:  # rel = r - 1
        return point, lo_r - 1.0, hi_r - 1.0
    return point, 1.0 - hi_r, 1.0 - lo_r  # rel = (m_a - m_b) / -m_b = 1 - r


def mean_interval(x, level: float = LEVEL) -> tuple[float, float, float]:
    """(mean, low, high): Student's t interval of the mean of ``x`` (e.g. per-seed paired
    differences); NaN bounds with fewer than 2 values."""
    x = np.asarray(x, dtype=float)
    x = x[~np.isnan(x)]
    if x.size == 0:
        return math.nan, math.nan, math.nan
    m = float(x.mean())
    if x.size < 2:
        return m, math.nan, math.nan
    from scipy.stats import t as student_t

    half = float(student_t.ppf(0.5 + level / 2.0, x.size - 1)) * x.std(ddof=1) / math.sqrt(x.size)
    return m, m - half, m + half


def worst_over_iterations(a: np.ndarray, b: np.ndarray, level: float = LEVEL):
    """(point, low, high) of the largest relative difference of seed means over iterations
    (columns of ``a`` (n_a, T) and ``b`` (n_b, T)): Fieller's interval per iteration, combined
    as [max of lows, max of highs] - "at least X% below at every iteration" holds with
    confidence when every iteration's interval lies below -X (an intersection-union test)."""
    per = [fieller_rel(a[:, j], b[:, j], level) for j in range(a.shape[1])]
    per = [p for p in per if not math.isnan(p[0])]
    if not per:
        return math.nan, math.nan, math.nan
    points, lows, highs = zip(*per, strict=True)
    if any(math.isnan(x) for x in lows + highs):
        return max(points), math.nan, math.nan
    return max(points), max(lows), max(highs)
