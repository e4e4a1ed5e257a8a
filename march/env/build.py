"""The single bridge from march's typed config to mjlab's environment config.

Everything mjlab-specific about *which* env a run gets is decided here: the G1 robot and its
sensors (taken from mjlab's G1 velocity task), terrain, command, observation groups, rewards,
terminations and domain randomization. Three purposes share one definition so that teacher,
student and evaluation always see the same world:

- ``teacher``: observation groups ``actor`` (policy) and ``critic``; no camera (it is only paid
  for where a student needs it).
- ``student``: ``actor`` (the frozen teacher labels from it), ``student`` (proprioception
  history, shape (E, H, P)) and ``depth`` (E, 1, 24, 32), with the chest depth camera.
- ``eval``: as ``student`` plus ``critic``, with the evaluation protocol's episode length.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from mjlab.envs import ManagerBasedRlEnv, ManagerBasedRlEnvCfg
from mjlab.envs import mdp as envs_mdp
from mjlab.managers.event_manager import EventTermCfg
from mjlab.managers.observation_manager import ObservationGroupCfg, ObservationTermCfg
from mjlab.managers.scene_entity_config import SceneEntityCfg
from mjlab.managers.termination_manager import TerminationTermCfg
from mjlab.sensor import CameraSensorCfg
from mjlab.tasks.velocity import mdp as vel_mdp
from mjlab.tasks.velocity.config.g1.env_cfgs import unitree_g1_rough_env_cfg
from mjlab.tasks.velocity.mdp import UniformVelocityCommandCfg
from mjlab.utils.noise import UniformNoiseCfg as Unoise
from scipy.spatial.transform import Rotation

from march.config import MarchConfig
from march.env.rewards import reward_terms

PURPOSES = ("teacher", "student", "eval")
DEPTH_SENSOR = "depth_cam"

# Honest list of what still stands in for the paper's pieces; printed in the start banner and
# reported by march.inspect. Each later issue removes its entry.
PLACEHOLDERS = {
    "terrain": "flat plane stands in for the stepping-stone courses until the world issue lands; "
    "distance is measured along +x from the spawn point over a nominal 8 m course",
    "reward=clf": "velocity-tracking terms stand in for r_clf / r_dclf until the CLF teacher lands",
    "reference": "no planner/HLIP reference in the teacher observation yet (reference issue)",
    "dr": "mjlab's G1 randomization terms set to the paper's ranges where they exist; link mass, "
    "added base mass, effort limits, joint damping/friction, control delay and camera pose/FOV "
    "randomization arrive with the world issue",
}

NOMINAL_COURSE_LENGTH_M = 8.0
"""Placeholder course length on flat ground [m]: distance is clipped to it."""
NOMINAL_GOAL_DISTANCE_M = 6.0
"""Placeholder success threshold: progress beyond this counts as reaching the goal [m]."""


@dataclass
class EnvSpec:
    """What a built env is for, kept next to it for tools (inspect, evaluate)."""

    purpose: str
    num_envs: int
    episode_length_s: float
    has_camera: bool
    placeholders: dict[str, str] = field(default_factory=dict)


def _camera_quat(pitch_deg: float) -> tuple[float, float, float, float]:
    """(w, x, y, z) of a camera looking along the body's +x axis, pitched down by pitch_deg.

    A MuJoCo camera looks along its -z axis with +y up; xyaxes (0,-1,0),(0,0,1) looks along +x.
    """
    forward = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]]).T
    pitched = Rotation.from_euler("y", pitch_deg, degrees=True).as_matrix() @ forward
    x, y, z, w = Rotation.from_matrix(pitched).as_quat()
    return (float(w), float(x), float(y), float(z))


def depth_camera_cfg(cfg: MarchConfig) -> CameraSensorCfg:
    e = cfg.env
    return CameraSensorCfg(
        name=DEPTH_SENSOR,
        parent_body="robot/torso_link",
        pos=tuple(e.depth_pos),
        quat=_camera_quat(e.depth_pitch_deg),
        fovy=e.depth_fovy_deg,
        width=e.depth_width,
        height=e.depth_height,
        data_types=("depth",),
        use_textures=False,
        enabled_geom_groups=(0,),
    )


def depth_image(
    env: ManagerBasedRlEnv,
    sensor_name: str,
    max_m: float,
    noise_scale: float,
    dropout: float,
) -> torch.Tensor:
    """(E, 1, H, W) depth in [0, 1] (1 = max range); misses (0) read as max range.

    With noise_scale/dropout > 0 (training) the image is corrupted: Gaussian noise with
    sigma = noise_scale * depth, and a fraction ``dropout`` of pixels set to max range.
    """
    raw = env.scene[sensor_name].data.depth  # (E, H, W, 1)
    depth = raw[..., 0].clone()
    depth = torch.where(depth <= 0.0, torch.full_like(depth, max_m), depth)
    if noise_scale > 0:
        depth = depth + torch.randn_like(depth) * noise_scale * depth
    if dropout > 0:
        depth = torch.where(torch.rand_like(depth) < dropout, torch.full_like(depth, max_m), depth)
    return (depth.clamp(0.0, max_m) / max_m).unsqueeze(1)


def _proprio_terms(noisy: bool) -> dict[str, ObservationTermCfg]:
    """One definition of proprioception for teacher and student (SPEC §2): no base linear velocity."""

    def n(lo: float) -> Unoise | None:
        return Unoise(n_min=-lo, n_max=lo) if noisy else None

    return {
        "base_ang_vel": ObservationTermCfg(
            func=vel_mdp.builtin_sensor, params={"sensor_name": "robot/imu_ang_vel"}, noise=n(0.2)
        ),
        "projected_gravity": ObservationTermCfg(func=vel_mdp.projected_gravity, noise=n(0.05)),
        "joint_pos": ObservationTermCfg(
            func=vel_mdp.joint_pos_rel, params={"biased": True}, noise=n(0.01)
        ),
        "joint_vel": ObservationTermCfg(func=vel_mdp.joint_vel_rel, noise=n(1.5)),
        "actions": ObservationTermCfg(func=vel_mdp.last_action),
        "command": ObservationTermCfg(
            func=vel_mdp.generated_commands, params={"command_name": "twist"}
        ),
    }


def _privileged_terrain_term() -> ObservationTermCfg:
    return ObservationTermCfg(
        func=envs_mdp.height_scan, params={"sensor_name": "terrain_scan"}, scale=1 / 5.0
    )


def _observations(cfg: MarchConfig, purpose: str) -> dict[str, ObservationGroupCfg]:
    h = cfg.env.history_length
    actor = {}
    for name, term in _proprio_terms(noisy=True).items():
        term.history_length = h
        actor[name] = term
    actor["height_scan"] = _privileged_terrain_term()
    groups = {
        "actor": ObservationGroupCfg(terms=actor, concatenate_terms=True, enable_corruption=True)
    }
    if purpose in ("teacher", "eval"):
        critic = {}
        for name, term in _proprio_terms(noisy=False).items():
            term.history_length = h
            critic[name] = term
        critic["height_scan"] = _privileged_terrain_term()
        critic["base_lin_vel"] = ObservationTermCfg(
            func=vel_mdp.builtin_sensor, params={"sensor_name": "robot/imu_lin_vel"}
        )
        critic["foot_contact"] = ObservationTermCfg(
            func=vel_mdp.foot_contact, params={"sensor_name": "feet_ground_contact"}
        )
        groups["critic"] = ObservationGroupCfg(terms=critic, concatenate_terms=True)
    if purpose in ("student", "eval"):
        groups["student"] = ObservationGroupCfg(
            terms=_proprio_terms(noisy=True),
            concatenate_terms=True,
            enable_corruption=True,
            history_length=h,
            flatten_history_dim=False,
        )
        corrupt = purpose == "student" or cfg.eval.corruption
        e = cfg.env
        groups["depth"] = ObservationGroupCfg(
            terms={
                "depth": ObservationTermCfg(
                    func=depth_image,
                    params={
                        "sensor_name": DEPTH_SENSOR,
                        "max_m": e.depth_max_m,
                        "noise_scale": e.depth_noise_scale if corrupt else 0.0,
                        "dropout": e.depth_dropout if corrupt else 0.0,
                    },
                    delay_min_lag=e.depth_delay_steps[0] if corrupt else 0,
                    delay_max_lag=e.depth_delay_steps[1] if corrupt else 0,
                )
            },
            concatenate_terms=True,
        )
    return groups


def pelvis_too_low(env: ManagerBasedRlEnv, min_height: float) -> torch.Tensor:
    """Pelvis below ``min_height`` above the env's terrain origin."""
    robot = env.scene["robot"]
    return robot.data.root_link_pos_w[:, 2] - env.scene.env_origins[:, 2] < min_height


