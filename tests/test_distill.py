"""Distillation on the real CPU env with a frozen teacher, for every student variant (issue 6).

One student env is built for the module and shared by the three variants.
"""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from march.cli import load
from march.config import LoggerCfg
from march.env.build import make_env
from march.learn.checkpoint import load_checkpoint
from march.learn.distill import DistillRunner
from march.learn.metrics import MetricsLog
from march.learn.teacher import EpisodeStats

pytestmark = pytest.mark.sim

OVERRIDES = ["compute=smoke", "distill.num_steps_per_env=16", "distill.num_learning_epochs=1"]


@pytest.fixture(scope="module")
def student_env():
    env = make_env(load(OVERRIDES), "student")
    yield env
    env.close()


def _runner(env, variant: str, smoke_run: Path, run_dir: Path) -> DistillRunner:
    teacher = smoke_run / "teacher" / "latest.pt"
    cfg = load([*OVERRIDES, f"student={variant}", f"teacher_ckpt={teacher}", "stage=student"])
    payload = load_checkpoint(teacher, "teacher")
    log = MetricsLog(run_dir, LoggerCfg(), run_dir.name)
    return DistillRunner(env, cfg, run_dir, log, payload, str(teacher))


@pytest.mark.parametrize("variant", ["full", "no_transformer", "no_mdn"])
def test_distillation_loss_falls_on_real_rollouts(variant, student_env, smoke_run, tmp_path):
    runner = _runner(student_env, variant, smoke_run, tmp_path)
    steps, teacher_reward = runner._rollout(EpisodeStats(student_env.num_envs, "cpu"))
    assert len(steps) == 16 and teacher_reward == teacher_reward  # finite
    infos = [runner._update(steps) for _ in range(8)]
    losses = [i["loss"] for i in infos]
    errors = [i["action_error"] for i in infos]
    assert losses[-1] < 0.7 * losses[0] if losses[0] > 0 else losses[-1] < losses[0], losses
    assert errors[-1] < errors[0], errors
    if variant == "no_mdn":
        assert "mode_weight_0" not in infos[0]
    else:
        assert abs(infos[-1]["mode_weight_0"] + infos[-1]["mode_weight_1"] - 1.0) < 1e-5


@pytest.mark.parametrize("variant", ["full", "no_transformer", "no_mdn"])
def test_distillation_logs_and_checkpoints(variant, student_env, smoke_run, tmp_path):
    runner = _runner(student_env, variant, smoke_run, tmp_path)
    runner.learn(2)
    with (tmp_path / "metrics.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["iteration"] for r in rows] == ["1", "2"]
    for r in rows:
        assert float(r["loss"]) == float(r["loss"]) and float(r["action_error"]) >= 0.0
        assert float(r["teacher_reward"]) == float(r["teacher_reward"])
        if variant == "no_mdn":
            assert r["mode_weight_0"] == ""  # no mixture, nothing logged
        else:
            assert 0.0 <= float(r["mode_weight_0"]) <= 1.0
    payload = load_checkpoint(tmp_path / "student" / "latest.pt", "student")
    assert payload["layout"]["variant"] == variant and payload["iteration"] == 2
