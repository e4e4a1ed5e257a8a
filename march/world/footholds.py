"""The safe set L_step_feas as data: every env's stones as batched torch tensors.

This is the contract between the terrain (which writes it), the footstep planner (which plans on
it), the evaluation (which measures progress along the course with it) and the teacher's
privileged observations. :func:`footholds_from_layouts` and :class:`FootholdTable` build it from
``march.world.courses`` layouts. Pure torch and numpy: no simulator import.

Conventions
- World frame, metres. A course runs along ``direction`` (a unit vector in the xy-plane; +x for
  the generated courses) from ``start_xy`` on the start platform to the goal platform.
- Stones are axis-aligned boxes in the course frame; ``center`` is the centre of the *top face*.
- Index 0 of every env is the start platform, index ``num_stones[e]-1`` the goal platform; the
  stepping stones lie in between in course order. Padding entries have ``valid == False``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from march.world.courses import CourseLayout


@dataclass
class Footholds:
    center: torch.Tensor
    """(E, S, 3) centre of each stone's top face (x, y, z_top), world frame [m]."""
    half_size: torch.Tensor
    """(E, S, 2) half extents of each top face along x and y [m]."""
    valid: torch.Tensor
    """(E, S) bool: False for padding entries."""
    start_xy: torch.Tensor
    """(E, 2) spawn point on the start platform [m]."""
    direction: torch.Tensor
    """(E, 2) unit vector along which the course runs."""
    goal_distance: torch.Tensor
    """(E,) progress along ``direction`` from ``start_xy`` at which the goal platform begins [m]."""
    course_length: torch.Tensor
    """(E,) progress along ``direction`` from ``start_xy`` to the far end of the goal platform [m]."""

    @property
    def num_envs(self) -> int:
        return self.center.shape[0]

    @property
    def device(self) -> torch.device:
        return self.center.device

    def to(self, device: torch.device | str) -> Footholds:
        return Footholds(**{k: v.to(device) for k, v in self.__dict__.items()})

    def index(self, env_ids: torch.Tensor) -> Footholds:
        """The footholds of a subset of envs."""
        return Footholds(**{k: v[env_ids] for k, v in self.__dict__.items()})

    def progress(self, xy: torch.Tensor) -> torch.Tensor:
        """(E,) distance travelled along the course from the start, clipped to [0, course_length]."""
        along = ((xy - self.start_xy) * self.direction).sum(-1)
        return torch.minimum(along.clamp(min=0.0), self.course_length)

    def contains(self, xy: torch.Tensor, margin: float = 0.0) -> torch.Tensor:
        """Whether points lie on a stone with at least ``margin`` to every edge.

        xy: (E, ..., 2) points; returns (E, ...) bool.
        """
        e = xy.shape[0]
        pts = xy.reshape(e, -1, 1, 2)
        d = (pts - self.center[:, None, :, :2]).abs()
        inside = (d <= (self.half_size[:, None] - margin)).all(-1) & self.valid[:, None]
        return inside.any(-1).reshape(xy.shape[:-1])


def _as_tensor(x: np.ndarray | torch.Tensor, device: torch.device | str) -> torch.Tensor:
    return torch.as_tensor(
        np.asarray(x) if not isinstance(x, torch.Tensor) else x, dtype=torch.float32
    ).to(device)


def _pack(layouts: Sequence[CourseLayout]) -> dict[str, np.ndarray]:
    """Stack layouts into arrays relative to each layout's spawn origin, padded to max N."""
    n = len(layouts)
    s = max(lay.num_boxes for lay in layouts)
    center = np.zeros((n, s, 3))
    half = np.zeros((n, s, 2))
    valid = np.zeros((n, s), dtype=bool)
    for i, lay in enumerate(layouts):
        k = lay.num_boxes
        center[i, :k] = lay.center - lay.origin
        half[i, :k] = lay.half_size
        valid[i, :k] = True
    return {
        "center": center,
        "half_size": half,
        "valid": valid,
        "goal_distance": np.array([lay.goal_distance for lay in layouts]),
        "course_length": np.array([lay.course_length for lay in layouts]),
        "difficulty": np.array([lay.difficulty for lay in layouts]),
    }


def _footholds(
    center_rel: torch.Tensor,
    half: torch.Tensor,
    valid: torch.Tensor,
    goal: torch.Tensor,
    length: torch.Tensor,
    origins: torch.Tensor,
    direction: torch.Tensor | None = None,
) -> Footholds:
    e = origins.shape[0]
    if direction is None:  # the generated courses run along +x
        direction = torch.zeros(e, 2, device=origins.device)
        direction[:, 0] = 1.0
    return Footholds(
        center=center_rel + origins[:, None, :],
        half_size=half,
        valid=valid,
        start_xy=origins[:, :2].clone(),
        direction=direction,
        goal_distance=goal,
        course_length=length,
    )


