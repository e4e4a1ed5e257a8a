"""Uncertainty across seeds: the one statistics module of the repository (intervals for the
paper's comparisons, the reward audit and the learning-signal study, and the claim verdict rule).

The seed is the unit of replication (SPEC §6); every interval is 95% and across seeds, and its
coverage at 3-5 seeds is checked by simulation (tests/test_claims.py). ``march`` may not import
``analysis``, so the package holds this module and ``analysis/``, ``march.audit`` and
``analysis/signal.py`` all import it (issue 54): there is one t interval (:func:`t_interval`),
every mean, paired or Welch interval is a use of it.

* A relative difference of two arms' seed means, (m_a - m_b) / |m_b|: Fieller's interval for a
  ratio of means with Welch's degrees of freedom (:func:`fieller_rel`, :func:`rel_estimate`), a
  closed form that widens as it should at 3-5 seeds (t quantiles), where a percentile
  bootstrap is too narrow (at n seeds it behaves like a normal interval with the SE shrunk by
  sqrt((n-1)/n): 85-87% coverage at n=3).
* A ratio of two positive means (env steps to a target): the same interval (:func:`ratio_estimate`).
* The worst relative difference over a range of iterations ("at least X% at every iteration"):
  a simultaneous interval, Fieller per iteration with a Bonferroni-corrected lower end
  (:func:`worst_over_iterations`).
* A mean (:func:`mean_ci`), a mean of per-seed paired differences (:func:`paired_ci`) and a
  difference of two independent means with Welch's degrees of freedom (:func:`welch_ci`): each
  the one Student's t interval (:func:`t_interval`); :func:`mean_summary` and
  :func:`welch_summary` give them as dicts (None where undefined) for JSON reports.
* A share of independent trials (:func:`proportion_ci`, Clopper-Pearson): the reference
  audit's reach per level.
* :func:`bootstrap` (percentile, each arm resampled independently, a fixed generator): kept for
  statistics without a closed form; no claim uses it (it under-covers at 3-5 seeds).

Each statistic is an :class:`Estimate` carrying the finite values per arm it used; :func:`judge`
gives the verdict from those counts, never from the number of runs: fewer than
:data:`MIN_SEEDS` on either side is ``inconclusive`` with the reason.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass, replace

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
    bounds when an arm has fewer than 2 seeds, when every seed of both arms has the same value
    (no spread: ties such as crossings read off one evaluation grid), or when the reference
    mean is not clearly nonzero (the interval is unbounded)."""
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
    if den == 0:  # every seed of both arms ties: no spread to estimate an interval from (a
        return point, math.nan, math.nan  # zero-width interval would claim certainty; issue 57)
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


def t_interval(
    point: float, se: float, dof: float, level: float = LEVEL
) -> tuple[float, float, float]:
    """(point, low, high) = point -/+ t_{dof, (1 + level)/2} x se: the repository's one t
    interval (a mean, a paired difference, a Welch difference all come here). NaN bounds when
    ``dof`` is not positive or ``se`` is not finite."""
    if not (dof > 0) or not math.isfinite(se):
        return point, math.nan, math.nan
    from scipy.stats import t as student_t

    half = float(student_t.ppf(0.5 + level / 2.0, dof)) * se
    return point, point - half, point + half


def proportion_ci(k: int, n: int, level: float = LEVEL) -> tuple[float, float, float]:
    """(k / n, low, high): the Clopper-Pearson (exact binomial) interval of a share, k successes
    of n independent trials; its coverage is at least ``level`` at every true share (used for
    the reference audit's reach, where a level has ~20 steps and 0 misses must not read as
    certainty). NaN everywhere when n = 0."""
    if n <= 0:
        return math.nan, math.nan, math.nan
    if not 0 <= k <= n:
        raise ValueError(f"proportion_ci: need 0 <= k <= n, got k={k}, n={n}")
    from scipy.stats import beta

    alpha = 1.0 - level
    low = 0.0 if k == 0 else float(beta.ppf(alpha / 2.0, k, n - k + 1))
    high = 1.0 if k == n else float(beta.ppf(1.0 - alpha / 2.0, k + 1, n - k))
    return k / n, low, high


