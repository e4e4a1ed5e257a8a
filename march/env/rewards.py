"""Reward terms by name: the vocabulary that ``conf/reward/*.yaml`` weights.

Every term, march's own and yours, is registered the same way: :func:`reward_term` on the
function (anywhere in this file or in any module named in ``extra_modules``), with its default
parameters and what it needs (``needs=("reference",)``; march.config.terms.NEEDS). The registry
itself is :mod:`march.config.terms` (pure data: the config checks a YAML's params against it). Sign convention (SPEC §2):
every term here is reward-signed — a penalty returns a value <= 0 — and every weight in the YAML
is positive. mjlab's own L2/limit costs return a positive magnitude, so they are wrapped by
:func:`_penalty`. A weight's sign is then never a second place where a penalty hides.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Iterable
from typing import Any

import torch
from mjlab.envs import ManagerBasedRlEnv
from mjlab.envs import mdp as envs_mdp
from mjlab.managers.reward_manager import RewardTermCfg
from mjlab.managers.scene_entity_config import SceneEntityCfg
from mjlab.tasks.velocity import mdp as vel_mdp
from mjlab.utils.lab_api.math import quat_apply_inverse

from march.config import RewardCfg
from march.config import terms as registry
from march.env.course import CourseRuler
from march.env.reference_command import reference_term
from march.env.step_cache import constant, shared, site_pos, site_state
from march.reference.plan_tables import locate_on_stones

FOOT_SITES = ("left_foot", "right_foot")

REFERENCE_COMMAND = "reference"
"""Name of the ``reference`` command term (march.env.reference_command) the CLF terms read."""


def reward_term(
    name: str | None = None, *, needs: Iterable[str] = (), **params: Any
) -> Callable[[Callable[..., torch.Tensor]], Callable[..., torch.Tensor]]:
    """Add a reward term to the vocabulary ``conf/reward/*.yaml`` weights::

        @reward_term("swing_clearance", needs=("reference",), height=0.08)
        def swing_clearance(env, height: float): ...

    The function takes the env (and ``params`` as keywords: these are the defaults a YAML's
    ``reward.terms.<name>.params`` overrides) and returns one value per env, reward-signed (a
    penalty returns <= 0 and gets a positive weight). ``needs``: what the env must build for it
    (``reference``: the planner and the reference command). A name already taken is an error:
    a term means one thing in every arm."""

    def register(func: Callable[..., torch.Tensor]) -> Callable[..., torch.Tensor]:
        registry.register_term(name or func.__name__, func, params, needs)
        return func

    return register


def _penalty(func: Callable[..., torch.Tensor]) -> Callable[..., torch.Tensor]:
    """Turn a mjlab cost (>= 0) into a penalty term (<= 0) so that its weight is positive."""

    @functools.wraps(func)  # the signature (what params the YAML may set) is mjlab's
    def term(env: ManagerBasedRlEnv, **params: Any) -> torch.Tensor:
        return -func(env, **params)

    term.__name__ = term.__qualname__ = f"penalty_{func.__name__}"
    return term


def _ids(env: ManagerBasedRlEnv, kind: str, names: tuple[str, ...]) -> torch.Tensor:
    """(n,) the robot's local body or site ids of ``names`` as a kept device tensor (mjlab's
    ``SceneEntityCfg`` holds them as a list: an index copied to the device on every call)."""

    def make() -> torch.Tensor:
        robot = env.scene["robot"]
        find = robot.find_bodies if kind == "body" else robot.find_sites
        ids, _ = find(names, preserve_order=True)
        return torch.tensor(ids, dtype=torch.long, device=env.device)

    return constant(env, ("ids", kind, names), make)


@reward_term(std=math.sqrt(0.2), body_names=("torso_link",))
def upright(env: ManagerBasedRlEnv, std: float, body_names: tuple[str, ...]) -> torch.Tensor:
    """mjlab's ``upright`` kernel exp(-|g_xy|^2 / std^2) of the body's projected gravity (flat
    ground: no terrain sensors), with the body index kept on the device."""
    robot = env.scene["robot"]
    quat = robot.data.body_link_quat_w[:, _ids(env, "body", body_names)].squeeze(1)
    gravity = quat_apply_inverse(quat, robot.data.gravity_vec_w)
    return torch.exp(-gravity[:, :2].square().sum(1) / std**2)


@reward_term(
    sensor_name="feet_ground_contact",
    command_name="twist",
    command_threshold=0.05,
    site_names=FOOT_SITES,
)
def foot_slip(
    env: ManagerBasedRlEnv,
    sensor_name: str,
    command_name: str,
    command_threshold: float,
    site_names: tuple[str, ...],
) -> torch.Tensor:
    """-(mjlab's ``feet_slip``): sum over feet in contact of |v_xy|^2 while the command is
    above the threshold, with the site index kept on the device (its log metric left out)."""
    command = env.command_manager.get_command(command_name)
    total = command[:, :2].norm(dim=1) + command[:, 2].abs()
    active = (total > command_threshold).float()
    in_contact = (env.scene[sensor_name].data.found > 0).float()
    vel = env.scene["robot"].data.site_lin_vel_w[:, _ids(env, "site", site_names), :2]
    return -(vel.norm(dim=-1).square() * in_contact).sum(1) * active


@reward_term()
def alive(env: ManagerBasedRlEnv) -> torch.Tensor:
    """1 per control step while the episode runs (one kept tensor: the reward manager only
    reads it)."""
    return constant(env, "ones", lambda: torch.ones(env.num_envs, device=env.device))


@reward_term(command_name="twist")
def forward_progress(env: ManagerBasedRlEnv, command_name: str) -> torch.Tensor:
    """Velocity along the commanded direction, capped at the command (rewards crossing)."""
    robot = env.scene["robot"]
    cmd = env.command_manager.get_command(command_name)[:, :2]
    vel = robot.data.root_link_lin_vel_b[:, :2]
    speed = cmd.norm(dim=-1).clamp(min=1e-6)
    along = (vel * cmd).sum(-1) / speed
    return torch.minimum(along, speed)


@reward_term("torque")
def torque_l2(env: ManagerBasedRlEnv) -> torch.Tensor:
    """Sum of squared actuator forces [N^2 m^2] (returned <= 0)."""
    return -env.scene["robot"].data.actuator_force.square().sum(-1)


@reward_term(needs=("reference",))
def clf(env: ManagerBasedRlEnv, command_name: str = REFERENCE_COMMAND) -> torch.Tensor:
    """r_clf = exp(-min(V, Vmax)/Vmax) in [e^-1, 1] (V computed once per step by the command)."""
    term = reference_term(env, command_name)
    v, _, _ = term.clf_state()
    return term.clf.clf_reward(v)


@reward_term(needs=("reference",))
def dclf(env: ManagerBasedRlEnv, command_name: str = REFERENCE_COMMAND) -> torch.Tensor:
    """r_dclf = -max((dV/dt + alpha V)/Vdmax, 0) <= 0; 0 where V has no history yet (episode
    start, or the step after a reference switch), so it is reset-safe."""
    term = reference_term(env, command_name)
    v, vdot, valid = term.clf_state()
    return term.clf.dclf_reward(v, vdot, valid)


def stance_foot(
    env: ManagerBasedRlEnv, command_name: str = REFERENCE_COMMAND
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Stance foot site position, linear and angular velocity, each (E, 3), world frame: the
    values of ``ReferenceCommand.stance_foot`` from the two foot sites only (not the pose and
    velocity of every robot site), once per reward compute for both holonomic terms."""

    def make() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        term = reference_term(env, command_name)
        pos, lin, ang = site_state(env, tuple(term.cfg.foot_sites), term.cfg.entity_name)
        left = term.stance_is_left[:, None]
        return tuple(torch.where(left, x[:, 0], x[:, 1]) for x in (pos, lin, ang))  # type: ignore[return-value]

    return shared(env, ("stance_foot", command_name), make)


@reward_term(needs=("reference",))
def holonomic_pos(
    env: ManagerBasedRlEnv, sigma: float = math.sqrt(0.05), command_name: str = REFERENCE_COMMAND
) -> torch.Tensor:
    """exp(-||p - p_td||^2 / sigma^2) in (0, 1]: stance foot site displacement from where it
    touched down (author's sigma^2 = 0.05 m^2; position only, no orientation part)."""
    term = reference_term(env, command_name)
    pos, _, _ = stance_foot(env, command_name)
    d2 = (pos - term.stance_anchor).square().sum(-1)
    return torch.exp(d2 * (-1.0 / sigma**2))


@reward_term(needs=("reference",))
def holonomic_vel(
    env: ManagerBasedRlEnv, sigma: float = math.sqrt(0.1), command_name: str = REFERENCE_COMMAND
) -> torch.Tensor:
    """exp(-(||v||^2 + w_z^2) / sigma^2) in (0, 1]: stance foot site linear velocity and yaw
    rate should be zero (author's sigma^2 = 0.1)."""
    _, vel, omega = stance_foot(env, command_name)
    e2 = torch.cat([vel, omega[:, 2:3]], dim=-1).square().sum(-1)
    return torch.exp(e2 * (-1.0 / sigma**2))


@reward_term()
def feet_edge_distance(
    env: ManagerBasedRlEnv, clearance: float = 0.08, sensor_name: str = "feet_ground_contact"
) -> torch.Tensor:
    """Foothold safety (model-free set), in [-2, 0]: for each foot touching the terrain,
    -(1 - min(d_edge / clearance, 1)), d_edge = distance of the foot site to the nearest edge of
    the stone under it (negative off every stone, which scores -1 or less, clipped at -1).
    0 while every foot in contact stands at least ``clearance`` inside a stone."""
    feet = site_pos(env, FOOT_SITES)[..., :2]  # (E, 2, 2)
    fh = CourseRuler(env).footholds()
    d_edge, _ = locate_on_stones(fh, feet)
    contact = env.scene[sensor_name].data.found > 0  # (E, 2): primaries left, right
    pen = 1.0 - (d_edge / clearance).clamp(min=0.0, max=1.0)
    return -(pen * contact.float()).sum(-1)


# mjlab's own functions, registered the same way.
reward_term("track_linear_velocity", command_name="twist", std=math.sqrt(0.25))(
    vel_mdp.track_linear_velocity
)
reward_term("track_angular_velocity", command_name="twist", std=math.sqrt(0.5))(
    vel_mdp.track_angular_velocity
)
reward_term("joint_limits")(_penalty(envs_mdp.joint_pos_limits))
reward_term("action_rate")(_penalty(envs_mdp.action_rate_l2))
reward_term("body_ang_vel", asset_cfg=SceneEntityCfg("robot", body_names=("torso_link",)))(
    _penalty(vel_mdp.body_angular_velocity_penalty)
)


def available_terms() -> list[str]:
    return sorted(registry.TERMS)


def needs_reference(reward: RewardCfg) -> bool:
    """Whether the env needs the ``reference`` command term (the planner): a term of the arm
    declares it needs it, or the teacher observes the reference (``reward.observe_reference``).
    Derived from the terms, never from ``reward.name`` (a label)."""
    return "reference" in registry.needs(reward)


def reward_terms(reward: RewardCfg) -> dict[str, RewardTermCfg]:
    """mjlab reward terms for ``reward.terms`` (name -> weight or {weight, params}); an unknown
    name or a param the function does not take is one line (march.config.terms.check_reward)."""
    registry.check_reward(reward)
    terms = {}
    for name, value in reward.terms.items():
        spec, weight, params = registry.resolve(name, value)
        terms[name] = RewardTermCfg(func=spec.func, weight=weight, params=params)
    return terms
