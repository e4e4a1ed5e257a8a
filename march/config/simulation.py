"""Config sections of the simulated world: compute, environment, depth camera, reward,
the reference trajectory, terrain curriculum and domain randomization (``conf/`` groups of the same names).

Each ``__post_init__`` checks its values with :mod:`march.config.checks`. Pure data: no simulator
import.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from march.config.checks import (
    COMPUTES,
    CURRICULA,
    DRS,
    MJ_GEOM_GROUPS,
    SEED_MAX,
    ConfigError,
    check_at_least,
    check_bounds,
    check_each,
    check_identifier,
    check_interval,
    check_one_of,
    check_positive,
    check_shapes,
    require,
)
from march.config.terms import check_entry


@dataclass
class ComputeCfg:
    """Where and how big: presets in ``conf/compute/`` also size teacher, distill and eval."""

    name: str = "cpu"
    """Preset name: auto (gpu if CUDA is available, else cpu), cpu, gpu or smoke."""
    device: str = "cpu"
    """Torch/warp device for simulation and learning: "cpu", "cuda" or "cuda:N"."""
    num_envs: int = 32
    """Parallel environments for teacher training and distillation."""
    eval_num_envs: int = 32
    """Parallel environments for evaluation rollouts (at most eval.num_rollouts are used)."""
    torch_threads: int = 0
    """torch.set_num_threads on CPU; 0 keeps torch's default."""
    dist_timeout_s: float = 300.0
    """A run over N processes: the process group's timeout [s]. A rank that waits longer for
    another one (dead, hung) stops the run with one line instead of holding every device
    (docs/scaling.md)."""
    compile_math: bool = False
    """``torch.compile`` the pure maths of a step (``march.compiled_math``): the footstep planner's
    search, the step reference, the measured CLF outputs and the height scan. On in the gpu
    preset, where it cuts the teacher step's kernel launches from 1,751 (eager) to 812, against
    bare mjlab rough's 760-795 (64 envs, 2026-12-03); off elsewhere: on CPU it makes the step
    slower (inductor's CPU kernels for the planner) and compiling takes minutes (README,
    "Speed"; ``python -m march.bench env`` reports the compile time)."""
    replan_only_when_due: bool = False
    """The reference command calls the footstep planner only in the updates where an env is
    reset, touches down or times out, at the cost of one host read per update (the same plans
    and numbers either way). On in the cpu preset, where a host read costs nothing and the
    planner's fixed batch, planned every update to avoid that read, was 41 of march's 56 ms per
    step at 32 envs (2026-12-06); off elsewhere (on a GPU the read stalls the stream)."""
    compile_mode: str = "default"
    """torch.compile's mode for ``compile_math``: ``default``, or ``reduce-overhead`` (each
    compiled graph also captured in a CUDA graph per input shape and replayed with one launch;
    GPU only, on CPU it is the default mode; outputs are cloned so no replay overwrites one a
    caller holds). Unmeasured on a GPU as of 2026-12-04: the GPU check's optional
    ``bench_graphs`` phase compares it with ``default``."""

    def __post_init__(self) -> None:
        check_shapes("compute", self)
        check_one_of("compute", "compile_mode", self.compile_mode, ("default", "reduce-overhead"))
        check_one_of("compute", "name", self.name, COMPUTES)
        dev = self.device
        if not (dev in ("cpu", "cuda") or (dev.startswith("cuda:") and dev[5:].isdigit())):
            raise ConfigError(f"compute.device={self.device!r}: use cpu, cuda or cuda:N")
        check_positive("compute", "num_envs", self.num_envs)
        check_positive("compute", "eval_num_envs", self.eval_num_envs)
        check_positive("compute", "dist_timeout_s", self.dist_timeout_s)
        require(
            "compute",
            "torch_threads",
            self.torch_threads,
            self.torch_threads >= 0,
            ">= 0 (0 = torch's default)",
        )


