"""Evaluations repeat exactly (planner included) and the teacher's episodes start staggered.

The sim test trains a one-iteration clf teacher (smoke preset; the run evaluates it once, on
an eval env built before the teacher env and stepped beside it), evaluates its checkpoint
twice on one freshly built eval env in this process, and once more in a fresh process
(``python -m march.train stage=eval``): the four eval rows must be identical, digit for digit.
One of the four renders the eval env's depth camera, which the teacher does not see; the
others pause it (``march.env.depth.camera_paused``), as the pipeline does for a teacher.
"""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from march.config.cli import load

ROOT = Path(__file__).resolve().parent.parent
METRICS = (
    "n_rollouts",
    "mean_distance_m",
    "se_distance_m",
    "mean_success_rate",
    "mean_abs_torque_nm",
    "se_abs_torque_nm",
    "mean_abs_ang_jerk",
    "se_abs_ang_jerk",
    "mean_reward",
    "se_reward",
    "n_torque",
    "n_jerk",
)


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def _metrics(row: dict) -> tuple[str, ...]:
    return tuple(str(row[k]) for k in METRICS)


@pytest.mark.sim
def test_evaluations_of_one_clf_teacher_are_bit_identical(tmp_path):
    from march.env.build import make_env
    from march.evaluation.protocol import evaluate, policy_from_checkpoint
    from march.store.checkpoint import load_checkpoint
    from march.train import run_pipeline

    # 6 rollouts on 4 envs: two waves; 1 s episodes (the smoke teacher falls after ~1.2 s, so
    # the waves run to the horizon and cross the planner's replans).
    common = ["compute=smoke", "reward=clf", "eval.num_rollouts=6", "eval.episode_length_s=1.0"]
    cfg = load([*common, "stage=teacher", "teacher.max_iterations=1"])
    train_dir = tmp_path / "train"
    run_pipeline(cfg, train_dir)
    (trained,) = _rows(train_dir / "eval.csv")
    ckpt = train_dir / "teacher" / "latest.pt"

    here = tmp_path / "here"
    here.mkdir()
    env = make_env(cfg, "eval")
    try:
        payload = load_checkpoint(str(ckpt), "teacher", "cpu")
        policy = policy_from_checkpoint(env, cfg, "teacher", payload, str(ckpt))
        torch.manual_seed(999)  # whatever the caller's random state, the rows repeat
        first = evaluate(env, policy, 6, here, "teacher", 1, 0, sees_depth=False)
        torch.rand(17)
        # With the depth camera rendered (the run and the fresh process pause it for a teacher):
        # the render changes no number.
        second = evaluate(env, policy, 6, here, "teacher", 1, 0, sees_depth=True)
    finally:
        env.close()

    fresh = tmp_path / "fresh"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "march.train",
            *common,
            "stage=eval",
            "eval.policy=teacher",
            f"teacher_ckpt={ckpt}",
            f"hydra.run.dir={fresh}",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=900,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    (again,) = _rows(fresh / "eval.csv")

    rows = [_metrics(r) for r in (trained, *_rows(here / "eval.csv"), again)]
    assert len(rows) == 4
    assert all(r == rows[0] for r in rows), rows
    assert first["mean_reward"] == second["mean_reward"]  # the floats themselves, not only text
    assert float(trained["mean_reward"]) != 0.0  # a real rollout was measured


@pytest.mark.sim
def test_teacher_episodes_start_at_seeded_random_steps():
    """The teacher env's episode counters after staggering: spread over [0, max length), the
    same for the same (seed, iteration), another draw after a resume at another iteration,
    and the global random stream untouched."""
    from march.env.build import make_env
    from march.learn.teacher import stagger_episodes

    # 1 s episodes: a 50-step horizon, crossed in full below (the check walks every step of it)
    cfg = load(
        ["compute=smoke", "reward=modelfree", "compute.num_envs=16", "env.episode_length_s=1.0"]
    )
    env = make_env(cfg, "teacher")
    try:
        horizon = int(env.max_episode_length)
        state = torch.get_rng_state()
        a = stagger_episodes(env, cfg.seed, 0)
        assert torch.equal(torch.get_rng_state(), state)
        assert torch.equal(env.episode_length_buf.cpu(), a.to(env.episode_length_buf.dtype))
        assert int(a.min()) >= 0 and int(a.max()) < horizon
        assert len(set(a.tolist())) >= 8  # 16 envs over 50 steps: spread, not in lockstep
        assert torch.equal(stagger_episodes(env, cfg.seed, 0), a)
        assert not torch.equal(stagger_episodes(env, cfg.seed, 5), a)
        # Envs near the horizon time out first: resets spread over the first episode.
        stagger_episodes(env, cfg.seed, 0)
        n_act = env.action_manager.total_action_dim
        first_reset = torch.full((env.num_envs,), -1)
        for t in range(horizon):
            _, _, term, trunc, _ = env.step(torch.zeros(env.num_envs, n_act))
            done = (term | trunc).cpu() & (first_reset < 0)
            first_reset[done] = t
        timed_out_early = (a >= horizon // 2) & (first_reset >= 0)
        assert bool(((first_reset[timed_out_early]) <= horizon - a[timed_out_early]).all())
    finally:
        env.close()
