"""The single bridge from march's typed config to mjlab's environment config.

Everything mjlab-specific about *which* env a run gets is decided here: the G1 robot and its
sensors (taken from mjlab's G1 velocity task), terrain, command, observation groups, rewards,
terminations and domain randomization. Three purposes share one definition so that teacher,
student and evaluation always see the same world:

- ``teacher``: observation groups ``actor`` (policy) and ``critic``; no camera (it is only paid
  for where a student needs it).
- ``student``: ``actor`` (the frozen teacher labels from it), ``student`` (proprioception
  history, shape (E, H, P)) and ``depth`` (E, 1, 24, 32), with the chest depth camera.
- ``eval``: as ``student`` plus ``critic``, with the evaluation protocol's episode length,
  command and terminations (time-out and falls only, the same for every arm).
"""

from __future__ import annotations

import contextlib
import inspect
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch
import warp as wp
from mjlab.envs import ManagerBasedRlEnv, ManagerBasedRlEnvCfg
from mjlab.envs import mdp as envs_mdp
from mjlab.managers.curriculum_manager import CurriculumTermCfg
from mjlab.managers.event_manager import EventTermCfg
from mjlab.managers.observation_manager import ObservationGroupCfg, ObservationTermCfg
from mjlab.managers.termination_manager import TerminationTermCfg
from mjlab.rl.vecenv_wrapper import RslRlVecEnvWrapper
from mjlab.sensor import ContactSensorCfg
from mjlab.tasks.velocity import mdp as vel_mdp
from mjlab.tasks.velocity.config.g1.env_cfgs import unitree_g1_rough_env_cfg
from mjlab.tasks.velocity.mdp import UniformVelocityCommandCfg
from mjlab.terrains import TerrainEntityCfg
from mjlab.utils.noise import UniformNoiseCfg as Unoise

from march.compiled_math import set_compile_mode
from march.config import MarchConfig
from march.config.terms import import_extra_modules
from march.env.clf_meter import attach as attach_clf_meter
from march.env.course import course_levels
from march.env.depth import corrupt, depth_camera_cfg, normalize
from march.env.nonfinite import nonfinite_termination
from march.env.observations import reference_obs, stones_ahead, terrain_height_scan
from march.env.randomization import T_PUSH, apply_dr
from march.env.reference_command import ReferenceCommandCfg
from march.env.reset_extras import keep_termination_counts_on_device
from march.env.rewards import REFERENCE_COMMAND, needs_reference, reward_terms
from march.env.solver_order import pinned as pinned_solver_order
from march.env.stone_terrain import terrain_entity_cfg
from march.env.term_meter import attach as attach_term_meter
from march.env.terminations import foot_too_low, goal_reached, planner_infeasible
from march.env.velocity_command import sync_free
from march.reference.trajectory import ReferenceCfg

PURPOSES = ("teacher", "student", "eval")
COURSE_HEADING = 0.0
"""World yaw of every generated course's direction (+x, ``march.world.courses``) [rad]: the heading
the twist command's heading controller steers to."""

# Warp reports every kernel module it loads (hundreds of lines per run); warnings still show.
wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)

# Honest list of what still stands in for the paper's pieces; printed in the start banner and
# reported by march.inspect. Each later issue removes its entry.
PLACEHOLDERS: dict[str, str] = {}


@dataclass
class EnvSpec:
    """What a built env is for, kept next to it for tools (inspect, evaluate)."""

    purpose: str
    num_envs: int
    episode_length_s: float
    has_camera: bool
    placeholders: dict[str, str] = field(default_factory=dict)


def depth_image(
    env: ManagerBasedRlEnv,
    sensor_name: str,
    min_range: float,
    max_range: float,
    noise_scale: float,
    dropout: float,
) -> torch.Tensor:
    """(E, 1, H, W) depth in [0, 1] (1 = max range) from the chest camera.

    Training corruption (noise_scale, dropout > 0): Gaussian noise sigma = noise_scale * depth and
    a fraction ``dropout`` of pixels invalid; misses and invalid pixels read as max range. The
    delay is the observation term's (delay_min_lag / delay_max_lag).
    """
    raw = env.scene[sensor_name].data.depth[..., 0]  # (E, H, W), 0 = miss
    if noise_scale > 0 or dropout > 0:
        raw = corrupt(raw, noise_scale, dropout)
    return normalize(raw, min_range, max_range).unsqueeze(1)


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


