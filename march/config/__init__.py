"""The one door from Hydra to typed config: ``conf/`` YAML -> :class:`MarchConfig` dataclasses.

The schema's sections live in :mod:`march.config.schema`; :mod:`march.config.cli` composes a
config for the command-line tools and :mod:`march.config.resume` decides what a resumed run may
override. The names below are the public schema (``from march.config import MarchConfig``).
"""

from march.config.schema import (
    COMPUTES,
    CURRICULA,
    REWARDS,
    SEED_MAX,
    STUDENTS,
    ConfigError,
    DepthCfg,
    DrCfg,
    EnvCfg,
    LoggerCfg,
    MarchConfig,
    RewardCfg,
    StudentCfg,
    TeacherCfg,
    cnn_output_hw,
    to_march_config,
)

__all__ = [
    "COMPUTES",
    "CURRICULA",
    "REWARDS",
    "SEED_MAX",
    "STUDENTS",
    "ConfigError",
    "DepthCfg",
    "DrCfg",
    "EnvCfg",
    "LoggerCfg",
    "MarchConfig",
    "RewardCfg",
    "StudentCfg",
    "TeacherCfg",
    "cnn_output_hw",
    "to_march_config",
]
