"""Synthetic stepping-stone courses: straight courses whose difficulty is one number.

``synthetic_courses`` builds simple straight courses whose stone size, gap, zig-zag, height
variation and side-by-side pairs grow with a difficulty in [0, 1]; it stands in for the terrain
generator's foothold tables so the planner can be timed (``march.bench.planner_speed``), drawn
(``march.viz.plan_view``) and tested without mjlab. Pure torch: no simulator import.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

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
