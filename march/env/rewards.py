"""Reward terms by name: the vocabulary that ``conf/reward/*.yaml`` weights.

Each entry maps a term name to the mjlab reward function and its parameters. Sign convention
(SPEC §2): a penalty's function returns a value <= 0... except mjlab's own L2/limit penalties,
which return a positive magnitude; those are wrapped by :func:`_penalty` so that every term here
is "reward-signed" and every weight in the YAML is positive. A weight's sign is then never a
second place where a penalty hides.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch
from mjlab.envs import ManagerBasedRlEnv
from mjlab.envs import mdp as envs_mdp
from mjlab.managers.reward_manager import RewardTermCfg
from mjlab.managers.scene_entity_config import SceneEntityCfg
from mjlab.tasks.velocity import mdp as vel_mdp

from march.config import ConfigError, RewardCfg

FOOT_SITES = ("left_foot", "right_foot")


def _penalty(func: Callable[..., torch.Tensor]) -> Callable[..., torch.Tensor]:
    """Turn a mjlab cost (>= 0) into a penalty term (<= 0) so that its weight is positive."""

    def term(env: ManagerBasedRlEnv, **params: Any) -> torch.Tensor:
        return -func(env, **params)

    term.__name__ = f"penalty_{func.__name__}"
    return term


def alive(env: ManagerBasedRlEnv) -> torch.Tensor:
    """1 per control step while the episode runs."""
    return torch.ones(env.num_envs, device=env.device)


def forward_progress(env: ManagerBasedRlEnv, command_name: str) -> torch.Tensor:
    """Velocity along the commanded direction, capped at the command (rewards crossing)."""
    robot = env.scene["robot"]
    cmd = env.command_manager.get_command(command_name)[:, :2]
    vel = robot.data.root_link_lin_vel_b[:, :2]
    speed = cmd.norm(dim=-1).clamp(min=1e-6)
    along = (vel * cmd).sum(-1) / speed
    return torch.minimum(along, speed)


def torque_l2(env: ManagerBasedRlEnv) -> torch.Tensor:
    """Sum of squared actuator forces [N^2 m^2] (returned <= 0)."""
    return -env.scene["robot"].data.actuator_force.square().sum(-1)


def _term_specs() -> dict[str, tuple[Callable[..., torch.Tensor], dict[str, Any]]]:
    return {
        "alive": (alive, {}),
        "track_linear_velocity": (
            vel_mdp.track_linear_velocity,
            {"command_name": "twist", "std": math.sqrt(0.25)},
        ),
        "track_angular_velocity": (
            vel_mdp.track_angular_velocity,
            {"command_name": "twist", "std": math.sqrt(0.5)},
        ),
        "forward_progress": (forward_progress, {"command_name": "twist"}),
        "upright": (
            vel_mdp.upright,
            {
                "std": math.sqrt(0.2),
                "asset_cfg": SceneEntityCfg("robot", body_names=("torso_link",)),
            },
        ),
        "torque": (torque_l2, {}),
        "joint_limits": (_penalty(envs_mdp.joint_pos_limits), {}),
        "action_rate": (_penalty(envs_mdp.action_rate_l2), {}),
        "foot_slip": (
            _penalty(vel_mdp.feet_slip),
            {
                "sensor_name": "feet_ground_contact",
                "command_name": "twist",
                "command_threshold": 0.05,
                "asset_cfg": SceneEntityCfg("robot", site_names=FOOT_SITES),
            },
        ),
        "body_ang_vel": (
            _penalty(vel_mdp.body_angular_velocity_penalty),
            {"asset_cfg": SceneEntityCfg("robot", body_names=("torso_link",))},
        ),
    }


def available_terms() -> list[str]:
    return sorted(_term_specs())


def reward_terms(reward: RewardCfg) -> dict[str, RewardTermCfg]:
    """mjlab reward terms for ``reward.terms`` (name -> weight); unknown names are an error."""
    specs = _term_specs()
    if not reward.terms:
        raise ConfigError(f"reward={reward.name} has no terms; add reward.terms in conf/reward/")
    unknown = sorted(set(reward.terms) - set(specs))
    if unknown:
        raise ConfigError(
            f"reward={reward.name}: unknown reward term(s) {unknown}; known: {', '.join(sorted(specs))}"
        )
    terms = {}
    for name, weight in reward.terms.items():
        func, params = specs[name]
        terms[name] = RewardTermCfg(func=func, weight=float(weight), params=dict(params))
    return terms