def footholds_from_layouts(
    layouts: Sequence[CourseLayout],
    origins: np.ndarray | torch.Tensor,
    device: torch.device | str = "cpu",
) -> Footholds:
    """Footholds of E envs, env e on ``layouts[e]`` spawned at world point ``origins[e]``.

    ``origins`` (E, 3) are the world positions of each layout's ``origin`` (mjlab's
    ``env_origins``); boxes keep their offset from it. Padded to the longest layout.
    """
    p = _pack(layouts)
    o = _as_tensor(origins, device).reshape(-1, 3)
    if o.shape[0] != len(layouts):
        raise ValueError(f"{len(layouts)} layouts but {o.shape[0]} origins")
    return _footholds(
        _as_tensor(p["center"], device),
        _as_tensor(p["half_size"], device),
        torch.as_tensor(p["valid"], device=device),
        _as_tensor(p["goal_distance"], device),
        _as_tensor(p["course_length"], device),
        o,
    )


@dataclass
class FootholdTable:
    """Foothold ground truth of every cell (row = curriculum level, col = column) of a terrain.

    Built once per compiled terrain (``march.env.stone_terrain.foothold_table``); positions are
    stored relative to each cell's spawn origin so that :meth:`for_envs` only adds mjlab's
    ``env_origins``. The table itself never changes: curriculum level changes only move an
    env to another (row, col), so look the env up again after every level change - in mjlab
    the curriculum manager runs first in ``_reset_idx`` and the command manager's reset later,
    so a command term that calls :meth:`for_envs` in its reset sees the new levels.
    """

    center: torch.Tensor
    """(R, C, S, 3) top-face centres relative to the cell's spawn origin [m]."""
    half_size: torch.Tensor
    """(R, C, S, 2) top-face half extents [m]."""
    valid: torch.Tensor
    """(R, C, S) bool: False for padding."""
    goal_distance: torch.Tensor
    """(R, C) progress from the spawn origin at which the goal platform begins [m]."""
    course_length: torch.Tensor
    """(R, C) progress from the spawn origin to the goal platform's far end [m]."""
    origins: torch.Tensor
    """(R, C, 3) world spawn origin of each cell (equals TerrainEntity.terrain_origins)."""
    difficulty: torch.Tensor
    """(R, C) difficulty each cell was generated at."""
    direction: torch.Tensor | None = None
    """(R, C, 2) unit vector along which each cell's course runs (world xy); None = +x (every
    generated course), filled in at construction."""
    layouts: list[list[CourseLayout]] = field(default_factory=list, repr=False)
    """The layouts themselves, [row][col] (numpy, local frame) - for plots and checks."""

    @classmethod
    def from_layouts(
        cls,
        grid: Sequence[Sequence[CourseLayout]],
        origins: np.ndarray | torch.Tensor,
        device: torch.device | str = "cpu",
    ) -> FootholdTable:
        """Table of a [row][col] grid of layouts whose spawn origins are ``origins`` (R, C, 3)."""
        rows, cols = len(grid), len(grid[0])
        flat = [lay for row in grid for lay in row]
        if len(flat) != rows * cols:
            raise ValueError("ragged layout grid")
        p = _pack(flat)
        s = p["center"].shape[1]

        def t(a: np.ndarray, *shape: int) -> torch.Tensor:
            return _as_tensor(a, device).reshape(rows, cols, *shape)

        return cls(
            center=t(p["center"], s, 3),
            half_size=t(p["half_size"], s, 2),
            valid=torch.as_tensor(p["valid"], device=device).reshape(rows, cols, s),
            goal_distance=t(p["goal_distance"]),
            course_length=t(p["course_length"]),
            origins=t(origins, 3),
            difficulty=t(p["difficulty"]),
            layouts=[list(row) for row in grid],
        )

    def __post_init__(self) -> None:
        if self.direction is None:
            rows, cols = self.goal_distance.shape
            self.direction = torch.zeros(rows, cols, 2, device=self.center.device)
            self.direction[..., 0] = 1.0

    @property
    def shape(self) -> tuple[int, int, int]:
        """(rows, cols, max boxes per course)."""
        r, c, s, _ = self.center.shape
        return r, c, s

    def to(self, device: torch.device | str) -> FootholdTable:
        kw = {
            k: (v.to(device) if isinstance(v, torch.Tensor) else v)
            for k, v in self.__dict__.items()
        }
        return FootholdTable(**kw)

    def world_center(self) -> torch.Tensor:
        """(R, C, S, 3) top-face centres in the world frame [m]."""
        return self.center + self.origins[:, :, None, :]

    def for_envs(
        self, terrain_levels: torch.Tensor, terrain_types: torch.Tensor, env_origins: torch.Tensor
    ) -> Footholds:
        """Footholds of envs on cells (terrain_levels[e], terrain_types[e]) spawned at
        env_origins[e] (mjlab TerrainEntity.terrain_levels / .terrain_types / .env_origins,
        or their values at a subset of env ids)."""
        lv = terrain_levels.long().to(self.center.device)
        ty = terrain_types.long().to(self.center.device)
        o = env_origins.to(self.center.device, torch.float32)
        return _footholds(
            self.center[lv, ty],
            self.half_size[lv, ty],
            self.valid[lv, ty],
            self.goal_distance[lv, ty],
            self.course_length[lv, ty],
            o,
            self.direction[lv, ty],
        )
