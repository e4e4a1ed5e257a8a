"""march.audit rewards: the verdict's arithmetic by hand, and the audit on real envs whose reward
is constructed so that the ranking of the behaviours is known in advance."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from march.audit.report import table, write_json
from march.audit.reward_audit import (
    PLACED_NOTE,
    audit_arm,
    equal_time_rates,
    paired_verdict,
    per_step_verdict,
    random_behaviour,
    random_options,
    roll_behaviour,
)

T_975_DOF3 = 3.182446305284263  # scipy.stats.t.ppf(0.975, 3), from a table


def test_paired_verdict_by_hand():
    standing = np.array([10.0, 11.0, 9.0, 10.0])
    above = standing + np.array([1.0, 2.0, 3.0, 4.0])  # differences: mean 2.5, sd sqrt(5/3)
    v = paired_verdict(above, standing, "reference")
    half = T_975_DOF3 * math.sqrt(5.0 / 3.0) / 2.0
    assert v["difference"]["mean"] == pytest.approx(2.5)
    assert v["difference"]["ci_low"] == pytest.approx(2.5 - half)
    assert v["difference"]["ci_high"] == pytest.approx(2.5 + half)
    assert v["verdict"] == "ranks reference above standing"
    assert v["relative"] == pytest.approx(2.5 / 10.0)
    below = standing - np.array([1.0, 2.0, 3.0, 4.0])
    assert paired_verdict(below, standing, "ckpt")["verdict"] == "ranks ckpt BELOW standing"
    mixed = standing + np.array([1.0, -1.0, 2.0, -2.0])
    assert paired_verdict(mixed, standing, "x")["verdict"] == "cannot tell x from standing at n=4"
    # the pairing matters: a constant shift with large between-env spread is still resolved
    spread = np.array([0.0, 100.0, -100.0, 50.0])
    assert "above" in paired_verdict(spread + 0.5, spread, "r")["verdict"]


def test_strict_json_has_no_nan_tokens(tmp_path):
    obj = {"a": math.nan, "b": [math.inf, 1.0, np.float32(2.0)], "c": {"d": -math.inf}}
    path = write_json(obj, tmp_path / "x.json")

    def refuse(token: str) -> None:
        raise ValueError(token)

    back = json.loads(path.read_text(), parse_constant=refuse)
    assert back == {"a": None, "b": [None, 1.0, 2.0], "c": {"d": None}}


@pytest.fixture(scope="module")
def constructed_env():
    """A real teacher env (modelfree arm, smoke sizes, no randomisation) whose reward is ONE
    term, swapped per test: the ranking is then known by construction."""
    from march.config.cli import load
    from march.env.build import make_env

    def build(terms: dict[str, float]):
        cfg = load(["compute=smoke", "reward=modelfree", "dr=none", "seed=3"])
        cfg.reward.terms = dict(terms)
        return cfg, make_env(cfg, "teacher", num_envs=4)

    return build


@pytest.mark.sim
def test_action_rate_only_ranks_standing_above_random(constructed_env):
    """Reward = -||a_t - a_{t-1}||^2 only: zero action is never penalised, random always is
    (in every step: 10 steps show it as well as 30 did)."""
    cfg, env = constructed_env({"action_rate": 1.0})
    arm = audit_arm(env, cfg, policy=None, horizon=10)
    by = {b["behaviour"]: b for b in arm["behaviours"]}
    assert by["zero"]["return"]["mean"] == 0.0
    assert by["zero"]["terms"] == {"action_rate": 0.0}
    assert by["random"]["return"]["ci_high"] < 0.0
    assert by["random"]["terms"]["action_rate"] == pytest.approx(by["random"]["return"]["mean"])
    zero = np.array(arm["raw"]["zero"]["return"])
    rand = np.array(arm["raw"]["random"]["return"])
    assert paired_verdict(rand, zero, "random")["verdict"] == "ranks random BELOW standing"
    text = table(arm)
    assert "zero" in text and "random" in text and "action_rate" in text


@pytest.mark.sim
def test_alive_only_pays_each_step_by_hand(constructed_env):
    """Reward = alive (1 per step, weight 2): each rollout's return is 2 x dt x its steps."""
    cfg, env = constructed_env({"alive": 2.0})
    res = roll_behaviour(env, lambda obs: __import__("torch").zeros(4, 29), "zero", 3, 25)
    np.testing.assert_allclose(res.ret, 2.0 * env.step_dt * res.steps, rtol=1e-6)
    assert (res.steps <= 25).all() and (res.steps >= 1).all()
    np.testing.assert_allclose(res.term_returns["alive"], res.ret, rtol=1e-6)


