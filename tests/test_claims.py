"""Claims with uncertainty (issue 35): the bootstrap interval against closed forms, the verdict
rule, the sample-efficiency statistic on constructed curves, the grouping key and the refusal of
duplicate seeds."""

from __future__ import annotations

import contextlib
import io
import math
import sys
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest
import synthetic_runs as syn
from scipy import stats as sps

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from analysis import figures as fig  # noqa: E402
from analysis.claims import from_iteration, sample_efficiency_stat, steps_to_reach  # noqa: E402
from analysis.groups import DuplicateRunsError, GroupKey, group_runs, series_names  # noqa: E402
from analysis.rundirs import Run  # noqa: E402
from analysis.stats import (  # noqa: E402
    bootstrap,
    fieller_rel,
    rel_of_means,
    verdict,
    worst_over_iterations,
)


@pytest.mark.parametrize(("n", "k"), [(20, 10), (30, 6), (12, 9)])
def test_bootstrap_interval_equals_the_binomial_closed_form(n, k):
    """Arm a: n seeds, k of them 1 and the rest 0; arm b: every seed 1. The resampled relative
    difference is Binomial(n, k/n)/n - 1, so its percentile interval is the binomial's quantiles
    (scipy's ppf: the smallest value whose CDF reaches the level), exactly."""
    a = np.array([1.0] * k + [0.0] * (n - k))
    b = np.ones(n)
    point, lo, hi = bootstrap(rel_of_means, a, b, resamples=40_000, seed=1)
    assert point == pytest.approx(k / n - 1)
    assert lo == pytest.approx(sps.binom.ppf(0.025, n, k / n) / n - 1)
    assert hi == pytest.approx(sps.binom.ppf(0.975, n, k / n) / n - 1)


def test_bootstrap_of_a_constant_arm_has_no_width_and_is_seeded():
    a, b = np.full(5, 8.0), np.full(4, 10.0)
    assert bootstrap(rel_of_means, a, b) == pytest.approx((-0.2, -0.2, -0.2))
    rng = np.random.default_rng(3)
    x, y = rng.normal(9, 1, 6), rng.normal(10, 1, 6)
    assert bootstrap(rel_of_means, x, y) == bootstrap(rel_of_means, x, y)  # repeatable


@pytest.mark.parametrize(
    ("lo", "hi", "direction", "n", "want"),
    [
        (-0.30, -0.15, "le", 3, "reproduced"),
        (-0.30, -0.05, "le", 3, "inconclusive"),
        (-0.05, 0.10, "le", 3, "not reproduced"),
        (-0.30, -0.15, "le", 2, "inconclusive"),  # fewer than 3 seeds: never a verdict
        (float("nan"), -0.15, "le", 5, "inconclusive"),
        (0.20, 0.40, "ge", 3, "reproduced"),
        (-0.20, -0.01, "ge", 3, "not reproduced"),
    ],
)
def test_verdict_rule(lo, hi, direction, n, want):
    claimed = -0.12 if direction == "le" else 0.0
    assert verdict(lo, hi, claimed, direction, n, 4) == want


def test_sample_efficiency_ratio_on_constructed_curves():
    """Arm a gains 1 m per 100 steps, arm b 0.5 m; both end at 4 m: the target 90% x 4 = 3.6 m
    is reached at 400 steps (a) and 800 (b): ratio 0.5."""
    steps_a = np.arange(0, 500, 100.0)  # 0..400
    steps_b = np.arange(0, 900, 100.0)  # 0..800
    a = (steps_a / 100.0)[None, None, :].repeat(3, axis=1)  # 3 identical seeds
    b = (steps_b / 200.0)[None, None, :].repeat(3, axis=1)
    stat = sample_efficiency_stat(steps_a, steps_b, 0.9)
    assert stat(a, b)[0] == pytest.approx(400 / 800)
    never = np.zeros_like(b)
    assert stat(a, never)[0] == 0.0  # b never reaches: a infinitely faster
    assert math.isnan(stat(np.zeros_like(a), np.zeros_like(b))[0])
    assert steps_to_reach(np.array([[0.0, 1.0, 2.0]]), np.array([5, 6, 7]), np.array([1.5]))[0] == 7


def test_from_iteration_scales_the_papers_500_of_1500():
    assert from_iteration(1500) == 500
    assert from_iteration(150) == 50
    assert from_iteration(2) == 1
    assert from_iteration(None) == 500


