"""One footstep's cost and feasibility, the progress (pace) term and the goal test: the
scoring of :mod:`march.reference.planner` (its module docstring states the cost)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from march.reference.planner import PlannerCfg
    from march.world.footholds import Footholds

_EPS = 1e-5
"""Slack of the margin tests [m]."""

Vec = tuple[torch.Tensor, torch.Tensor]
"""A 2-D vector field as separate (x, y) tensors: elementwise ops on split components are several
times faster on CPU than on (..., 2) tensors with broadcasting."""


def _step_cost(
    prev: Vec,
    prev_z: torch.Tensor,
    pos: Vec,
    z: torch.Tensor,
    clearance: torch.Tensor,
    duration: torch.Tensor,
    lands_left: torch.Tensor,
    v_cmd: Vec,
    axis: Vec,
    lat: Vec,
    pace: tuple[torch.Tensor, torch.Tensor],
    cfg: PlannerCfg,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Cost and feasibility of one step; all inputs broadcast against each other.

    ``clearance`` is the landing point's distance to the nearest edge of its stone (negative off
    the stones). The velocity is measured between the feet's nominal lines (module docstring).
    ``pace`` = (floor, scale) from :func:`pace_terms`: the progress term is
    scale * max(0, floor - advance / dt).
    """
    sx, sy = pos[0] - prev[0], pos[1] - prev[1]
    along = sx * axis[0] + sy * axis[1]
    across = sx * lat[0] + sy * lat[1]
    side = lands_left.to(sx.dtype) * 2.0 - 1.0
    # Remove the nominal lateral offset (side * width along ``lat``) before dividing by dt.
    across_v = (across - side * cfg.step_width) / duration
    along_v = along / duration
    cmd_along = v_cmd[0] * axis[0] + v_cmd[1] * axis[1]
    cmd_across = v_cmd[0] * lat[0] + v_cmd[1] * lat[1]
    c_vel = cfg.w_velocity * ((along_v - cmd_along) ** 2 + (across_v - cmd_across) ** 2)
    pen = ((cfg.edge_clearance - clearance) / cfg.edge_clearance).clamp(0.0, 1.0)
    c_edge = cfg.edge_cost * pen**2
    c_time = cfg.w_time * (duration - cfg.nominal_duration) ** 2
    floor, scale = pace
    c_pace = (floor - along_v).clamp_(min=0.0).mul_(scale)
    signed_lat = side * across
    feasible = (
        (clearance >= cfg.stone_margin - 2 * _EPS)
        & (sx * sx + sy * sy <= cfg.max_step**2)
        & (along >= cfg.min_step_forward)
        & (signed_lat >= cfg.min_lateral)
        & (signed_lat <= cfg.max_lateral)
        & ((z - prev_z).abs() <= cfg.max_step_height)
    )
    # In place on the freshly allocated (full-shape) velocity cost: the summands only broadcast.
    cost = c_vel.add_(c_edge).add_(c_time).add_(c_pace)
    return torch.where(feasible, cost, cost + cfg.infeasible_cost), feasible


def goal_ahead(footholds: Footholds, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """(E, ...) bool: points (x, y), each (E, ...), lie before the goal platform along the course."""
    shape = (-1,) + (1,) * (x.dim() - 1)
    ax, ay = (a.view(shape) for a in footholds.direction.unbind(-1))
    sx, sy = (a.view(shape) for a in footholds.start_xy.unbind(-1))
    along = (x - sx) * ax + (y - sy) * ay
    return along < footholds.goal_distance.view(shape)


def pace_terms(
    cmd_along: torch.Tensor, ahead: torch.Tensor, cfg: PlannerCfg
) -> tuple[torch.Tensor, torch.Tensor]:
    """(floor, scale) of the progress term, broadcast from the inputs.

    floor = rho * max(v_D, 0) is the least step velocity along the course that keeps pace [m/s]
    (an advance of rho v_D dt in a step of duration dt); scale = pace_cost / floor where the term
    applies (goal ahead and floor > 0), else 0, so that scale * max(0, floor - advance / dt) is
    pace_cost times the fraction of the required advance rho v_D dt that the step misses.
    """
    floor = cfg.pace_fraction * cmd_along.clamp(min=0.0)
    on = ahead & (floor > 1e-6)
    scale = torch.where(on, cfg.pace_cost / floor.clamp(min=1e-6), 0.0)
    return floor, scale
