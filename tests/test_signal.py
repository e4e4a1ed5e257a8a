"""The learning-signal study's reading (analysis/signal.py, issue 56): three verdicts (signal, no
signal, adverse), C4 like with like (the deterministic policy's V against standing's on the same
evaluation rollouts), and the standing floor and the update's columns beside every distance."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from analysis import signal

ITERS = 12


def _run(reward: str, seed: int, ref: bool, v_eval: float, v_floor: float | None, floor_d: float):
    it = np.arange(1, ITERS + 1)
    metrics = pd.DataFrame(
        {
            "stage": "teacher",
            "iteration": it,
            "env_steps": it * 768,
            "clf/v_p50": 3.0 + 0.01 * it + 0.1 * seed,
            "clf/saturated": 0.98,
            "mean_episode_length": 40 + it,
            "mean_distance_m": 0.01 * it,
            "learning_rate": 1e-5,
            "lr_mean": 1e-4 + 1e-6 * seed,
            "lr_min": 1e-5,
            "lr_max": 3e-4,
            "kl_update": 0.03,
            "kl_normaliser": 1e-4,
            "clip_fraction": 0.3,
            "action_std": 1.0,
            "action_std_legs": 0.9,
            "action_std_waist": 1.0,
            "action_std_arms": 1.1,
        }
    )
    evals = pd.DataFrame(
        {
            "stage": "teacher",
            "iteration": [6, 12],
            "env_steps": [6 * 768, 12 * 768],
            "mean_distance_m": [0.05, 0.08 + 0.01 * seed],
            "floor_distance_m": [floor_d, floor_d],
            "mean_success_rate": [0.0, 0.25 * seed],
            "floor_success_rate": [0.0, 0.0],
            "clf/v_p50": [v_eval + 0.2, v_eval],
        }
    )
    if v_floor is not None:
        evals["floor_clf/v_p50"] = v_floor
    return SimpleNamespace(
        reward=reward, observe_reference=ref, seed=seed, metrics=metrics, evals=evals
    )


def _hand_t(x) -> tuple[float, float, float]:
    x = np.asarray(x, float)
    h = stats.t.ppf(0.975, len(x) - 1) * x.std(ddof=1) / math.sqrt(len(x))
    return x.mean(), x.mean() - h, x.mean() + h


@pytest.mark.parametrize("seed", range(5))
def test_three_verdicts_over_generated_intervals(seed):
    rng = np.random.default_rng(seed)
    for _ in range(200):
        lo, hi = np.sort(rng.normal(0, 1, 2))
        thr = float(rng.normal(0, 0.5))
        ci = {"low": lo, "high": hi, "n": 3}
        down, up = signal.verdict(ci, "down", thr), signal.verdict(ci, "up", thr)
        below, above = hi < thr, lo > thr
        assert down == ("signal" if below else "adverse" if above else "no signal at this scale")
        assert up == ("signal" if above else "adverse" if below else "no signal at this scale")
    assert signal.verdict({"low": None, "high": None, "n": 1}, "up").startswith("inconclusive")


def test_the_c1_reading_of_the_last_study_is_adverse():
    """docs/signal.md's C1: V/Vmax rose by +0.357 [0.163, 0.551] where a fall was claimed."""
    ci = {"mean": 0.357, "low": 0.163, "high": 0.551, "n": 3}
    assert signal.verdict(ci, "down") == "adverse"


def test_c4_pairs_each_seeds_policy_with_standing_on_the_same_rollouts():
    v_eval, v_floor = [0.9, 1.1, 0.7], [0.8, 0.85, 0.9]
    runs = [_run("clf", s, True, v_eval[s], v_floor[s], 0.03) for s in range(3)]
    runs += [_run("modelfree", s, True, 2.0, 0.8, 0.03) for s in range(3)]
    result = signal.study(runs, standing=5.0)  # the audit's value is not used: the floor is there
    c4 = [r for r in result["criteria"] if r["criterion"].startswith("C4")]
    assert len(c4) == 1 and "policy - standing" in c4[0]["criterion"]
    m, lo, hi = _hand_t(np.subtract(v_eval, v_floor))
    assert (c4[0]["mean"], c4[0]["low"], c4[0]["high"]) == pytest.approx((m, lo, hi))
    assert c4[0]["verdict"] == signal.verdict({"low": lo, "high": hi, "n": 3}, "down")
    # rows from before the floor: the deterministic V against the audit's standing value
    old = [_run("clf", s, True, v_eval[s], None, 0.03) for s in range(3)]
    c4 = [r for r in signal.study(old, standing=0.2)["criteria"] if r["criterion"][:2] == "C4"]
    m, lo, hi = _hand_t(v_eval)  # 0.9 [0.40, 1.40]: wholly above standing's 0.2
    assert (c4[0]["mean"], c4[0]["low"], c4[0]["high"]) == pytest.approx((m, lo, hi))
    assert lo > 0.2 and c4[0]["verdict"] == "adverse"


