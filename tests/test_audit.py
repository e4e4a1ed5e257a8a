"""march.audit rewards: the verdict's arithmetic by hand, and the audit on real envs whose reward
is constructed so that the ranking of the behaviours is known in advance."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from march.audit.report import table, write_json
from march.audit.reward_audit import audit_arm, paired_verdict, roll_behaviour

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
    """Reward = -||a_t - a_{t-1}||^2 only: zero action is never penalised, random always is."""
    cfg, env = constructed_env({"action_rate": 1.0})
    arm = audit_arm(env, cfg, policy=None, horizon=30)
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
