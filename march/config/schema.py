"""Typed configuration schema: the single source of truth for every option march takes.

:class:`MarchConfig` gathers the sections of :mod:`march.config.simulation` and
:mod:`march.config.training`. Hydra composes ``conf/`` on top of these dataclasses (registered in
the ConfigStore as ``march_schema``), so a misspelt key or a wrong type fails at composition,
before any simulation. Values are checked once more when the composed config is turned into
objects (:func:`to_march_config`): ``__post_init__`` of each section raises :class:`ConfigError`
with one line saying what is wrong and how to fix it (:mod:`march.config.checks`).

Pure data: no simulator import.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from hydra.core.config_store import ConfigStore
from omegaconf import DictConfig, OmegaConf

from march.config.checks import (
    SEED_MAX,
    STAGES,
    ConfigError,
    check_interval,
    cnn_output_hw,
    fmt_value,
    require,
)
from march.config.registry import SWEEPS_DIR
from march.config.simulation import (
    ComputeCfg,
    CurriculumCfg,
    DepthCfg,
    DrCfg,
    EnvCfg,
    ReferenceSectionCfg,
    RewardCfg,
    TerminationCfg,
)
from march.config.training import (
    DistillCfg,
    EvalCfg,
    FiguresCfg,
    LoggerCfg,
    StudentCfg,
    TeacherCfg,
)
from march.world.courses import CourseCfg

EVAL_METRICS = (
    "distance_m",
    "success_rate",
    "abs_torque_nm",
    "abs_ang_jerk",
    "reward",
    "reward_per_step",
    "torque_success",
    "jerk_success",
)
"""What an evaluation measures per rollout (march.evaluation.protocol), summarised as
``mean_<metric>`` and ``se_<metric>`` in eval.csv and summary.json (march.learn.metrics)."""

OBJECTIVES = tuple(f"{p}_{m}" for m in EVAL_METRICS for p in ("mean", "se"))
"""What ``objective`` may name: summary.json's mean_/se_ keys."""


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
    extra_modules: list[str] = field(default_factory=list)
    """Python modules (dotted names on ``sys.path``) every entry point imports before it checks
    the config: where your own reward terms and student parts register
    (``extra_modules=[my_lab.terms]``; docs/extending.md)."""
    objective: str = "mean_distance_m"
    """The final evaluation's value ``march.train`` returns (what a Hydra sweeper such as
    Optuna optimises): mean_<metric> or se_<metric> of summary.json."""
    compute: ComputeCfg = field(default_factory=ComputeCfg)
    env: EnvCfg = field(default_factory=EnvCfg)
    reward: RewardCfg = field(default_factory=RewardCfg)
    reference: ReferenceSectionCfg = field(default_factory=ReferenceSectionCfg)
    termination: TerminationCfg = field(default_factory=TerminationCfg)
    curriculum: CurriculumCfg = field(default_factory=CurriculumCfg)
    student: StudentCfg = field(default_factory=StudentCfg)
    teacher: TeacherCfg = field(default_factory=TeacherCfg)
    distill: DistillCfg = field(default_factory=DistillCfg)
    eval: EvalCfg = field(default_factory=EvalCfg)
    logger: LoggerCfg = field(default_factory=LoggerCfg)
    dr: DrCfg = field(default_factory=DrCfg)
    depth: DepthCfg = field(default_factory=DepthCfg)
    terrain: CourseCfg = field(default_factory=CourseCfg)
    figures: FiguresCfg = field(default_factory=FiguresCfg)

    def __post_init__(self) -> None:
        self.termination.adopt(self.reward)  # reward.tilt_limit_deg etc. of older configs
        for name in self.extra_modules:
            require(
                "", "extra_modules", self.extra_modules, _module_name(name), "dotted module names"
            )
        if self.stage not in STAGES:
            raise ConfigError(
                f"stage={self.stage!r} is not valid; choose one of {', '.join(STAGES)}"
            )
        check_interval("", "seed", self.seed, 0, SEED_MAX)
        if self.objective not in OBJECTIVES:
            raise ConfigError(
                f"objective={self.objective!r} is not a summary value; choose one of "
                f"{', '.join(OBJECTIVES)}"
            )
        for key in ("teacher_ckpt", "student_ckpt", "resume", "out"):
            require("", key, getattr(self, key), getattr(self, key) != "", "a path (or left unset)")
        hw = cnn_output_hw(
            (self.depth.height, self.depth.width),
            self.student.cnn_kernels,
            self.student.cnn_strides,
        )
        if min(hw) < 1:
            raise ConfigError(
                f"depth.height x depth.width={self.depth.height}x{self.depth.width} must be at "
                f"least what the student CNN (kernels {fmt_value(self.student.cnn_kernels)}, strides "
                f"{fmt_value(self.student.cnn_strides)}) reduces to 1x1; it gives {hw[0]}x{hw[1]}"
            )
        batch = self.compute.num_envs * self.teacher.num_steps_per_env
        require(
            "teacher",
            "num_mini_batches",
            self.teacher.num_mini_batches,
            self.teacher.num_mini_batches <= batch,
            f"<= compute.num_envs x teacher.num_steps_per_env = {batch} "
            "(one sample per mini-batch at least)",
        )
        require(
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
            require(
                "terrain",
                "size",
                t.size,
                t.size[0] >= length,
                f"[x, y] with x >= {length:.3g}: "
                "the hardware course (eval.course=hardware) is that long",
            )
        if self.eval.course == "stones" and self.eval.terrain_seed == self.curriculum.terrain_seed:
            raise ConfigError(
                f"eval.terrain_seed={self.eval.terrain_seed} equals curriculum.terrain_seed: "
                "the evaluation would run on training courses; choose another seed"
            )
        lo, hi = self.env.command_vx
        if not lo <= self.eval.command_vx <= hi:
            raise ConfigError(
                f"eval.command_vx={self.eval.command_vx} lies outside the training range "
                f"env.command_vx=[{lo}, {hi}]: evaluate at a command the policy was trained on"
            )


def _module_name(name: object) -> bool:
    return isinstance(name, str) and all(p.isidentifier() for p in name.split("."))


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
