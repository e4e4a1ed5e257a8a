"""End to end on the real mjlab env (CPU): the smoke pipeline, checkpoints, resume, determinism."""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf
from tool_in_process import run_tool

from march.config import ConfigError
from march.config.cli import load
from march.store.checkpoint import CheckpointError, load_checkpoint
from march.store.provenance import apply_checkpoint_config
from march.train import run_pipeline

ROOT = Path(__file__).resolve().parent.parent
pytestmark = pytest.mark.sim


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def test_smoke_summary_in_range(smoke_run):
    cfg = load(["compute=smoke"])
    summary = json.loads((smoke_run / "summary.json").read_text())
    assert summary["n_rollouts"] == cfg.eval.num_rollouts
    assert 0.0 <= summary["mean_success_rate"] <= 1.0
    table_len = cfg.terrain.size[0]
    assert 0.0 <= summary["mean_distance_m"] <= table_len
    assert summary["mean_abs_torque_nm"] > 0.0  # a standing G1 holds itself up
    assert summary["mean_abs_ang_jerk"] >= 0.0
    for key in ("mean_distance_m", "mean_abs_torque_nm", "mean_reward"):
        assert math.isfinite(summary[key]) and math.isfinite(summary[key.replace("mean_", "se_")])
    assert json.loads((smoke_run / "status.json").read_text())["state"] == "done"


def test_smoke_logs_every_iteration(smoke_run):
    cfg = load(["compute=smoke"])
    rows = _rows(smoke_run / "metrics.csv")
    teacher = [r for r in rows if r["stage"] == "teacher"]
    student = [r for r in rows if r["stage"] == "student"]
    assert [int(r["iteration"]) for r in teacher] == list(range(1, cfg.teacher.iterations + 1))
    assert [int(r["iteration"]) for r in student] == list(range(1, cfg.distill.max_iterations + 1))
    steps = cfg.compute.num_envs * cfg.teacher.num_steps_per_env
    assert [int(r["env_steps"]) for r in teacher] == [steps * (i + 1) for i in range(len(teacher))]
    assert all(math.isfinite(float(r["loss"])) and float(r["loss"]) > -1e6 for r in student)
    mode_w = [float(r["mode_weight_0"]) + float(r["mode_weight_1"]) for r in student]
    assert all(abs(w - 1.0) < 1e-4 for w in mode_w)  # MDN mode weights sum to one
    # The smoke preset evaluates each stage once, at its end (eval_interval 0).
    assert cfg.teacher.eval_interval == 0 == cfg.distill.eval_interval
    evals = [r for r in _rows(smoke_run / "eval.csv") if r["stage"] == "student"]
    assert [int(r["iteration"]) for r in evals] == [cfg.distill.max_iterations]
    teacher_evals = [r for r in _rows(smoke_run / "eval.csv") if r["stage"] == "teacher"]
    assert [int(r["iteration"]) for r in teacher_evals] == [cfg.teacher.iterations]
    assert all(int(r["n_rollouts"]) == cfg.eval.num_rollouts for r in evals)
    text = (smoke_run / "stdout.txt").read_text()
    assert "scale: compute=smoke" in text and "ETA" in text and "summary (mean" in text
    # The smoke teacher has 2 iterations: the wall-time line comes after both.
    assert "[eta] measured " in text and " s/it over the first 2 iterations: teacher ~" in text
    assert "over the first 2 distillation iterations: distillation ~" in text


def test_smoke_checkpoints_load(smoke_run):
    teacher = load_checkpoint(smoke_run / "teacher" / "latest.pt", "teacher")
    student = load_checkpoint(smoke_run / "student" / "latest.pt", "student")
    assert teacher["iteration"] == 2 and student["iteration"] == 2
    assert teacher["layout"]["num_actions"] == 29 == student["layout"]["num_actions"]
    assert student["layout"]["image_hw"] == [24, 32]
    assert student["config"]["student"]["variant"] == "full"
    with pytest.raises(CheckpointError, match="not a 'student'|not a student"):
        load_checkpoint(smoke_run / "teacher" / "latest.pt", "student")


def test_student_checkpoint_rejects_other_variant(smoke_run):
    from march.store.checkpoint import check_layout

    payload = load_checkpoint(smoke_run / "student" / "latest.pt", "student")
    other = dict(payload["layout"], variant="no_mdn")
    with pytest.raises(CheckpointError, match="variant"):
        check_layout(payload["layout"], other, "student", "x.pt")


def _teacher_only(run_dir: Path, iterations: int, *overrides: str):
    # Evaluation episodes of 5 steps: these tests read the training rows and weights only.
    cfg = load(
        [
            "compute=smoke",
            "stage=teacher",
            f"teacher.max_iterations={iterations}",
            "eval.episode_length_s=0.1",
            *overrides,
        ]
    )
    run_pipeline(cfg, run_dir)
    return _rows(run_dir / "metrics.csv")


