"""The share interval (``march.stats.proportion_ci``, Clopper-Pearson) against hand-derived
bounds and its exact coverage over generated cases, and the reference audit's reach line."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import binom

from march.audit.feasibility import overall_reach
from march.stats import proportion_ci


def test_hand_derived_bounds():
    """All or none of n: the one-sided end is (0.025)^(1/n) (0.8316 at n = 20: 20 steps
    without a miss do not show 99 %); 5 of 10: the tabulated 0.1871-0.8129."""
    for n in (1, 7, 20, 299):
        assert proportion_ci(n, n)[1] == pytest.approx(0.025 ** (1 / n), rel=1e-9)
        assert proportion_ci(0, n)[2] == pytest.approx(1 - 0.025 ** (1 / n), rel=1e-9)
        assert proportion_ci(n, n)[2] == 1.0 and proportion_ci(0, n)[1] == 0.0
    p, lo, hi = proportion_ci(5, 10)
    assert (p, round(lo, 4), round(hi, 4)) == (0.5, 0.1871, 0.8129)
    assert all(math.isnan(x) for x in proportion_ci(0, 0))
    with pytest.raises(ValueError):
        proportion_ci(3, 2)


def test_exact_coverage_is_at_least_95_percent_at_every_share():
    """Over 300 generated (n, true share) pairs, the exact coverage (sum of the binomial
    probabilities of the k whose interval holds the share) is >= 95 %, and the interval is not
    trivially wide: below 99.5 % on average (Clopper-Pearson is conservative, not useless)."""
    rng = np.random.default_rng(0)
    coverages = []
    for _ in range(300):
        n = int(rng.integers(1, 60))
        share = float(rng.uniform(0.01, 0.99))
        ends = np.array([proportion_ci(k, n)[1:] for k in range(n + 1)])
        inside = (ends[:, 0] <= share) & (share <= ends[:, 1])
        coverages.append(float(binom.pmf(np.arange(n + 1), n, share)[inside].sum()))
    assert min(coverages) >= 0.95 - 1e-9, min(coverages)
    assert np.mean(coverages) < 0.995, np.mean(coverages)


def test_the_audit_prints_the_reach_over_every_level_with_its_interval():
    """201 of 209 steps over 10 levels: 96.2 % [92.6, 98.3]; 21 steps without a miss show at
    least 0.025^(1/21) = 84 %; 99 % needs ceil(ln 0.025 / ln 0.99) = 368 steps without one."""
    reached = [21, 24, 19, 19, 22, 23, 20, 20, 19, 14]
    steps = [22, 25, 20, 19, 22, 23, 20, 20, 21, 17]
    levels = [
        {"steps": n, "reach": {"reached_steps": k}} for k, n in zip(reached, steps, strict=True)
    ]
    line = overall_reach(levels)
    assert "201 of 209 steps reached, 96.2 % [92.6, 98.3]" in line, line
    assert "21 steps without a miss show >= 84 %" in line, line
    assert "99 % needs 368 without a miss" in line, line
