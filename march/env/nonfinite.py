"""Which envs' physics state holds a NaN or inf (the fields of mjlab's ``NanGuard.detect_nans``:
qpos, qvel, qacc, warm start, sensors), for the fault handling of the runners (:mod:`march.learn.faults`),
which import nothing of mjlab themselves.

Faults are reset without a host sync (issue 20): the training envs carry a ``nonfinite``
termination (:func:`nonfinite_termination`), so that mjlab's own reset of the terminated envs,
which every step makes anyway, resets an env whose physics state went non-finite in the same
step; an env the runner finds faulty after a step (a non-finite action, observation or reward)
is marked in :class:`FaultFlags` and reset by that termination in the next step. The flags stay
on the device.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from mjlab.envs import ManagerBasedRlEnv


def nonfinite_physics(env: ManagerBasedRlEnv) -> torch.Tensor:
    """(num_envs,) bool: the env's simulation state holds a NaN or inf: the fields of mjlab's
    ``NanGuard.detect_nans`` (qpos, qvel, qacc, warm start, sensors), checked as one
    concatenated row per env (4 ops instead of 4 per field)."""
    data = env.sim.data
    fields = [getattr(data, name)[:] for name in NAN_GUARD_FIELDS]  # plain tensor views
    return ~torch.isfinite(torch.cat(fields, dim=-1)).all(-1)


NAN_GUARD_FIELDS = ("qpos", "qvel", "qacc", "qacc_warmstart", "sensordata")
"""What ``mjlab.utils.nan_guard.NanGuard.detect_nans`` checks (mjlab 1.6)."""


class FaultFlags:
    """Per env, on the env's device: ``pending`` (the runner found a fault after the last step:
    reset at the next termination check) and ``physics`` (the last termination check found the
    physics state non-finite and ended the env)."""

    def __init__(self, num_envs: int, device: str | torch.device) -> None:
        self.pending = torch.zeros(num_envs, dtype=torch.bool, device=device)
        self.physics = torch.zeros(num_envs, dtype=torch.bool, device=device)


def fault_flags(env: ManagerBasedRlEnv) -> FaultFlags:
    """The env's :class:`FaultFlags` (made on first use)."""
    flags = getattr(env, "_march_fault_flags", None)
    if flags is None:
        flags = FaultFlags(env.num_envs, env.device)
        env._march_fault_flags = flags
    return flags


def nonfinite_termination(env: ManagerBasedRlEnv) -> torch.Tensor:
    """Termination term: the physics state is non-finite now, or the runner marked the env
    faulty after the last step (:class:`FaultFlags`)."""
    flags = fault_flags(env)
    flags.physics.copy_(nonfinite_physics(env))
    bad = flags.physics | flags.pending
    flags.pending.zero_()
    return bad
