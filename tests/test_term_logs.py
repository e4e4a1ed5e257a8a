"""Per-term training logs (issue 36, item 1): each reward term's contribution, each termination's
share of ended episodes and the curriculum level's spread, summed on the device and read once;
checked against the same quantities read step by step from mjlab's managers, and the metrics
file and tensorboard names they go to."""

from __future__ import annotations

import csv

import pytest
import torch

from march.config.cli import load
from march.learn.metrics import MetricsLog, _scalar_name

STEPS = 12


@pytest.mark.sim
def test_meter_equals_the_managers_step_by_step():
    from march.env.build import make_env

    cfg = load(["compute=smoke", "reward=modelfree", "dr=none", "env.episode_length_s=0.1"])
    env = make_env(cfg, "teacher", num_envs=4)
    try:
        env.reset()
        meter = env.term_meter
        rm, tm = env.reward_manager, env.termination_manager
        want_r = torch.zeros(len(rm.active_terms))
        want_t = torch.zeros(len(tm.active_terms))
        episodes = 0
        total = 0.0
        gen = torch.Generator().manual_seed(0)
        for _ in range(STEPS):
            act = 0.3 * torch.randn(4, env.action_manager.total_action_dim, generator=gen)
            _, reward, terminated, truncated, _ = env.step(act)
            want_r += rm._step_reward.sum(0).cpu() * env.step_dt
            want_t += torch.stack([tm._term_dones[k] for k in tm.active_terms]).sum(1).cpu()
            episodes += int((terminated | truncated).sum())
            total += float(reward.sum())
        row = meter.pop()
        n = STEPS * 4
        for i, k in enumerate(rm.active_terms):
            assert row[f"reward/{k}"] == pytest.approx(float(want_r[i]) / n, rel=1e-5, abs=1e-9)
        # the terms add up to the mean step reward
        parts = sum(row[f"reward/{k}"] for k in rm.active_terms)
        assert parts == pytest.approx(total / n, rel=1e-5, abs=1e-9)
        assert episodes >= 4  # 0.1 s episodes: every env timed out at least once
        for i, k in enumerate(tm.active_terms):
            assert row[f"termination/{k}"] == pytest.approx(float(want_t[i]) / episodes)
        assert row["termination/time_out"] > 0
        levels = env.scene.terrain.terrain_levels.float()
        assert row["terrain_level_std"] == pytest.approx(float(levels.std(correction=0)))
        # read once and started over
        again = meter.pop()
        assert all(again[f"reward/{k}"] == 0.0 for k in rm.active_terms)
    finally:
        env.close()


def test_metrics_file_keeps_every_term_column_and_external_names(tmp_path):
    from march.config import LoggerCfg

    log = MetricsLog(tmp_path, LoggerCfg(), "x")
    base = {"iteration": 1, "env_steps": 10, "wall_s": 1.0}
    log.log({"stage": "teacher", **base, "reward/clf": 0.5, "termination/tilt": 0.25})
    log.log({"stage": "student", **base, "loss/nll": 2.0})
    again = MetricsLog(tmp_path, LoggerCfg(), "x")  # a resumed run: the file's columns stay
    again.log({"stage": "student", **base, "iteration": 2, "loss/nll": 1.0})
    with (tmp_path / "metrics.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [r["reward/clf"] for r in rows] == ["0.5", "", ""]
    assert [r["termination/tilt"] for r in rows] == ["0.25", "", ""]
    assert [r["loss/nll"] for r in rows] == ["", "2", "1"]
    assert _scalar_name("teacher", "reward/clf") == "Episode_Reward/clf"
    assert _scalar_name("teacher", "termination/tilt") == "Episode_Termination/tilt"
    assert _scalar_name("student", "loss/nll") == "student/loss/nll"