@dataclass
class EnvCfg:
    """The mjlab environment around the Unitree G1 (SPEC §2)."""

    episode_length_s: float = 20.0
    """Episode length [s]."""
    sim_dt: float = 0.005
    """Physics time step [s]."""
    decimation: int = 4
    """Physics steps per control step (50 Hz control at 0.005 s)."""
    history_length: int = 5
    """Proprioception history length [control steps] for teacher and student."""
    command_vx: tuple[float, float] = (0.3, 0.8)
    """Forward speed command range [m/s], sampled once per episode; the speed along the course
    (``Footholds.direction``; the robot is steered to face it)."""
    command_vy: tuple[float, float] = (0.0, 0.0)
    """Lateral velocity command range [m/s], across the course. 0 on the straight stone courses:
    0.1 m/s sideways for a 20 s episode is 2 m off the course axis (README, reference/commands)."""
    command_yaw_rate: tuple[float, float] = (-0.2, 0.2)
    """Bounds of the yaw-rate command [rad/s]. The yaw rate is not sampled: a heading controller
    steers back to the course heading, yaw rate = clip(command_heading_stiffness * (course
    heading - robot heading), these bounds) (mjlab's heading command); must contain 0."""
    command_heading_stiffness: float = 0.5
    """Gain of that heading controller [1/s] (mjlab's velocity task uses 0.5)."""

    def __post_init__(self) -> None:
        check_shapes("env", self)
        check_positive("env", "episode_length_s", self.episode_length_s)
        check_positive("env", "sim_dt", self.sim_dt)
        check_positive("env", "decimation", self.decimation)
        check_positive("env", "history_length", self.history_length)
        step = self.sim_dt * self.decimation
        require(
            "env",
            "episode_length_s",
            self.episode_length_s,
            self.episode_length_s >= step,
            f">= one control step (sim_dt * decimation = {step:g} s)",
        )
        for key in ("command_vx", "command_vy", "command_yaw_rate"):
            lo, hi = getattr(self, key)
            if lo > hi:
                raise ConfigError(f"env.{key}=[{lo}, {hi}]: the lower bound exceeds the upper")
        lo, hi = self.command_yaw_rate
        if not lo <= 0.0 <= hi:
            raise ConfigError(
                f"env.command_yaw_rate=[{lo}, {hi}] must contain 0: it bounds the heading "
                "controller that steers back to the course (0 once the robot faces along it)"
            )
        if self.command_heading_stiffness < 0.0:
            raise ConfigError(
                f"env.command_heading_stiffness={self.command_heading_stiffness} must be >= 0"
            )


@dataclass
class DepthCfg:
    """Chest depth camera (Realsense D435i-like) and its corruption."""

    name: str = "depth_cam"
    """Camera / sensor name in the scene."""
    width: int = 32
    """Image width [px]."""
    height: int = 24
    """Image height [px]."""
    fovy: float = 55.2
    """Vertical field of view [deg]."""
    min_range: float = 0.1
    """Closest depth the camera reports [m] (D435i ~0.1 m at low resolution); nearer is clipped."""
    max_range: float = 3.0
    """Farthest depth kept [m]; misses, invalid and dropped pixels read as this."""
    pos: tuple[float, float, float] = (0.0576, 0.0175, 0.42)
    """Camera position in the torso_link frame [m] (x forward, y left, z up): the D435 mount of
    Unitree's G1 URDF (d435_joint), ~1.25 m above the ground when standing."""
    pitch_deg: float = 47.6
    """Downward pitch of the optical axis below the torso's forward (+x) axis [deg] (URDF
    d435_joint: 0.83 rad); with fovy 55.2 the view spans ~20-75 deg below the horizon."""
    geom_groups: tuple[int, ...] = (0,)
    """Geom groups the camera renders: 0 = terrain only (the robot's own visual geoms are
    group 2). All cameras of a scene must share this (mujoco_warp)."""
    noise_scale: float = 0.1
    """Gaussian depth noise sigma as a fraction of depth (sigma = noise_scale * depth)."""
    dropout: float = 0.05
    """Fraction of pixels dropped (set invalid -> max range) per frame."""
    delay_steps: tuple[int, int] = (0, 1)
    """Per-env delay [control steps], drawn uniformly from [lo, hi] at reset (1 step = 20 ms)."""

    def __post_init__(self) -> None:
        check_shapes("depth", self)
        require("depth", "name", self.name, bool(self.name), "a non-empty sensor name")
        check_at_least("depth", "width", self.width, 1)
        check_at_least("depth", "height", self.height, 1)
        check_interval("depth", "fovy", self.fovy, 0, 180, lo_open=True, hi_open=True)
        check_positive("depth", "max_range", self.max_range)
        check_interval("depth", "min_range", self.min_range, 0, self.max_range, hi_open=True)
        check_interval("depth", "pitch_deg", self.pitch_deg, -90, 90)
        require(
            "depth",
            "geom_groups",
            self.geom_groups,
            len(self.geom_groups) > 0 and all(0 <= g < MJ_GEOM_GROUPS for g in self.geom_groups),
            f"a non-empty list of MuJoCo geom groups 0..{MJ_GEOM_GROUPS - 1}",
        )
        check_at_least("depth", "noise_scale", self.noise_scale, 0)
        if not 0.0 <= self.dropout < 1.0:
            raise ConfigError(f"depth.dropout={self.dropout} must be in [0, 1)")
        if self.delay_steps[0] > self.delay_steps[1] or self.delay_steps[0] < 0:
            raise ConfigError(f"depth.delay_steps={list(self.delay_steps)}: need 0 <= lo <= hi")