def test_resume_continues_iteration_count(tmp_path):
    short = "teacher.num_steps_per_env=2"  # the iteration count is checked, not the learning
    first = _teacher_only(tmp_path, 1, short)
    assert [r["iteration"] for r in first] == ["1"]
    rows = _teacher_only(tmp_path, 3, short)  # same dir: resumes from teacher/latest.pt
    assert [r["iteration"] for r in rows] == ["1", "2", "3"]
    assert int(rows[-1]["env_steps"]) == 3 * int(rows[0]["env_steps"])
    assert load_checkpoint(tmp_path / "teacher" / "latest.pt", "teacher")["iteration"] == 3


def test_same_seed_same_numbers(tmp_path):
    a = _teacher_only(tmp_path / "a", 1)
    b = _teacher_only(tmp_path / "b", 1)
    keys = ("value_loss", "surrogate_loss", "entropy", "action_std")
    assert [a[0][k] for k in keys] == [b[0][k] for k in keys]
    wa = load_checkpoint(tmp_path / "a" / "teacher" / "latest.pt", "teacher")["actor_state_dict"]
    wb = load_checkpoint(tmp_path / "b" / "teacher" / "latest.pt", "teacher")["actor_state_dict"]
    assert all(torch.equal(wa[k], wb[k]) for k in wa)


# ------------------------------------------------------- a checkpoint defines its policy


def test_smoke_checkpoints_define_their_policy(smoke_run):
    """The saved config of the real smoke checkpoints (clf, full) wins over today's choices."""
    for kind in ("teacher", "student"):
        path = str(smoke_run / kind / "latest.pt")
        payload = load_checkpoint(path, kind)
        overrides = ["compute=smoke", "stage=eval", f"eval.policy={kind}", "reward=modelfree"]
        with pytest.raises(ConfigError) as err:
            apply_checkpoint_config(load(overrides), payload, overrides, path, kind)
        assert f"reward=modelfree conflicts with {kind}_ckpt={path}" in str(err.value)
        assert "reward.name=clf" in str(err.value) and "\n" not in str(err.value)
        # Without the override the defaults give way: a modelfree default would become clf.
        cfg = load(["compute=smoke", "reward=modelfree"])
        new = apply_checkpoint_config(cfg, payload, ["compute=smoke"], path, kind)
        assert new.reward.name == "clf" and new.reward.terms == load(["compute=smoke"]).reward.terms
    payload = load_checkpoint(smoke_run / "student" / "latest.pt", "student")
    with pytest.raises(ConfigError, match="student=no_mdn conflicts .*student.variant=full"):
        apply_checkpoint_config(
            load(["student=no_mdn"]), payload, ["student=no_mdn"], "s", "student"
        )


@pytest.fixture(scope="module")
def modelfree_teacher(tmp_path_factory) -> Path:
    """An untrained teacher checkpoint written by TeacherRunner in the reward=modelfree env."""
    from march.config import LoggerCfg
    from march.env.build import make_env
    from march.learn.metrics import MetricsLog
    from march.learn.teacher import TeacherRunner

    run_dir = tmp_path_factory.mktemp("modelfree_teacher")
    cfg = load(["compute=smoke", "reward=modelfree", "stage=teacher"])
    env = make_env(cfg, "teacher", log=run_dir / "env.log")
    try:
        runner = TeacherRunner(env, cfg, run_dir, MetricsLog(run_dir, LoggerCfg(), "mf"))
        runner.save()
    finally:
        env.close()
    return run_dir / "teacher" / "latest.pt"


def _train(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "march.train", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=900,
    )


def test_eval_of_a_modelfree_teacher_runs_the_modelfree_env(modelfree_teacher, tmp_path, capfd):
    payload = load_checkpoint(modelfree_teacher, "teacher")
    common = [
        "compute=smoke",
        "stage=eval",
        "eval.policy=teacher",
        f"teacher_ckpt={modelfree_teacher}",
        "eval.episode_length_s=0.1",  # the env and its labels are checked, not the walking
    ]
    # An explicit clf is one line naming both, before anything is built (in this process: the
    # refusal's line, without a subprocess's start-up; the run below is a real process).
    out = run_tool(capfd, "march.train", *common, "reward=clf", f"hydra.run.dir={tmp_path / 'clf'}")
    assert out.returncode == 2, out.stderr[-2000:]
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: reward=clf conflicts with teacher_ckpt=")
    assert "reward.name=modelfree" in lines[0]
    assert not (tmp_path / "clf" / "env.log").exists()
    # No reward on the command line: the checkpoint's modelfree env and labels.
    run = tmp_path / "mf"
    out = _train(*common, f"hydra.run.dir={run}")
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    saved = OmegaConf.load(run / "config.yaml")
    assert saved.reward.name == "modelfree"
    assert dict(saved.reward.terms) == load(["reward=modelfree"]).reward.terms
    assert "defines the policy: reward.name: clf -> modelfree" in out.stdout
    assert "reward=modelfree" in out.stdout.split("scale:")[0]  # the banner
    # The eval env's actor observation is the modelfree one (no reference terms): the layout
    # the checkpoint was built on, which a clf env (checked in the smoke run) does not have.
    env_line = next(ln for ln in out.stdout.splitlines() if ln.startswith("[env] eval:"))
    assert f"obs actor ({payload['layout']['actor_obs_dim']},)" in env_line
    assert (
        json.loads((run / "summary.json").read_text())["n_rollouts"]
        == load(["compute=smoke"]).eval.num_rollouts
    )
