"""The event functions mjlab calls for the paper's DR rows it has no exact counterpart for.

:func:`scale_link_mass` and :func:`add_base_mass` (startup: they change ``body_mass`` /
``body_inertia`` and need mjwarp's ``set_const``), :func:`scale_joint_damping` (passive damping and
the position actuator's kd), :func:`sample_control_delay` with :func:`install_control_delay`,
which switches on the actuator command buffer that event drives, and :func:`control_delay_lags`
to read the lags back. ``march.env.randomization`` maps the paper's table onto these and onto
mjlab's own ``dr`` terms. Small torch functions; the simulator is only touched when mjlab calls
them.

Control delay. mjlab 1.6's action terms have no delay, but its actuators do: a
``delay_max_lag > 0`` on the actuator configs gives every builtin actuator group a command
``DelayBuffer`` that the position target passes through on each *physics* step (5 ms). The lag is
normally re-drawn every physics step; :func:`install_control_delay` sets ``delay_hold_prob=1`` so
the buffer never re-draws by itself, and the ``control_delay`` reset event draws one lag per env
and episode: t ~ U(0, 20) ms, lag = round(t / physics_dt) physics steps, i.e. {0, 5, 10, 15, 20} ms
with probabilities {1/8, 1/4, 1/4, 1/4, 1/8} at 5 ms (mean 10 ms, the nearest-step quantisation of
the continuous draw). One lag is shared by all joints of an env (one command bus). The event also
seeds the reset env's joint position target with what a zero action commands
(default pose - encoder bias): mjlab zeroes the targets on reset, and without the seed the first
``lag`` physics steps of an episode would command 0 rad on every joint. The event's first call puts
:class:`march.env.command_delay.GatherDelay` in place of mjlab's buffer: the same delayed commands
in one gather per physics step instead of ~24 ops (issue 41).
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import torch
from mjlab.actuator import BuiltinPositionActuator
from mjlab.actuator.actuator import TransmissionType
from mjlab.actuator.xml_actuator import XmlActuator
from mjlab.managers.event_manager import RecomputeLevel, requires_model_fields
from mjlab.managers.scene_entity_config import SceneEntityCfg

from march.config import DrCfg
from march.env.command_delay import use_gather_delay
from march.env.step_cache import constant

if TYPE_CHECKING:
    from mjlab.envs import ManagerBasedRlEnv, ManagerBasedRlEnvCfg


def _env_ids(env: ManagerBasedRlEnv, env_ids: torch.Tensor | None) -> torch.Tensor:
    if env_ids is None:
        return torch.arange(env.num_envs, device=env.device, dtype=torch.long)
    return env_ids.to(env.device, dtype=torch.long)


def _defaults(
    env: ManagerBasedRlEnv, field: str, env_ids: torch.Tensor, idx: torch.Tensor
) -> torch.Tensor:
    """Compile-time default of ``field`` as (len(env_ids), len(idx), ...)."""
    default = env.sim.get_default_field(field)
    if field in env.sim.per_world_default_fields:
        return default[env_ids[:, None], idx[None, :]]
    values = default[idx].unsqueeze(0)
    return values.expand((env_ids.numel(),) + tuple(values.shape[1:]))


def _uniform(lo: float, hi: float, shape: tuple[int, ...], device: str) -> torch.Tensor:
    return torch.rand(shape, device=device) * (hi - lo) + lo


def _applied_scale(inertia: torch.Tensor, default_inertia: torch.Tensor) -> torch.Tensor:
    """The link-mass factor currently applied to each body (inertia scales with it)."""
    num = inertia.sum(-1)
    den = default_inertia.sum(-1)
    return torch.where(den > 0, num / den.clamp_min(1e-12), torch.ones_like(num))


def _body_idx(env: ManagerBasedRlEnv, asset_cfg: SceneEntityCfg) -> torch.Tensor:
    asset = env.scene[asset_cfg.name]
    return asset.indexing.body_ids[asset_cfg.body_ids].to(env.device, dtype=torch.long)


def _mass_fields(env: ManagerBasedRlEnv, env_ids: torch.Tensor | None, asset_cfg: SceneEntityCfg):
    """(model, env index grid, body index grid, default masses, default inertias)."""
    ids = _env_ids(env, env_ids)
    idx = _body_idx(env, asset_cfg)
    eg, bg = torch.meshgrid(ids, idx, indexing="ij")
    m_def = _defaults(env, "body_mass", ids, idx)
    i_def = _defaults(env, "body_inertia", ids, idx)
    return env.sim.model, eg, bg, m_def, i_def


@requires_model_fields("body_mass", "body_inertia", recompute=RecomputeLevel.set_const)
def scale_link_mass(
    env: ManagerBasedRlEnv,
    env_ids: torch.Tensor | None,
    scale_range: tuple[float, float],
    asset_cfg: SceneEntityCfg,
) -> None:
    """Link mass x U(scale_range) with the inertia scaled alike (uniform density), COM unchanged.

    Mass that :func:`add_base_mass` added on top (``mass - default * applied_scale``) is kept, so
    the two terms commute and neither accumulates over repeated calls.
    """
    model, eg, bg, m_def, i_def = _mass_fields(env, env_ids, asset_cfg)
    added = model.body_mass[eg, bg] - m_def * _applied_scale(model.body_inertia[eg, bg], i_def)
    s = _uniform(scale_range[0], scale_range[1], tuple(m_def.shape), env.device)
    model.body_mass[eg, bg] = m_def * s + added
    model.body_inertia[eg, bg] = i_def * s.unsqueeze(-1)


@requires_model_fields("body_mass", "body_inertia", recompute=RecomputeLevel.set_const)
def add_base_mass(
    env: ManagerBasedRlEnv,
    env_ids: torch.Tensor | None,
    mass_range: tuple[float, float],
    asset_cfg: SceneEntityCfg,
) -> None:
    """Base mass = default x (link-mass factor in effect) + U(mass_range) kg: a point mass at the
    COM (inertia untouched). Reads the link-mass factor back from the inertia, so it does not
    matter whether :func:`scale_link_mass` runs before or after, or at all."""
    model, eg, bg, m_def, i_def = _mass_fields(env, env_ids, asset_cfg)
    scale = _applied_scale(model.body_inertia[eg, bg], i_def)
    added = _uniform(mass_range[0], mass_range[1], tuple(m_def.shape), env.device)
    model.body_mass[eg, bg] = m_def * scale + added


def _joint_local_ids(env: ManagerBasedRlEnv, asset_cfg: SceneEntityCfg) -> torch.Tensor:
    asset = env.scene[asset_cfg.name]
    if isinstance(asset_cfg.joint_ids, slice):
        return torch.arange(asset.num_joints, device=env.device)[asset_cfg.joint_ids]
    return torch.as_tensor(asset_cfg.joint_ids, device=env.device, dtype=torch.long)


def _damping_plan(
    env: ManagerBasedRlEnv, asset_cfg: SceneEntityCfg
) -> tuple[torch.Tensor, torch.Tensor, list[tuple[torch.Tensor, torch.Tensor]]]:
    """(local joint ids, their dof addresses, [(global ctrl ids, columns of the draw)] per
    actuator group that drives some of these joints): index tensors fixed once the env is built,
    made on first use and kept on the env (no per-reset look-ups or host syncs)."""
    asset = env.scene[asset_cfg.name]
    local = _joint_local_ids(env, asset_cfg)
    dof = asset.indexing.joint_v_adr[local].to(env.device, dtype=torch.long)
    column = {int(j): c for c, j in enumerate(local.tolist())}  # joint -> column of the draw
    groups = []
    for act in asset.actuators:
        position = isinstance(act, BuiltinPositionActuator) or (
            isinstance(act, XmlActuator) and act.command_field == "position"
        )
        if not position or act.transmission_type != TransmissionType.JOINT:
            raise TypeError(
                f"scale_joint_damping handles joint position actuators; got {type(act).__name__}"
            )
        targets = act.target_ids.tolist()
        ctrl_all = act.global_ctrl_ids.tolist()
        chosen = [i for i, j in enumerate(targets) if int(j) in column]
        if not chosen:
            continue
        ctrl = torch.tensor([ctrl_all[i] for i in chosen], dtype=torch.long, device=env.device)
        cols = torch.tensor(
            [column[int(targets[i])] for i in chosen], dtype=torch.long, device=env.device
        )
        groups.append((ctrl, cols))
    return local, dof, groups


@requires_model_fields("dof_damping", "actuator_biasprm")
def scale_joint_damping(
    env: ManagerBasedRlEnv,
    env_ids: torch.Tensor | None,
    scale_range: tuple[float, float],
    asset_cfg: SceneEntityCfg,
) -> None:
    """Joint damping x U(scale_range), one draw per joint: the passive ``dof_damping`` and the
    position actuator's derivative gain kd (``actuator_biasprm[..., 2] = -kd``) of that joint."""
    ids = _env_ids(env, env_ids)
    local, dof, groups = constant(
        env, ("damping_plan", id(asset_cfg)), lambda: _damping_plan(env, asset_cfg)
    )
    model = env.sim.model
    s = _uniform(scale_range[0], scale_range[1], (ids.numel(), local.numel()), env.device)
    eg, dg = torch.meshgrid(ids, dof, indexing="ij")
    model.dof_damping[eg, dg] = _defaults(env, "dof_damping", ids, dof) * s
    for ctrl, cols in groups:
        kd_def = _defaults(env, "actuator_biasprm", ids, ctrl)[..., 2]
        model.actuator_biasprm[ids[:, None], ctrl[None, :], 2] = kd_def * s[:, cols]


