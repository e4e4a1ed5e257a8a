"""march.play: argument errors (fast) and a short filmed rollout of a student (sim)."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import asdict
from pathlib import Path

import pytest
import torch

from march import play
from march.env import rendering

REPO = Path(__file__).resolve().parent.parent


def test_no_checkpoint_exits_2_with_one_line():
    proc = subprocess.run(
        [sys.executable, "-m", "march.play", "out=x.mp4"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert proc.stderr.startswith("error: give a checkpoint: student_ckpt=<file>")
    assert len(proc.stderr.strip().splitlines()) == 1
    assert "Traceback" not in proc.stderr


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["student_ckpt=nope.pt"], "student_ckpt=nope.pt: no such file"),
        (["teacher_ckpt=nope.pt"], "teacher_ckpt=nope.pt: no such file"),
        (["student_ckpt=a.pt", "teacher_ckpt=b.pt"], "not both"),
        (["student_ckpt={ckpt}", "out=video.avi"], "out=video.avi: write a video ending in"),
        (["student_ckpt={ckpt}"], "this is a 'teacher' checkpoint, not a student"),
        (["teacher_ckpt={junk}"], "not a readable checkpoint"),
    ],
)
def test_argument_errors(args, message, tmp_path, capsys):
    ckpt, junk = tmp_path / "teacher.pt", tmp_path / "junk.pt"
    torch.save({"kind": "teacher"}, ckpt)
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(SystemExit) as exc:
        play.main([a.format(ckpt=ckpt, junk=junk) for a in args])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err


@pytest.mark.sim
def test_play_writes_a_moving_video_of_a_student(tmp_path):
    why = rendering.rendering_error()  # first: without a GL library even ``import mujoco`` fails
    if why:
        pytest.skip(f"offscreen rendering unavailable: {why}")
    import imageio.v3 as iio

    from march.config.cli import load
    from march.env.build import make_env
    from march.learn.distill import build_student, student_layout

    torch.set_num_threads(1)
    ckpt, out = tmp_path / "student.pt", tmp_path / "rollout.gif"
    cfg = load(["compute=smoke", "eval.episode_length_s=0.5", f"student_ckpt={ckpt}", f"out={out}"])
    env = make_env(cfg, "eval", num_envs=1)
    try:
        # A freshly initialised student stands in for a trained one (same layout, same loader).
        obs, _ = env.reset()
        layout = student_layout(obs, cfg, env.action_manager.total_action_dim)
        student = build_student(cfg, layout, cfg.compute.device)
        payload = {
            "kind": "student",
            "iteration": 0,
            "env_steps": 0,
            "config": asdict(cfg),
            "layout": layout,
            "student_state_dict": student.state_dict(),
        }
        torch.save(payload, ckpt)
        result = play.play(cfg, env=env)
        horizon = int(env.max_episode_length)
        stride = play.frame_stride(env.step_dt)
    finally:
        env.close()

    assert result.out == out and out.is_file()
    assert result.fps == pytest.approx(1.0 / (stride * cfg.env.sim_dt * cfg.env.decimation))
    if not result.fell:
        assert result.steps == horizon
    assert result.frames == play.expected_frames(result.steps, stride)
    frames = iio.imread(out, index=None)
    assert frames.shape[0] == result.frames
    assert frames.shape[1:3] == (rendering.HEIGHT, rendering.WIDTH)
    assert any(not (frames[i] == frames[0]).all() for i in range(1, len(frames)))
    assert result.distance_m >= 0.0


def test_checkpoint_policy_conflict_is_one_line_before_any_env(tmp_path, capsys):
    """A modelfree student checkpoint played with reward=clf: one line naming both values."""
    from march.config.cli import load

    ckpt = tmp_path / "student.pt"
    torch.save({"kind": "student", "config": asdict(load(["reward=modelfree"]))}, ckpt)
    with pytest.raises(SystemExit) as exc:
        play.main([f"student_ckpt={ckpt}", "reward=clf", f"out={tmp_path / 'x.mp4'}"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert err.startswith(f"error: reward=clf conflicts with student_ckpt={ckpt}")
    assert "reward.name=modelfree" in err
    assert not (tmp_path / "x.env.log").exists()  # no env was built
