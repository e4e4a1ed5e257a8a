"""One footstep's cost and feasibility, the progress (pace) term and the goal test: the
scoring of :mod:`march.reference.planner` (its module docstring states the cost)."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, NamedTuple

import torch

from march.reference.planner_cfg import EPS, PlannerCfg

if TYPE_CHECKING:
    from march.world.footholds import Footholds

XY = torch.Tensor
"""A 2-D vector field as one (2, ...) tensor, x (or the along component) at [0] and y (or the
across one) at [1]: one elementwise op computes both components (the op count is what a GPU
launches), and each component stays a contiguous block (elementwise ops on (..., 2) tensors
with broadcasting are several times slower on CPU). Only elementwise ops act on the stack, and
the two components are added explicitly (``a[0] + a[1]``), so every value is the one the
component-wise expression gives, bit for bit."""


class StepTerms(NamedTuple):
    """The parts of :func:`score_steps` that do not depend on where the step lands: they depend on
    the duration, the landing side, the command and the course frame only, so the planner builds
    them once per plan (not per candidate; :func:`step_terms`)."""

    duration: torch.Tensor
    """dt [s]."""
    own_side: XY
    """(1, side), side = +1 where the left foot lands and -1 where the right one does: times a
    course-frame (along, across) step, (along, across toward the landing foot's own side)."""
    lower: XY
    """(min_step_forward, min_lateral): the lower bounds of that own-side step [m], one
    comparison for both (the scalar comparisons are float32 too: the same masks)."""
    offset: torch.Tensor
    """side * step_width: the landing foot's nominal lateral offset along ``lat`` [m]."""
    nominal: XY
    """(0, offset): the landing foot's nominal offset in the course frame (along, across) [m]."""
    cmd: XY
    """The velocity command's components (along, across) the course [m/s]."""
    c_time: torch.Tensor
    """w_time (dt - T_nom)^2."""
    to_course: torch.Tensor
    """(2, 2, ...): [j] the course-frame (along, across) components of the world's unit vector
    along x (j = 0) or y (j = 1), so that a world vector s maps to s[0] * [0] + s[1] * [1]."""


def step_terms(
    duration: torch.Tensor,
    lands_left: torch.Tensor,
    v_cmd: XY,
    axis: XY,
    lat: XY,
    cfg: PlannerCfg,
) -> StepTerms:
    """:class:`StepTerms` of steps of ``duration`` landing on the left where ``lands_left``, under
    the command ``v_cmd`` (world frame) in the course frame (axis, lat); all broadcast."""
    own_side = torch.stack([torch.ones_like(lands_left), lands_left]).to(duration.dtype)
    own_side = own_side * 2.0 - 1.0
    to_course = torch.stack([axis, lat], dim=1)
    # Row 0: the lower bounds; row 1: (0, step_width), whose product with (1, side) is the
    # nominal offset (+0.0, side * step_width) (float32 products, as with scalar operands).
    # Filled on the device from Python scalars (a tensor made from a host list would be a
    # host-to-device copy per call on a GPU).
    shape = (2, 2) + (1,) * (own_side.dim() - 1)
    consts = torch.zeros(shape, device=duration.device, dtype=duration.dtype)
    consts[0, 0], consts[0, 1], consts[1, 1] = cfg.min_step_forward, cfg.min_lateral, cfg.step_width
    nominal = own_side * consts[1]
    return StepTerms(
        duration=duration,
        own_side=own_side,
        lower=consts[0],
        offset=nominal[1],
        nominal=nominal,
        cmd=v_cmd[0] * to_course[0] + v_cmd[1] * to_course[1],
        c_time=cfg.w_time * (duration - cfg.nominal_duration) ** 2,
        to_course=to_course,
    )


def height_ok(prev_z: torch.Tensor, z: torch.Tensor, cfg: PlannerCfg) -> torch.Tensor:
    """The height constraint of a step from stance height ``prev_z`` to landing height ``z``."""
    return (z - prev_z).abs() <= cfg.max_step_height


def into(
    out: torch.Tensor, op: Callable[..., torch.Tensor], *args: Any, **kwargs: Any
) -> torch.Tensor:
    """``op(*args, **kwargs, out=out)``: eagerly one op and no new tensor; under
    ``torch.compile``, whose tracer breaks the graph at an ``out=`` into a view (20 breaks per
    plan: the compiled search fell apart into ~480 ops), the value computed and copied in (cast
    to ``out``'s dtype, as ``out=`` does), which inductor fuses."""
    if torch.compiler.is_compiling():
        return out.copy_(op(*args, **kwargs))
    return op(*args, **kwargs, out=out)


def all_of(*masks: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
    """The elementwise AND of ``masks`` (broadcast), in two ops however many there are (a stack
    and a reduction, where a chain of ``&`` takes one op per mask); into ``out`` if given.

    The reduction is a min over the masks' bytes (bool is one byte, 0 or 1): on CPU torch.all
    over the stacked dim is about 7x slower than the min (and than the ``&`` chain)."""
    stacked = torch.stack(torch.broadcast_tensors(*masks)).view(torch.uint8)
    if out is None:
        return stacked.amin(0).view(torch.bool)
    into(out.view(torch.uint8), torch.amin, stacked, 0)
    return out


def score_steps(
    prev: XY,
    pos: XY,
    clearance: torch.Tensor,
    height: torch.Tensor,
    terms: StepTerms,
    pace: tuple[torch.Tensor, torch.Tensor],
    cfg: PlannerCfg,
    feasible_out: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Cost and feasibility of a step from ``prev`` to ``pos``; all inputs broadcast.

    ``clearance`` is the landing point's distance to the nearest edge of its stone (negative off
    the stones), ``height`` the step's :func:`height_ok`, ``terms`` its :func:`step_terms`. The
    velocity is measured between the feet's nominal lines (module docstring). ``pace`` = (floor,
    scale) from :func:`pace_terms`: the progress term is scale * max(0, floor - advance / dt).
    ``feasible_out``: a bool tensor of the broadcast shape to write the feasibility into (the
    planner's candidate buffer).
    """
    # In place where an op's output is a fresh tensor of its input's shape: the same values,
    # fewer and smaller live temporaries (the stacks are twice a component's size).
    step = pos - prev
    course = (step[0] * terms.to_course[0]).add_(step[1] * terms.to_course[1])  # along, across
    # Remove the nominal lateral offset (side * width along ``lat``) before dividing by dt.
    vel = (course - terms.nominal) / terms.duration
    err = (vel - terms.cmd).pow_(2)
    c_vel = err[0] + err[1]
    if cfg.w_velocity != 1.0:  # (the paper's weight 1 is exact without the op)
        c_vel = c_vel.mul_(cfg.w_velocity)
    pen = (cfg.edge_clearance - clearance).div_(cfg.edge_clearance).clamp_(0.0, 1.0)
    c_edge = pen.pow_(2).mul_(cfg.edge_cost)
    floor, scale = pace
    c_pace = (floor - vel[0]).clamp_(min=0.0).mul_(scale)
    own = course * terms.own_side  # (along, signed lateral distance)
    sq = step.mul_(step)
    feasible = all_of(
        clearance >= cfg.stone_margin - 2 * EPS,
        sq[0] + sq[1] <= cfg.max_step**2,
        *(own >= terms.lower).unbind(0),
        own[1] <= cfg.max_lateral,
        height,
        out=feasible_out,
    )
    # In place on the freshly allocated (full-shape) velocity cost: the summands only broadcast.
    cost = c_vel.add_(c_edge).add_(terms.c_time).add_(c_pace)
    return torch.where(feasible, cost, cost + cfg.infeasible_cost), feasible


def goal_ahead(footholds: Footholds, xy: XY) -> torch.Tensor:
    """(E, ...) bool: points ``xy``, (2, E, ...), lie before the goal platform along the course."""
    shape = (2, -1) + (1,) * (xy.dim() - 2)
    rel = (xy - footholds.start_xy.T.reshape(shape)) * footholds.direction.T.reshape(shape)
    return rel[0] + rel[1] < footholds.goal_distance.view(shape[1:])


def pace_floor(cmd_along: torch.Tensor, cfg: PlannerCfg) -> tuple[torch.Tensor, torch.Tensor]:
    """(floor, scale) of the progress term while the goal lies ahead (:func:`pace_terms`)."""
    floor = cfg.pace_fraction * cmd_along.clamp(min=0.0)
    # Times the mask, not torch.where: x * False is 0.0 and x * True is x exactly (x is finite).
    scale = (cfg.pace_cost / floor.clamp(min=1e-6)) * (floor > 1e-6)
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
    return floor, scale * ahead  # (as in pace_floor: exactly 0 where the goal is behind)
