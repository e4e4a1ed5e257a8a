"""Config sections of learning and measuring: the student network, the PPO teacher, student
distillation, the evaluation protocol and the metrics logger.

Each ``__post_init__`` checks its values with :mod:`march.config.checks`. Pure data: no simulator
import.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from march.config.checks import (
    ACTIVATIONS,
    BUILTIN_PARTS,
    COURSES,
    LOGGERS,
    RSL_ACTIVATIONS,
    SEED_MAX,
    ConfigError,
    check_at_least,
    check_each,
    check_identifier,
    check_interval,
    check_one_of,
    check_positive,
    check_shapes,
    fmt_value,
    require,
)
from march.config.parts import check_parts, check_value


@dataclass
class StudentCfg:
    """Student network (conf/student/*.yaml); SPEC §2 has the author's sizes."""

    variant: str = "full"
    """The variant's name, one per ``conf/student/<name>.yaml`` (march.config.registry): full
    (CNN + transformer + MDN), no_transformer (MLP fusion), no_mdn (deterministic head), ..."""
    image: str = ""
    """Image encoder: cnn, or none (the depth image is not read). Empty: the paper variant's."""
    fusion: str = ""
    """Fusion of image, history and command: transformer, mlp, gru, ... (``python -m
    march.inspect list``). Empty: the paper variant's."""
    head: str = ""
    """Output: mdn (NLL of teacher samples) or deterministic (Huber against the teacher mean).
    Empty: the paper variant's."""
    parts: dict[str, Any] = field(default_factory=dict)
    """Config blocks of parts that have their own (part name -> its keys), e.g.
    ``parts: {gru: {hidden_size: 128}}`` (march.config.parts; the paper's parts use the
    ``student.*`` keys below)."""
    label: str = ""
    """How figures and tables name the variant (empty: the name)."""
    color: str = ""
    """The variant's matplotlib colour in figures (empty: one no other variant uses)."""
    order: int = 100
    """The variant's position in legends and tables (lower first)."""
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
        check_shapes("student", self)
        check_identifier("student", "variant", self.variant)
        parts = BUILTIN_PARTS.get(self.variant, ("", "", ""))
        for key, default in zip(("image", "fusion", "head"), parts, strict=True):
            if not getattr(self, key):
                if not default:
                    raise ConfigError(
                        f"student={self.variant}: set student.{key} in "
                        f"conf/student/{self.variant}.yaml (python -m march.inspect list)"
                    )
                setattr(self, key, default)
            check_value(key, getattr(self, key))
        check_parts(self.parts, {"image": self.image, "fusion": self.fusion, "head": self.head})
        check_each("student", "cnn_channels", self.cnn_channels, 1, nonempty=True)
        check_each("student", "cnn_kernels", self.cnn_kernels, 1)
        check_each("student", "cnn_strides", self.cnn_strides, 1)
        for key in ("d_model", "n_heads", "n_layers", "dim_feedforward", "num_modes"):
            check_at_least("student", key, getattr(self, key), 1)
        check_each("student", "fusion_mlp", self.fusion_mlp, 1)
        check_each("student", "head_hidden", self.head_hidden, 1)
        check_positive("student", "min_std", self.min_std)
        check_one_of("student", "activation", self.activation, ACTIVATIONS)
        check_positive("student", "huber_delta", self.huber_delta)
        check_positive("student", "normalizer_eps", self.normalizer_eps)
        if not len(self.cnn_channels) == len(self.cnn_kernels) == len(self.cnn_strides):
            raise ConfigError(
                f"student.cnn_channels={fmt_value(self.cnn_channels)}, student.cnn_kernels="
                f"{fmt_value(self.cnn_kernels)} and student.cnn_strides={fmt_value(self.cnn_strides)} "
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
        check_interval(
            "student", "init_log_std", self.init_log_std, self.log_std_min, self.log_std_max
        )


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
    """Initial action std of every joint (the paper's 1.0), before the per-group factors below:
    joint j starts at init_std x init_std_<group of j> (march.env.joint_groups)."""
    init_std_legs: float = 1.0
    """Initial action std of the 12 leg joints (hip, knee, ankle) as a multiple of init_std;
    1.0 = the paper's (the same std on every joint)."""
    init_std_waist: float = 1.0
    """Initial action std of the 3 waist joints as a multiple of init_std; 1.0 = the paper's.
    Below 1 explores the upper body less at the start (docs/signal.md: at std 1 the 17 waist
    and arm joints carry 52-62 % of the CLF's V and saturate r_clf for the whole robot)."""
    init_std_arms: float = 1.0
    """Initial action std of the 14 arm joints (shoulder, elbow, wrist) as a multiple of
    init_std; 1.0 = the paper's."""
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

    @property
    def group_init_std(self) -> dict[str, float]:
        """Joint group (legs, waist, arms) -> its initial action std (init_std x its factor)."""
        return {
            "legs": self.init_std * self.init_std_legs,
            "waist": self.init_std * self.init_std_waist,
            "arms": self.init_std * self.init_std_arms,
        }

    def __post_init__(self) -> None:
        check_shapes("teacher", self)
        check_positive("teacher", "max_iterations", self.max_iterations)
        check_positive("teacher", "budget_scale", self.budget_scale)
        check_positive("teacher", "num_steps_per_env", self.num_steps_per_env)
        check_each("teacher", "hidden_dims", self.hidden_dims, 1, nonempty=True)
        check_one_of("teacher", "activation", self.activation, RSL_ACTIVATIONS)
        check_positive("teacher", "init_std", self.init_std)
        for group in ("legs", "waist", "arms"):
            check_positive("teacher", f"init_std_{group}", getattr(self, f"init_std_{group}"))
        check_positive("teacher", "learning_rate", self.learning_rate)
        check_positive("teacher", "save_interval", self.save_interval)
        check_at_least("teacher", "max_nonfinite_updates", self.max_nonfinite_updates, 1)
        check_one_of("teacher", "schedule", self.schedule, ("adaptive", "fixed"))
        check_at_least("teacher", "num_learning_epochs", self.num_learning_epochs, 1)
        check_at_least("teacher", "num_mini_batches", self.num_mini_batches, 1)
        check_positive("teacher", "clip_param", self.clip_param)
        check_at_least("teacher", "value_loss_coef", self.value_loss_coef, 0)
        check_at_least("teacher", "entropy_coef", self.entropy_coef, 0)
        check_interval("teacher", "gamma", self.gamma, 0, 1)
        check_interval("teacher", "lam", self.lam, 0, 1)
        check_positive("teacher", "desired_kl", self.desired_kl)
        check_positive("teacher", "max_grad_norm", self.max_grad_norm)
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
        check_shapes("distill", self)
        check_positive("distill", "learning_rate", self.learning_rate)
        check_positive("distill", "max_grad_norm", self.max_grad_norm)
        check_at_least("distill", "teacher_std_scale", self.teacher_std_scale, 0)
        check_positive("distill", "max_iterations", self.max_iterations)
        check_positive("distill", "num_steps_per_env", self.num_steps_per_env)
        check_positive("distill", "num_learning_epochs", self.num_learning_epochs)
        check_positive("distill", "gradient_length", self.gradient_length)
        check_positive("distill", "teacher_samples", self.teacher_samples)
        check_positive("distill", "save_interval", self.save_interval)
        check_at_least("distill", "max_nonfinite_updates", self.max_nonfinite_updates, 1)
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
    """Episode length [s] (a rollout ends earlier on reaching the goal platform or a fall); the
    farthest goal platform must be reached at command_vx with >= 25% of it to spare
    (tests/test_evaluate.py checks every compute preset)."""
    course: str = "stones"
    """stones (every level x column of the stone courses) or hardware (4 alternating stones)."""
    terrain_seed: int = 104729
    """Seed of the evaluation's stone courses: held out, the same for every arm and curriculum,
    and unlike curriculum.terrain_seed (default 0) so that no evaluation course is a training
    course (tests/test_evaluate.py compares the stone rectangles)."""
    command_vx: float = 0.7
    """Forward velocity command along the course during evaluation [m/s], inside
    env.command_vx: 0.7 m/s reaches the 12 m course's farthest goal (9.25 m) in 13.2 s of 20."""
    corruption: bool = True
    """Depth corruption (noise, dropout, delay) as in training."""
    randomization: bool = True
    """Domain randomization as in training."""
    pushes: bool = True
    """The velocity pushes of the DR table (every 10-15 s) during evaluation. On by default
    (evaluation under training's DR); false evaluates the undisturbed gait. Either way both arms
    get the same pushes at the same steps, and the headline gait metrics are taken over
    successful rollouts (docs/decisions.md, "Gait metrics and pushes")."""
    policy: str = "student"
    """Which policy to evaluate in stage=eval: student or teacher."""

    def __post_init__(self) -> None:
        check_shapes("eval", self)
        check_positive("eval", "num_rollouts", self.num_rollouts)
        check_positive("eval", "episode_length_s", self.episode_length_s)
        check_one_of("eval", "course", self.course, COURSES)
        check_interval("eval", "terrain_seed", self.terrain_seed, 0, SEED_MAX)
        check_one_of("eval", "policy", self.policy, ("student", "teacher"))
        check_positive("eval", "command_vx", self.command_vx)


@dataclass
class LoggerCfg:
    """Where per-iteration metrics go besides metrics.csv (always written)."""

    name: str = "csv"
    """csv, tensorboard or wandb (offline unless WANDB_MODE says otherwise)."""
    project: str = "march"
    """wandb project."""

    def __post_init__(self) -> None:
        check_shapes("logger", self)
        check_one_of("logger", "name", self.name, LOGGERS)
        require("logger", "project", self.project, bool(self.project), "a non-empty project name")


@dataclass
class FiguresCfg:
    """What ``python analysis/figures.py`` compares for the runs of this config (a sweep file
    names its comparison here; the command line's ``--compare`` wins). Labels only: no run
    reads it."""

    compare: tuple[str, ...] = ()
    """Reward-arm pairs ``ARM:REFERENCE``, relative difference (ARM - REFERENCE) / REFERENCE;
    empty: the paper's clf:modelfree."""
    reference_variant: str = "full"
    """The student variant arms are compared with; the ablation is relative to it."""
    ablation_teacher: str = "clf"
    """The reward arm whose students form the ablation."""

    def __post_init__(self) -> None:
        for pair in self.compare:
            parts = str(pair).split(":")
            require(
                "figures",
                "compare",
                list(self.compare),
                len(parts) == 2 and all(parts) and parts[0] != parts[1],
                "a list of ARM:REFERENCE pairs of two different arms",
            )
        check_identifier("figures", "reference_variant", self.reference_variant)
        check_identifier("figures", "ablation_teacher", self.ablation_teacher)
