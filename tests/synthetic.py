"""Hand-built Footholds for tests: straight courses with chosen stone size, gap and zig-zag."""

from __future__ import annotations

import torch

from march.world.footholds import Footholds

Rect = tuple[float, float, float, float, float]
"""(x, y, z_top, half_x, half_y) of one stone [m]."""


def make_footholds(courses: list[list[Rect]], start_xy: list[tuple[float, float]]) -> Footholds:
    """Footholds from per-env lists of rectangles (index 0 start platform, last goal platform)."""
    e, s = len(courses), max(len(c) for c in courses)
    center = torch.zeros(e, s, 3)
    half = torch.zeros(e, s, 2)
    valid = torch.zeros(e, s, dtype=torch.bool)
    for i, course in enumerate(courses):
        for j, (x, y, z, hx, hy) in enumerate(course):
            center[i, j] = torch.tensor([x, y, z])
            half[i, j] = torch.tensor([hx, hy])
            valid[i, j] = True
    start = torch.tensor(start_xy, dtype=torch.float32)
    goal = torch.tensor([c[-1][0] - c[-1][3] for c in courses]) - start[:, 0]
    end = torch.tensor([c[-1][0] + c[-1][3] for c in courses]) - start[:, 0]
    direction = torch.zeros(e, 2)
    direction[:, 0] = 1.0
    return Footholds(center, half, valid, start, direction, goal, end)


def straight_course(
    num_stones: int,
    stone_size: float,
    gap: float,
    zigzag: float = 0.0,
    heights: list[float] | None = None,
    platform: float = 0.6,
) -> list[Rect]:
    """Start platform around x = 0 (half size ``platform``), then square stones along +x with
    edge-to-edge ``gap``, centres alternating y = +/- zigzag, then a goal platform."""
    h = 0.5 * stone_size
    rects: list[Rect] = [(0.0, 0.0, 0.0, platform, platform)]
    x = platform + gap + h
    for k in range(num_stones):
        y = zigzag if k % 2 == 0 else -zigzag
        z = heights[k] if heights is not None else 0.0
        rects.append((x, y, z, h, h))
        x += stone_size + gap
    rects.append((x - h + platform, 0.0, 0.0, platform, platform))
    return rects


def grid_course(
    num_stones: int, pitch: float, width: float, stone_size: float, shift: list[float]
) -> list[Rect]:
    """Stones centred on a constant-step walk (x = k * pitch, y = -/+ width / 2 alternating,
    first one a right foot), each shifted along x by ``shift[k]``; start at a small pad."""
    h = 0.5 * stone_size
    rects: list[Rect] = [(0.0, 0.5 * width, 0.0, h, h)]
    for k in range(1, num_stones + 1):
        y = -0.5 * width if k % 2 == 1 else 0.5 * width
        rects.append((k * pitch + shift[k - 1], y, 0.0, h, h))
    return rects
