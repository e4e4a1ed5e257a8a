"""The evaluation's ruler: progress along the course and whether the goal was reached.

Placeholder (see march.env.build.PLACEHOLDERS) until the stepping-stone courses land: on flat
ground the course is the +x direction from the env's origin, NOMINAL_COURSE_LENGTH_M long, and the
goal begins at NOMINAL_GOAL_DISTANCE_M. With stone courses the ruler reads the env's Footholds.
"""

from __future__ import annotations

import torch
from mjlab.envs import ManagerBasedRlEnv

from march.env.build import NOMINAL_COURSE_LENGTH_M, NOMINAL_GOAL_DISTANCE_M


class CourseRuler:
    def __init__(self, env: ManagerBasedRlEnv) -> None:
        self.env = env
        self.robot = env.scene["robot"]
        n = env.num_envs
        self.direction = torch.tensor([1.0, 0.0], device=env.device).expand(n, 2)
        self.course_length = torch.full((n,), NOMINAL_COURSE_LENGTH_M, device=env.device)
        self.goal_distance = torch.full((n,), NOMINAL_GOAL_DISTANCE_M, device=env.device)

    def start_xy(self) -> torch.Tensor:
        return self.env.scene.env_origins[:, :2]

    def progress(self) -> torch.Tensor:
        """(E,) pelvis progress along the course from the start [m], clipped to [0, length]."""
        xy = self.robot.data.root_link_pos_w[:, :2]
        along = ((xy - self.start_xy()) * self.direction).sum(-1)
        return torch.minimum(along.clamp(min=0.0), self.course_length)

    def reached_goal(self, progress: torch.Tensor) -> torch.Tensor:
        return progress >= self.goal_distance