def _run(label: str, **kw) -> Run:
    base = dict(
        reward="clf",
        variant="full",
        curriculum="stones",
        seed=0,
        stage="all",
        compute="smoke",
        teacher_budget=2,
        distill_budget=2,
        observe_reference=False,
    )
    return Run(path=Path(label), label=label, **{**base, **kw})


CHANGES = {
    "reward": "modelfree",
    "variant": "no_mdn",
    "curriculum": "flat_first",
    "stage": "student",
    "compute": "cpu",
    "teacher_budget": 4,
    "distill_budget": 10,
    "observe_reference": True,
    "checkpoints": "runs/a/teacher/latest.pt",
}


@pytest.mark.parametrize("field", sorted(CHANGES))
def test_every_key_field_separates_groups(field):
    """Two runs that differ in one field of the key are two groups, never one point."""
    assert {f.name for f in fields(GroupKey)} == set(CHANGES)
    a, b = _run("a"), _run("b", **{field: CHANGES[field]})
    groups = group_runs([a, b])
    assert len(groups) == 2
    names = series_names(list(groups), "reward")
    assert len(set(names.values())) == 2  # distinguishable in a legend


def test_seeds_of_one_group_pool_and_duplicates_are_refused():
    runs = [_run(f"r{s}", seed=s) for s in range(3)]
    groups = group_runs(runs)
    assert [len(v) for v in groups.values()] == [3]
    dup = _run("again", seed=1)
    with pytest.raises(DuplicateRunsError) as err:
        group_runs([*runs, dup])
    text = str(err.value)
    assert "\n" not in text and "r1" in text and "again" in text and "seed 1" in text
    runs[1].mtime, dup.mtime = 10.0, 20.0
    notes: list[str] = []
    kept = group_runs([*runs, dup], allow_duplicates=True, notes=notes)
    assert [r.label for r in next(iter(kept.values()))] == ["r0", "again", "r2"]
    assert any("kept the newest, again" in n and "left out r1" in n for n in notes)


def test_figures_refuses_a_duplicate_run_in_one_line(tmp_path):
    syn.make_run(tmp_path / "sweep" / "0", "clf", "full", 0)
    syn.make_run(tmp_path / "sweep" / "1", "clf", "full", 0)  # the same seed again
    err, out = io.StringIO(), io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        code = fig.main([str(tmp_path / "sweep"), "--out", str(tmp_path / "o")])
    assert code == 2
    lines = err.getvalue().strip().splitlines()
    assert len(lines) == 1 and "sweep/0" in lines[0] and "sweep/1" in lines[0]
    assert not (tmp_path / "o").exists()  # nothing written
    with contextlib.redirect_stdout(out):
        code = fig.main(
            [str(tmp_path / "sweep"), "--out", str(tmp_path / "o"), "--allow-duplicates"]
        )
    assert code == 0 and "--allow-duplicates: seed 0" in out.getvalue()
    claims = (tmp_path / "o" / "claims.csv").read_text().splitlines()[0]
    assert claims == "claim,paper,measured,ci_low,ci_high,n_seeds,scale,verdict"


def test_claims_table_on_three_seeds_per_arm(tmp_path, monkeypatch):
    """Three seeds per arm (modelfree seed 2 = seed 0's values), distillation budget 60: the
    torque claim reads the student rows from iteration 20 (500/1500 of 60) on, i.e. 25 and 49,
    where both arms scale alike; its point estimate is (8.8 - 9.8333) / 9.8333 by hand."""
    monkeypatch.setitem(syn.FINAL, ("modelfree", "full", 2), syn.FINAL[("modelfree", "full", 0)])
    sweep = tmp_path / "sweep"
    runs = [(r, s) for r in ("clf", "modelfree") for s in (0, 1, 2)]
    for i, (reward, seed) in enumerate(runs):
        d = syn.make_run(sweep / str(i), reward, "full", seed)
        cfg = d / "config.yaml"
        cfg.write_text(cfg.read_text() + "distill:\n  max_iterations: 60\n")
    res = fig.analyze([sweep], tmp_path / "o")
    claims = res["claims"].set_index("claim")
    name = next(c for c in claims.index if c.startswith("baseline: |joint torque|, all rollouts"))
    row = claims.loc[name]
    assert "from distill it 20 on" in name
    mf = (9.5 + 10.5 + 9.5) / 3
    assert row["measured"] == pytest.approx((8.8 - mf) / mf)
    assert row["ci_low"] <= row["measured"] <= row["ci_high"]
    assert row["n_seeds"] == "3 vs 3"
    # -10.5%, with an interval that straddles -12% at 3 seeds: inconclusive.
    assert row["ci_low"] < -0.12 < row["ci_high"] and row["verdict"] == "inconclusive"
    md = (tmp_path / "o" / "claims.md").read_text()
    assert "\\|joint torque\\|" in md  # pipes escaped: the table keeps its columns