@dataclass
class RewardCfg:
    """The teacher's reward: named terms and weights (conf/reward/*.yaml)."""

    name: str = "clf"
    """The arm's name, e.g. clf (CLF-RL terms around the model-based reference) or modelfree
    (RPL-style baseline): one per ``conf/reward/<name>.yaml`` (march.config.registry)."""
    label: str = ""
    """How figures and tables name the arm (empty: the name)."""
    color: str = ""
    """The arm's matplotlib colour in figures (empty: one no other arm uses)."""
    order: int = 100
    """The arm's position in legends and tables (lower first)."""
    observe_reference: bool = False
    """The teacher observes the planner's reference even when no term needs it (the planner
    runs for it). A factorial control: modelfree with the clf teacher's reference observation
    (``+sweep=factorial``) separates the CLF reward's effect from the observation's."""
    terms: dict[str, Any] = field(default_factory=dict)
    """Reward term name -> weight, or ``{weight: w, params: {...}}`` (params: keyword arguments
    of the term's function, checked against its signature; ``python -m march.inspect list``
    shows each term's parameters). A penalty term returns a value <= 0 and carries a positive
    weight, so every weight here is the sign the term's contribution has (SPEC §2)."""
    tilt_limit_deg: float | None = None
    """Moved to ``termination.tilt_limit_deg`` (an old config's value is carried over there)."""
    min_base_height_m: float | None = None
    """Moved to ``termination.min_base_height_m``."""
    max_foot_drop_m: float | None = None
    """Moved to ``termination.max_foot_drop_m``."""

    def __post_init__(self) -> None:
        check_shapes("reward", self)
        check_identifier("reward", "name", self.name)
        for name, value in self.terms.items():
            check_entry(name, value)


COM_ANCHORINGS = ("continuous", "stance")
"""``reference.com_anchoring`` values (march.reference.com_carry.COM_ANCHORINGS)."""
COM_HEIGHTS = ("fixed", "step")
"""``reference.com_height`` values (march.reference.com_carry.COM_HEIGHTS)."""


