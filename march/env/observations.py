"""Privileged teacher observation terms: the stones ahead and the CLF reference.

Both are expressed relative to the base: positions as (dx, dy, dz) from the pelvis, with the
horizontal part rotated by -heading (a yaw-aligned pelvis frame), so they do not depend on where
an env's course lies in the world.
"""

from __future__ import annotations

import torch
from mjlab.envs import ManagerBasedRlEnv

from march.env.course import CourseRuler
from march.env.reference_command import reference_term
from march.env.step_cache import shared

NUM_STONES = 5
"""K: stones observed ahead of the robot."""
STONE_FEATURES = 5
"""Per stone: dx, dy, dz (top-face centre from the pelvis) and half sizes along x, y."""


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
    robot = env.scene["robot"]
    base = robot.data.root_link_pos_w
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
    yaw = robot.data.heading_w[:, None]
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
