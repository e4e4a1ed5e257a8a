"""Privileged teacher observation terms: the stones ahead and the CLF reference.

Both are expressed relative to the base: positions as (dx, dy, dz) from the pelvis, with the
horizontal part rotated by -heading (a yaw-aligned pelvis frame), so they do not depend on where
an env's course lies in the world.
"""

from __future__ import annotations

import torch
from mjlab.envs import ManagerBasedRlEnv

from march.compiled_math import maybe_fused
from march.env.course import CourseRuler, foothold_table
from march.env.reference_command import reference_term
from march.env.step_cache import constant, root_frame, shared
from march.env.stone_terrain import max_boxes_in_reach, terrain_boxes

NUM_STONES = 5
"""K: stones observed ahead of the robot."""
STONE_FEATURES = 5
"""Per stone: dx, dy, dz (top-face centre from the pelvis) and half sizes along x, y."""
SCAN_SIZE = (1.6, 1.0)
"""Height-scan grid extent (along, across the heading) [m]: mjlab's G1 ``terrain_scan``."""
SCAN_RESOLUTION = 0.1
"""Height-scan grid spacing [m] (17 x 11 = 187 points)."""
SCAN_MAX_DISTANCE = 5.0
"""Height-scan range [m]: a point with nothing within this below the pelvis reads this."""


def scan_offsets(
    size: tuple[float, float] = SCAN_SIZE, resolution: float = SCAN_RESOLUTION, device: str = "cpu"
) -> torch.Tensor:
    """(N, 2) the scan points in the yaw-aligned pelvis frame, in the order of mjlab's
    ``GridPatternCfg`` (its own code makes them)."""
    from mjlab.sensor import GridPatternCfg

    offsets, _ = GridPatternCfg(size=size, resolution=resolution).generate_rays(None, device)
    return offsets[:, :2].contiguous()


def terrain_height_scan(
    env: ManagerBasedRlEnv,
    size: tuple[float, float] = SCAN_SIZE,
    resolution: float = SCAN_RESOLUTION,
    max_distance: float = SCAN_MAX_DISTANCE,
    compiled: bool = False,
) -> torch.Tensor:
    """(E, N) height of the pelvis above the terrain at the points of a yaw-aligned grid around
    it: what mjlab's ``terrain_scan`` ray-cast sensor + ``height_scan`` observation give
    (vertical rays from pelvis height, first terrain surface below, ``max_distance`` for a
    miss), computed from the terrain's boxes (:func:`march.env.stone_terrain.terrain_boxes`: every
    terrain geom is an axis-aligned box whose top is its only upward face) instead of casting
    rays through the scene. The robot's own geoms are not terrain (geom groups 2 and 3; the
    sensor scans group 0 only), so the two agree; a box whose top lies above the pelvis is
    skipped (the pelvis inside a stone is not a state a rollout reaches). Shared by the actor
    and critic groups within one observation compute. ``compiled``: the maths
    (:func:`scan_heights`) under ``torch.compile`` (``compute.compile_math``).
    """
    return shared(
        env,
        ("terrain_height_scan", size, resolution, max_distance),
        lambda: _terrain_height_scan(env, size, resolution, max_distance, compiled),
    )


