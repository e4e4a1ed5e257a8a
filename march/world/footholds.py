"""The safe set L_step_feas as data: every env's stones as batched torch tensors.

This is the contract between the terrain (which writes it), the footstep planner (which plans on
it), the evaluation (which measures progress along the course with it) and the teacher's
privileged observations. Pure torch: no simulator import.

Conventions
- World frame, metres. A course runs along ``direction`` (a unit vector in the xy-plane; +x for
  the generated courses) from ``start_xy`` on the start platform to the goal platform.
- Stones are axis-aligned boxes in the course frame; ``center`` is the centre of the *top face*.
- Index 0 of every env is the start platform, index ``num_stones[e]-1`` the goal platform; the
  stepping stones lie in between in course order. Padding entries have ``valid == False``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


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
