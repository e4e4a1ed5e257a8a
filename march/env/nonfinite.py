"""Which envs' physics state holds a NaN or inf: mjlab's ``NanGuard.detect_nans`` (qpos, qvel,
qacc, warm start, sensors), for the fault handling of the runners (:mod:`march.learn.faults`),
which import nothing of mjlab themselves."""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from mjlab.utils.nan_guard import NanGuard

if TYPE_CHECKING:
    from mjlab.envs import ManagerBasedRlEnv


def nonfinite_physics(env: ManagerBasedRlEnv) -> torch.Tensor:
    """(num_envs,) bool: the env's simulation state holds a NaN or inf."""
    return NanGuard.detect_nans(env.sim.data)
