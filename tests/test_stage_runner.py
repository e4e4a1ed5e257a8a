"""The loop both training stages share (march.learn.stage_runner.StageRunner): what a real
smoke run logs and checkpoints through it, and a preemption and resume of each stage through
the one skeleton."""

from __future__ import annotations

import csv
import math
import os
import signal
from pathlib import Path

import pytest

from march.config.cli import load
from march.learn import preemption
from march.learn.distill import DistillRunner
from march.learn.stage_runner import StageRunner
from march.learn.teacher import TeacherRunner
from march.store.checkpoint import load_checkpoint

pytestmark = pytest.mark.sim

#: What a checkpoint of either stage holds besides its algorithm's entries (older readers,
#: resume and provenance read these).
COMMON_KEYS = (
    "kind", "iteration", "env_steps", "wall_s", "config", "layout", "rng",
    "common_step_counter", "curriculum", "episode", "streams",
)  # fmt: skip
#: The distillation loss parts the smoke student (full: an MDN head) reports each iteration.
MDN_PARTS = ("loss", "nll", "action_error", "mode_weight_0", "mode_weight_1", "top_mode_weight")


def _rows(path: Path, stage: str) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return [r for r in csv.DictReader(f) if r["stage"] == stage]


def test_both_runners_are_the_one_skeleton():
    assert issubclass(TeacherRunner, StageRunner) and issubclass(DistillRunner, StageRunner)
    for runner in (TeacherRunner, DistillRunner):  # the loop is not redefined by a stage
        for name in ("learn", "try_resume", "save", "payload", "evaluate"):
            assert getattr(runner, name) is getattr(StageRunner, name), (runner, name)


def test_smoke_run_logs_per_term_and_loss_columns(smoke_run):
    """Every iteration of `python -m march.train compute=smoke`: one reward/<term> column per
    active reward term, termination/<term> fractions, and the distillation's loss/<part>."""
    cfg = load(["compute=smoke"])
    terms = [k for k, w in cfg.reward.terms.items() if w]
    teacher = _rows(smoke_run / "metrics.csv", "teacher")
    student = _rows(smoke_run / "metrics.csv", "student")
    assert len(teacher) == cfg.teacher.iterations and len(student) == cfg.distill.max_iterations
    for row in teacher + student:  # the student env runs the teacher's reward terms too
        for term in terms:
            assert math.isfinite(float(row[f"reward/{term}"])), (row["stage"], term)
        # Fractions of the episodes that ended (empty: none ended in the iteration).
        assert {"termination/time_out", "termination/nonfinite"} <= row.keys()
        ended = {k: float(v) for k, v in row.items() if k.startswith("termination/") and v}
        assert all(0.0 <= v <= 1.0 for v in ended.values()), ended
    for row in student:
        for part in MDN_PARTS:
            assert math.isfinite(float(row[f"loss/{part}"])), part
        assert float(row["loss/loss"]) == float(row["loss"])
        assert float(row["loss/action_error"]) == float(row["action_error"])
    assert all(row["loss/nll"] == "" for row in teacher)  # a teacher row has no loss parts


def test_smoke_checkpoints_hold_the_common_entries(smoke_run):
    for stage in ("teacher", "student"):
        payload = load_checkpoint(smoke_run / stage / "latest.pt", stage)
        missing = [k for k in COMMON_KEYS if k not in payload]
        assert not missing, (stage, missing)
        assert payload["kind"] == stage and payload["iteration"] == 2
    student = load_checkpoint(smoke_run / "student" / "latest.pt", "student")
    assert {"student_state_dict", "optimizer_state_dict", "generator", "teacher_ckpt"} <= set(
        student
    )
    assert "distill" in student["streams"]  # the distillation generator, restored on resume


@pytest.mark.parametrize("save_interval", [1, 2])
@pytest.mark.parametrize("stage", ["teacher", "student"])
def test_a_preempted_stage_names_its_checkpoint_and_resumes_there(
    stage, save_interval, smoke_run, tmp_path
):
    """SIGTERM during iteration 1 of 3: the iteration is checkpointed (a save point with
    save_interval 1, else by the preemption), the stop names that file, and a new runner
    resumes there."""
    from march.env.build import make_env
    from march.learn.metrics import MetricsLog

    group = "teacher" if stage == "teacher" else "distill"
    teacher = smoke_run / "teacher" / "latest.pt"
    cfg = load(
        ["compute=smoke", f"{group}.save_interval={save_interval}", f"teacher_ckpt={teacher}"]
    )

    def runner(env, log):
        if stage == "teacher":
            return TeacherRunner(env, cfg, tmp_path, log)
        payload = load_checkpoint(teacher, "teacher")
        return DistillRunner(env, cfg, tmp_path, log, payload, str(teacher))

    envs = [make_env(cfg, stage)]
    log = MetricsLog(tmp_path, cfg.logger, stage)
    assert preemption.install()
    try:
        first = runner(envs[0], log)
        assert not first.try_resume()
        os.kill(os.getpid(), signal.SIGTERM)  # recorded; the iteration goes on to its end
        with pytest.raises(preemption.Preempted) as stop:
            first.learn(3)
        saved = tmp_path / stage / "model_000001.pt"
        assert (stop.value.stage, stop.value.iteration) == (stage, 1)
        assert stop.value.checkpoint == saved and saved.is_file()
        assert str(saved) in stop.value.line()
        assert [r["iteration"] for r in _rows(tmp_path / "metrics.csv", stage)] == ["1"]
        preemption.uninstall()
        # The requeued run: a new process builds its env afresh and resumes.
        envs.append(make_env(cfg, stage))
        again = runner(envs[1], log)
        assert again.try_resume()
        assert (again.iteration, again.env_steps) == (1, first.env_steps)
        again.learn(2)  # iteration 2: a save point
        assert [r["iteration"] for r in _rows(tmp_path / "metrics.csv", stage)] == ["1", "2"]
        assert load_checkpoint(tmp_path / stage / "latest.pt", stage)["iteration"] == 2
    finally:
        preemption.uninstall()
        log.close()
        for env in envs:
            env.close()