PROPRIO_TERMS = tuple(_proprio_terms(noisy=False))
"""Per-step term order of proprioception (the student's ``student`` group; ONNX metadata)."""


def _privileged_terrain_term(cfg: MarchConfig) -> ObservationTermCfg:
    # The G1 task's terrain_scan (17 x 11 points, 5 m range) computed from the course boxes:
    # the same numbers without ray casting through the scene every step (issue 11).
    return ObservationTermCfg(
        func=terrain_height_scan,
        scale=1 / 5.0,
        params={"compiled": cfg.compute.compile_math},
    )


def _privileged_teacher_terms(cfg: MarchConfig) -> dict[str, ObservationTermCfg]:
    """Privileged terms of the teacher (actor and critic): the next stones as rectangles for
    both rewards (SPEC: the same privileged terrain), and the reference for reward=clf only."""
    terms = {"stones": ObservationTermCfg(func=stones_ahead)}
    if needs_reference(cfg.reward):
        terms["reference"] = ObservationTermCfg(
            func=reference_obs, params={"command_name": REFERENCE_COMMAND}
        )
    return terms


def _teacher_terms(cfg: MarchConfig, noisy: bool) -> dict[str, ObservationTermCfg]:
    """Proprioception history + privileged terrain (+ the reference for clf): actor and critic."""
    terms = _proprio_terms(noisy=noisy)
    for term in terms.values():
        term.history_length = cfg.env.history_length
    terms["height_scan"] = _privileged_terrain_term(cfg)
    terms.update(_privileged_teacher_terms(cfg))
    return terms


def _observations(cfg: MarchConfig, purpose: str) -> dict[str, ObservationGroupCfg]:
    actor = _teacher_terms(cfg, noisy=True)
    groups = {
        "actor": ObservationGroupCfg(terms=actor, concatenate_terms=True, enable_corruption=True)
    }
    if purpose in ("teacher", "eval"):
        critic = _teacher_terms(cfg, noisy=False)
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
            history_length=cfg.env.history_length,
            flatten_history_dim=False,
        )
        noisy = purpose == "student" or cfg.eval.corruption
        d = cfg.depth
        groups["depth"] = ObservationGroupCfg(
            terms={
                "depth": ObservationTermCfg(
                    func=depth_image,
                    params={
                        "sensor_name": d.name,
                        "min_range": d.min_range,
                        "max_range": d.max_range,
                        "noise_scale": d.noise_scale if noisy else 0.0,
                        "dropout": d.dropout if noisy else 0.0,
                    },
                    delay_min_lag=d.delay_steps[0] if noisy else 0,
                    delay_max_lag=d.delay_steps[1] if noisy else 0,
                )
            },
            concatenate_terms=True,
        )
    return groups


def pelvis_too_low(env: ManagerBasedRlEnv, min_height: float) -> torch.Tensor:
    """Pelvis below ``min_height`` above the env's terrain origin."""
    robot = env.scene["robot"]
    return robot.data.root_link_pos_w[:, 2] - env.scene.env_origins[:, 2] < min_height


EVAL_TERMINATIONS = ("time_out", "goal_reached", "tilt", "pelvis_too_low", "foot_too_low")
"""The evaluation protocol's terminations, the same for every arm: the time-out, the success
(``goal_reached``: the pelvis over the goal platform, a ``time_out`` term so it is no failure)
and the falls. Nothing privileged (the planner's verdict, a training-only rule) ends an
evaluation rollout."""
SUCCESS_TERMINATION = "goal_reached"


