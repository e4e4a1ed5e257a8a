"""The faults issue 49 planted in the claims, each refused or separated: a seed whose metric is
NaN, a cross-scale pair, a run differing only in ``eval.pushes`` or only in a reward weight.

These tests go through ``analysis/figures.py`` on synthetic sweep directories (tests/
synthetic_runs.py) and import nothing else from the analysis, so they run unchanged against the
code before issue 49, where each of them fails (the report of issue 49 quotes how)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import synthetic_runs as syn

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from analysis import figures as fig  # noqa: E402

DISTILL = {"distill": {"max_iterations": 60}}  # rows from distill it 20 on: 25 and 49
TORQUE_SUCCESS = {  # per (reward, seed): a clear -50% with little spread
    ("clf", 0): 5.0,
    ("clf", 1): 5.1,
    ("clf", 2): 4.9,
    ("modelfree", 0): 10.0,
    ("modelfree", 1): 10.2,
    ("modelfree", 2): 9.9,
}


@pytest.fixture
def three_seeds(monkeypatch):
    """FINAL values for modelfree seed 2 and for an extra seed 7 of clf."""
    monkeypatch.setitem(syn.FINAL, ("modelfree", "full", 2), syn.FINAL[("modelfree", "full", 0)])
    monkeypatch.setitem(syn.FINAL, ("clf", "full", 7), syn.FINAL[("clf", "full", 2)])
    monkeypatch.setitem(syn.SEED_OFF, 7, 0.05)


def _sweep(root: Path, runs: list[tuple[str, int, dict]]) -> Path:
    sweep = root / "sweep"
    for i, (reward, seed, extra) in enumerate(runs):
        merged = {**DISTILL, **extra}
        d = syn.make_run(sweep / str(i), reward, "full", seed, extra=merged)
        evals = pd.read_csv(d / "eval.csv")
        student = evals["stage"] == "student"
        evals.loc[student, "mean_torque_success"] = TORQUE_SUCCESS.get((reward, seed), np.nan)
        evals.to_csv(d / "eval.csv", index=False)
    return sweep


def _baseline(res) -> pd.DataFrame:
    table = res["claims"]
    return table[table["claim"].str.startswith("baseline")]


def _claims_md(out: Path) -> str:
    return (out / "claims.md").read_text()


def test_a_nan_seed_is_not_counted(tmp_path, three_seeds):
    """clf seed 1 has no successful rollout (torque_success NaN): the torque row is computed
    from 2 clf values, says so, and is inconclusive although the remaining values show -50%."""
    TORQUE_SUCCESS[("clf", 1)] = np.nan
    try:
        sweep = _sweep(tmp_path, [(r, s, {}) for r in ("clf", "modelfree") for s in (0, 1, 2)])
        res = fig.analyze([sweep], tmp_path / "o")
    finally:
        TORQUE_SUCCESS[("clf", 1)] = 5.1
    row = _baseline(res).set_index("claim").filter(like="successful rollouts", axis=0)
    row = row[row.index.str.contains("torque")].iloc[0]
    print("planted NaN seed:", row["n_seeds"], row["verdict"], row["measured"])
    assert row["measured"] == pytest.approx((4.95 - 10.0333333) / 10.0333333)
    assert row["n_seeds"].startswith("2 vs 3")
    assert row["verdict"] == "inconclusive"


def test_the_same_values_with_every_seed_finite_reproduce(tmp_path, three_seeds):
    """The control of the NaN test: with clf seed 1's value present the row is 3 vs 3 and
    reproduced, so the NaN test's 'inconclusive' comes from the missing seed."""
    sweep = _sweep(tmp_path, [(r, s, {}) for r in ("clf", "modelfree") for s in (0, 1, 2)])
    res = fig.analyze([sweep], tmp_path / "o")
    row = _baseline(res).set_index("claim").filter(like="successful rollouts", axis=0)
    row = row[row.index.str.contains("torque")].iloc[0]
    assert row["n_seeds"] == "3 vs 3" and row["verdict"] == "reproduced"


def test_a_cross_scale_pair_is_refused(tmp_path, three_seeds):
    """clf at compute=smoke against modelfree at compute=gpu: no baseline claim; claims.md says
    which fields differ."""
    runs = [("clf", s, {}) for s in (0, 1, 2)]
    runs += [("modelfree", s, {"compute": {"name": "gpu"}}) for s in (0, 1, 2)]
    sweep = _sweep(tmp_path, runs)
    res = fig.analyze([sweep], tmp_path / "o")
    assert _baseline(res).empty
    md = _claims_md(tmp_path / "o")
    line = next(x for x in md.splitlines() if "not compared" in x and "modelfree" in x)
    print("cross-scale:", line)
    assert "compute.name" in line


@pytest.mark.parametrize("seed", [7, 0])
@pytest.mark.parametrize(
    ("change", "named"),
    [
        ({"eval": {"pushes": False}}, "eval.pushes=false"),
        ({"reward": {"terms": {"clf": 5.0}}}, "reward.terms.clf=5"),
    ],
)
def test_a_run_differing_in_one_setting_is_a_separate_series(
    tmp_path, three_seeds, seed, change, named
):
    """A fourth clf run that differs only in eval.pushes (or only in the clf weight) neither
    pools into the clf arm (3 seeds stay 3) nor, with a seed the arm already has, is refused
    as a duplicate: it is its own series, named by what differs, and listed as not compared."""
    runs = [(r, s, {}) for r in ("clf", "modelfree") for s in (0, 1, 2)]
    runs.append(("clf", seed, change))
    sweep = _sweep(tmp_path, runs)
    res = fig.analyze([sweep], tmp_path / "o")
    base = _baseline(res)
    assert not base.empty
    steps = base[base["claim"].str.contains("env steps")].iloc[0]
    print(f"{named} (seed {seed}):", steps["n_seeds"], steps["verdict"])
    assert steps["n_seeds"] == "3 vs 3"
    md = _claims_md(tmp_path / "o")
    assert any(named in x for x in md.split("## Not compared")[1].splitlines())
    final = res["final"]
    assert any(named in str(name) for name in final["reward"])  # a series of its own


def test_every_group_no_claim_uses_is_listed_with_why(tmp_path, three_seeds, monkeypatch):
    """A run of a reward neither arm names (clf_only) appears under "Not compared" with why."""
    for table, value in (
        (syn.TEACHER_EVAL_SLOPE, 0.05),
        (syn.TEACHER_ITERS, 60),
        (syn.TRAIN_SLOPE, 1.0),
    ):
        monkeypatch.setitem(table, "clf_only", value)
    monkeypatch.setitem(syn.FINAL, ("clf_only", "full", 0), syn.FINAL[("clf", "full", 0)])
    runs = [(r, s, {}) for r in ("clf", "modelfree") for s in (0, 1, 2)]
    runs.append(("clf_only", 0, {}))
    sweep = _sweep(tmp_path, runs)
    fig.analyze([sweep], tmp_path / "o")
    listed = _claims_md(tmp_path / "o").split("## Not compared")[1]
    line = next(x for x in listed.splitlines() if x.startswith("- clf_only"))
    assert "reward clf_only is neither clf, modelfree nor the ablation's" in line
