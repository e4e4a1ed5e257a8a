"""Evaluations repeat exactly (planner included) and the teacher's episodes start staggered.

The sim test reads the session's smoke run (``python -m march.train compute=smoke``, the clf
teacher evaluated at its end on an eval env built before the teacher env and stepped beside it;
tests/conftest.py), evaluates its teacher checkpoint twice on one freshly built eval env in this
process, and once more in a fresh process (``python -m march.train stage=eval``): the four
teacher rows must be identical, digit for digit. One of the four renders the eval env's depth
camera, which the teacher does not see; the others pause it (``march.env.depth.camera_paused``),
as the pipeline does for a teacher.
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
def test_evaluations_of_one_clf_teacher_are_bit_identical(smoke_run, tmp_path):
    from march.env.build import make_env
    from march.env.reference_command import reference_term
    from march.evaluation.protocol import evaluate, policy_from_checkpoint
    from march.store.checkpoint import load_checkpoint

    # The smoke run's teacher (2 iterations) falls after 1.1-1.4 s of its 3 s episodes: each
    # evaluation's wave of 4 rollouts on 4 envs crosses the planner's timeout replans.
    cfg = load(["compute=smoke"])
    (trained,) = [r for r in _rows(smoke_run / "eval.csv") if r["stage"] == "teacher"]
    ckpt = smoke_run / "teacher" / "latest.pt"
    n = cfg.eval.num_rollouts

    here = tmp_path / "here"
    here.mkdir()
    env = make_env(cfg, "eval")
    try:
        payload = load_checkpoint(str(ckpt), "teacher", "cpu")
        policy = policy_from_checkpoint(env, cfg, "teacher", payload, str(ckpt))
        term = reference_term(env)
        torch.manual_seed(999)  # whatever the caller's random state, the rows repeat
        first = evaluate(env, policy, n, here, "teacher", 2, 0, sees_depth=False)
        torch.rand(17)
        ended = int((term.touchdown_count + term.forced_count).sum())
        # With the depth camera rendered (the run and the fresh process pause it for a teacher):
        # the render changes no number. (The standing floor is cached: the policy's rollouts.)
        second = evaluate(env, policy, n, here, "teacher", 2, 0, sees_depth=True)
        replans = int((term.touchdown_count + term.forced_count).sum()) - ended
    finally:
        env.close()

    fresh = tmp_path / "fresh"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "march.train",
            "compute=smoke",
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
    assert replans > 0  # steps ended and were replanned inside the rollouts (planner included)


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
