"""One footstep's cost and feasibility, the progress (pace) term and the goal test: the
scoring of :mod:`march.reference.planner` (its module docstring states the cost)."""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import torch

if TYPE_CHECKING:
    from march.reference.planner import PlannerCfg
    from march.world.footholds import Footholds

_EPS = 1e-5
"""Slack of the margin tests [m]."""

Vec = tuple[torch.Tensor, torch.Tensor]
"""A 2-D vector field as separate (x, y) tensors: elementwise ops on split components are several
times faster on CPU than on (..., 2) tensors with broadcasting."""


class StepTerms(NamedTuple):
    """The parts of :func:`_step_cost` that do not depend on where the step lands: they depend on
    the duration, the landing side, the command and the course frame only, so the planner builds
    them once per plan (not per candidate; :func:`step_terms`)."""

    duration: torch.Tensor
    """dt [s]."""
    side: torch.Tensor
    """+1 where the left foot lands, -1 where the right one does."""
    offset: torch.Tensor
    """side * step_width: the landing foot's nominal lateral offset along ``lat`` [m]."""
    cmd: Vec
    """The velocity command's components (along, across) the course [m/s]."""
    c_time: torch.Tensor
    """w_time (dt - T_nom)^2."""
    axis: Vec
    """Unit vector along the course."""
    lat: Vec
    """Unit vector across the course (to the left)."""


def step_terms(
    duration: torch.Tensor,
    lands_left: torch.Tensor,
    v_cmd: Vec,
    axis: Vec,
    lat: Vec,
    cfg: PlannerCfg,
) -> StepTerms:
    """:class:`StepTerms` of steps of ``duration`` landing on the left where ``lands_left``, under
    the command ``v_cmd`` (world frame) in the course frame (axis, lat); all broadcast."""
    side = lands_left.to(duration.dtype) * 2.0 - 1.0
    return StepTerms(
        duration=duration,
        side=side,
        offset=side * cfg.step_width,
        cmd=(v_cmd[0] * axis[0] + v_cmd[1] * axis[1], v_cmd[0] * lat[0] + v_cmd[1] * lat[1]),
        c_time=cfg.w_time * (duration - cfg.nominal_duration) ** 2,
        axis=axis,
        lat=lat,
    )


def height_ok(prev_z: torch.Tensor, z: torch.Tensor, cfg: PlannerCfg) -> torch.Tensor:
    """The height constraint of a step from stance height ``prev_z`` to landing height ``z``."""
    return (z - prev_z).abs() <= cfg.max_step_height


def _step_cost(
    prev: Vec,
    pos: Vec,
    clearance: torch.Tensor,
    height: torch.Tensor,
    terms: StepTerms,
    pace: tuple[torch.Tensor, torch.Tensor],
    cfg: PlannerCfg,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Cost and feasibility of a step from ``prev`` to ``pos``; all inputs broadcast.

    ``clearance`` is the landing point's distance to the nearest edge of its stone (negative off
    the stones), ``height`` the step's :func:`height_ok`, ``terms`` its :func:`step_terms`. The
    velocity is measured between the feet's nominal lines (module docstring). ``pace`` = (floor,
    scale) from :func:`pace_terms`: the progress term is scale * max(0, floor - advance / dt).
    """
    sx, sy = pos[0] - prev[0], pos[1] - prev[1]
    (ax, ay), (lx, ly) = terms.axis, terms.lat
    along = sx * ax + sy * ay
    across = sx * lx + sy * ly
    # Remove the nominal lateral offset (side * width along ``lat``) before dividing by dt.
    across_v = (across - terms.offset) / terms.duration
    along_v = along / terms.duration
    c_vel = (along_v - terms.cmd[0]) ** 2 + (across_v - terms.cmd[1]) ** 2
    if cfg.w_velocity != 1.0:  # (the paper's weight 1 is exact without the op)
        c_vel = c_vel.mul_(cfg.w_velocity)
    pen = ((cfg.edge_clearance - clearance) / cfg.edge_clearance).clamp(0.0, 1.0)
    c_edge = cfg.edge_cost * pen**2
    floor, scale = pace
    c_pace = (floor - along_v).clamp_(min=0.0).mul_(scale)
    signed_lat = terms.side * across
    feasible = (
        (clearance >= cfg.stone_margin - 2 * _EPS)
        & (sx * sx + sy * sy <= cfg.max_step**2)
        & (along >= cfg.min_step_forward)
        & (signed_lat >= cfg.min_lateral)
        & (signed_lat <= cfg.max_lateral)
        & height
    )
    # In place on the freshly allocated (full-shape) velocity cost: the summands only broadcast.
    cost = c_vel.add_(c_edge).add_(terms.c_time).add_(c_pace)
    return torch.where(feasible, cost, cost + cfg.infeasible_cost), feasible


def goal_ahead(footholds: Footholds, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """(E, ...) bool: points (x, y), each (E, ...), lie before the goal platform along the course."""
    shape = (-1,) + (1,) * (x.dim() - 1)
    ax, ay = (a.view(shape) for a in footholds.direction.unbind(-1))
    sx, sy = (a.view(shape) for a in footholds.start_xy.unbind(-1))
    along = (x - sx) * ax + (y - sy) * ay
    return along < footholds.goal_distance.view(shape)


def pace_floor(cmd_along: torch.Tensor, cfg: PlannerCfg) -> tuple[torch.Tensor, torch.Tensor]:
    """(floor, scale) of the progress term while the goal lies ahead (:func:`pace_terms`)."""
    floor = cfg.pace_fraction * cmd_along.clamp(min=0.0)
    scale = torch.where(floor > 1e-6, cfg.pace_cost / floor.clamp(min=1e-6), 0.0)
    return floor, scale


def pace_terms(
    cmd_along: torch.Tensor, ahead: torch.Tensor, cfg: PlannerCfg
) -> tuple[torch.Tensor, torch.Tensor]:
    """(floor, scale) of the progress term, broadcast from the inputs.

    floor = rho * max(v_D, 0) is the least step velocity along the course that keeps pace [m/s]
    (an advance of rho v_D dt in a step of duration dt); scale = pace_cost / floor where the term
    applies (goal ahead and floor > 0), else 0, so that scale * max(0, floor - advance / dt) is
    pace_cost times the fraction of the required advance rho v_D dt that the step misses. The
    planner takes :func:`pace_floor` once per plan and applies ``ahead`` per step.
    """
    floor, scale = pace_floor(cmd_along, cfg)
    return floor, torch.where(ahead, scale, 0.0)
