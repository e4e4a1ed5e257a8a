"""Distillation on the real CPU env with a frozen teacher: every student variant (issue 6)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from march.cli import load
from march.learn.checkpoint import load_checkpoint
from march.train import run_pipeline

pytestmark = pytest.mark.sim


def _student_rows(run_dir: Path) -> list[dict[str, str]]:
    with (run_dir / "metrics.csv").open(newline="") as f:
        return [r for r in csv.DictReader(f) if r["stage"] == "student"]


@pytest.mark.parametrize("variant", ["full", "no_transformer", "no_mdn"])
def test_distillation_loss_falls(variant, smoke_run, tmp_path):
    teacher = smoke_run / "teacher" / "latest.pt"
    cfg = load(
        [
            "compute=smoke",
            "stage=student",
            f"student={variant}",
            f"teacher_ckpt={teacher}",
            "distill.max_iterations=4",
            "distill.num_steps_per_env=16",
            "distill.num_learning_epochs=3",
            "distill.eval_interval=0",
            "eval.num_rollouts=2",
            "compute.eval_num_envs=2",
            "eval.episode_length_s=0.5",
        ]
    )
    summary = run_pipeline(cfg, tmp_path)
    rows = _student_rows(tmp_path)
    losses = [float(r["loss"]) for r in rows]
    errors = [float(r["action_error"]) for r in rows]
    assert len(losses) == 4
    assert losses[-1] < losses[0], losses
    assert errors[-1] < errors[0], errors
    if variant == "no_mdn":
        assert all(r["mode_weight_0"] == "" for r in rows)  # no mixture, nothing logged
    else:
        assert all(0.0 <= float(r["mode_weight_0"]) <= 1.0 for r in rows)
    assert all(float(r["teacher_reward"]) == float(r["teacher_reward"]) for r in rows)
    payload = load_checkpoint(tmp_path / "student" / "latest.pt", "student")
    assert payload["layout"]["variant"] == variant and payload["iteration"] == 4
    saved = json.loads((tmp_path / "summary.json").read_text())
    assert saved["n_rollouts"] == 2 == summary["n_rollouts"]
