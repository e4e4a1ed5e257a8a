"""The course as the env sees it: the ruler (progress, goal) and the level curriculum.

Every env's course comes from the foothold table of the compiled terrain
(:func:`march.env.stone_terrain.terrain_foothold_table`), built once per env and cached on it. Progress
is the pelvis displacement along the course's own direction (``FootholdTable.direction``, the
``Footholds.direction`` the planner plans along; +x for the generated courses) from the env's
spawn origin on the start platform, clipped to [0, course length]; the goal is reached when
progress passes the start of the goal platform. The ruler, the level curriculum and the
evaluation's success termination all measure with :func:`course_progress`.

The evaluation's distance is measured at the feet (:meth:`CourseRuler.foothold_progress`: the
point both feet have reached), not at the pelvis: a robot that topples forward moves its pelvis
half a metre along the course without a step (issue 56, docs/evaluation.md).
"""

from __future__ import annotations

import torch
from mjlab.envs import ManagerBasedRlEnv

from march.env.step_cache import site_pos
from march.env.stone_terrain import terrain_foothold_table
from march.world.footholds import Footholds, FootholdTable

_TABLE_ATTR = "_march_foothold_table"

FOOT_SITES = ("left_foot", "right_foot")
"""mjlab's G1 foot sites (under each ankle roll link, on the sole): where the ruler measures the
footholds reached."""


def foothold_table(env: ManagerBasedRlEnv) -> FootholdTable:
    """The env's foothold table (built on first use, then cached on the env)."""
    table = getattr(env, _TABLE_ATTR, None)
    if table is None:
        table = terrain_foothold_table(env.scene.terrain, device=env.device)
        setattr(env, _TABLE_ATTR, table)
    return table


def course_progress(
    table: FootholdTable,
    levels: torch.Tensor,
    types: torch.Tensor,
    origins: torch.Tensor,
    pos_w: torch.Tensor,
) -> torch.Tensor:
    """(E,) progress [m] of world points ``pos_w`` (E, >= 2) along the course of cell
    (levels[e], types[e]) spawned at ``origins[e]`` (E, 3): the displacement from the spawn
    point projected on the course direction, clipped to [0, course length]."""
    along = ((pos_w[:, :2] - origins[:, :2]) * table.direction[levels, types]).sum(-1)
    return torch.minimum(along.clamp(min=0.0), table.course_length[levels, types])


class CourseRuler:
    """Progress along each env's current course and whether its goal was reached."""

    def __init__(self, env: ManagerBasedRlEnv) -> None:
        self.env = env
        self.robot = env.scene["robot"]
        self.terrain = env.scene.terrain
        self.table = foothold_table(env)

    def _cell(self) -> tuple[torch.Tensor, torch.Tensor]:
        return self.terrain.terrain_levels, self.terrain.terrain_types

    @property
    def course_length(self) -> torch.Tensor:
        return self.table.course_length[self._cell()]

    @property
    def goal_distance(self) -> torch.Tensor:
        return self.table.goal_distance[self._cell()]

    def footholds(self) -> Footholds:
        levels, types = self._cell()
        return self.table.for_envs(levels, types, self.env.scene.env_origins)

    def progress(self) -> torch.Tensor:
        """(E,) pelvis progress along the course from the start [m], clipped to [0, length]."""
        levels, types = self._cell()
        pos = self.robot.data.root_link_pos_w
        return course_progress(self.table, levels, types, self.env.scene.env_origins, pos)

    def foothold_progress(self) -> torch.Tensor:
        """(E,) progress both feet have reached along the course [m]: the lesser of the two
        foot sites' progress (the rear foot's), each clipped to [0, length]. Standing still it
        stays at ~0 however far the pelvis leans or topples; walking it is the last stance
        foot's progress."""
        levels, types = self._cell()
        origins = self.env.scene.env_origins
        feet = site_pos(self.env, FOOT_SITES)  # (E, 2, 3)
        left = course_progress(self.table, levels, types, origins, feet[:, 0])
        right = course_progress(self.table, levels, types, origins, feet[:, 1])
        return torch.minimum(left, right)

    def reached_goal(self, progress: torch.Tensor) -> torch.Tensor:
        return progress >= self.goal_distance


def eval_cells(
    first: int, count: int, num_rows: int, num_cols: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """(level, column) of evaluation rollouts ``first .. first + count - 1``.

    Rollout i runs on level ``i mod R`` and column ``(i // R + i mod R) mod C`` (R levels, C
    columns):
    every R consecutive rollouts visit every level once, and every R * C consecutive ones every
    (level, column) cell once (for a fixed level, i // R runs through all C columns). So any
    number n of rollouts puts floor(n / R) or ceil(n / R) on each level and spreads each level's
    rollouts over its courses as evenly as it can: the plain mean over rollouts weights every
    level (nearly) equally, whatever n and however many envs run in parallel.
    """
    i = torch.arange(first, first + count)
    return i % num_rows, (i // num_rows + i % num_rows) % num_cols


def assign_eval_cells(env: ManagerBasedRlEnv, first: int) -> None:
    """Put env e on the course cell of rollout ``first + e`` (:func:`eval_cells`); takes effect
    at the next reset (the reset events spawn at ``env_origins``, the reference command and the
    ruler look the cell up from ``terrain_levels`` / ``terrain_types``)."""
    terrain = env.scene.terrain
    rows, cols = terrain.terrain_origins.shape[:2]
    levels, types = eval_cells(first, env.num_envs, rows, cols)
    dev = terrain.terrain_levels.device
    terrain.terrain_levels[:] = levels.to(dev, terrain.terrain_levels.dtype)
    terrain.terrain_types[:] = types.to(dev, terrain.terrain_types.dtype)
    terrain.env_origins[:] = terrain.terrain_origins[terrain.terrain_levels, terrain.terrain_types]


def course_levels(
    env: ManagerBasedRlEnv,
    env_ids: torch.Tensor,
    promote_fraction: float,
    demote_fraction: float,
) -> None:
    """Curriculum term: level up when the episode got ``promote_fraction`` of the way to the goal
    platform, down when it got less than ``demote_fraction`` of it (SPEC: levels move with how
    far along the course the robot got). For flat_first the lowest rows are flat ground, so
    the same rule walks envs from flat ground onto stones."""
    terrain = env.scene.terrain
    table = foothold_table(env)
    levels, types = terrain.terrain_levels[env_ids], terrain.terrain_types[env_ids]
    robot = env.scene["robot"]
    pos, origins = robot.data.root_link_pos_w[env_ids], env.scene.env_origins[env_ids]
    along = course_progress(table, levels, types, origins, pos)
    goal = table.goal_distance[levels, types]
    move_up = along >= promote_fraction * goal
    move_down = (along < demote_fraction * goal) & ~move_up
    if env.common_step_counter == 0:  # initial reset: the robot has not walked yet
        move_up = torch.zeros_like(move_up)
        move_down = torch.zeros_like(move_down)
    terrain.update_env_origins(env_ids, move_up, move_down)
    # Nothing to log: mjlab would read each returned tensor with .item() on every reset (a host
    # sync); the runners log mean_terrain_level themselves (march.env.reset_extras).