def sample_control_delay(
    env: ManagerBasedRlEnv,
    env_ids: torch.Tensor | None,
    delay_ms: tuple[float, float],
    asset_cfg: SceneEntityCfg,
) -> None:
    """Per-env command delay for the episode: t ~ U(delay_ms), lag = round(t / physics_dt) physics
    steps, written into the actuators' delay buffer; seeds the reset envs' joint position target
    with the zero-action command (default pose - encoder bias). Needs
    :func:`install_control_delay` on the env config."""
    asset = env.scene[asset_cfg.name]
    ids = _env_ids(env, env_ids)
    delayed = [a for a in asset.actuators if a.has_delay]
    if not delayed:
        raise RuntimeError(
            f"control_delay: entity {asset_cfg.name!r} has no actuator delay buffer; call "
            "march.env.dr_terms.install_control_delay(env_cfg, dr) before building the env"
        )
    dt_ms = env.physics_dt * 1000.0
    max_lag = min(a.cfg.delay_max_lag for a in delayed)
    # The largest lag a draw can give is known on the host: checked without reading the draw.
    if round(delay_ms[1] / dt_ms) > max_lag:
        raise RuntimeError(
            f"control_delay: delays up to {delay_ms[1]} ms need lag {round(delay_ms[1] / dt_ms)} > "
            f"buffer max_lag {max_lag}; install_control_delay was called with a different dr "
            "or physics dt"
        )
    t = _uniform(delay_ms[0], delay_ms[1], (ids.numel(),), env.device)
    lags = torch.round(t / dt_ms).long()
    if not getattr(asset, "_march_gather_delay", False):
        # mjlab's buffer re-draws (and discards) the lags every physics step: the same buffer
        # as one gather (march.env.command_delay), in place once
        use_gather_delay(asset)
        asset._march_gather_delay = True
    for act in delayed:  # builtin actuators share one fused buffer; setting each is idempotent
        act.set_lags(lags, ids)
    data = asset.data
    if data.joint_pos_target.shape[-1]:
        data.joint_pos_target[ids] = data.default_joint_pos[ids] - data.encoder_bias[ids]