def test_final_table_differences_carry_intervals_or_say_no_claim(tmp_path, monkeypatch):
    """Three seeds per arm: each relative difference in final_metrics carries its bootstrap
    interval; two seeds per arm: the line says it is no claim."""
    monkeypatch.setitem(syn.FINAL, ("modelfree", "full", 2), syn.FINAL[("modelfree", "full", 0)])
    for n_seeds, sweep in ((3, tmp_path / "three"), (2, tmp_path / "two")):
        for i, (reward, seed) in enumerate(
            [(r, s) for r in ("clf", "modelfree") for s in range(n_seeds)]
        ):
            syn.make_run(sweep / str(i), reward, "full", seed)
        res = fig.analyze([sweep], tmp_path / f"o{n_seeds}")
        table = res["final"]
        text = table.loc[table["reward"] == "clf", "relative"].item()
        if n_seeds == 3:
            mf = (9.5 + 10.5 + 9.5) / 3
            assert f"torque {round((8.8 - mf) / mf * 100):+d}% [" in text
            assert text.endswith("n=3 vs 3 seeds, 95% CI across seeds in brackets")
        else:
            assert "[" not in text
            assert text.endswith("n=2 vs 2 seeds: fewer than 3 per arm, no claim")


def test_fieller_interval_by_hand_with_a_constant_reference():
    """b constant (no variance): the interval is m_a/m_b - 1 +- t(n_a - 1) s_a / (sqrt(n_a) m_b):
    a = 8, 9, 10 (mean 9, s = 1), b = 10 -> -0.1 +- 4.3027 x 0.57735 / 10."""
    point, lo, hi = fieller_rel([8.0, 9.0, 10.0], [10.0, 10.0, 10.0])
    half = sps.t.ppf(0.975, 2) * (1 / math.sqrt(3)) / 10
    assert point == pytest.approx(-0.1)
    assert (lo, hi) == pytest.approx((-0.1 - half, -0.1 + half))


@pytest.mark.parametrize("seed", range(25))
def test_fieller_interval_inverts_the_welch_test(seed):
    """Generated arms: the interval's ends are exactly the ratios where the Welch statistic
    |m_a - r m_b| / sqrt(v_a + r^2 v_b) equals its t quantile, and it is below it inside."""
    rng = np.random.default_rng(seed)
    n_a, n_b = rng.integers(3, 8, size=2)
    a = rng.normal(rng.uniform(5, 15), rng.uniform(0.2, 2), n_a)
    b = rng.normal(rng.uniform(8, 15), rng.uniform(0.2, 2), n_b)
    point, lo, hi = fieller_rel(a, b)
    ma, mb = a.mean(), b.mean()
    va, vb = a.var(ddof=1) / n_a, b.var(ddof=1) / n_b
    r0 = ma / mb
    df = (va + r0**2 * vb) ** 2 / (va**2 / (n_a - 1) + (r0**2 * vb) ** 2 / (n_b - 1))
    t = sps.t.ppf(0.975, df)

    def stat(rel):
        r = rel + 1.0
        return abs(ma - r * mb) / math.sqrt(va + r**2 * vb)

    assert lo < point < hi
    assert stat(lo) == pytest.approx(t, rel=1e-6) and stat(hi) == pytest.approx(t, rel=1e-6)
    assert stat(point) < t and stat(lo - 0.01) > t and stat(hi + 0.01) > t


def test_worst_over_iterations_combines_per_iteration_intervals():
    a = np.array([[8.0, 9.5], [9.0, 10.0], [10.0, 10.5]])  # means 9, 10
    b = np.full((3, 2), 10.0)
    point, lo, hi = worst_over_iterations(a, b)
    first, second = fieller_rel(a[:, 0], b[:, 0]), fieller_rel(a[:, 1], b[:, 1])
    assert point == pytest.approx(0.0)  # the second iteration: no reduction at all
    assert (lo, hi) == pytest.approx((max(first[1], second[1]), max(first[2], second[2])))
