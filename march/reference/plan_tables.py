"""The footstep planner's view of the envs' courses, plain torch.

:class:`PlanTables` stacks what the search reads into two tensors: per stone the clamping bounds
and half sizes with the margins applied, per env the course frame, start and goal. Built once per
plan, or once for all envs and then indexed, so that the search reads rows of two tensors instead
of one op per ``Footholds`` field (issue 41). :func:`course_frame` and :func:`locate_on_stones`
are the two course readings the planner's callers share (the env's command, the rewards)."""

from __future__ import annotations

from typing import NamedTuple

import torch

from march.reference.kept import kept
from march.reference.planner_cfg import EPS, PlannerCfg
from march.world.footholds import Footholds


def course_frame(footholds: Footholds) -> tuple[torch.Tensor, torch.Tensor]:
    """(E, 2) unit vectors along and across (to the left of) the course."""
    axis = footholds.direction / footholds.direction.norm(dim=-1, keepdim=True).clamp(min=1e-9)
    return axis, torch.stack([-axis[:, 1], axis[:, 0]], dim=-1)


def locate_on_stones(footholds: Footholds, xy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Signed edge clearance (E, ...) and stone top height (E, ...) of points xy (E, ..., 2).

    The clearance is the largest over the env's stones of min(half_size - |xy - center|): on a stone
    it is the distance to that stone's nearest edge, off every stone it is negative. z is the top
    height of the stone attaining it.
    """
    e = xy.shape[0]
    pts = xy.reshape(e, -1, 1, 2)
    d = (pts - footholds.center[:, None, :, :2]).abs()
    clearance = (footholds.half_size[:, None] - d).min(-1).values  # (E, P, S)
    clearance = clearance.masked_fill(~footholds.valid[:, None], -1e9)
    best, idx = clearance.max(-1)
    z = torch.gather(footholds.center[..., 2], 1, idx)
    return best.reshape(xy.shape[:-1]), z.reshape(xy.shape[:-1])


class PlanTables(NamedTuple):
    """What the search reads of the envs' courses, built once per plan (:func:`plan_tables`) or
    by the env for all its envs and then indexed (:meth:`index`: two ops instead of one per
    ``Footholds`` field). Rows first, so that an x-y pair of rows is a (2, ...) stack."""

    stones: torch.Tensor
    """(17, E, S) per stone: centre x, y (``CENTER_XY``), z (``CZ``); the lower (``LOWER``)
    and upper (``UPPER``) bounds of a foothold clamped into the stone, (2 margins, 2 axes)
    each (hard: with the hard margin, soft: with margin + edge clearance); the half extents with
    the hard margin (``SPREAD``), over which group (b)'s points spread; the half sizes the
    clearance is measured against (``HALF``): -inf on a padding entry or a stone too small for
    the hard margin, so that every point on it is off the stones; the half sizes with -inf on a
    padding entry only (``HALVES``: the nearest-stone search and the stance foot's stone)."""
    course: torch.Tensor
    """(13, E) per env: the course frame as (2 world axes j, 4) rows (``FRAME``): [lat_j,
    axis_j, lat_j, axis_j] (axis along the course, lat across it, to the left), so that a world
    step s maps to s[0] * [0] + s[1] * [1] = (across, along, across, along); the course start
    xy (``START``), its direction as given (``DIR``) and the goal distance (``GOAL``)."""

    def index(self, env_ids: torch.Tensor) -> PlanTables:
        """The tables of ``env_ids`` (an index into E)."""
        return PlanTables(
            self.stones.index_select(1, env_ids), self.course.index_select(1, env_ids)
        )

    @property
    def axis(self) -> torch.Tensor:
        """(E, 2) unit vector along the course (:func:`course_frame`'s, the same numbers)."""
        return self.course[1:6:4].T

    @property
    def lat(self) -> torch.Tensor:
        """(E, 2) unit vector across the course, to its left."""
        return self.course[0:5:4].T


# Rows of PlanTables.stones (first dim) and .course.
CENTER_XY, CZ = slice(0, 2), 2
LOWER, UPPER = slice(3, 7), slice(7, 11)
SPREAD, HALF, HALVES = slice(11, 13), slice(13, 15), slice(15, 17)
FRAME, START, DIR, GOAL = slice(0, 8), slice(8, 10), slice(10, 12), 12


def plan_tables(footholds: Footholds, cfg: PlannerCfg) -> PlanTables:
    """:class:`PlanTables` of ``footholds`` (the same numbers as :func:`course_frame` and the
    margin arithmetic of the module docstring)."""
    half = footholds.half_size.movedim(-1, 0)  # (2, E, S)
    # (2 margins, 2 axes, E, S): hard = half - margin - eps, soft = half - margin - clearance
    margins = kept(
        ("margins", EPS, cfg.edge_clearance, half.device, half.dtype),
        lambda: torch.stack(
            [
                torch.full((), v, device=half.device, dtype=half.dtype)
                for v in (EPS, cfg.edge_clearance)
            ]
        ).view(2, 1, 1, 1),
    )
    extent = (half - cfg.stone_margin) - margins
    usable = footholds.valid & (extent[0].amin(0) >= 0.0)
    extent = extent.clamp_(min=0.0)
    center = footholds.center.movedim(-1, 0)  # (3, E, S)
    xy = center[:2]
    stones = torch.cat(
        [
            center,
            (xy - extent).flatten(0, 1),
            (xy + extent).flatten(0, 1),
            extent[0],
            torch.where(usable, half, float("-inf")),
            torch.where(footholds.valid, half, float("-inf")),
        ],
    )
    d = footholds.direction
    axis = d / d.norm(dim=-1, keepdim=True).clamp(min=1e-9)
    signs = kept(
        ("frame signs", axis.device, axis.dtype),
        lambda: torch.ones(8, device=axis.device, dtype=axis.dtype).index_fill_(
            0, torch.arange(0, 3, 2, device=axis.device), -1.0
        ),
    )
    order = kept(  # (axis column of each frame row) = (i % 2) xor (i < 4)
        ("frame order", axis.device),
        lambda: (
            torch.arange(8, device=axis.device).remainder(2)
            ^ torch.arange(8, device=axis.device).lt(4).long()
        ),
    )
    frame = axis.index_select(1, order) * signs  # (E, 8): [-a1, a0, -a1, a0, a0, a1, a0, a1]
    course = torch.cat([frame, footholds.start_xy, d, footholds.goal_distance[:, None]], dim=1).T
    return PlanTables(stones, course)


def pad_stones(tables: PlanTables, count: int) -> PlanTables:
    """``tables`` with at least ``count`` stones per env: padding entries (half sizes -inf, as a
    padded ``Footholds`` entry's: never nearest, never under a foot, every point on them off the
    stones) appended where it has fewer. The planner searches a fixed number of stones, so its
    draws have one shape whatever the batch's stone count (issue 55)."""
    s = tables.stones.shape[2]
    if s >= count:
        return tables
    pad = torch.zeros(
        tables.stones.shape[0],
        tables.stones.shape[1],
        count - s,
        device=tables.stones.device,
        dtype=tables.stones.dtype,
    )
    pad[HALF] = float("-inf")
    pad[HALVES] = float("-inf")
    return PlanTables(torch.cat([tables.stones, pad], dim=2), tables.course)


def stance_z(tables: PlanTables, xy: torch.Tensor) -> torch.Tensor:
    """(E,) top height of the stone under the points ``xy`` (E, 2): the valid stone with the
    largest clearance min(half - |xy - c|) (:func:`locate_on_stones`'s choice)."""
    st = tables.stones
    inside = st[HALVES] - (xy.T[:, :, None] - st[CENTER_XY]).abs_()
    best = torch.minimum(inside[0], inside[1]).argmax(-1, keepdim=True)
    return st[CZ].gather(1, best)[:, 0]