def mean_ci(x, level: float = LEVEL) -> tuple[float, float, float]:
    """(mean, low, high): Student's t interval of the mean of the non-NaN values of ``x``; NaN
    bounds with fewer than 2 values (NaN mean with none)."""
    x = np.asarray(x, dtype=float)
    x = x[~np.isnan(x)]
    if x.size == 0:
        return math.nan, math.nan, math.nan
    m = float(x.mean())
    if x.size < 2:
        return m, math.nan, math.nan
    return t_interval(m, float(x.std(ddof=1)) / math.sqrt(x.size), x.size - 1, level)


def paired_ci(a, b, level: float = LEVEL) -> tuple[float, float, float]:
    """(mean, low, high) of the per-pair differences ``a - b`` (same length: seed pairs, or the
    same rollouts under two behaviours), by :func:`mean_ci`; a pair with a NaN side is dropped."""
    return mean_ci(np.asarray(a, dtype=float) - np.asarray(b, dtype=float), level)


def welch_ci(a, b, level: float = LEVEL) -> tuple[float, float, float]:
    """(mean_a - mean_b, low, high) over the finite values of two independent arms: the t
    interval with Welch's standard error and degrees of freedom (Welch-Satterthwaite; 1 when
    both arms are constant, where the interval is the point). NaN bounds with fewer than 2
    values in an arm."""
    a, b = finite(a), finite(b)
    if a.size == 0 or b.size == 0:
        return math.nan, math.nan, math.nan
    d = float(a.mean() - b.mean())
    if a.size < 2 or b.size < 2:
        return d, math.nan, math.nan
    va, vb = a.var(ddof=1) / a.size, b.var(ddof=1) / b.size
    se = math.sqrt(va + vb)
    dof = (va + vb) ** 2 / (va**2 / (a.size - 1) + vb**2 / (b.size - 1)) if se > 0 else 1.0
    return t_interval(d, se, dof, level)


def _none_if_nan(x: float) -> float | None:
    return None if math.isnan(x) else x


def mean_summary(x, level: float = LEVEL) -> dict:
    """``{"mean", "low", "high", "n"}`` of :func:`mean_ci` over the finite values of ``x`` (n:
    their count), None where undefined: the dict a JSON report writes."""
    x = finite(x)
    m, lo, hi = mean_ci(x, level)
    return {"mean": _none_if_nan(m), "low": _none_if_nan(lo), "high": _none_if_nan(hi), "n": len(x)}


def welch_summary(a, b, level: float = LEVEL) -> dict:
    """``{"mean", "low", "high", "n"}`` of :func:`welch_ci` (mean: the difference a - b; n:
    ``"n_a vs n_b"`` finite values), None where undefined."""
    na, nb = finite(a).size, finite(b).size
    d, lo, hi = welch_ci(a, b, level)
    if na < 2 or nb < 2:
        d = math.nan
    return {
        "mean": _none_if_nan(d),
        "low": _none_if_nan(lo),
        "high": _none_if_nan(hi),
        "n": f"{na} vs {nb}",
    }


@dataclass(frozen=True)
class Estimate:
    """A claim's statistic: point, 95% interval, the finite per-seed values each arm gave it
    (the smallest count over iterations for an "every iteration" statistic) and, where the
    interval or a verdict is missing, why (one clause)."""

    point: float
    low: float
    high: float
    n_a: int
    n_b: int
    why: str = ""
    allowed: tuple[str, ...] = ("reproduced", "not reproduced")  # verdicts the data may give

    @classmethod
    def none(cls, why: str, n_a: int = 0, n_b: int = 0) -> Estimate:
        return cls(math.nan, math.nan, math.nan, n_a, n_b, why)


def finite(x) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    return x[np.isfinite(x)]


