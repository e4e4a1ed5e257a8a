"""Typed configuration schema: the single source of truth for every option march takes.

Hydra composes ``conf/`` on top of these dataclasses (registered in the ConfigStore as
``march_schema``), so a misspelt key or a wrong type fails at composition, before any simulation.
Values are checked once more when the composed config is turned into objects
(:func:`to_march_config`): ``__post_init__`` of each section raises :class:`ConfigError` with one
line saying what is wrong and how to fix it.

Pure data: no simulator import.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from functools import cache
from pathlib import Path
from typing import Any, get_args, get_origin, get_type_hints

from hydra.core.config_store import ConfigStore
from omegaconf import DictConfig, OmegaConf

from march.world.courses import CourseCfg

STAGES = ("all", "teacher", "student", "eval")
REWARDS = ("clf", "modelfree")
STUDENTS = ("full", "no_transformer", "no_mdn")
CURRICULA = ("stones", "flat_first")
COMPUTES = ("auto", "cpu", "gpu", "smoke")
LOGGERS = ("csv", "tensorboard", "wandb")
DRS = ("paper", "none")
COURSES = ("stones", "hardware")


class ConfigError(ValueError):
    """A configuration value that cannot work; the message says how to fix it."""


def _one_of(section: str, key: str, value: Any, valid: tuple[str, ...]) -> None:
    if value not in valid:
        raise ConfigError(
            f"{section}.{key}={value!r} is not valid; choose one of {', '.join(valid)}"
        )


def _positive(section: str, key: str, value: float) -> None:
    if not value > 0:
        raise ConfigError(f"{section}.{key}={value} must be > 0")


SEED_MAX = 2**31 - 1
"""Largest seed every RNG of a run accepts: numpy takes 0..2**32-1, but warp's ``wp.rand_init``
(mjlab's ``seed_rng``) takes an int32 and silently wraps anything larger."""

ACTIVATIONS = ("elu", "relu", "gelu", "silu", "tanh")
"""Activations of march's own networks (march.policies.student._activation)."""
RSL_ACTIVATIONS = ("elu", "selu", "relu", "crelu", "lrelu", "tanh", "sigmoid", "softplus")
RSL_ACTIVATIONS += ("gelu", "swish", "mish", "identity")
"""Activations rsl-rl's actor-critic MLP takes (rsl_rl.utils.resolve_nn_activation)."""
MJ_GEOM_GROUPS = 6
"""MuJoCo's number of geom groups (mjNGROUP): valid groups are 0..5."""


def _fmt(value: Any) -> str:
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_fmt(v) for v in value) + "]"
    return str(value)


def _need(section: str, key: str, value: Any, ok: bool, allowed: str) -> None:
    """Raise ``<section>.<key>=<value> must be <allowed>`` unless ``ok``."""
    if not ok:
        name = f"{section}.{key}" if section else key
        raise ConfigError(f"{name}={_fmt(value)} must be {allowed}")


def _at_least(section: str, key: str, value: float, lo: float) -> None:
    _need(section, key, value, value >= lo, f">= {lo}")


def _interval(
    section: str, key: str, value: float, lo: float, hi: float, *, lo_open=False, hi_open=False
) -> None:
    ok = (value > lo if lo_open else value >= lo) and (value < hi if hi_open else value <= hi)
    text = f"in {'(' if lo_open else '['}{lo}, {hi}{')' if hi_open else ']'}"
    _need(section, key, value, ok, text)


def _bounds(
    section: str, key: str, pair: Any, lo: float | None = None, *, lo_open: bool = False
) -> None:
    """A range [a, b]: a <= b, and a >= lo (a > lo with ``lo_open``)."""
    a, b = pair
    _need(section, key, pair, a <= b, "[lo, hi] with lo <= hi")
    if lo is not None:
        ok = a > lo if lo_open else a >= lo
        _need(section, key, pair, ok, f"[lo, hi] with lo {'>' if lo_open else '>='} {lo}")