def _terminations(cfg: MarchConfig) -> dict[str, TerminationTermCfg]:
    return {
        "time_out": TerminationTermCfg(func=envs_mdp.time_out, time_out=True),
        "tilt": TerminationTermCfg(
            func=envs_mdp.bad_orientation,
            params={"limit_angle": math.radians(cfg.reward.tilt_limit_deg)},
        ),
        "pelvis_too_low": TerminationTermCfg(
            func=pelvis_too_low, params={"min_height": cfg.reward.min_base_height_m}
        ),
    }


def _events(cfg: MarchConfig, base: dict[str, EventTermCfg]) -> dict[str, EventTermCfg]:
    events = {
        "reset_base": EventTermCfg(
            func=vel_mdp.reset_root_state_uniform,
            mode="reset",
            params={
                "pose_range": {"x": (-0.05, 0.05), "y": (-0.05, 0.05), "yaw": (-0.05, 0.05)},
                "velocity_range": {},
            },
        ),
        "reset_robot_joints": base["reset_robot_joints"],
    }
    if cfg.dr.name == "none":
        return events
    dr = cfg.dr
    friction = base["foot_friction"]
    friction.params["ranges"] = tuple(dr.friction)
    bias = base["encoder_bias"]
    bias.params["bias_range"] = tuple(dr.encoder_bias_rad)
    com = base["base_com"]
    com.params["ranges"] = {i: (-r, r) for i, r in enumerate(dr.base_com_offset_m)}
    push = base["push_robot"]
    push.interval_range_s = tuple(dr.push_interval_s)
    lv, av = dr.push_lin_vel, dr.push_ang_vel
    push.params["velocity_range"] = {
        "x": (-lv, lv),
        "y": (-lv, lv),
        "roll": (-av, av),
        "pitch": (-av, av),
        "yaw": (-av, av),
    }
    events.update(foot_friction=friction, encoder_bias=bias, base_com=com, push_robot=push)
    return events