def rel_estimate(a, b, level: float = LEVEL) -> Estimate:
    """:func:`fieller_rel` of the finite values of ``a`` and ``b``, with their counts."""
    fa, fb = finite(a), finite(b)
    point, lo, hi = fieller_rel(fa, fb, level)
    why = ""
    if math.isnan(lo) and fa.size >= 2 and fb.size >= 2:
        if np.ptp(fa) == 0 and np.ptp(fb) == 0:
            why = "every seed of both arms has the same value (no spread, no interval)"
        else:
            why = "the reference mean is not clearly nonzero (Fieller's interval is unbounded)"
    return Estimate(point, lo, hi, int(fa.size), int(fb.size), why)


def ratio_estimate(a, b, level: float = LEVEL) -> Estimate:
    """mean(a) / mean(b) with Fieller's interval (Welch's degrees of freedom) over the finite
    per-seed values: the ratio of two positive means, e.g. env steps to a target."""
    est = rel_estimate(a, b, level)
    return replace(est, point=est.point + 1.0, low=est.low + 1.0, high=est.high + 1.0)


CORNERS_MAX = 4096
"""At most this many corners of the seeds' intervals are searched (2^12: 6 interval-censored
seeds per arm); beyond it only the two extreme corners are."""


def censored_ratio_estimate(a_low, a_high, b_low, b_high, level: float = LEVEL) -> Estimate:
    """mean(a) / mean(b) when each seed's value is known only to lie in ``(low, high]``
    (interval-censored: e.g. the env steps at which a teacher first reaches a distance, read off
    an evaluation grid; ``high = inf``: never reached by ``low``, right-censored). The point is
    the ratio of the means of what the grid shows (the high ends; ``low`` where never reached). The interval is the union of Fieller's intervals
    (:func:`ratio_estimate`) over the corners of the seeds' intervals (each seed at either end):
    its low end the smallest low, its high end the largest high, so a verdict drawn from it
    holds wherever in their intervals the seeds' true values lie (the data decide, not the
    grid). A right-censored seed makes the high end infinite (in ``a``) or the low end 0 (in
    ``b``); a corner without spread (every seed tied in both arms) or with an unbounded interval
    makes the interval NaN, with the reason in ``why``."""
    a_low, a_high, b_low, b_high = (
        np.asarray(x, dtype=float) for x in (a_low, a_high, b_low, b_high)
    )
    n_a, n_b = int(a_high.size), int(b_high.size)
    seen_a, seen_b = (np.where(np.isinf(h), lo, h) for lo, h in ((a_low, a_high), (b_low, b_high)))
    point = float(np.mean(seen_a) / np.mean(seen_b)) if n_a and n_b and seen_b.any() else math.nan
    if min(n_a, n_b) < 2:
        return Estimate(point, math.nan, math.nan, n_a, n_b, "fewer than 2 seeds in an arm")
    ends = [(a_low, seen_a), (b_low, seen_b)]
    free = [(arm, i) for arm, (lo, hi) in enumerate(ends) for i in range(lo.size) if lo[i] != hi[i]]
    if 2 ** len(free) <= CORNERS_MAX:
        corners = range(2 ** len(free))
        masks = [[(c >> j) & 1 for j in range(len(free))] for c in corners]
    else:
        masks = [[arm == 0 for arm, _ in free], [arm == 1 for arm, _ in free]]
    low, high = math.inf, -math.inf
    for mask in masks:
        vals = [ends[0][0].copy(), ends[1][0].copy()]
        for (arm, i), up in zip(free, mask, strict=True):
            if up:
                vals[arm][i] = ends[arm][1][i]
        if not vals[0].any() and vals[1].mean() > 0:  # every a at 0 (all crossed by step 0):
            low, high = min(low, 0.0), max(high, 0.0)  # the ratio is 0 there, exactly
            continue
        est = ratio_estimate(vals[0], vals[1], level)
        if math.isnan(est.low) or math.isnan(est.high):
            why = est.why or "a corner of the seeds' intervals has no interval"
            return Estimate(
                point, math.nan, math.nan, n_a, n_b, f"at a corner of the seeds' intervals: {why}"
            )
        low, high = min(low, est.low), max(high, est.high)
    if np.isinf(a_high).any():
        high = math.inf
    if np.isinf(b_high).any():
        low = min(low, 0.0)
    return Estimate(point, low, high, n_a, n_b)


