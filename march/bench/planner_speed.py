"""Timing of the footstep planner on synthetic stepping-stone courses (no simulator import).

``synthetic_courses`` builds simple straight courses whose stone size, gap, zig-zag, height
variation and side-by-side pairs grow with a difficulty in [0, 1]; it stands in for the terrain
generator's foothold tables so the planner can be timed and drawn without mjlab.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Sequence

import torch

from march.reference.planner import PlannerCfg, plan_footsteps
from march.world.footholds import Footholds

PLATFORM_HALF = 0.6
"""Half size of the square start and goal platforms [m]."""


def _lerp(a: float, b: float, t: float) -> float:
    return a + (b - a) * t


def _course(difficulty: float, length: float, rng: torch.Generator) -> list[list[float]]:
    """Rectangles [x, y, z, hx, hy] of one course: start platform, stones, goal platform."""

    def uni(lo: float, hi: float) -> float:
        return lo + (hi - lo) * float(torch.rand((), generator=rng))

    size = _lerp(0.45, 0.25, difficulty)
    gap = _lerp(0.10, 0.40, difficulty)
    zig = _lerp(0.0, 0.12, difficulty)
    dz = _lerp(0.0, 0.08, difficulty)
    p_pair = _lerp(0.0, 0.3, difficulty)
    rects = [[0.0, 0.0, 0.0, PLATFORM_HALF, PLATFORM_HALF]]
    x_edge, k = PLATFORM_HALF, 0
    while x_edge < length:
        s = size * uni(0.9, 1.1)
        x = x_edge + gap * uni(0.8, 1.0) + 0.5 * s
        y = (zig if k % 2 == 0 else -zig) + uni(-0.03, 0.03)
        if uni(0.0, 1.0) < p_pair:
            # A side-by-side pair: a left/right choice for the planner.
            for sign in (-1.0, 1.0):
                rects.append([x, sign * (0.5 * s + 0.1), uni(-dz, dz), 0.5 * s, 0.5 * s])
        else:
            rects.append([x, y, uni(-dz, dz), 0.5 * s, 0.5 * s])
        x_edge, k = x + 0.5 * s, k + 1
    x_goal = x_edge + gap + PLATFORM_HALF
    rects.append([x_goal, 0.0, 0.0, PLATFORM_HALF, PLATFORM_HALF])
    return rects


def synthetic_courses(
    difficulties: Sequence[float], seed: int = 0, length: float = 6.0
) -> Footholds:
    """One straight course along +x per difficulty; start at the origin on the start platform."""
    rng = torch.Generator().manual_seed(seed)
    courses = [_course(float(d), length, rng) for d in difficulties]
    e, s = len(courses), max(len(c) for c in courses)
    table = torch.zeros(e, s, 5)
    valid = torch.zeros(e, s, dtype=torch.bool)
    for i, course in enumerate(courses):
        table[i, : len(course)] = torch.tensor(course)
        valid[i, : len(course)] = True
    goal = torch.tensor([c[-1][0] - c[-1][3] for c in courses])
    end = torch.tensor([c[-1][0] + c[-1][3] for c in courses])
    direction = torch.zeros(e, 2)
    direction[:, 0] = 1.0
    return Footholds(
        center=table[..., :3],
        half_size=table[..., 3:],
        valid=valid,
        start_xy=torch.zeros(e, 2),
        direction=direction,
        goal_distance=goal,
        course_length=end,
    )


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

    def sync() -> None:
        if torch.device(device).type == "cuda":
            torch.cuda.synchronize()

    plan = plan_footsteps(stance, left, command, footholds, cfg, gen)
    sync()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        plan = plan_footsteps(stance, left, command, footholds, cfg, gen)
        sync()
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
