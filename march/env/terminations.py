"""Termination terms beyond mjlab's own (time out, bad orientation) and build.pelvis_too_low."""

from __future__ import annotations

import torch
from mjlab.envs import ManagerBasedRlEnv

from march.env.course import CourseRuler
from march.env.reference_command import reference_term
from march.env.step_cache import site_pos

FOOT_SITES = ("left_foot", "right_foot")


def foot_too_low(env: ManagerBasedRlEnv, max_drop: float) -> torch.Tensor:
    """A foot site is more than ``max_drop`` below the env's start-platform top (its terrain
    origin z): the foot fell off a stone into the pit. Stone tops vary by at most
    ``terrain.height_hard`` (0.10 m) around the platform, so a 0.15 m drop is off every stone."""
    z = site_pos(env, FOOT_SITES)[..., 2]  # the two sites only, ids found once
    return (z < env.scene.env_origins[:, 2:3] - max_drop).any(-1)


def planner_infeasible(env: ManagerBasedRlEnv, command_name: str = "reference") -> torch.Tensor:
    """The footstep plan made at the last touchdown (or reset) violates a planner constraint:
    no safe sequence of N footholds exists from where the robot stands (reward=clf only)."""
    return ~reference_term(env, command_name).plan_feasible


def goal_reached(env: ManagerBasedRlEnv) -> torch.Tensor:
    """The pelvis is over the goal platform: its progress along the course (the course frame,
    :func:`march.env.course.course_progress`) has passed the goal platform's start. The
    evaluation env's success termination (``time_out=True``: not a failure); training never
    ends an episode on it."""
    ruler = CourseRuler(env)
    return ruler.reached_goal(ruler.progress())