def worst_over_iterations(
    a: np.ndarray, b: np.ndarray, level: float = LEVEL, names: list | None = None
) -> Estimate:
    """The largest relative difference of seed means over iterations (columns of ``a`` (n_a, T)
    and ``b`` (n_b, T)), theta_max = max_j theta_j, with an interval that holds ``level`` for
    theta_max whatever T is:

    * high = max_j of the per-iteration Fieller highs at one-sided (1 - level)/2: theta_max
      exceeds it only if theta_j* does at the iteration j* where the maximum is, which happens
      with probability (1 - level)/2 ("at least X% at every iteration" is an intersection-union
      test: no correction is owed);
    * low = max_j of the per-iteration lows at one-sided (1 - level)/(2T) (Bonferroni): theta_max
      falls below it only if some iteration's low exceeds its own theta_j, at most T x
      (1 - level)/(2T). Without the correction the lows of 11 iterations made "not reproduced"
      fire 14% of the time at the boundary instead of 2.5% (issue 49).

    Every iteration needs a bounded interval from at least :data:`MIN_SEEDS` finite values per
    arm; otherwise the interval is NaN and ``why`` names the first iteration (``names``, else
    the column index) that lacks them."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    t = a.shape[1]
    if t == 0:
        return Estimate.none("no iteration both arms evaluated")
    n_a = int(np.isfinite(a).sum(axis=0).min())
    n_b = int(np.isfinite(b).sum(axis=0).min())
    nominal = [fieller_rel(finite(a[:, j]), finite(b[:, j]), level) for j in range(t)]
    corrected = [
        fieller_rel(finite(a[:, j]), finite(b[:, j]), 1.0 - (1.0 - level) / t) for j in range(t)
    ]
    points = [p[0] for p in nominal]
    point = max((p for p in points if not math.isnan(p)), default=math.nan)
    short = [
        j
        for j in range(t)
        if min(np.isfinite(a[:, j]).sum(), np.isfinite(b[:, j]).sum()) < MIN_SEEDS
    ]
    if short:
        return Estimate(
            point,
            math.nan,
            math.nan,
            n_a,
            n_b,
            f"iteration {_name(names, short[0])}: {_counts(a, b, short[0])}",
        )
    unbounded = [j for j in range(t) if math.isnan(corrected[j][1]) or math.isnan(nominal[j][2])]
    if unbounded:
        return Estimate(
            point,
            math.nan,
            math.nan,
            n_a,
            n_b,
            f"iteration {_name(names, unbounded[0])}: interval unbounded",
        )
    return Estimate(point, max(c[1] for c in corrected), max(p[2] for p in nominal), n_a, n_b)


def _name(names: list | None, j: int) -> str:
    return str(j if names is None else names[j])


def _counts(a: np.ndarray, b: np.ndarray, j: int) -> str:
    return f"{int(np.isfinite(a[:, j]).sum())} vs {int(np.isfinite(b[:, j]).sum())} finite values"


def judge(est: Estimate, claimed: float, direction: str) -> tuple[str, str]:
    """(verdict, why) of an :class:`Estimate` by :func:`verdict`, counting the finite values it
    was computed from (never the runs): fewer than :data:`MIN_SEEDS` either side, a missing
    interval, or a verdict the data cannot give (censored seeds) is ``inconclusive`` with the
    reason."""
    if min(est.n_a, est.n_b) < MIN_SEEDS:
        return "inconclusive", (
            f"{est.n_a} vs {est.n_b} seeds with a finite value: fewer than {MIN_SEEDS} per arm"
            + (f" ({est.why})" if est.why else "")
        )
    if math.isnan(est.low) or math.isnan(est.high):
        return "inconclusive", est.why or "no interval"
    out = verdict(est.low, est.high, claimed, direction, est.n_a, est.n_b)
    if out != "inconclusive" and out not in est.allowed:
        return "inconclusive", f"would be '{out}', but {est.why}"
    return out, est.why if out == "inconclusive" else ""