def _each(section: str, key: str, values: Any, lo: float, *, nonempty: bool = False) -> None:
    """Every entry >= lo (and at least one entry with ``nonempty``)."""
    if nonempty:
        _need(section, key, values, len(values) > 0, "a non-empty list")
    _need(section, key, values, all(v >= lo for v in values), f"a list of values >= {lo}")


@cache
def _hints(cls: type) -> dict[str, Any]:
    return get_type_hints(cls)


def _check_shapes(section: str, obj: Any) -> None:
    """Every number finite and every fixed-size tuple of its declared length.

    OmegaConf accepts ``nan``/``inf`` for floats and a list of any length for a ``tuple[float,
    float]``; both would fail far from the command line."""
    hints = _hints(type(obj))
    for f in fields(obj):
        value, hint = getattr(obj, f.name), hints[f.name]
        items = list(value.values()) if isinstance(value, dict) else value
        if isinstance(items, (list, tuple)):
            args = get_args(hint)
            if get_origin(hint) is tuple and args and Ellipsis not in args:
                _need(
                    section, f.name, value, len(items) == len(args), f"a list of {len(args)} values"
                )
            nums = [v for v in items if isinstance(v, float)]
        else:
            nums = [items] if isinstance(items, float) else []
        _need(section, f.name, value, all(math.isfinite(v) for v in nums), "finite")