def _scan_table(env: ManagerBasedRlEnv, reach: float) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Per cell (flattened row-major), kept on the env: the boxes' x-extents (R*C, K, 2) (lo, hi;
    padding +inf, -inf), the boxes packed (R*C*K, 6) as (x, y, top, half x, half y, valid)
    (padding's top -inf: never hit) and the most boxes any scan can reach
    (:func:`march.env.stone_terrain.max_boxes_in_reach`)."""
    top_center, half, valid = terrain_boxes(foothold_table(env))
    r, c, k = valid.shape
    lo = (top_center[..., 0] - half[..., 0]).masked_fill(~valid, float("inf"))
    hi = (top_center[..., 0] + half[..., 0]).masked_fill(~valid, -float("inf"))
    top_center = top_center.clone()
    top_center[..., 2] = top_center[..., 2].masked_fill(~valid, -float("inf"))
    extent = torch.stack([lo, hi], dim=-1).reshape(r * c, k, 2)
    packed = torch.cat([top_center, half, valid[..., None].float()], dim=-1).reshape(r * c * k, 6)
    return extent, packed, min(k, max_boxes_in_reach(top_center, half, valid, reach))


def _terrain_height_scan(
    env: ManagerBasedRlEnv,
    size: tuple[float, float],
    resolution: float,
    max_distance: float,
    compiled: bool,
) -> torch.Tensor:
    offsets = constant(
        env, ("scan_offsets", size, resolution), lambda: scan_offsets(size, resolution, env.device)
    )
    extent, packed, k_near = constant(
        env,
        ("scan_table", size, resolution),
        # reach: the farthest scan point from the pelvis (+1 mm); a box beyond it is never hit
        lambda: _scan_table(env, float(offsets.norm(dim=-1).max()) + 1e-3),
    )
    terrain = env.scene.terrain
    heights = maybe_fused(scan_heights, compiled)
    return heights(
        *root_frame(env),
        terrain.terrain_levels,
        terrain.terrain_types,
        terrain.terrain_origins.shape[1],
        (extent, packed, k_near),
        offsets,
        max_distance,
    )


def scan_heights(
    base: torch.Tensor,
    yaw: torch.Tensor,
    levels: torch.Tensor,
    types: torch.Tensor,
    num_cols: int,
    table: tuple[torch.Tensor, torch.Tensor, int],
    offsets: torch.Tensor,
    max_distance: float,
) -> torch.Tensor:
    """The maths of :func:`terrain_height_scan` (pure torch): pelvis position ``base`` (E, 3) and
    heading ``yaw`` (E,), each env's terrain cell (level, type; ``num_cols`` types), the cells'
    boxes (``_scan_table``: padding's top is -inf) and the scan grid ``offsets`` (N, 2) ->
    (E, N) heights [m]."""
    extent, packed, k_near = table
    cell = levels.long() * num_cols + types.long()  # (E,)
    # Only boxes whose x-extent comes within reach of the pelvis can be hit, and no scan reaches
    # more than k_near boxes: the k_near nearest along x include every box that can be hit.
    ext = extent.index_select(0, cell)  # (E, K, 2)
    bx = base[:, 0:1]
    gap = torch.maximum(ext[..., 0] - bx, bx - ext[..., 1])  # < 0 inside the x-extent
    near = gap.topk(k_near, dim=1, largest=False).indices  # (E, k_near)
    k_all = extent.shape[1]
    boxes = packed.index_select(0, (cell[:, None] * k_all + near).flatten())
    boxes = boxes.view(base.shape[0], k_near, 6)
    c, s = torch.cos(yaw)[:, None, None], torch.sin(yaw)[:, None, None]
    ox, oy = offsets[:, 0:1], offsets[:, 1:2]
    # (E, N, 2) scan points, world: (bx + c ox) - s oy, (by + s ox) + c oy, x and y at once
    points = (base[:, None, :2] + torch.cat([c, s], -1) * ox) + torch.cat([-s, c], -1) * oy
    z0 = base[:, 2:3]
    # A box whose top lies above the pelvis is never hit (nor padding: its top is -inf).
    top = boxes[..., 2].masked_fill(boxes[..., 2] > z0, -float("inf"))
    # One (E, N, k_near) pass over the near boxes (a few ops, not a few per box; k_near is
    # small, so the temporaries are E x N x k_near x 2): the highest top each point is inside.
    b = boxes.unsqueeze(1)  # (E, 1, k_near, 6)
    inside = ((points.unsqueeze(2) - b[..., 0:2]).abs() <= b[..., 3:5]).all(-1)
    hit = top.unsqueeze(1).masked_fill(~inside, -float("inf")).amax(dim=-1)
    height = z0 - hit
    return torch.where(height <= max_distance, height, torch.full_like(height, max_distance))


def stones_ahead(env: ManagerBasedRlEnv, num_stones: int = NUM_STONES) -> torch.Tensor:
    """(E, 5K) the next K stones as rectangles relative to the base, nearest first.

    A stone is "ahead" while its far edge along the course is ahead of the pelvis (so the stone
    the robot stands on is included); stones are ordered by the progress of their centres (the
    two stones of a side-by-side pair both count). Near the goal, missing entries repeat the
    goal platform. Per stone: dx, dy (yaw-aligned base frame), dz (stone top minus pelvis
    height), half size along the course, half size across it. Computed once per observation
    compute and shared by the actor and critic groups (:func:`march.env.step_cache.shared`).
    """
    return shared(env, ("stones_ahead", num_stones), lambda: _stones_ahead(env, num_stones))


def _stones_ahead(env: ManagerBasedRlEnv, num_stones: int) -> torch.Tensor:
    fh = CourseRuler(env).footholds()
    base, heading = root_frame(env)
    axis = fh.direction
    rel = fh.center[..., :2] - base[:, None, :2]  # (E, S, 2)
    along = (rel * axis[:, None]).sum(-1)
    half_along = (fh.half_size * axis[:, None].abs()).sum(-1)
    ahead = fh.valid & (along + half_along > 0.0)
    key = along.masked_fill(~ahead, float("inf"))
    k = min(num_stones, key.shape[1])
    dist, idx = key.topk(k, dim=-1, largest=False)
    goal = along.masked_fill(~fh.valid, -float("inf")).argmax(-1, keepdim=True)  # (E, 1)
    idx = torch.where(torch.isfinite(dist), idx, goal.expand_as(idx))
    if k < num_stones:
        idx = torch.cat([idx, goal.expand(-1, num_stones - k)], dim=-1)
    center = torch.gather(fh.center, 1, idx[..., None].expand(-1, -1, 3))
    half = torch.gather(fh.half_size, 1, idx[..., None].expand(-1, -1, 2))
    d = center - base[:, None]
    yaw = heading[:, None]
    c, s = torch.cos(yaw), torch.sin(yaw)
    dx = c * d[..., 0] + s * d[..., 1]
    dy = -s * d[..., 0] + c * d[..., 1]
    feats = torch.stack([dx, dy, d[..., 2], half[..., 0], half[..., 1]], dim=-1)
    return feats.flatten(1)


def reference_obs(env: ManagerBasedRlEnv, command_name: str = "reference") -> torch.Tensor:
    """(E, 2*29 + 3N + 2) the CLF reference relative to the base
    (:meth:`march.env.reference_command.ReferenceCommand.observation`); once per observation
    compute, shared by the actor and critic groups."""
    term = reference_term(env, command_name)
    return shared(env, ("reference_obs", command_name), term.observation)