def test_the_verdict_compares_per_step_at_equal_time_not_survival():
    """Rollout i of the candidate earns 1.0 per step and lives 10 steps; standing earns 2.0 per
    step for 4 + i steps (i = 0..3), then falls (NaN). Per step over the common steps (4 + i)
    the candidate earns 1.0 against 2.0 in every rollout: BELOW standing, difference exactly
    -1. Against a standing that falls sooner (1 + i steps: totals 2, 4, 6, 8 against 10) the
    total return would rank the candidate above, paying its survival; per step it stays below."""
    horizon, n = 12, 4
    cand = np.full((horizon, n), np.nan)
    cand[:10] = 1.0
    stand = np.full((horizon, n), np.nan)
    for i in range(n):
        stand[: 4 + i, i] = 2.0
    rate_c, rate_s, m = equal_time_rates(cand, stand)
    np.testing.assert_array_equal(m, [4, 5, 6, 7])
    np.testing.assert_allclose(rate_c, 1.0)
    np.testing.assert_allclose(rate_s, 2.0)
    v = per_step_verdict(cand, stand, "reference")
    assert v["verdict"] == "ranks reference BELOW standing"
    assert v["difference"]["mean"] == pytest.approx(-1.0)
    assert v["common_steps"] == {"mean": 5.5, "min": 4, "max": 7}
    totals = paired_verdict(np.nansum(cand, 0), np.nansum(stand, 0), "reference")
    assert totals["difference"]["mean"] == pytest.approx(10.0 - 11.0)
    short = np.full((horizon, n), np.nan)
    for i in range(n):
        short[: 1 + i, i] = 2.0
    assert "above" in paired_verdict(np.nansum(cand, 0), np.nansum(short, 0), "r")["verdict"]
    assert "BELOW" in per_step_verdict(cand, short, "r")["verdict"]


def test_the_random_behaviour_draws_each_joint_at_its_groups_std():
    """random_options: the configured initial std, then the upper body (waist, arms) at 0.5
    and 0.25 with the legs kept; the draws' std per joint within 4 % of its group's over
    4,000 draws, mean within 0.05 of 0, and the same seed gives the same draws."""
    import torch

    opts = random_options({"legs": 1.0, "waist": 1.0, "arms": 1.0})
    assert opts == {
        "random": {"legs": 1.0, "waist": 1.0, "arms": 1.0},
        "random upper 0.5": {"legs": 1.0, "waist": 0.5, "arms": 0.5},
        "random upper 0.25": {"legs": 1.0, "waist": 0.25, "arms": 0.25},
    }
    assert list(random_options({"legs": 1.0, "waist": 0.5, "arms": 0.5})) == [
        "random",
        "random upper 0.25",
    ]
    std = torch.tensor([1.0] * 12 + [0.5] * 3 + [0.25] * 14)
    act = random_behaviour(std, 4000, seed=3)
    draws = act({})
    assert draws.shape == (4000, 29)
    np.testing.assert_allclose(draws.std(0).numpy(), std.numpy(), rtol=0.04)
    assert draws.mean(0).abs().max() < 0.05
    assert torch.equal(random_behaviour(std, 4000, seed=3)({}), draws)


@pytest.mark.sim
def test_the_clf_arms_audit_reports_touchdowns_upper_body_and_the_placed_note():
    """A clf smoke env (2 envs, 12 steps): every behaviour reports its touchdowns (a count), V
    without the upper-body outputs never above V (every output's term of V is >= 0), the
    verdict is per step, and the table says the reference is placed, not simulated."""
    from march.config.cli import load
    from march.env.build import make_env

    cfg = load(["compute=smoke", "reward=clf", "dr=none", "seed=1"])
    env = make_env(cfg, "teacher", num_envs=2)
    arm = audit_arm(env, cfg, policy=None, horizon=12)
    env.close()
    by = {b["behaviour"]: b for b in arm["behaviours"]}
    assert list(by) == ["zero", "random", "random upper 0.5", "random upper 0.25", "reference"]
    for b in by.values():
        assert isinstance(b["touchdowns"], int) and b["touchdowns"] >= 0
        assert b["saturated_no_upper"] <= b["saturated"]
        assert b["v_over_vmax_no_upper"]["p90"] <= b["v_over_vmax"]["p90"] + 1e-9
    # less upper-body noise, less V
    assert by["random upper 0.25"]["v_over_vmax"]["p50"] < by["random"]["v_over_vmax"]["p50"]
    assert arm["verdicts"][0]["measure"].startswith("reward per step")
    assert arm["notes"] == [PLACED_NOTE]
    text = table(arm)
    assert "PLACED" in text and "per step at equal time since reset" in text
    assert "pays survival" in text


@pytest.mark.sim
def test_a_behaviour_rolls_the_same_whatever_was_rolled_before():
    """Each behaviour starts from the same seeded state, the planner's per-env streams included:
    standing rolled again after a random rollout (whose replans advanced the streams) earns the
    same rewards step for step, in a clf smoke env long enough for timeout replans (60 steps).
    The planner is called on every update (march.env.replan_queue), so the random rollout's
    10 steps advance every env's stream as far as its 60 did for the check."""
    import torch

    from march.config.cli import load
    from march.env.build import make_env

    cfg = load(["compute=smoke", "reward=clf", "dr=none", "seed=1"])
    env = make_env(cfg, "teacher", num_envs=2)
    zero = torch.zeros(2, env.action_manager.total_action_dim)
    first = roll_behaviour(env, lambda obs: zero, "zero", 1, 60)
    roll_behaviour(env, lambda obs: 0.5 * torch.randn_like(zero), "random", 1, 10)
    again = roll_behaviour(env, lambda obs: zero, "zero", 1, 60)
    env.close()
    assert np.array_equal(first.reward_by_step, again.reward_by_step, equal_nan=True)
    assert np.array_equal(first.touchdowns, again.touchdowns)