def test_the_table_puts_the_standing_floor_and_the_update_beside_the_distance(tmp_path):
    runs = [_run("clf", s, True, 1.0, 0.8, 0.031 + 0.002 * s) for s in range(3)]
    result = signal.study(runs, standing=None)
    arm = result["arms"]["clf"]
    assert arm["standing_floor_m"]["mean"] == pytest.approx(0.033)
    assert arm["final_eval_distance_m"]["mean"] == pytest.approx(0.09)
    assert arm["lr_mean"]["mean"] == pytest.approx(1e-4 + 1e-6)
    md = signal.markdown(result)
    header = next(line for line in md.splitlines() if "standing floor" in line)
    row = next(line for line in md.splitlines() if line.startswith("| clf | 3 |"))
    cells = dict(zip(header.split("|"), row.split("|"), strict=True))
    assert cells[" standing floor [m] "].strip() == "0.033"
    assert cells[" lr mean (min-max) "].strip() == "0.000101 (1e-05-0.0003)"
    assert cells[" std legs / waist / arms "].strip() == "0.9 / 1 / 1.1"
    # success at the last evaluation, 0 / 0.25 / 0.5 over the seeds, with standing's beside it
    m, lo, hi = _hand_t([0.0, 0.25, 0.5])
    assert cells[" final eval success (standing) "].strip() == f"0.25 [{lo:.3g}, {hi:.3g}] (0)"
    png = signal.figure(runs, tmp_path / "signal.png", "test")
    assert png.is_file() and png.stat().st_size > 10_000


def _crossing_run(reward: str, seed: int, first: int | None):
    """A run evaluated at every iteration (768 env steps each) whose distance is 0.1 m until
    iteration ``first`` and 1.0 m from it on (never: 0.1 m throughout, ending at 0.5 m)."""
    run = _run(reward, seed, False, 1.0, 1.0, 0.02)
    it = np.arange(1, ITERS + 1)
    dist = np.where(it >= (first or ITERS + 1), 1.0, 0.1)
    if first is None:
        dist[-1] = 0.5
    run.evals = pd.DataFrame(
        {"stage": "teacher", "iteration": it, "env_steps": it * 768, "mean_distance_m": dist}
    )
    return run


@pytest.mark.parametrize(
    ("clf_first", "mf_first", "word"),
    [
        ((2, 2, 2), (9, 10, 11), "reproduced (CPU scale)"),
        ((8, 9, 10), (8, 9, 10), "not reproduced (CPU scale)"),
        ((4, 5, 6), (8, 9, 10), "inconclusive at this scale"),
        ((1, 2, 2), (8, 9, 10), "inconclusive at this scale"),  # high 0.56: just above 0.5
        ((2, 2, None), (9, 10, 11), "unbounded above"),
    ],
)
def test_c6_reads_the_papers_half_the_env_steps_claim(clf_first, mf_first, word):
    """C6: the ratio of the arms' mean env steps to 90 % of the better final distance, read off
    the evaluation grid. Here every seed of both arms ends at 1.0 m (target 0.9 m) and crosses
    at iteration ``first`` (at the evaluation of that iteration; below at the one before), so the
    point is mean(first_clf) / mean(first_mf) (a never-reaching seed counts at its last
    evaluation, 12), and the verdict compares the interval with the paper's 0.5."""
    clf = [_crossing_run("clf", s, k) for s, k in enumerate(clf_first)]
    mf = [_crossing_run("modelfree", s, k) for s, k in enumerate(mf_first)]
    row = signal.sample_efficiency(clf, mf)
    seen = [ITERS if k is None else k for k in clf_first]
    assert row["mean"] == pytest.approx(np.mean(seen) / np.mean(mf_first))
    assert row["target_m"] == pytest.approx(0.9)
    assert row["n"] == "3 vs 3"
    assert word in row["verdict"], row
    if word.startswith("reproduced"):
        assert row["high"] <= 0.5
    if word.startswith("not"):
        assert row["low"] > 0.5
    if "unbounded" in word:
        assert row["high"] is None and "never reach" in row["note"]


def test_c6_is_in_the_study_table_when_both_arms_ran():
    runs = [_crossing_run("clf", s, k) for s, k in enumerate((2, 2, 2))]
    runs += [_crossing_run("modelfree", s, k) for s, k in enumerate((9, 10, 11))]
    result = signal.study(runs, None)
    (c6,) = [r for r in result["criteria"] if r["criterion"].startswith("C6")]
    assert c6["arm"] == "clf vs modelfree" and c6["verdict"] == "reproduced (CPU scale)"
    assert "0.9 m" in c6["criterion"] and "paper: <= 0.5" in c6["criterion"]
    assert "| C6 env steps" in signal.markdown(result)