def _terminations(cfg: MarchConfig, purpose: str) -> dict[str, TerminationTermCfg]:
    """Training: time_out, tilt, pelvis_too_low, foot_too_low (both rewards); planner_infeasible
    when the env runs the planner (reward=clf); nonfinite (fault resets). Evaluation: only
    ``EVAL_TERMINATIONS``."""
    terms = {
        "time_out": TerminationTermCfg(func=envs_mdp.time_out, time_out=True),
        "tilt": TerminationTermCfg(
            func=envs_mdp.bad_orientation,
            params={"limit_angle": math.radians(cfg.termination.tilt_limit_deg)},
        ),
        "pelvis_too_low": TerminationTermCfg(
            func=pelvis_too_low, params={"min_height": cfg.termination.min_base_height_m}
        ),
        "foot_too_low": TerminationTermCfg(
            func=foot_too_low, params={"max_drop": cfg.termination.max_foot_drop_m}
        ),
    }
    if needs_reference(cfg.reward):
        terms["planner_infeasible"] = TerminationTermCfg(
            func=planner_infeasible, params={"command_name": REFERENCE_COMMAND}
        )
    # Training: a non-finite env is reset by mjlab's own reset, without a host sync
    # (march.env.nonfinite; the runners' fault handling relies on it).
    terms["nonfinite"] = TerminationTermCfg(func=nonfinite_termination)
    if purpose == "eval":  # an allow-list: a termination added for training never leaks in
        terms[SUCCESS_TERMINATION] = TerminationTermCfg(func=goal_reached, time_out=True)
        terms = {k: terms[k] for k in EVAL_TERMINATIONS}
    return terms