@dataclass
class ReferenceSectionCfg:
    """The CLF teacher's reference trajectory (``reference``; SPEC section 2, "References";
    march.reference.com_carry, docs/method.md). Used by the env's ``reference`` command, the
    audits and every tool that builds the env."""

    com_anchoring: str = "continuous"
    """``continuous`` (default): the CoM reference carries the previous reference's CoM state
    across a touchdown (continuous in position and velocity; each step ends on its planned HLIP
    orbit). ``stance``: each step's HLIP orbit is anchored at the new stance foot (the earlier
    reference; it jumps by about (l_old - l_new)/2 at every touchdown), kept for comparison."""
    com_height: str = "fixed"
    """``fixed`` (default): CoM height z0 = 0.67 m (author) for every step. ``step``: the CoM
    is lowered with the step's length along the course, z = clamp(0.67 - com_height_slope
    (|l| - com_height_free_step), com_height_min, 0.67), so long steps are within the G1's
    reach; the HLIP's lambda uses that height."""
    com_height_free_step: float = 0.5
    """``com_height=step``: steps up to this long [m] keep z0."""
    com_height_slope: float = 0.35
    """``com_height=step``: CoM lowered per metre of step beyond the free length [m/m]."""
    com_height_min: float = 0.57
    """``com_height=step``: the lowest CoM height [m]."""
    swing_toe_down: float = 0.0
    """Swing-foot pitch reference at mid-swing [rad], positive toe down: swing_toe_down
    64 s^3 (1 - s)^3 of the swing phase s, flat with zero rate at lift-off and touchdown
    (march.reference.trajectory.toe_down). 0 (default): flat all swing, as the author's.
    Issue 55: at the apex of short steps the G1's swing ankle is at its dorsiflexion limit
    (-0.873 rad) and cannot hold the foot flat; 0.35 is what docs/audit.md measures."""
    swing_toe_roll: float = 0.0
    """Swing-foot pitch added to the toe-down [rad], positive: toe down by up to this early in
    the swing (phase 0.311) and toe up by as much late (0.689), flat with zero rate at lift-off,
    mid-swing and touchdown (march.reference.trajectory.toe_down). 0 (default): none."""
    swing_height: float = 0.10
    """Apex clearance of the swing foot above the higher of its lift-off and landing stones [m]
    (march.reference.trajectory.swing_trajectory; 0.10 m, the default, as before)."""
    swing_xy_shape: float = 0.0
    """a in [0, 0.5] [-]: the swing foot's horizontal Bezier has control points (p0, p0,
    p0 + a D, p1 - a D, p1, p1), D the swing's travel (march.reference.trajectory.
    swing_trajectory). 0 (default): minimum jerk, as the author's (peak speed 1.875 |D| / T);
    a > 0 leaves and lands with an acceleration of 20 a |D| / T^2 and a flatter speed
    ((30 - 20 a) / 16 |D| / T at mid-swing). Issue 55, docs/audit.md."""

    swing_pitch_carry: float = 0.0
    """c in [0, 1]: the swing foot's pitch reference starts at the pitch the foot has at
    lift-off (measured, like the lift-off position) and blends into the flat / toe-down
    profile over c T (march.reference.trajectory.swing_pitch_carry). 0 (default): none, as
    the author's. Issue 55: a rear foot that lifted its heel leaves the ground toe down;
    docs/audit.md measures it with ``audit.stance=heel_off``."""

    swing_roll_out: float = 0.0
    """Swing-foot roll reference at mid-swing [rad], toward the swing foot's own side (+ left
    foot, - right foot): swing_roll_out 64 s^3 (1 - s)^3 of the swing phase, level with zero
    rate at lift-off and touchdown (march.reference.trajectory.swing_roll_out). 0 (default):
    level all swing, as the author's. Issue 55: at mid-swing the knee-bent leg is abducted
    beyond what the G1's ankle roll range can level; docs/audit.md measures it."""

    swing_heel_strike: float = 0.0
    """Swing-foot toe-up pitch at touchdown [rad] (a heel strike): the pitch reference turns
    toe up over the swing's second half (zero rate at mid-swing and touchdown) and the foot's
    position is offset so that its heel lands where a flat foot's would
    (march.reference.trajectory.heel_strike). 0 (default): the foot lands flat, as the
    author's. Issue 55: on the longest steps a flat landing needs the front ankle at its
    limit; docs/audit.md measures it with ``audit.stance=heel_toe``."""

    def __post_init__(self) -> None:
        check_shapes("reference", self)
        check_one_of("reference", "com_anchoring", self.com_anchoring, COM_ANCHORINGS)
        check_one_of("reference", "com_height", self.com_height, COM_HEIGHTS)
        check_at_least("reference", "com_height_free_step", self.com_height_free_step, 0)
        check_at_least("reference", "com_height_slope", self.com_height_slope, 0)
        check_interval("reference", "com_height_min", self.com_height_min, 0.3, 0.67)
        check_interval("reference", "swing_toe_down", self.swing_toe_down, -1.0, 1.0)
        check_interval("reference", "swing_toe_roll", self.swing_toe_roll, -1.0, 1.0)
        check_interval("reference", "swing_roll_out", self.swing_roll_out, -0.5, 0.5)
        check_interval("reference", "swing_heel_strike", self.swing_heel_strike, 0.0, 0.5)
        check_interval("reference", "swing_height", self.swing_height, 0.02, 0.3)
        check_interval("reference", "swing_xy_shape", self.swing_xy_shape, 0.0, 0.5)
        check_interval("reference", "swing_pitch_carry", self.swing_pitch_carry, 0.0, 1.0)