def build_env_cfg(
    cfg: MarchConfig, purpose: str, num_envs: int | None = None
) -> ManagerBasedRlEnvCfg:
    """The mjlab env config for ``purpose`` (teacher | student | eval)."""
    if purpose not in PURPOSES:
        raise ValueError(f"purpose={purpose!r}; choose one of {PURPOSES}")
    env_cfg = unitree_g1_rough_env_cfg()
    base_events = env_cfg.events

    n = num_envs or (cfg.compute.eval_num_envs if purpose == "eval" else cfg.compute.num_envs)
    env_cfg.scene.num_envs = n
    env_cfg.seed = cfg.seed
    env_cfg.decimation = cfg.env.decimation
    env_cfg.sim.mujoco.timestep = cfg.env.sim_dt
    env_cfg.episode_length_s = (
        cfg.eval.episode_length_s if purpose == "eval" else cfg.env.episode_length_s
    )

    # Terrain (placeholder: flat plane; see PLACEHOLDERS).
    assert env_cfg.scene.terrain is not None
    env_cfg.scene.terrain.terrain_type = "plane"
    env_cfg.scene.terrain.terrain_generator = None
    env_cfg.curriculum = {}
    env_cfg.sim.njmax = 300
    env_cfg.sim.mujoco.ccd_iterations = 50
    env_cfg.sim.contact_sensor_maxmatch = 64
    env_cfg.sim.nconmax = None

    sensors = tuple(s for s in (env_cfg.scene.sensors or ()) if s.name not in ("foot_height_scan",))
    if purpose in ("student", "eval"):
        sensors = sensors + (depth_camera_cfg(cfg),)
    env_cfg.scene.sensors = sensors

    twist = env_cfg.commands["twist"]
    assert isinstance(twist, UniformVelocityCommandCfg)
    # One command per episode: the course runs ahead of the robot (forward-biased ranges).
    twist.resampling_time_range = (1.0e9, 1.0e9)
    twist.rel_standing_envs = 0.0
    twist.rel_heading_envs = 0.0
    twist.rel_forward_envs = 0.0
    twist.heading_command = False
    twist.debug_vis = False
    if purpose == "eval":
        vx = cfg.eval.command_vx
        twist.ranges = UniformVelocityCommandCfg.Ranges(
            lin_vel_x=(vx, vx), lin_vel_y=(0.0, 0.0), ang_vel_z=(0.0, 0.0), heading=None
        )
    else:
        twist.ranges = UniformVelocityCommandCfg.Ranges(
            lin_vel_x=tuple(cfg.env.command_vx),
            lin_vel_y=tuple(cfg.env.command_vy),
            ang_vel_z=tuple(cfg.env.command_yaw_rate),
            heading=None,
        )

    env_cfg.observations = _observations(cfg, purpose)
    env_cfg.rewards = reward_terms(cfg.reward)
    env_cfg.terminations = _terminations(cfg)
    env_cfg.events = _events(cfg, base_events)
    env_cfg.metrics = {}
    if purpose == "eval" and not cfg.eval.randomization:
        env_cfg.events = _events_without_dr(env_cfg.events)
    return env_cfg


def _events_without_dr(events: dict[str, EventTermCfg]) -> dict[str, EventTermCfg]:
    return {k: v for k, v in events.items() if k in ("reset_base", "reset_robot_joints")}


def make_env(cfg: MarchConfig, purpose: str, num_envs: int | None = None) -> ManagerBasedRlEnv:
    """Build the real mjlab env for ``purpose`` on ``cfg.compute.device``."""
    env_cfg = build_env_cfg(cfg, purpose, num_envs)
    env = ManagerBasedRlEnv(cfg=env_cfg, device=cfg.compute.device)
    env.march_spec = EnvSpec(  # type: ignore[attr-defined]
        purpose=purpose,
        num_envs=env.num_envs,
        episode_length_s=env_cfg.episode_length_s,
        has_camera=purpose in ("student", "eval"),
        placeholders=dict(PLACEHOLDERS),
    )
    return env


def robot_entity_cfg() -> SceneEntityCfg:
    return SceneEntityCfg("robot")