def _reset_events(base: dict[str, EventTermCfg]) -> dict[str, EventTermCfg]:
    """Spawn on the start platform facing along the course (+x), small pose noise."""
    return {
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


def _terrain(cfg: MarchConfig, purpose: str) -> TerrainEntityCfg:
    """Training: curriculum rows (levels) of stone courses (flat rows first for flat_first).
    Evaluation: held-out stone courses of every level, drawn with ``eval.terrain_seed``
    (whatever the training curriculum; the evaluation assigns rollouts to cells,
    ``march.env.course.eval_cells``); or the hardware course."""
    c = cfg.curriculum
    common = {"num_rows": c.num_levels, "num_cols": c.num_cols, "seed": c.terrain_seed}
    if purpose == "eval":
        if cfg.eval.course == "hardware":
            return terrain_entity_cfg("hardware", cfg.terrain, max_init_terrain_level=None)
        # Held-out courses: the evaluation's own seed, the same for every arm and curriculum.
        held_out = {**common, "seed": cfg.eval.terrain_seed}
        return terrain_entity_cfg("stones", cfg.terrain, max_init_terrain_level=None, **held_out)
    if c.name == "flat_first":
        return terrain_entity_cfg(
            "flat_first",
            cfg.terrain,
            max_init_terrain_level=c.max_init_level,
            flat_levels=c.flat_levels,
            **common,
        )
    return terrain_entity_cfg(
        "stones", cfg.terrain, max_init_terrain_level=c.max_init_level, **common
    )


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

    env_cfg.scene.terrain = _terrain(cfg, purpose)
    env_cfg.curriculum = (
        {
            "terrain_levels": CurriculumTermCfg(
                func=course_levels,
                params={
                    "promote_fraction": cfg.curriculum.promote_fraction,
                    "demote_fraction": cfg.curriculum.demote_fraction,
                },
            )
        }
        if purpose != "eval"
        else {}
    )

    # terrain_scan: the height scan is computed from the course boxes (_privileged_terrain_term).
    dropped = ("foot_height_scan", "terrain_scan")
    sensors = tuple(s for s in (env_cfg.scene.sensors or ()) if s.name not in dropped)
    if purpose in ("student", "eval"):
        sensors = sensors + (depth_camera_cfg(cfg.depth),)
    env_cfg.scene.sensors = sensors

    twist = env_cfg.commands["twist"]
    assert isinstance(twist, UniformVelocityCommandCfg)
    # Commands in the course frame (README "The reference and the commands"): one forward speed
    # per episode (no resampling, no standing envs); the yaw rate is mjlab's heading controller
    # toward the course heading (every generated course runs along +x: heading 0), clipped to
    # env.command_yaw_rate, so no command leads off the stones and the ``command`` observation
    # is what the robot is asked to do. Both reward arms read this one command.
    twist.resampling_time_range = (1.0e9, 1.0e9)
    twist.rel_standing_envs = 0.0
    twist.rel_forward_envs = 0.0
    twist.rel_world_envs = 0.0
    twist.init_velocity_prob = 0.0  # episodes start standing (the CoM reference ramps from rest)
    twist.heading_command = True
    twist.rel_heading_envs = 1.0
    twist.heading_control_stiffness = cfg.env.command_heading_stiffness
    twist.debug_vis = False
    if purpose == "eval":
        vx = cfg.eval.command_vx
        vx_range, vy_range = (vx, vx), (0.0, 0.0)
    else:
        vx_range, vy_range = tuple(cfg.env.command_vx), tuple(cfg.env.command_vy)
    twist.ranges = UniformVelocityCommandCfg.Ranges(
        lin_vel_x=vx_range,
        lin_vel_y=vy_range,
        ang_vel_z=tuple(cfg.env.command_yaw_rate),
        heading=(COURSE_HEADING, COURSE_HEADING),
    )
    # The same command without mjlab's per-step host syncs (march.env.velocity_command).
    env_cfg.commands["twist"] = sync_free(twist)

    if needs_reference(cfg.reward):
        # Stage (1): planner + HLIP/Bezier reference + CLF state (march.env.reference_command).
        # Evaluation plans every env that touches down in the step it touches down (capacity =
        # all envs): a wave resets every env at once, so a training-sized batch would defer
        # touchdowns (the clf arm scored with a stale reference meanwhile). Training keeps its
        # fixed share (replan_capacity_fraction).
        ref = cfg.reference
        env_cfg.commands[REFERENCE_COMMAND] = ReferenceCommandCfg(
            planner_seed=cfg.seed,
            compile_math=cfg.compute.compile_math,
            replan_only_when_due=cfg.compute.replan_only_when_due,
            reference=ReferenceCfg(
                com_anchoring=ref.com_anchoring,
                com_height=ref.com_height,
                com_height_free_step=ref.com_height_free_step,
                com_height_slope=ref.com_height_slope,
                com_height_min=ref.com_height_min,
                swing_toe_down=ref.swing_toe_down,
                swing_xy_shape=ref.swing_xy_shape,
                swing_height=ref.swing_height,
                swing_toe_roll=ref.swing_toe_roll,
                swing_pitch_carry=ref.swing_pitch_carry,
                swing_roll_out=ref.swing_roll_out,
                swing_heel_strike=ref.swing_heel_strike,
            ),
            **({"replan_capacity_fraction": 1.0} if purpose == "eval" else {}),
        )

    env_cfg.observations = _observations(cfg, purpose)
    import_extra_modules(cfg.extra_modules)  # a worker's own plug-ins (the terms they register)
    env_cfg.rewards = reward_terms(cfg.reward)
    env_cfg.terminations = _terminations(cfg, purpose)
    env_cfg.events = _reset_events(base_events)
    camera = cfg.depth.name if purpose in ("student", "eval") else None
    dr = cfg.dr if purpose != "eval" or cfg.eval.randomization else replace(cfg.dr, name="none")
    apply_dr(env_cfg, dr, camera=camera)
    if purpose == "eval" and not cfg.eval.pushes:
        env_cfg.events.pop(T_PUSH, None)
    env_cfg.metrics = {}
    env_cfg.scene.sensors = _air_time_if_read(env_cfg)
    return env_cfg


AIR_TIME_READS = ("air_time", "first_contact", "first_air")
"""What a term's source names when it reads a contact sensor's air / contact timers."""


def _reads_air_time(func: object) -> bool:
    try:
        source = inspect.getsource(func)  # a function or a class term
    except (OSError, TypeError):
        return True  # source unknown: keep the timers
    return any(name in source for name in AIR_TIME_READS)


def _air_time_if_read(env_cfg: ManagerBasedRlEnvCfg) -> tuple:
    """The scene's sensors with contact air-time tracking only where a term can read it.

    mjlab's G1 task tracks the feet's air and contact times (92 ops a step at 16 envs, eager
    also on a GPU) for its ``feet_air_time`` reward and ``foot_air_time`` observation; neither
    arm of march reads them. A term whose source names them (``AIR_TIME_READS``) keeps the
    tracking, so a user's arm that adds such a term needs nothing else."""
    groups = (env_cfg.observations or {}).values()
    terms = [t for g in groups for t in g.terms.values()]
    for table in (env_cfg.rewards, env_cfg.terminations, env_cfg.events, env_cfg.curriculum):
        terms += list((table or {}).values())
    read = any(_reads_air_time(t.func) for t in terms if t is not None)
    return tuple(
        replace(s, track_air_time=False)
        if isinstance(s, ContactSensorCfg) and s.track_air_time and not read
        else s
        for s in env_cfg.scene.sensors or ()
    )


@contextlib.contextmanager
def _output_to(log: Path | None) -> Iterator[None]:
    """mjlab and warp print tables and kernel timings while building: keep them in a log file."""
    if log is None:
        yield
        return
    log.parent.mkdir(parents=True, exist_ok=True)
    with log.open("a") as f, contextlib.redirect_stdout(f):
        yield


def make_env(
    cfg: MarchConfig, purpose: str, num_envs: int | None = None, log: Path | None = None
) -> ManagerBasedRlEnv:
    """Build the real mjlab env for ``purpose`` on ``cfg.compute.device``.

    With ``log``, mjlab's build report goes to that file and one summary line is printed.
    """
    env_cfg = build_env_cfg(cfg, purpose, num_envs)
    set_compile_mode(cfg.compute.compile_mode)  # the env's compiled maths (compute.compile_math)
    t0 = time.time()
    with _output_to(log), pinned_solver_order(purpose == "eval"):  # batch-free order (issue 57)
        env = ManagerBasedRlEnv(cfg=env_cfg, device=cfg.compute.device)
    keep_termination_counts_on_device(env)  # no .item() per term and reset (reset_extras)
    # the per-step meters, on the device: per-term reward / termination sums (not for an
    # evaluation) and the CLF diagnostics (where the env has the reference command)
    if purpose != "eval":
        attach_term_meter(env)
    attach_clf_meter(env)
    env.march_spec = EnvSpec(  # type: ignore[attr-defined]
        purpose=purpose,
        num_envs=env.num_envs,
        episode_length_s=env_cfg.episode_length_s,
        has_camera=purpose in ("student", "eval"),
        placeholders=dict(PLACEHOLDERS),
    )
    if log is not None:
        shapes = ", ".join(
            f"{g} {tuple(d)}" for g, d in env.observation_manager.group_obs_dim.items()
        )
        print(
            f"[env] {purpose}: {env.num_envs} envs on {cfg.compute.device}, built in "
            f"{time.time() - t0:.0f}s; obs {shapes}; {env.action_manager.total_action_dim} actions"
            f" (build log: {log})",
            flush=True,
        )
    return env


def reseed_env(env: ManagerBasedRlEnv, seed: int) -> None:
    """Put the env's own state where a full reset makes it independent of the env's past, and
    seed the random states it owns besides torch's global one. Called at the start of every
    evaluation, before torch is seeded and every env is reset, so that an evaluation runs the
    same whatever the env did before (just built, trained beside, evaluated):

    - the observation buffers are initialised (one observation pass): mjlab's first pass after a
      build pushes a frame and draws the delay lags where every later reset only backfills, so
      a first evaluation would otherwise run one delay draw ahead of the others;
    - each command term's own generator and per-env planner streams (the reference command's
      planner) restart from ``seed``, and the resets its replan queue has not planned yet are forgotten (the caller's
      reset queues every env again)."""
    env.observation_manager.compute(update_history=True)
    for name in env.command_manager.active_terms:
        term = env.command_manager.get_term(name)
        generator = getattr(term, "generator", None)
        if isinstance(generator, torch.Generator):
            generator.manual_seed(int(seed))
        streams = getattr(term, "planner_streams", None)  # each env's planner stream
        if streams is not None:
            streams.assign(int(seed), 0)
        queue = getattr(term, "queue", None)
        if queue is not None:
            queue.take_resets()


def bare_env(task: str, num_envs: int, seed: int, device: str) -> ManagerBasedRlEnv:
    """mjlab's registered task ``task`` (e.g. ``Mjlab-Velocity-Rough-Unitree-G1``) with only
    ``num_envs`` and ``seed`` changed: the reference ``python -m march.bench`` measures against."""
    from mjlab.tasks.registry import load_env_cfg

    env_cfg = load_env_cfg(task)
    env_cfg.scene.num_envs = num_envs
    env_cfg.seed = seed
    return ManagerBasedRlEnv(cfg=env_cfg, device=device)


def rsl_rl_env(env: ManagerBasedRlEnv) -> RslRlVecEnvWrapper:
    """``env`` behind mjlab's rsl-rl vec-env wrapper (TensorDict observations), as rsl-rl's
    runners and algorithms expect it."""
    return RslRlVecEnvWrapper(env)