def control_delay_lags(env: ManagerBasedRlEnv, robot: str = "robot") -> torch.Tensor:
    """The per-env command delay currently in effect, in physics steps (E,)."""
    asset = env.scene[robot]
    for act in asset.actuators:
        if act.has_delay and act._delay_buffer is not None:
            return act._delay_buffer.current_lags.clone()
    return torch.zeros(env.num_envs, dtype=torch.long, device=env.device)


# ---------------------------------------------------------------------------------------------
# The delay buffer on the env config.
# ---------------------------------------------------------------------------------------------


def max_delay_steps(dr: DrCfg, physics_dt: float) -> int:
    """Largest lag the ``control_delay`` event can draw, in physics steps."""
    return int(round(dr.control_delay_ms[1] / (physics_dt * 1000.0)))


def install_control_delay(cfg: ManagerBasedRlEnvCfg, dr: DrCfg, robot: str = "robot") -> int:
    """Give every actuator of ``robot`` a command delay buffer the ``control_delay`` event drives.

    Replaces the entity config and its actuator configs by copies (mjlab's G1 actuator configs
    are module-level singletons). Returns the buffer's max lag in physics steps; 0 (and no change)
    for dr=none or a zero delay range.
    """
    if dr.name == "none":
        return 0
    max_lag = max_delay_steps(dr, cfg.sim.mujoco.timestep)
    if max_lag == 0:
        return 0
    entity = cfg.scene.entities[robot]
    art = entity.articulation
    if art is None or not art.actuators:
        raise ValueError(f"entity {robot!r} has no actuators to delay")
    actuators = tuple(
        dataclasses.replace(
            a,
            delay_min_lag=0,
            delay_max_lag=max_lag,
            delay_hold_prob=1.0,  # never re-drawn per step: the reset event sets the lag
            delay_update_period=0,
            delay_per_env_phase=False,
        )
        for a in art.actuators
    )
    cfg.scene.entities[robot] = dataclasses.replace(
        entity, articulation=dataclasses.replace(art, actuators=actuators)
    )
    return max_lag