def cnn_output_hw(hw: tuple[int, int], kernels: Any, strides: Any) -> tuple[int, int]:
    """The student CNN's feature-map size for an image of ``hw`` (height, width) pixels: conv
    layers with same padding (kernel // 2), as march.policies.student builds them."""
    h, w = hw
    for k, s in zip(kernels, strides, strict=True):
        h = (h + 2 * (k // 2) - k) // s + 1
        w = (w + 2 * (k // 2) - k) // s + 1
    return h, w


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

    def __post_init__(self) -> None:
        _check_shapes("compute", self)
        _one_of("compute", "name", self.name, COMPUTES)
        dev = self.device
        if not (dev in ("cpu", "cuda") or (dev.startswith("cuda:") and dev[5:].isdigit())):
            raise ConfigError(f"compute.device={self.device!r}: use cpu, cuda or cuda:N")
        _positive("compute", "num_envs", self.num_envs)
        _positive("compute", "eval_num_envs", self.eval_num_envs)
        _need(
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
        _check_shapes("env", self)
        _positive("env", "episode_length_s", self.episode_length_s)
        _positive("env", "sim_dt", self.sim_dt)
        _positive("env", "decimation", self.decimation)
        _positive("env", "history_length", self.history_length)
        step = self.sim_dt * self.decimation
        _need(
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
        _check_shapes("depth", self)
        _need("depth", "name", self.name, bool(self.name), "a non-empty sensor name")
        _at_least("depth", "width", self.width, 1)
        _at_least("depth", "height", self.height, 1)
        _interval("depth", "fovy", self.fovy, 0, 180, lo_open=True, hi_open=True)
        _positive("depth", "max_range", self.max_range)
        _interval("depth", "min_range", self.min_range, 0, self.max_range, hi_open=True)
        _interval("depth", "pitch_deg", self.pitch_deg, -90, 90)
        _need(
            "depth",
            "geom_groups",
            self.geom_groups,
            len(self.geom_groups) > 0 and all(0 <= g < MJ_GEOM_GROUPS for g in self.geom_groups),
            f"a non-empty list of MuJoCo geom groups 0..{MJ_GEOM_GROUPS - 1}",
        )
        _at_least("depth", "noise_scale", self.noise_scale, 0)
        if not 0.0 <= self.dropout < 1.0:
            raise ConfigError(f"depth.dropout={self.dropout} must be in [0, 1)")
        if self.delay_steps[0] > self.delay_steps[1] or self.delay_steps[0] < 0:
            raise ConfigError(f"depth.delay_steps={list(self.delay_steps)}: need 0 <= lo <= hi")


@dataclass
class RewardCfg:
    """The teacher's reward: named terms and weights (conf/reward/*.yaml)."""

    name: str = "clf"
    """clf (CLF-RL terms around the model-based reference) or modelfree (RPL-style baseline)."""
    terms: dict[str, float] = field(default_factory=dict)
    """Reward term name -> weight. A penalty term returns a value <= 0 and carries a positive
    weight, so every weight here is the sign the term's contribution has (SPEC §2)."""
    tilt_limit_deg: float = 50.0
    """Terminate when the torso tilts beyond this [deg]."""
    min_base_height_m: float = 0.4
    """Terminate when the pelvis is lower than this above the start platform [m]."""
    max_foot_drop_m: float = 0.15
    """Terminate when a foot is more than this below the start platform top [m] (it fell off a
    stone; stone tops vary by at most terrain.height_hard = 0.10 m)."""

    def __post_init__(self) -> None:
        _check_shapes("reward", self)
        _one_of("reward", "name", self.name, REWARDS)
        _interval("reward", "tilt_limit_deg", self.tilt_limit_deg, 0, 180, lo_open=True)
        _at_least("reward", "min_base_height_m", self.min_base_height_m, 0)
        _positive("reward", "max_foot_drop_m", self.max_foot_drop_m)


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
        _one_of("curriculum", "name", self.name, CURRICULA)
        _check_shapes("curriculum", self)
        _positive("curriculum", "num_levels", self.num_levels)
        _positive("curriculum", "num_cols", self.num_cols)
        _interval("curriculum", "max_init_level", self.max_init_level, 0, self.num_levels - 1)
        _interval("curriculum", "flat_levels", self.flat_levels, 0, self.num_levels - 1)
        _interval("curriculum", "terrain_seed", self.terrain_seed, 0, SEED_MAX)
        # Progress is measured against the goal distance: 1 = the goal platform was reached.
        _interval("curriculum", "promote_fraction", self.promote_fraction, 0, 1, lo_open=True)
        _interval(
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
class StudentCfg:
    """Student network (conf/student/*.yaml); SPEC §2 has the author's sizes."""

    variant: str = "full"
    """full (CNN + transformer + MDN), no_transformer (MLP fusion) or no_mdn (deterministic head)."""
    cnn_channels: tuple[int, ...] = (24, 32, 48, 64)
    """CNN output channels per layer."""
    cnn_kernels: tuple[int, ...] = (5, 3, 3, 3)
    """Square kernel size [px] of each conv layer, same padding (kernel // 2)."""
    cnn_strides: tuple[int, ...] = (1, 2, 2, 1)
    """Stride of each conv layer; (1, 2, 2, 1) maps 24x32 to a 6x8 map = 48 image tokens."""
    d_model: int = 256
    """Transformer token width."""
    n_heads: int = 8
    """Attention heads."""
    n_layers: int = 2
    """Transformer encoder layers."""
    dim_feedforward: int = 512
    """Hidden width of each transformer layer's feed-forward block."""
    fusion_mlp: tuple[int, ...] = (512, 256)
    """Hidden sizes of the MLP that replaces the transformer (no_transformer)."""
    head_hidden: tuple[int, ...] = (256, 128)
    """Hidden sizes of the output head."""
    num_modes: int = 2
    """MDN mixture components."""
    min_std: float = 1e-3
    """MDN minimum standard deviation."""
    log_std_min: float = -3.0
    """MDN log-std lower clamp."""
    log_std_max: float = 2.0
    """MDN log-std upper clamp."""
    init_log_std: float = 0.0
    """Initial log-std of every MDN mode."""
    activation: str = "elu"
    """Activation of the CNN and MLPs (the transformer layers use GELU)."""
    huber_delta: float = 1.0
    """Huber loss threshold (action units) of no_mdn."""
    normalizer_eps: float = 1e-2
    """eps added to the running std of the observation normalisers (rsl-rl default)."""

    def __post_init__(self) -> None:
        _check_shapes("student", self)
        _one_of("student", "variant", self.variant, STUDENTS)
        _each("student", "cnn_channels", self.cnn_channels, 1, nonempty=True)
        _each("student", "cnn_kernels", self.cnn_kernels, 1)
        _each("student", "cnn_strides", self.cnn_strides, 1)
        for key in ("d_model", "n_heads", "n_layers", "dim_feedforward", "num_modes"):
            _at_least("student", key, getattr(self, key), 1)
        _each("student", "fusion_mlp", self.fusion_mlp, 1)
        _each("student", "head_hidden", self.head_hidden, 1)
        _positive("student", "min_std", self.min_std)
        _one_of("student", "activation", self.activation, ACTIVATIONS)
        _positive("student", "huber_delta", self.huber_delta)
        _positive("student", "normalizer_eps", self.normalizer_eps)
        if not len(self.cnn_channels) == len(self.cnn_kernels) == len(self.cnn_strides):
            raise ConfigError(
                f"student.cnn_channels={_fmt(self.cnn_channels)}, student.cnn_kernels="
                f"{_fmt(self.cnn_kernels)} and student.cnn_strides={_fmt(self.cnn_strides)} "
                "must have equal length (one entry per conv layer)"
            )
        if self.d_model % self.n_heads:
            raise ConfigError(
                f"student.d_model={self.d_model} must be divisible by student.n_heads="
                f"{self.n_heads}"
            )
        if self.log_std_min >= self.log_std_max:
            raise ConfigError(
                f"student.log_std_min={self.log_std_min} must be < student.log_std_max="
                f"{self.log_std_max}"
            )
        _interval("student", "init_log_std", self.init_log_std, self.log_std_min, self.log_std_max)


@dataclass
class TeacherCfg:
    """PPO teacher (paper Table: HLIP CLF Teacher PPO)."""

    max_iterations: int = 10000
    """PPO iterations (set by the compute preset)."""
    budget_scale: float = 1.0
    """Multiplies max_iterations (the baseline sweep gives modelfree 2x, as in the paper)."""
    num_steps_per_env: int = 24
    """Rollout length per iteration [control steps]."""
    hidden_dims: tuple[int, ...] = (512, 256, 128)
    """Actor and critic MLP hidden sizes."""
    activation: str = "elu"
    """Activation function."""
    init_std: float = 1.0
    """Initial action std."""
    learning_rate: float = 5e-5
    """Adam learning rate (adaptive schedule)."""
    schedule: str = "adaptive"
    """Learning-rate schedule: adaptive (KL-based) or fixed."""
    num_learning_epochs: int = 5
    """PPO epochs per iteration."""
    num_mini_batches: int = 4
    """Mini-batches per epoch."""
    clip_param: float = 0.2
    """PPO clip."""
    value_loss_coef: float = 1.0
    """Value loss coefficient."""
    entropy_coef: float = 0.008
    """Entropy coefficient."""
    gamma: float = 0.99
    """Discount."""
    lam: float = 0.95
    """GAE lambda."""
    desired_kl: float = 0.01
    """Target KL for the adaptive schedule."""
    max_grad_norm: float = 1.0
    """Gradient clip."""
    save_interval: int = 50
    """Checkpoint every this many iterations."""
    eval_interval: int = 500
    """Evaluate the current teacher (deterministic actor) on the fixed stone evaluation set
    every this many iterations (a ``stage=teacher`` row in eval.csv, same protocol for every
    arm); 0 = only at the end of the teacher stage, which is always evaluated."""
    max_nonfinite_updates: int = 3
    """PPO updates in a row with a non-finite loss or parameter (each undone and counted in
    metrics.csv) that stop the run with one line; its last checkpoint is the last good one."""

    @property
    def iterations(self) -> int:
        return max(1, round(self.max_iterations * self.budget_scale))

    def __post_init__(self) -> None:
        _check_shapes("teacher", self)
        _positive("teacher", "max_iterations", self.max_iterations)
        _positive("teacher", "budget_scale", self.budget_scale)
        _positive("teacher", "num_steps_per_env", self.num_steps_per_env)
        _each("teacher", "hidden_dims", self.hidden_dims, 1, nonempty=True)
        _one_of("teacher", "activation", self.activation, RSL_ACTIVATIONS)
        _positive("teacher", "init_std", self.init_std)
        _positive("teacher", "learning_rate", self.learning_rate)
        _positive("teacher", "save_interval", self.save_interval)
        _at_least("teacher", "max_nonfinite_updates", self.max_nonfinite_updates, 1)
        _one_of("teacher", "schedule", self.schedule, ("adaptive", "fixed"))
        _at_least("teacher", "num_learning_epochs", self.num_learning_epochs, 1)
        _at_least("teacher", "num_mini_batches", self.num_mini_batches, 1)
        _positive("teacher", "clip_param", self.clip_param)
        _at_least("teacher", "value_loss_coef", self.value_loss_coef, 0)
        _at_least("teacher", "entropy_coef", self.entropy_coef, 0)
        _interval("teacher", "gamma", self.gamma, 0, 1)
        _interval("teacher", "lam", self.lam, 0, 1)
        _positive("teacher", "desired_kl", self.desired_kl)
        _positive("teacher", "max_grad_norm", self.max_grad_norm)
        if self.eval_interval < 0:
            raise ConfigError(
                f"teacher.eval_interval={self.eval_interval} must be >= 0 (0 = only at the end)"
            )


@dataclass
class DistillCfg:
    """Student distillation (paper Table: MDN Distillation)."""

    max_iterations: int = 1500
    """Distillation iterations (set by the compute preset)."""
    num_steps_per_env: int = 120
    """Rollout length per iteration [control steps]."""
    learning_rate: float = 5e-4
    """Adam learning rate."""
    num_learning_epochs: int = 10
    """Passes over each rollout."""
    gradient_length: int = 2
    """Steps whose losses are summed per optimiser step."""
    max_grad_norm: float = 2.0
    """Gradient clip."""
    teacher_samples: int = 8
    """Teacher actions sampled per observation for the NLL loss."""
    teacher_std_scale: float = 0.1
    """Teacher std multiplier when sampling those actions."""
    eval_interval: int = 100
    """Evaluate the student every this many iterations (a row in eval.csv); 0 = only at the end."""
    save_interval: int = 50
    """Checkpoint every this many iterations."""
    max_nonfinite_updates: int = 3
    """Student updates in a row with a non-finite loss or parameter (each undone and counted in
    metrics.csv) that stop the run with one line; its last checkpoint is the last good one."""

    def __post_init__(self) -> None:
        _check_shapes("distill", self)
        _positive("distill", "learning_rate", self.learning_rate)
        _positive("distill", "max_grad_norm", self.max_grad_norm)
        _at_least("distill", "teacher_std_scale", self.teacher_std_scale, 0)
        _positive("distill", "max_iterations", self.max_iterations)
        _positive("distill", "num_steps_per_env", self.num_steps_per_env)
        _positive("distill", "num_learning_epochs", self.num_learning_epochs)
        _positive("distill", "gradient_length", self.gradient_length)
        _positive("distill", "teacher_samples", self.teacher_samples)
        _positive("distill", "save_interval", self.save_interval)
        _at_least("distill", "max_nonfinite_updates", self.max_nonfinite_updates, 1)
        if self.eval_interval < 0:
            raise ConfigError(
                f"distill.eval_interval={self.eval_interval} must be >= 0 (0 = only at the end)"
            )


@dataclass
class EvalCfg:
    """Evaluation protocol (SPEC §2)."""

    num_rollouts: int = 2048
    """Episodes rolled out per evaluation; rollout i runs on course cell (level i mod L,
    column (i // L + i mod L) mod C), so every level gets num_rollouts / L rollouts (+-1)."""
    episode_length_s: float = 20.0
    """Fixed episode length [s]; the farthest goal platform must be reached at command_vx
    with >= 25% of it to spare (tests/test_evaluate.py checks every compute preset)."""
    course: str = "stones"
    """stones (every level x column of the stone courses) or hardware (4 alternating stones)."""
    command_vx: float = 0.7
    """Forward velocity command along the course during evaluation [m/s], inside
    env.command_vx: 0.7 m/s reaches the 12 m course's farthest goal (9.25 m) in 13.2 s of 20."""
    corruption: bool = True
    """Depth corruption (noise, dropout, delay) as in training."""
    randomization: bool = True
    """Domain randomization as in training."""
    policy: str = "student"
    """Which policy to evaluate in stage=eval: student or teacher."""

    def __post_init__(self) -> None:
        _check_shapes("eval", self)
        _positive("eval", "num_rollouts", self.num_rollouts)
        _positive("eval", "episode_length_s", self.episode_length_s)
        _one_of("eval", "course", self.course, COURSES)
        _one_of("eval", "policy", self.policy, ("student", "teacher"))
        _positive("eval", "command_vx", self.command_vx)


@dataclass
class LoggerCfg:
    """Where per-iteration metrics go besides metrics.csv (always written)."""

    name: str = "csv"
    """csv, tensorboard or wandb (offline unless WANDB_MODE says otherwise)."""
    project: str = "march"
    """wandb project."""

    def __post_init__(self) -> None:
        _check_shapes("logger", self)
        _one_of("logger", "name", self.name, LOGGERS)
        _need("logger", "project", self.project, bool(self.project), "a non-empty project name")


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
        _check_shapes("dr", self)
        _one_of("dr", "name", self.name, DRS)
        _bounds("dr", "friction", self.friction, 0)
        _bounds("dr", "link_mass_scale", self.link_mass_scale, 0, lo_open=True)
        _bounds("dr", "base_added_mass_kg", self.base_added_mass_kg)
        _bounds("dr", "encoder_bias_rad", self.encoder_bias_rad)
        _each("dr", "base_com_offset_m", self.base_com_offset_m, 0)
        _bounds("dr", "effort_limit_scale", self.effort_limit_scale, 0, lo_open=True)
        _bounds("dr", "joint_damping_scale", self.joint_damping_scale, 0)
        _bounds("dr", "joint_friction", self.joint_friction, 0)
        _bounds("dr", "push_interval_s", self.push_interval_s, 0, lo_open=True)
        _at_least("dr", "push_lin_vel", self.push_lin_vel, 0)
        _at_least("dr", "push_ang_vel", self.push_ang_vel, 0)
        _bounds("dr", "control_delay_ms", self.control_delay_ms, 0)
        _at_least("dr", "camera_pos_m", self.camera_pos_m, 0)
        _each("dr", "camera_rot_deg", self.camera_rot_deg, 0)
        _at_least("dr", "camera_fov_deg", self.camera_fov_deg, 0)


@dataclass
class MarchConfig:
    """The whole composed config of a march run (conf/config.yaml)."""

    seed: int = 0
    """Seeds torch, numpy, python and the simulator; same seed on CPU -> same numbers."""
    stage: str = "all"
    """all (teacher -> student -> eval), teacher, student or eval."""
    teacher_ckpt: str | None = None
    """Teacher checkpoint file (stage=student, stage=eval with eval.policy=teacher)."""
    student_ckpt: str | None = None
    """Student checkpoint file (stage=eval)."""
    resume: str | None = None
    """A run directory to continue from its last checkpoints."""
    out: str | None = None
    """A file a tool writes (viz, export, play)."""
    compute: ComputeCfg = field(default_factory=ComputeCfg)
    env: EnvCfg = field(default_factory=EnvCfg)
    reward: RewardCfg = field(default_factory=RewardCfg)
    curriculum: CurriculumCfg = field(default_factory=CurriculumCfg)
    student: StudentCfg = field(default_factory=StudentCfg)
    teacher: TeacherCfg = field(default_factory=TeacherCfg)
    distill: DistillCfg = field(default_factory=DistillCfg)
    eval: EvalCfg = field(default_factory=EvalCfg)
    logger: LoggerCfg = field(default_factory=LoggerCfg)
    dr: DrCfg = field(default_factory=DrCfg)
    depth: DepthCfg = field(default_factory=DepthCfg)
    terrain: CourseCfg = field(default_factory=CourseCfg)

    def __post_init__(self) -> None:
        if self.stage not in STAGES:
            raise ConfigError(
                f"stage={self.stage!r} is not valid; choose one of {', '.join(STAGES)}"
            )
        _interval("", "seed", self.seed, 0, SEED_MAX)
        for key in ("teacher_ckpt", "student_ckpt", "resume", "out"):
            _need("", key, getattr(self, key), getattr(self, key) != "", "a path (or left unset)")
        hw = cnn_output_hw(
            (self.depth.height, self.depth.width),
            self.student.cnn_kernels,
            self.student.cnn_strides,
        )
        if min(hw) < 1:
            raise ConfigError(
                f"depth.height x depth.width={self.depth.height}x{self.depth.width} must be at "
                f"least what the student CNN (kernels {_fmt(self.student.cnn_kernels)}, strides "
                f"{_fmt(self.student.cnn_strides)}) reduces to 1x1; it gives {hw[0]}x{hw[1]}"
            )
        batch = self.compute.num_envs * self.teacher.num_steps_per_env
        _need(
            "teacher",
            "num_mini_batches",
            self.teacher.num_mini_batches,
            self.teacher.num_mini_batches <= batch,
            f"<= compute.num_envs x teacher.num_steps_per_env = {batch} (one sample per mini-batch at least)",
        )
        _need(
            "dr",
            "camera_fov_deg",
            self.dr.camera_fov_deg,
            self.dr.camera_fov_deg < self.depth.fovy,
            f"< depth.fovy={self.depth.fovy} (the randomized field of view stays > 0)",
        )
        if self.eval.course == "hardware":
            t = self.terrain
            length = t.end_margin + t.start_length + sum(t.hardware_gaps) + t.goal_length
            length += len(t.hardware_lateral) * t.hardware_stone_size[0]
            _need(
                "terrain",
                "size",
                t.size,
                t.size[0] >= length,
                f"[x, y] with x >= {length:.3g}: the hardware course (eval.course=hardware) is that long",
            )
        lo, hi = self.env.command_vx
        if not lo <= self.eval.command_vx <= hi:
            raise ConfigError(
                f"eval.command_vx={self.eval.command_vx} lies outside the training range "
                f"env.command_vx=[{lo}, {hi}]: evaluate at a command the policy was trained on"
            )


SWEEPS_DIR = Path(__file__).resolve().parents[2] / "sweeps"


def register_schema() -> None:
    """Register the schema (conf/config.yaml extends it) and the sweeps (idempotent).

    Each ``sweeps/<name>.yaml`` becomes the option ``sweep=<name>`` (package _global_), so
    ``python -m march.train -m +sweep=baseline`` finds it wherever march is run from.
    """
    cs = ConfigStore.instance()
    cs.store(name="march_schema", node=MarchConfig)
    for path in sorted(SWEEPS_DIR.glob("*.yaml")):
        cs.store(group="sweep", name=path.stem, node=OmegaConf.load(path), package="_global_")


register_schema()


def to_march_config(cfg: DictConfig) -> MarchConfig:
    """Turn a composed (and compute-resolved) DictConfig into validated dataclasses."""
    obj = OmegaConf.to_object(cfg)
    if not isinstance(obj, MarchConfig):  # composed without the schema (e.g. a raw YAML)
        merged = OmegaConf.merge(OmegaConf.structured(MarchConfig), cfg)
        obj = OmegaConf.to_object(merged)
    assert isinstance(obj, MarchConfig)
    return obj