MOVED_TO_TERMINATION = ("tilt_limit_deg", "min_base_height_m", "max_foot_drop_m")
"""``reward.<key>`` of configs before issue 36, now ``termination.<key>``."""


@dataclass
class TerminationCfg:
    """When a training or evaluation episode ends in a fall (the same thresholds go into the
    deployment bundle, ``deploy.json``'s ``fall``)."""

    tilt_limit_deg: float = 50.0
    """Terminate when the torso tilts beyond this [deg]."""
    min_base_height_m: float = 0.4
    """Terminate when the pelvis is lower than this above the start platform [m]."""
    max_foot_drop_m: float = 0.15
    """Terminate when a foot is more than this below the start platform top [m] (it fell off a
    stone; stone tops vary by at most terrain.height_hard = 0.10 m)."""

    def __post_init__(self) -> None:
        check_shapes("termination", self)
        check_interval("termination", "tilt_limit_deg", self.tilt_limit_deg, 0, 180, lo_open=True)
        check_at_least("termination", "min_base_height_m", self.min_base_height_m, 0)
        check_positive("termination", "max_foot_drop_m", self.max_foot_drop_m)

    def adopt(self, reward: RewardCfg) -> None:
        """Carry an old config's ``reward.<threshold>`` over (then clear it there); a value set
        in both places differently is one line saying which to keep."""
        for key in MOVED_TO_TERMINATION:
            old = getattr(reward, key)
            if old is None:
                continue
            default = getattr(TerminationCfg, key)
            new = getattr(self, key)
            if new != default and new != old:
                raise ConfigError(
                    f"reward.{key}={old} and termination.{key}={new}: the threshold moved to "
                    f"termination.{key}; set it there only"
                )
            setattr(self, key, old)
            setattr(reward, key, None)
        self.__post_init__()


@dataclass
class CurriculumCfg:
    """Terrain curriculum (conf/curriculum/*.yaml)."""

    name: str = "stones"
    """stones (stepping stones from the start, easiest level first) or flat_first."""
    num_levels: int = 10
    """Difficulty levels (terrain rows)."""
    num_cols: int = 8
    """Courses per level (terrain columns)."""
    max_init_level: int = 0
    """Highest level an env may start on."""
    flat_levels: int = 0
    """Lowest levels that are flat ground (flat_first: envs start there and climb onto stones)."""
    terrain_seed: int = 0
    """Seed of the terrain generator; fixed so the foothold table can regenerate the courses."""
    promote_fraction: float = 1.0
    """Level up when progress >= this x the goal distance (the goal platform was reached)."""
    demote_fraction: float = 0.3
    """Level down when progress < this x the goal distance."""

    def __post_init__(self) -> None:
        check_one_of("curriculum", "name", self.name, CURRICULA)
        check_shapes("curriculum", self)
        check_positive("curriculum", "num_levels", self.num_levels)
        check_positive("curriculum", "num_cols", self.num_cols)
        check_interval("curriculum", "max_init_level", self.max_init_level, 0, self.num_levels - 1)
        check_interval("curriculum", "flat_levels", self.flat_levels, 0, self.num_levels - 1)
        check_interval("curriculum", "terrain_seed", self.terrain_seed, 0, SEED_MAX)
        # Progress is measured against the goal distance: 1 = the goal platform was reached.
        check_interval("curriculum", "promote_fraction", self.promote_fraction, 0, 1, lo_open=True)
        check_interval(
            "curriculum",
            "demote_fraction",
            self.demote_fraction,
            0,
            self.promote_fraction,
            hi_open=True,
        )
        if self.name == "flat_first" and not 0 < self.flat_levels < self.num_levels:
            raise ConfigError(
                f"curriculum.flat_levels={self.flat_levels}: flat_first needs 1..num_levels-1"
            )
        if self.name == "stones" and self.flat_levels:
            raise ConfigError("curriculum=stones has no flat levels; set curriculum.flat_levels=0")


