"""Evaluation protocol (SPEC §2): fixed-length rollouts, honest metrics measured from them.

Per rollout (one episode of ``eval.episode_length_s``, or until a fall):
- ``distance_m``: pelvis progress along the course from the start, clipped at the course end,
  taken at the last control step before the episode ended.
- ``success_rate``: 1 if the goal was reached and the episode ended by time-out, not by a fall.
- ``abs_torque_nm``: mean over control steps and joints of |actuator force| [N m].
- ``abs_ang_jerk``: mean over control steps and the three body axes of |d^2 omega / dt^2|, with
  omega the pelvis angular velocity in the body frame sampled at the control rate and the second
  derivative taken as (omega_t - 2 omega_{t-1} + omega_{t-2}) / dt^2 [rad/s^3]; the first two
  steps of an episode have no jerk.
- ``reward``: the episode's return under the teacher's full reward function (the env's reward).
Summary: mean and standard error (sample std / sqrt(n)) over ``eval.num_rollouts`` rollouts.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from mjlab.envs import ManagerBasedRlEnv

from march.config import MarchConfig
from march.env.course import CourseRuler
from march.learn.checkpoint import write_json_atomic
from march.learn.metrics import EVAL_COLUMNS, EVAL_METRICS, append_row

Policy = Callable[[dict[str, Any]], torch.Tensor]


def policy_from_checkpoint(
    env: ManagerBasedRlEnv, cfg: MarchConfig, kind: str, payload: dict[str, Any], path: str
) -> Policy:
    """The deterministic policy of a loaded teacher or student checkpoint on ``env``."""
    from march.learn.distill import load_student, student_policy
    from march.learn.teacher import build_teacher_actor, teacher_obs, teacher_policy

    obs = env.observation_manager.compute()
    num_actions = env.action_manager.total_action_dim
    if kind == "student":
        return student_policy(env, load_student(payload, cfg, obs, num_actions, path))
    td = teacher_obs(obs, env.num_envs)
    actor = build_teacher_actor(payload, td, num_actions, cfg.compute.device, path)
    return teacher_policy(env, actor)


def _summarise(per_rollout: dict[str, torch.Tensor]) -> dict[str, float]:
    out: dict[str, float] = {}
    for name in EVAL_METRICS:
        x = per_rollout[name].double()
        n = x.numel()
        out[f"mean_{name}"] = x.mean().item()
        out[f"se_{name}"] = (x.std(unbiased=True).item() / math.sqrt(n)) if n > 1 else float("nan")
    return out


@torch.no_grad()
def rollout_metrics(
    env: ManagerBasedRlEnv, policy: Policy, num_rollouts: int
) -> dict[str, torch.Tensor]:
    """Run waves of ``env.num_envs`` episodes until ``num_rollouts`` are collected."""
    ruler = CourseRuler(env)
    robot = env.scene["robot"]
    n_env, dev = env.num_envs, env.device
    horizon = int(env.max_episode_length)
    dt = env.step_dt
    collected: dict[str, list[torch.Tensor]] = {m: [] for m in EVAL_METRICS}
    total = 0
    while total < num_rollouts:
        obs, _ = env.reset()
        active = torch.ones(n_env, dtype=torch.bool, device=dev)
        ret = torch.zeros(n_env, device=dev)
        torque_sum = torch.zeros(n_env, device=dev)
        jerk_sum = torch.zeros(n_env, device=dev)
        steps = torch.zeros(n_env, device=dev)
        jerk_steps = torch.zeros(n_env, device=dev)
        dist = torch.zeros(n_env, device=dev)
        success = torch.zeros(n_env, device=dev)
        w_prev2 = w_prev1 = None
        for _ in range(horizon + 1):
            before = ruler.progress()
            obs, reward, terminated, truncated, _ = env.step(policy(obs))
            done = terminated | truncated
            ret += reward * active
            live = active & ~done  # post-step state belongs to this episode only if not reset
            torque_sum += robot.data.actuator_force.abs().mean(-1) * live
            steps += live.float()
            w = robot.data.root_link_ang_vel_b.clone()
            if w_prev2 is not None:
                jerk = ((w - 2 * w_prev1 + w_prev2) / dt**2).abs().mean(-1)
                ok = live & (steps >= 3)
                jerk_sum += jerk * ok
                jerk_steps += ok.float()
            w_prev2, w_prev1 = w_prev1, w
            ended = active & done
            dist = torch.where(ended, before, dist)
            success = torch.where(
                ended, (ruler.reached_goal(before) & ~terminated).float(), success
            )
            active &= ~done
            if not active.any():
                break
        take = min(n_env, num_rollouts - total)
        collected["distance_m"].append(dist[:take])
        collected["success_rate"].append(success[:take])
        collected["abs_torque_nm"].append((torque_sum / steps.clamp(min=1))[:take])
        collected["abs_ang_jerk"].append((jerk_sum / jerk_steps.clamp(min=1))[:take])
        collected["reward"].append(ret[:take])
        total += take
    return {k: torch.cat(v).cpu() for k, v in collected.items()}


def evaluate(
    env: ManagerBasedRlEnv,
    policy: Policy,
    num_rollouts: int,
    run_dir: Path,
    stage: str,
    iteration: int,
    env_steps: int,
) -> dict[str, Any]:
    """Roll out, append a row to ``eval.csv`` and return the summary row."""
    per = rollout_metrics(env, policy, num_rollouts)
    row = {
        "stage": stage,
        "iteration": iteration,
        "env_steps": env_steps,
        "n_rollouts": num_rollouts,
        **_summarise(per),
    }
    append_row(run_dir / "eval.csv", EVAL_COLUMNS, row)
    return row


def write_summary(row: dict[str, Any], run_dir: Path, extra: dict[str, Any]) -> Path:
    path = run_dir / "summary.json"
    write_json_atomic({**row, **extra}, path)
    return path


def format_summary(row: dict[str, Any]) -> str:
    def pm(name: str, unit: str = "", scale: float = 1.0) -> str:
        return f"{row[f'mean_{name}'] * scale:.3g} ± {row[f'se_{name}'] * scale:.2g}{unit}"

    return (
        f"  rollouts          {row['n_rollouts']}\n"
        f"  distance          {pm('distance_m', ' m')}\n"
        f"  success           {pm('success_rate', ' %', 100.0)}\n"
        f"  |joint torque|    {pm('abs_torque_nm', ' N m')}\n"
        f"  |angular jerk|    {pm('abs_ang_jerk', ' rad/s^3')}\n"
        f"  teacher reward    {pm('reward')} (episode return)"
    )
