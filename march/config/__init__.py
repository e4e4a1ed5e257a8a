"""The one door from Hydra to typed config: ``conf/`` YAML -> :class:`MarchConfig` dataclasses.

The whole config is :mod:`march.config.schema`; its sections live in
:mod:`march.config.simulation` and :mod:`march.config.training`, the name tuples and checks in
:mod:`march.config.checks`. :mod:`march.config.cli` composes a config for the command-line tools
and :mod:`march.store.resume_rules` decides what a resumed run may override. The names below are the
public schema (``from march.config import MarchConfig``).
"""

from march.config.checks import (
    COMPUTES,
    CURRICULA,
    REWARDS,
    SEED_MAX,
    STUDENTS,
    ConfigError,
    cnn_output_hw,
)
from march.config.schema import MarchConfig, to_march_config
from march.config.simulation import DepthCfg, DrCfg, EnvCfg, RewardCfg, TerminationCfg
from march.config.training import LoggerCfg, StudentCfg, TeacherCfg

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
    "TerminationCfg",
    "StudentCfg",
    "TeacherCfg",
    "cnn_output_hw",
    "to_march_config",
]