@dataclass
class DrCfg:
    """Domain randomization (conf/dr/*.yaml): the paper's table or none."""

    name: str = "paper"
    """paper (every row of the paper's table) or none."""
    friction: tuple[float, float] = (0.5, 1.25)
    """Foot friction coefficient range."""
    link_mass_scale: tuple[float, float] = (0.9, 1.2)
    """Link mass multiplier range."""
    base_added_mass_kg: tuple[float, float] = (-1.0, 3.0)
    """Added torso mass range [kg]."""
    encoder_bias_rad: tuple[float, float] = (-0.015, 0.015)
    """Joint encoder bias range [rad]."""
    base_com_offset_m: tuple[float, float, float] = (0.025, 0.05, 0.05)
    """Torso CoM offset half-ranges in x, y, z [m]."""
    effort_limit_scale: tuple[float, float] = (0.85, 1.1)
    """Motor effort limit multiplier range."""
    joint_damping_scale: tuple[float, float] = (0.75, 1.25)
    """Joint damping multiplier range."""
    joint_friction: tuple[float, float] = (0.0, 0.04)
    """Joint friction loss range [N m]."""
    push_interval_s: tuple[float, float] = (10.0, 15.0)
    """Velocity push interval [s]."""
    push_lin_vel: float = 1.0
    """Push linear velocity half-range in x and y [m/s]."""
    push_ang_vel: float = 0.4
    """Push angular velocity half-range in roll, pitch, yaw [rad/s]."""
    control_delay_ms: tuple[float, float] = (0.0, 20.0)
    """Action delay range [ms]."""
    camera_pos_m: float = 0.025
    """Camera translation half-range per axis [m]."""
    camera_rot_deg: tuple[float, float, float] = (2.5, 3.0, 2.5)
    """Camera rotation half-ranges roll, pitch, yaw [deg]."""
    camera_fov_deg: float = 2.0
    """Camera FOV half-range [deg]."""

    def __post_init__(self) -> None:
        check_shapes("dr", self)
        check_one_of("dr", "name", self.name, DRS)
        check_bounds("dr", "friction", self.friction, 0)
        check_bounds("dr", "link_mass_scale", self.link_mass_scale, 0, lo_open=True)
        check_bounds("dr", "base_added_mass_kg", self.base_added_mass_kg)
        check_bounds("dr", "encoder_bias_rad", self.encoder_bias_rad)
        check_each("dr", "base_com_offset_m", self.base_com_offset_m, 0)
        check_bounds("dr", "effort_limit_scale", self.effort_limit_scale, 0, lo_open=True)
        check_bounds("dr", "joint_damping_scale", self.joint_damping_scale, 0)
        check_bounds("dr", "joint_friction", self.joint_friction, 0)
        check_bounds("dr", "push_interval_s", self.push_interval_s, 0, lo_open=True)
        check_at_least("dr", "push_lin_vel", self.push_lin_vel, 0)
        check_at_least("dr", "push_ang_vel", self.push_ang_vel, 0)
        check_bounds("dr", "control_delay_ms", self.control_delay_ms, 0)
        check_at_least("dr", "camera_pos_m", self.camera_pos_m, 0)
        check_each("dr", "camera_rot_deg", self.camera_rot_deg, 0)
        check_at_least("dr", "camera_fov_deg", self.camera_fov_deg, 0)
