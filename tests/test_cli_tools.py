"""The thin CLIs: march.export, march.viz, march.bench (one command-line convention, SPEC §1)."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path

import pytest
import torch

from march.config import MarchConfig, StudentCfg
from march.policies.student import StudentPolicy

REPO = Path(__file__).resolve().parent.parent
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
A, H = 4, 5
P = 9 + 3 * A  # base_ang_vel 3, projected_gravity 3, joint_pos/joint_vel/actions A, command 3


def small_student_cfg(variant: str = "full") -> StudentCfg:
    return StudentCfg(
        variant=variant,
        cnn_channels=(4, 8),
        cnn_kernels=(3, 3),
        cnn_strides=(2, 2),
        d_model=32,
        n_heads=4,
        n_layers=1,
        dim_feedforward=64,
        fusion_mlp=(64,),
        head_hidden=(32,),
    )


def write_student_ckpt(path: Path, variant: str = "full") -> StudentPolicy:
    """A checkpoint in the format DistillRunner.payload() writes, with a tiny student."""
    torch.manual_seed(0)
    cfg = MarchConfig(student=small_student_cfg(variant))
    layout = {
        "variant": variant,
        "proprio_dim": P,
        "history_len": H,
        "image_hw": [24, 32],
        "num_actions": A,
    }
    policy = StudentPolicy(cfg.student, P, H, 3, (24, 32), A)
    # non-trivial normaliser statistics, so that baking them into the graph is exercised
    policy.update_normalization(torch.randn(64, H, P) * 2.0 + 1.0, torch.randn(64, 3))
    torch.save(
        {
            "kind": "student",
            "iteration": 7,
            # a whole number of its config's iterations (the disk gate checks it)
            "env_steps": 7 * cfg.distill.num_steps_per_env * cfg.compute.num_envs,
            "wall_s": 1.0,
            "config": asdict(cfg),
            "layout": layout,
            "teacher_ckpt": "outputs/run/teacher/latest.pt",
            "student_state_dict": policy.state_dict(),
        },
        path,
    )
    return policy


def run_module(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", *args], cwd=REPO, capture_output=True, text=True, timeout=300
    )


# ---------------------------------------------------------------------------------------------
# march.export


@pytest.mark.parametrize("variant", ["full", "no_mdn"])
def test_export_writes_onnx_with_parity_and_metadata(tmp_path, capsys, variant):
    from march.export.bundle import main
    from march.export.onnx_graph import read_onnx_metadata

    ckpt = tmp_path / "run" / "student" / "latest.pt"
    ckpt.parent.mkdir(parents=True)
    write_student_ckpt(ckpt, variant)
    main([f"student_ckpt={ckpt}"])
    out = capsys.readouterr().out
    onnx_file = ckpt.parent / "student.onnx"  # default: next to the checkpoint
    assert onnx_file.is_file() and onnx_file.stat().st_size > 10_000
    parity = float(re.search(r"max \|onnx - torch\| = (\S+)", out).group(1))
    assert 0.0 <= parity < 1e-4
    median, p95 = map(float, re.search(r"median (\S+) ms, p95 (\S+) ms", out).groups())
    assert 0.0 < median <= p95 < 1000.0
    assert f"wrote {onnx_file}" in out

    meta = read_onnx_metadata(onnx_file)
    assert meta["variant"] == variant and meta["iteration"] == "7"
    assert meta["teacher_ckpt"] == "run/teacher/latest.pt"  # no training-machine directories
    obs = json.loads(meta["observations"])
    assert obs["proprio_hist"]["shape"] == [1, H, P]
    names = [t["name"] for t in obs["proprio_hist"]["terms"]]
    assert names == [
        "base_ang_vel",
        "projected_gravity",
        "joint_pos",
        "joint_vel",
        "actions",
        "command",
    ]
    assert sum(t["dim"] for t in obs["proprio_hist"]["terms"]) == P
    assert obs["command"]["shape"] == [1, 3]
    assert obs["depth"]["shape"] == [1, 1, 24, 32] and obs["depth"]["range"] == [0.0, 1.0]
    assert json.loads(meta["actions"])["shape"] == [1, A]
    assert "normalised" in meta["input_depth"]  # not metres: the env feeds normalised depth


def test_export_out_override(tmp_path, capsys):
    from march.export.bundle import main

    ckpt = tmp_path / "ckpt.pt"
    write_student_ckpt(ckpt, "no_transformer")
    target = tmp_path / "deploy" / "g1.onnx"
    main([f"student_ckpt={ckpt}", f"out={target}"])
    assert target.is_file() and target.stat().st_size > 10_000
    assert not (tmp_path / "student.onnx").exists()
    assert f"wrote {target}" in capsys.readouterr().out


def test_export_metadata_for_the_g1_layout():
    from march.export.bundle import metadata

    payload = {
        "layout": {
            "variant": "full",
            "proprio_dim": 96,
            "history_len": 5,
            "image_hw": [24, 32],
            "num_actions": 29,
        },
        "config": asdict(MarchConfig()),
        "iteration": 1500,
    }
    meta = metadata(payload)
    assert all(isinstance(k, str) and isinstance(v, str) for k, v in meta.items())
    names = json.loads(meta["action_joint_names"])
    scale = json.loads(meta["action_scale"])
    default = json.loads(meta["default_joint_pos"])
    assert len(names) == len(scale) == len(default) == 29
    assert names[0] == "left_hip_pitch_joint" and names[-1] == "right_wrist_yaw_joint"
    assert all(0.0 < s < 1.0 for s in scale)
    assert default[names.index("left_knee_joint")] > 0.3  # the G1's bent-knee default pose
    terms = json.loads(meta["observations"])["proprio_hist"]["terms"]
    assert [t["dim"] for t in terms] == [3, 3, 29, 29, 29, 3]
    depth = json.loads(meta["observations"])["depth"]
    assert (depth["min_range_m"], depth["max_range_m"]) == (0.1, 3.0)


def test_export_missing_checkpoint_is_one_line_exit_2(tmp_path):
    res = run_module("march.export", f"student_ckpt={tmp_path / 'nope.pt'}")
    assert res.returncode == 2
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "no such file" in lines[0]
    assert "Traceback" not in res.stderr


def test_export_wrong_checkpoint_kind_and_no_argument(tmp_path, capsys):
    from march.export.bundle import main

    teacher = tmp_path / "teacher.pt"
    torch.save({"kind": "teacher", "iteration": 1}, teacher)
    with pytest.raises(SystemExit) as exc:
        main([f"student_ckpt={teacher}"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'teacher' checkpoint, not a student" in err[0]

    with pytest.raises(SystemExit) as exc:
        main([])
    assert exc.value.code == 2
    assert "student_ckpt=<file>" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------
# march.viz (terrain and plan need no simulator)


def test_viz_terrain_writes_png(tmp_path, capsys):
    from march.viz.views import main

    out = tmp_path / "t.png"
    main(["terrain", f"out={out}"])
    assert capsys.readouterr().out.strip().endswith(str(out))
    data = out.read_bytes()
    assert data[:8] == PNG_MAGIC and len(data) > 50_000


def test_viz_plan_writes_png(tmp_path, capsys):
    from march.viz.views import main

    out = tmp_path / "p.png"
    main(["plan", f"out={out}", "seed=1"])
    assert capsys.readouterr().out.strip().endswith(str(out))
    data = out.read_bytes()
    assert data[:8] == PNG_MAGIC and len(data) > 50_000


def test_viz_unknown_job_names_the_valid_ones():
    res = run_module("march.viz", "bogus")
    assert res.returncode == 2
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1
    for job in ("terrain", "depth", "plan"):
        assert job in lines[0]


# ---------------------------------------------------------------------------------------------
# Slow: these build real mjlab envs (left out of the default run; pytest -m slow)


@pytest.mark.slow
def test_viz_depth_writes_png(tmp_path):
    out = tmp_path / "d.png"
    res = run_module("march.viz", "depth", f"out={out}", "compute=cpu")
    assert res.returncode == 0, res.stderr[-2000:]
    data = out.read_bytes()
    assert data[:8] == PNG_MAGIC and len(data) > 20_000
    levels = [int(m) for m in re.findall(r"env \d: level (\d+)", res.stdout)]
    assert levels == [0, 3, 6, 9]


# march.bench's tests: tests/test_bench.py


# --------------------------------------------- what a run will cost (march.learn.eta, march.train)

ETA_CFG = [
    "compute=smoke",
    "compute.num_envs=8",
    "compute.eval_num_envs=4",
    "teacher.max_iterations=10",
    "teacher.num_steps_per_env=20",
    "teacher.eval_interval=4",
    "distill.max_iterations=6",
    "distill.num_steps_per_env=40",
    "distill.num_learning_epochs=2",
    "distill.eval_interval=4",
    "eval.num_rollouts=10",
    "eval.episode_length_s=2",
]


@pytest.mark.parametrize(
    ("seconds", "text"),
    [
        (0, "0 s"),
        (59.4, "59 s"),
        (60, "1 min"),
        (3599, "1 h"),
        (4200, "1 h 10 min"),
        (93600, "26 h"),
    ],
)
def test_format_duration(seconds, text):
    from march.learn.eta import format_duration

    assert format_duration(seconds) == text


def test_wall_time_estimate_by_hand():
    from march.config.cli import load
    from march.learn import eta

    cfg = load(ETA_CFG)
    k = eta.STEP_COSTS["cpu"]
    assert k.per_rollout_step
    # 2 s per iteration of which the rollout is 1.5 s: the other stages scale from the rollout.
    est = eta.estimate_wall_s(cfg, teacher_s_per_it=2.0, rollout_s_per_it=1.5)
    step = 1.5 / 20  # s per rollout step of the 8 teacher envs
    distill_it = step * 40 * (k.distill_rollout + 2 * k.distill_epoch)
    # 3 waves of 4 envs (10 rollouts) x 100 control steps, at 4 of the 8 envs.
    one_eval = 3 * 100 * step * k.eval * 4 / 8
    # Teacher evaluations at 4, 8 and the end (10); student at 4 and the final one; and the
    # standing floor once.
    assert eta.evaluation_counts(cfg) == (3, 2)
    assert est["teacher"] == pytest.approx(20.0)
    assert est["distill"] == pytest.approx(6 * distill_it)
    assert est["eval"] == pytest.approx(6 * one_eval)
    assert est["total"] == pytest.approx(20.0 + 6 * distill_it + 6 * one_eval)
    # Over 2 processes the 10 rollouts are dealt between 2 x 4 eval envs: 2 waves, not 3.
    two = eta.estimate_wall_s(cfg, teacher_s_per_it=2.0, rollout_s_per_it=1.5, world=2)
    assert two["eval"] == pytest.approx(6 * one_eval * 2 / 3)
    # Without the rollout's time (an older run's rows) the whole iteration is the step.
    whole = eta.estimate_wall_s(cfg, teacher_s_per_it=2.0)
    assert whole["eval"] == pytest.approx(6 * one_eval * 2.0 / 1.5)
    # Resumed at teacher iteration 4: 6 iterations and 2 teacher evaluations (+ the floor) left.
    est = eta.estimate_wall_s(cfg, teacher_s_per_it=2.0, teacher_from=4, rollout_s_per_it=1.5)
    assert est["teacher"] == pytest.approx(12.0) and est["eval"] == pytest.approx(5 * one_eval)
    # stage=student: distillation and its evaluations only, from the distillation's speed.
    cfg = load([*ETA_CFG, "stage=student"])
    est = eta.estimate_wall_s(cfg, distill_s_per_it=distill_it)
    assert est["teacher"] == 0.0 and est["distill"] == pytest.approx(6 * distill_it)
    assert est["eval"] == pytest.approx(3 * one_eval)
    # Distillation after a teacher in the same process: its eval env has the floor already.
    est = eta.estimate_wall_s(cfg, distill_s_per_it=distill_it, floor_done=True)
    assert est["eval"] == pytest.approx(2 * one_eval)
    # A GPU's factors are per whole iteration: its rollout is not timed apart.
    gpu = load([*ETA_CFG, "compute.device=cuda"])
    g = eta.STEP_COSTS["cuda"]
    est = eta.estimate_wall_s(gpu, teacher_s_per_it=2.0, rollout_s_per_it=1.5)
    assert est["eval"] == pytest.approx(6 * 3 * 100 * (2.0 / 20) * g.eval * 4 / 8)


def test_eta_line_after_the_first_iterations():
    from march.config.cli import load
    from march.learn import eta

    cfg = load(ETA_CFG)
    watch = eta.EtaWatch(cfg, echo=False)
    # Iteration 1 is the warm-up (3 s of one-off costs): measured are iterations 2-4.
    lines = [
        watch.observe({"stage": "teacher", "iteration": i, "wall_s": w})
        for i, w in ((1, 5.0), (2, 7.0), (3, 9.0), (4, 11.0), (5, 13.0))
    ]
    assert lines[:3] == [None, None, None] and lines[4] is None  # once, after iteration 4
    total = eta.estimate_wall_s(cfg, teacher_s_per_it=2.0)["total"]
    assert lines[3].startswith(
        "[eta] measured 2 s/it over iterations 2-4: teacher ~20 s, whole run "
        f"~{eta.format_duration(total)} (distillation ~"
    )
    distill = [
        watch.observe({"stage": "student", "iteration": i, "wall_s": 10.0 * i + 5})
        for i in (1, 2, 3, 4)
    ]
    est = eta.estimate_wall_s(cfg, 2.0, 10.0, teacher_from=10, floor_done=True)
    assert est["teacher"] == 0.0
    assert distill[:3] == [None, None, None]
    assert distill[3] == (
        "[eta] measured 10 s/it over distillation iterations 2-4: distillation ~1 min, with its "
        f"evaluations up to ~{eta.format_duration(est['distill'] + est['eval'])}"
    )
    # A stage of no more than 3 iterations left is measured whole: here a resumed one.
    watch = eta.EtaWatch(load([*ETA_CFG, "teacher.max_iterations=6"]), echo=False)
    watch.start("teacher", 4, 100.0)
    assert watch.observe({"stage": "teacher", "iteration": 5, "wall_s": 103.0}) is None
    line = watch.observe({"stage": "teacher", "iteration": 6, "wall_s": 106.0})
    assert line.startswith("[eta] measured 3 s/it over the first 2 iterations: teacher ~6 s")


def test_banner_says_the_chosen_scale():
    from march.config.cli import load
    from march.train import banner

    text = banner(load(["compute=auto"]), Path("outputs/x_cpu"), {}, auto=True)
    assert "scale: compute=cpu (compute=auto: no CUDA) on cpu" in text
    assert "[eta] line after the first 4 teacher iterations" in text  # 3 + the warm-up
    text = banner(load(["compute=smoke", "stage=eval"]), Path("x"), {})
    assert "scale: compute=smoke on cpu" in text and "[eta]" not in text
