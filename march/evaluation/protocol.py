"""Evaluation protocol (SPEC §2): rollouts that end at the goal, honest metrics measured from them.

One protocol for every arm (reward=clf and reward=modelfree, either curriculum, teacher or
student): the eval env (``march.env.build``, purpose ``eval``) ends a rollout by success (the
first control step the pelvis is over the goal platform, ``goal_reached``), a fall, or the
time-out (``EVAL_TERMINATIONS``); it runs held-out stone courses of every difficulty level
(``eval.terrain_seed``, no training course of either curriculum) with DR and depth corruption
as in training and the forward command ``eval.command_vx`` along the course.

Sampling: rollout i runs on course cell (level i mod L, column (i // L + i mod L) mod C)
(:func:`march.env.course.eval_cells`), in waves of ``env.num_envs``; each env contributes the
first episode of its wave (:mod:`march.evaluation.sharding` deals the waves to the ranks of an
N-process run). Every level gets floor(n/L) or ceil(n/L) of the n rollouts, so the plain mean
over rollouts weights the levels (nearly) equally.

Seeding: every random number of rollout i (reset pose, DR, observation noise and delays,
pushes, command, depth corruption, the planner's samples) is keyed by (the run's seed
``env.cfg.seed``, i) (:mod:`march.env.rollout_draws`): rollout i gives the same row whatever the
wave size, its place in the wave, the number of ranks, or what the env ran before. Training's
random stream is left untouched (torch's state is forked), the env's own state is put back where
a full reset makes it independent of its past (:func:`march.env.build.reseed_env`); two
evaluations of one checkpoint give bit-identical rows, the first after the env is built as
later ones.

Per rollout (its env's first episode, up to its end: success, fall or time-out), computed from
per-step tensors by :func:`episode_metrics`:
- ``success_rate``: 1 if the episode ended by the success termination and not by a fall in the
  same step (a fall and the goal in one step count as a fall).
- ``distance_m``: the farthest progress along the course that both feet reached during the
  rollout (the rear foot's progress, :meth:`march.env.course.CourseRuler.foothold_progress`),
  the goal distance for a success. Measured at the feet, not the pelvis: toppling forward
  moves the pelvis ~0.56 m along the course (zero action, cpu preset) and the feet ~0.03 m,
  so a fall is not paid as progress (issue 56). ``pelvis_distance_m`` (eval_rollouts.csv) is
  the former measure, the pelvis progress at the last control step before the end, for
  comparison.
- ``abs_torque_nm``: mean over the episode's live control steps (those whose post-step state
  still belongs to it) and joints of |actuator force| [N m]; undefined with no live step.
- ``abs_ang_jerk``: mean over live control steps and the three body axes of |d^2 omega / dt^2|,
  with omega the pelvis angular velocity in the body frame sampled at the control rate and the
  second derivative taken as (omega_t - 2 omega_{t-1} + omega_{t-2}) / dt^2 [rad/s^3]; the first
  two steps have none, so it is undefined with fewer than 3 live steps. Never spans a reset.
- ``reward``: the episode's return under the teacher's full reward function (the env's reward).
Summary: mean and standard error (sample std / sqrt(n)) over the rollouts where the metric is
defined; ``n_torque`` / ``n_jerk`` count those for torque and jerk (a rollout too short for them
is left out, not counted as 0).

The standing floor: every evaluation row also carries the zero action's distance, success and
return on the same rollouts (same courses, same keyed draws; ``floor_*`` columns,
:func:`standing_floor`), computed once per eval env and printed beside the policy's: a distance
is read against what doing nothing scores there.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from contextlib import nullcontext
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from march.config import MarchConfig
from march.env.build import SUCCESS_TERMINATION, reseed_env
from march.env.clf_meter import pop_clf, pop_clf_pooled
from march.env.course import CourseRuler, assign_eval_cells, eval_cells
from march.env.depth import camera_paused
from march.env.rollout_draws import KeyedDraws, keyed_draws
from march.env.solver_order import pinned as pinned_solver_order
from march.evaluation.sharding import sharded_rollouts
from march.learn import distributed
from march.learn.metrics import (
    EVAL_COLUMNS,
    EVAL_LEVEL_COLUMNS,
    EVAL_METRICS,
    EVAL_ROLLOUT_COLUMNS,
    append_row,
    append_rows,
    truncate_rows,
)

if TYPE_CHECKING:
    from mjlab.envs import ManagerBasedRlEnv

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


def episode_metrics(
    torque: torch.Tensor,
    ang_vel: torch.Tensor,
    reward: torch.Tensor,
    terminated: torch.Tensor,
    truncated: torch.Tensor,
    progress: torch.Tensor,
    goal_distance: torch.Tensor,
    dt: float,
    reached: torch.Tensor | None = None,
    deferred: torch.Tensor | None = None,
    foothold: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """Per-rollout metrics of E rollouts from T recorded control steps (pure tensor arithmetic).

    Step t records, for each env: ``torque[t]`` (E,) the mean |actuator force| over joints and
    ``ang_vel[t]`` (E, 3) the pelvis angular velocity (body frame) read after ``env.step`` (the
    post-step state, which is the next episode's after an auto-reset); ``reward[t]``,
    ``terminated[t]``, ``truncated[t]`` as the step returned them; ``progress[t]`` the progress
    along the course [m] read *before* the step; ``reached[t]`` the success termination of the
    step (the pelvis over the goal platform in the post-step state; the env also reports it as
    truncated). ``goal_distance`` (E,) [m]; ``dt`` the control step [s].

    Rollout e is its env's first episode: steps 0..end_e, end_e the first step with terminated,
    truncated or reached (a rollout still running at step T-1 counts as timed out there). Its
    live steps are t < end_e. Success: reached at end_e and not terminated (a fall) there.
    ``foothold[t]`` (E,): the progress both feet had reached, read before the step as
    ``progress`` (None: ``progress`` is the measure, e.g. a hand-made trajectory). Distance:
    the goal distance for a success, else the largest ``foothold[t]`` over t <= end_e (never past
    the goal); ``pelvis_distance_m`` the goal distance for a success, else ``progress[end_e]``.
    ``deferred[t]`` (E,): env-steps a due replan waited for the planner in step t (the replan
    queue's counter increments; None: no planner), summed over the episode's steps.
    Returns (E,) tensors keyed by ``EVAL_METRICS`` (torque NaN with no live step, jerk with
    fewer than 3; ``torque_success`` / ``jerk_success`` the same values for successful rollouts,
    NaN for the others; ``reward_per_step`` the return / ``episode_steps``), ``episode_steps``
    (end_e + 1, the control steps of the episode), ``pelvis_distance_m`` and
    ``deferred_replans``.
    """
    t_len, e = reward.shape
    if torque.shape != (t_len, e) or ang_vel.shape != (t_len, e, 3):
        raise ValueError(
            f"torque {tuple(torque.shape)} / ang_vel {tuple(ang_vel.shape)} do not match "
            f"reward {(t_len, e)} (want (T, E) and (T, E, 3))"
        )
    dev = reward.device
    if reached is None:
        reached = torch.zeros_like(terminated, dtype=torch.bool)
    if reached.shape != (t_len, e):
        raise ValueError(f"reached {tuple(reached.shape)} does not match reward {(t_len, e)}")
    done = terminated.bool() | truncated.bool() | reached.bool()
    ended = done.any(0)
    end = torch.where(
        ended, done.int().argmax(0), torch.full_like(ended, t_len - 1, dtype=torch.long)
    )
    t = torch.arange(t_len, device=dev)[:, None]
    live = t < end[None]
    in_episode = t <= end[None]
    nan = torch.tensor(float("nan"), device=dev, dtype=torch.float64)

    n_live = live.sum(0)
    torque_sum = torch.where(live, torque.double(), 0.0).sum(0)
    abs_torque = torch.where(n_live > 0, torque_sum / n_live.clamp(min=1), nan)

    w = ang_vel.double()
    jerk = torch.zeros(t_len, e, device=dev, dtype=torch.float64)
    if t_len >= 3:
        jerk[2:] = ((w[2:] - 2 * w[1:-1] + w[:-2]) / dt**2).abs().mean(-1)
    jerk_ok = live & (t >= 2)  # live at t => t-1 and t-2 are live: never across a reset
    n_jerk = jerk_ok.sum(0)
    jerk_sum = torch.where(jerk_ok, jerk, 0.0).sum(0)
    abs_jerk = torch.where(n_jerk > 0, jerk_sum / n_jerk.clamp(min=1), nan)

    idx = end[None]
    goal = goal_distance.double()
    fell = terminated.bool().gather(0, idx).squeeze(0) & ended
    success = reached.bool().gather(0, idx).squeeze(0) & ended & ~fell
    last_progress = torch.minimum(progress.double().gather(0, idx).squeeze(0), goal)
    feet = progress if foothold is None else foothold
    if feet.shape != (t_len, e):
        raise ValueError(f"foothold {tuple(feet.shape)} does not match reward {(t_len, e)}")
    reached_far = torch.where(in_episode, feet.double(), -math.inf).amax(0)
    distance = torch.where(success, goal, torch.minimum(reached_far, goal))
    ret = torch.where(in_episode, reward.double(), 0.0).sum(0)
    steps = (end + 1).double()
    if deferred is None:
        deferred_sum = torch.zeros(e, device=dev, dtype=torch.float64)
    else:
        deferred_sum = torch.where(in_episode, deferred.double(), 0.0).sum(0)
    return {
        "distance_m": distance,
        "pelvis_distance_m": torch.where(success, goal, last_progress),
        "success_rate": success.double(),
        "abs_torque_nm": abs_torque,
        "abs_ang_jerk": abs_jerk,
        "reward": ret,
        "reward_per_step": ret / steps,
        "torque_success": torch.where(success, abs_torque, nan),
        "jerk_success": torch.where(success, abs_jerk, nan),
        "episode_steps": steps,
        "deferred_replans": deferred_sum,
    }


def summarise(per_rollout: dict[str, torch.Tensor]) -> dict[str, float | int]:
    """mean_/se_ of each metric over the rollouts where it is defined (finite), the standard
    error being the unbiased sample std / sqrt(n) (NaN for n < 2); n_torque / n_jerk count the
    rollouts behind the torque and jerk means."""
    out: dict[str, float | int] = {}
    for name in EVAL_METRICS:
        x = per_rollout[name].double().flatten()
        x = x[torch.isfinite(x)]
        n = x.numel()
        out[f"mean_{name}"] = x.mean().item() if n else float("nan")
        out[f"se_{name}"] = (x.std(unbiased=True).item() / math.sqrt(n)) if n > 1 else float("nan")
    for count, name in COUNTED.items():
        out[count] = int(torch.isfinite(per_rollout[name]).sum())
    deferred = per_rollout.get("deferred_replans")
    out["deferred_replans"] = 0 if deferred is None else int(deferred.sum())
    return out


COUNTED = {
    "n_torque": "abs_torque_nm",
    "n_jerk": "abs_ang_jerk",
    "n_torque_success": "torque_success",
    "n_jerk_success": "jerk_success",
}
"""eval.csv count column -> the metric whose defined (finite) rollouts it counts."""


def _nanmean(x: torch.Tensor) -> float:
    x = x[torch.isfinite(x)]
    return x.mean().item() if x.numel() else float("nan")


def level_rows(per_rollout: dict[str, torch.Tensor], stage: str, iteration: int) -> list[dict]:
    """eval_levels.csv rows: per difficulty level, its rollouts and mean metrics (NaN where no
    rollout of the level defines the metric)."""
    rows = []
    levels = per_rollout["level"].long()
    for level in sorted(set(levels.tolist())):
        at = levels == level
        rows.append(
            {
                "stage": stage,
                "iteration": iteration,
                "level": level,
                "rollouts": int(at.sum()),
                "success": _nanmean(per_rollout["success_rate"][at].double()),
                "distance": _nanmean(per_rollout["distance_m"][at].double()),
                "torque": _nanmean(per_rollout["abs_torque_nm"][at].double()),
                "jerk": _nanmean(per_rollout["abs_ang_jerk"][at].double()),
                "torque_success": _nanmean(per_rollout["torque_success"][at].double()),
                "jerk_success": _nanmean(per_rollout["jerk_success"][at].double()),
            }
        )
    return rows


def rollout_rows(per_rollout: dict[str, torch.Tensor], stage: str, iteration: int) -> list[dict]:
    """eval_rollouts.csv rows: one per rollout, in rollout order, with its course cell."""
    cols = {
        "level": "level",
        "column": "column",
        "success": "success_rate",
        "distance": "distance_m",
        "pelvis_distance": "pelvis_distance_m",
        "torque": "abs_torque_nm",
        "jerk": "abs_ang_jerk",
        "reward": "reward",
        "reward_per_step": "reward_per_step",
        "episode_steps": "episode_steps",
        "deferred_replans": "deferred_replans",
    }
    cols = {k: v for k, v in cols.items() if v in per_rollout}  # a hand-made set may lack some
    values = {k: per_rollout[v].double().tolist() for k, v in cols.items()}
    ints = ("level", "column", "success", "episode_steps", "deferred_replans")
    rows = []
    for i in range(len(values["level"])):
        row: dict[str, Any] = {"stage": stage, "iteration": iteration, "rollout": i}
        for k in cols:
            v = values[k][i]
            row[k] = int(v) if k in ints else v
        rows.append(row)
    return rows


@torch.no_grad()
def _wave(env: ManagerBasedRlEnv, policy: Policy, ruler: CourseRuler) -> dict[str, torch.Tensor]:
    """Reset every env and step until each has finished its first episode; per-rollout metrics."""
    robot = env.scene["robot"]
    obs, _ = env.reset()
    goal = ruler.goal_distance.clone()
    keys = ("torque", "ang_vel", "reward", "terminated", "truncated", "progress", "reached")
    keys += ("foothold",)
    rec: dict[str, list[torch.Tensor]] = {k: [] for k in keys}
    queue = replan_queue(env)
    deferred: list[torch.Tensor] = []
    finished = torch.zeros(env.num_envs, dtype=torch.bool, device=env.device)
    clf_meter = getattr(env, "clf_meter", None)  # counts each rollout up to its end only
    for _ in range(int(env.max_episode_length) + 1):
        if clf_meter is not None:
            clf_meter.active = ~finished
        rec["progress"].append(ruler.progress())
        rec["foothold"].append(ruler.foothold_progress())
        before = None if queue is None else queue.deferred_count.clone()
        obs, reward, terminated, truncated, _ = env.step(policy(obs))
        if queue is not None:
            deferred.append(queue.deferred_count - before)
        rec["torque"].append(robot.data.actuator_force.abs().mean(-1))
        rec["ang_vel"].append(robot.data.root_link_ang_vel_b.clone())
        # mjlab returns its own reward / termination buffers, rewritten in place every step.
        rec["reward"].append(reward.clone())
        rec["terminated"].append(terminated.clone())
        rec["truncated"].append(truncated.clone())
        rec["reached"].append(env.termination_manager.get_term(SUCCESS_TERMINATION).clone())
        finished |= terminated | truncated
        if finished.all():
            break
    if clf_meter is not None:
        clf_meter.active = None
    s = {k: torch.stack(v) for k, v in rec.items()}
    if not torch.equal((s["terminated"] | s["truncated"]).any(0), finished):
        raise RuntimeError("evaluation: the recorded done flags lost an episode end")
    return episode_metrics(
        s["torque"],
        s["ang_vel"],
        s["reward"],
        s["terminated"],
        s["truncated"],
        s["progress"],
        goal,
        env.step_dt,
        s["reached"],
        torch.stack(deferred) if deferred else None,
        s["foothold"],
    )


def replan_queue(env: ManagerBasedRlEnv):
    """The reference command's replan queue (march.env.replan_queue), or None (no planner)."""
    from march.env.rewards import REFERENCE_COMMAND

    if REFERENCE_COMMAND not in env.command_manager.active_terms:
        return None
    return getattr(env.command_manager.get_term(REFERENCE_COMMAND), "queue", None)


def _eval_rng(env: ManagerBasedRlEnv):
    """A forked torch random state seeded with the env's seed (see module doc)."""
    dev = torch.device(env.device)
    devices = [dev.index or 0] if dev.type == "cuda" else []
    return torch.random.fork_rng(devices=devices)


def start_wave(env: ManagerBasedRlEnv, draws: KeyedDraws, first: int) -> None:
    """Rows b = 0.. of ``env`` run rollouts ``first + b`` from the next reset: their course cells,
    the env's own state put back where a full reset makes it independent of its past (the replans
    still queued, :func:`march.env.build.reseed_env`) and their keyed streams (``draws``)."""
    assign_eval_cells(env, first)
    reseed_env(env, draws.seed)
    draws.start_wave(first)


@torch.no_grad()
def rollout_metrics(
    env: ManagerBasedRlEnv,
    policy: Policy,
    num_rollouts: int,
    first: int = 0,
    seed: int | None = None,
) -> dict[str, torch.Tensor]:
    """Per-rollout metrics of ``num_rollouts`` rollouts on the stratified course cells, run in
    waves of ``env.num_envs`` (the last wave keeps its first envs, i.e. the next rollout
    indices). ``first``: the index of the first rollout (a rank's share of a distributed
    evaluation: one wave of march.evaluation.sharding); ``seed``: default the env's."""
    ruler = CourseRuler(env)
    collected: dict[str, list[torch.Tensor]] = {}
    total = 0
    seed = int(env.cfg.seed or 0) if seed is None else int(seed)
    with _eval_rng(env), keyed_draws(env, seed) as draws, pinned_solver_order():
        while total < num_rollouts:
            start_wave(env, draws, first + total)
            per = _wave(env, policy, ruler)
            take = min(env.num_envs, num_rollouts - total)
            rows, cols = env.scene.terrain.terrain_origins.shape[:2]
            level, column = eval_cells(first + total, take, rows, cols)
            dev = per["reward"].device
            per = {**per, "level": level.to(dev), "column": column.to(dev)}
            for k, v in per.items():
                collected.setdefault(k, []).append(v[:take])
            total += take
    return {k: torch.cat(v).cpu() for k, v in collected.items()}


FLOOR_COLUMNS = (
    "floor_distance_m",
    "floor_se_distance_m",
    "floor_success_rate",
    "floor_reward",
)
"""eval.csv / summary.json: the standing floor of the row's evaluation (:func:`standing_floor`):
the zero action's mean distance [m] and its standard error, success rate and mean return."""
FLOOR_CLF = "floor_clf/v_p50"
"""Arms with the reference: the zero action's median V/Vmax on the same rollouts (the signal
study's criterion C4 compares the deterministic policy's ``clf/v_p50`` with it)."""


def standing_floor(env: ManagerBasedRlEnv, num_rollouts: int) -> dict[str, float]:
    """The zero action (PD targets at the default pose) rolled out on the evaluation's own
    rollouts: the same courses and keyed draws as any policy's evaluation with this env and
    ``num_rollouts`` (the evaluation is seeded per rollout, so running it first changes no
    other row). Computed once per env and rollout count, then cached on the env. Returns the
    :data:`FLOOR_COLUMNS`."""
    cache = env.__dict__.setdefault("_march_standing_floor", {})
    key = (int(env.cfg.seed or 0), int(num_rollouts))
    if key not in cache:
        zeros = torch.zeros(env.num_envs, env.action_manager.total_action_dim, device=env.device)

        def stand(obs: dict[str, Any]) -> torch.Tensor:
            return zeros

        pop_clf(env)  # the CLF diagnostics of the standing rollouts only
        with camera_paused(env):  # standing looks at nothing
            s = summarise(sharded_rollouts(env, stand, num_rollouts, rollout_metrics))
        clf = pop_clf_pooled(env, distributed.gather_objects)  # {} without the reference
        cache[key] = {
            "floor_distance_m": s["mean_distance_m"],
            "floor_se_distance_m": s["se_distance_m"],
            "floor_success_rate": s["mean_success_rate"],
            "floor_reward": s["mean_reward"],
            **({FLOOR_CLF: clf["clf/v_p50"]} if "clf/v_p50" in clf else {}),
        }
    return dict(cache[key])


def evaluate(
    env: ManagerBasedRlEnv,
    policy: Policy,
    num_rollouts: int,
    run_dir: Path,
    stage: str,
    iteration: int,
    env_steps: int,
    sees_depth: bool = True,
) -> dict[str, Any]:
    """Roll out, append a row to ``eval.csv`` and return the summary row. Over N processes each
    rank runs its waves of the rollouts (march.evaluation.sharding) and every rank gets the
    summary of all of them. The row carries the standing floor (:func:`standing_floor`).
    ``sees_depth=False`` (a teacher): the env's depth camera is not rendered meanwhile
    (:func:`march.env.depth.camera_paused`; the same numbers, a cheaper step)."""
    floor = standing_floor(env, num_rollouts)  # before pop_clf: its CLF samples are not kept
    pop_clf(env)  # the CLF diagnostics of this evaluation's rollouts only (clf_meter)
    with nullcontext() if sees_depth else camera_paused(env):
        per = sharded_rollouts(env, policy, num_rollouts, rollout_metrics)  # N ranks: waves
    # {} without the reference command; every rank's samples pooled (quantiles of all of them)
    clf = pop_clf_pooled(env, distributed.gather_objects)
    row = {
        "stage": stage,
        "iteration": iteration,
        "env_steps": env_steps,
        "n_rollouts": num_rollouts,
        **summarise(per),
        **floor,
        **clf,
    }
    floor_cols = FLOOR_COLUMNS + ((FLOOR_CLF,) if FLOOR_CLF in floor else ())
    append_row(run_dir / "eval.csv", EVAL_COLUMNS + floor_cols + tuple(clf), row)
    # The side files follow eval.csv: rows of a resumed run's re-done evaluations replace the
    # ones written before the kill (eval.csv itself is truncated by the runners on resume).
    for side in ("eval_levels.csv", "eval_rollouts.csv"):
        truncate_rows(run_dir / side, stage, iteration - 1)
    append_rows(run_dir / "eval_levels.csv", EVAL_LEVEL_COLUMNS, level_rows(per, stage, iteration))
    append_rows(
        run_dir / "eval_rollouts.csv", EVAL_ROLLOUT_COLUMNS, rollout_rows(per, stage, iteration)
    )
    return row
