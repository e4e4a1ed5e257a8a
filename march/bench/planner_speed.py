"""``python -m march.bench planner``: how long the footstep planner takes, alone and in the env.

:func:`bench_planner` times the planner on :func:`march.world.synthetic.synthetic_courses` (no
simulator import). The ``planner`` job (:func:`bench_planner_share`) reports
:func:`bench_planner` (``steps`` timed replans of all ``num_envs`` envs on synthetic courses),
plus the march teacher env's step time measured in the same run: ``planner_share_of_env_step`` =
ms per full-batch replan / ms per env step (an upper bound: the env plans its reset envs plus one
fixed batch of 1/8 of the envs per step). ``in_env_*`` measures the planner calls the teacher env
itself made in its timed steps (random actions: mostly resets after falls); ``walk_*`` estimates
a walking robot's share: touchdown rate = control step / mean step duration of the planner's own
walks over generated courses, times one replan of that many envs.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable
from typing import Any

import torch

from march.bench.harness import Actions, free, stdout_to_stderr, sync
from march.bench.profiler import planner_timer
from march.config import MarchConfig
from march.reference.planner import PlannerCfg, plan_footsteps
from march.world.synthetic import synthetic_courses


def bench_planner(num_envs: int, device: str, repeats: int, seed: int) -> dict:
    """Time ``plan_footsteps`` for ``num_envs`` envs (difficulties spread over [0, 1]).

    Returns a dict with the setting and ms per replan (mean, p95, min) over ``repeats`` timed calls
    after one warm-up call, plus the fraction of feasible plans.
    """
    cfg = PlannerCfg()
    difficulties = torch.linspace(0.0, 1.0, num_envs).tolist()
    footholds = synthetic_courses(difficulties, seed=seed).to(device)
    stance = torch.zeros(num_envs, 2, device=device)
    stance[:, 1] = 0.5 * cfg.step_width
    stance[:, 0] = 0.3  # near the platform's front edge, the first stones in reach
    left = torch.ones(num_envs, dtype=torch.bool, device=device)
    command = torch.zeros(num_envs, 3, device=device)
    command[:, 0] = 0.6
    gen = torch.Generator(device=device).manual_seed(seed)

    plan = plan_footsteps(stance, left, command, footholds, cfg, gen)
    sync(device)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        plan = plan_footsteps(stance, left, command, footholds, cfg, gen)
        sync(device)
        times.append(1e3 * (time.perf_counter() - t0))
    ordered = sorted(times)
    p95 = ordered[min(len(ordered) - 1, int(round(0.95 * (len(ordered) - 1))))]
    return {
        "num_envs": num_envs,
        "device": str(device),
        "repeats": repeats,
        "torch_threads": torch.get_num_threads(),
        "ms_per_replan_mean": statistics.fmean(times),
        "ms_per_replan_p95": p95,
        "ms_per_replan_min": ordered[0],
        "feasible_fraction": float(plan.feasible.float().mean()),
    }


def time_env_steps(
    env: Any, steps: int, warmup: int, seed: int, planner: dict[str, float] | None = None
) -> float:
    """Seconds for ``steps`` control steps after ``warmup`` untimed ones, seeded random actions.
    ``planner`` (from :func:`planner_timer`) is cleared when the timed steps begin."""
    import torch

    device = str(env.device)
    env.reset()
    act = Actions(env, "random", seed)
    with torch.no_grad():
        for _ in range(warmup):
            env.step(act())
        sync(device)
        if planner is not None:
            planner.update(calls=0, envs=0, s=0.0)
        t0 = time.perf_counter()
        for _ in range(steps):
            env.step(act())
        sync(device)
        return time.perf_counter() - t0


def _measure(
    build: Callable[[], Any],
    steps: int,
    warmup: int,
    seed: int,
    device: str,
    planner: dict[str, float] | None = None,
) -> tuple[float, float, int]:
    """(build seconds, timed seconds, num_envs) of one env, closed afterwards."""
    t0 = time.perf_counter()
    env = build()
    build_s = time.perf_counter() - t0
    try:
        elapsed = time_env_steps(env, steps, warmup, seed, planner)
        n = env.num_envs
    finally:
        env.close()
        del env
        free(device)
    return build_s, elapsed, n


def touchdown_rate(cfg: MarchConfig, num_courses: int = 8) -> tuple[float, float]:
    """(mean planned step duration [s], touchdowns per env per control step) of the planner's
    own walks (:func:`march.reference.walk.walk_course`) over generated courses at difficulties
    spread over [0, 1], forward command = the middle of ``env.command_vx``."""
    import numpy as np
    import torch

    from march.reference.walk import walk_course
    from march.world.courses import generate_course
    from march.world.footholds import footholds_from_layouts

    rng = np.random.default_rng(cfg.seed)
    layouts = [generate_course(d, cfg.terrain, rng) for d in np.linspace(0, 1, num_courses)]
    footholds = footholds_from_layouts(layouts, np.stack([lay.origin for lay in layouts]))
    vx = 0.5 * (cfg.env.command_vx[0] + cfg.env.command_vx[1])
    command = torch.tensor([[vx, 0.0, 0.0]]).expand(num_courses, 3)
    walked, _ = walk_course(footholds, command, max_steps=60, seed=cfg.seed)
    durations = walked.durations[torch.isfinite(walked.durations)]
    mean_t = float(durations.mean())
    return mean_t, cfg.env.sim_dt * cfg.env.decimation / mean_t


def bench_planner_share(cfg: MarchConfig, steps: int, warmup: int) -> dict[str, Any]:
    from march.env.build import make_env
    from march.env.rewards import needs_reference

    n, device = cfg.compute.num_envs, cfg.compute.device
    result = bench_planner(n, device, steps, cfg.seed)
    with stdout_to_stderr(), planner_timer(device) as planner:
        print(f"[bench] march_teacher: building {n} envs on {device}", flush=True)
        build_s, elapsed, _ = _measure(
            lambda: make_env(cfg, "teacher"), steps, warmup, cfg.seed, device, planner
        )
    ms_env = 1e3 * elapsed / steps
    mean_t, rate = touchdown_rate(cfg)
    k = min(n, max(1, math.ceil(rate * n)))
    subset = bench_planner(k, device, steps, cfg.seed)
    in_env = needs_reference(cfg.reward)  # only the CLF teacher env runs the planner
    result.update(
        {
            "ms_per_env_step": ms_env,
            "env_build_s": round(build_s, 2),
            "planner_share_of_env_step": result["ms_per_replan_mean"] / ms_env,
            "in_env_planner_ms_per_env_step": 1e3 * planner["s"] / steps if in_env else None,
            "in_env_planner_share": 1e3 * planner["s"] / steps / ms_env if in_env else None,
            "in_env_replans_per_env_per_step": planner["envs"] / (n * steps) if in_env else None,
            "in_env_planner_calls_per_step": planner["calls"] / steps if in_env else None,
            "walk_mean_step_duration_s": mean_t,
            "walk_touchdown_rate_per_env_step": rate,
            "walk_envs_replanning_per_step": k,
            "walk_ms_per_replan_touchdown_envs": subset["ms_per_replan_mean"],
            "walk_planner_share_estimate": subset["ms_per_replan_mean"] / ms_env,
            "note": (
                "planner_share_of_env_step: one replan of all num_envs envs (synthetic courses, "
                "ms_per_replan_mean) per march teacher env step (random actions, same num_envs "
                "and device; the step already includes the env's own replans) - an upper bound. "
                "in_env_*: the planner calls the teacher env's reference command made during "
                "the timed steps (only envs at a reset, touchdown or step timeout replan; with "
                "random actions the robot falls, so resets dominate; null for reward=modelfree, "
                "which has no planner). walk_*: a walking estimate - touchdown rate = control "
                "step / mean planned step duration of the planner's own walks over generated "
                "courses, and the time of one replan of ceil(rate * num_envs) envs per step."
            ),
        }
    )
    return result
