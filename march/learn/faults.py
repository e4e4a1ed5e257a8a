"""Numerical faults in training: non-finite envs are reset, non-finite updates undone; both counted.

Built once by the loop both stages share (:class:`march.learn.stage_runner.StageRunner`):

- :class:`EnvFaults`: an env whose physics state (mjlab's ``NanGuard.detect_nans``: qpos, qvel,
  qacc, warm start, sensors) holds a NaN or inf is reset in the same step by the training envs'
  ``nonfinite`` termination (mjlab's own reset of terminated envs; :mod:`march.env.nonfinite`);
  one whose action, observation or reward does gets zeros there, its episode ends, and the
  termination resets it in the next step. Its reward is zeroed either way. No host sync per
  step (issue 20); the runners log the count per iteration (``nonfinite_resets``).
- :class:`UpdateGuard`: an iteration whose update produced a non-finite loss or parameter is
  undone (networks, normalizers and optimizer restored from a copy taken just before it) and
  counted (``nonfinite_updates``). ``limit`` such iterations in a row raise
  :class:`NumericalFault` (one line) before that iteration's checkpoint: the last checkpoint on
  disk is the last good one.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Mapping
from typing import Any

import torch

from march.env.nonfinite import fault_flags


class NumericalFault(RuntimeError):
    """Training cannot go on: its updates keep producing NaN or inf; says what is kept."""


def nonfinite_rows(num_envs: int, *values: Any) -> torch.Tensor:
    """(num_envs,) bool: rows holding a NaN or inf in any of ``values``.

    ``values``: tensors whose first dimension is the env (any trailing shape), or mappings of
    them (an observation dict or TensorDict, looked into recursively).
    """
    bad: torch.Tensor | None = None
    for v in values:
        if isinstance(v, Mapping) or hasattr(v, "keys"):
            rows = nonfinite_rows(num_envs, *(v[k] for k in v.keys()))
        elif isinstance(v, torch.Tensor):
            rows = ~torch.isfinite(v.reshape(num_envs, -1)).all(dim=-1)
        else:
            continue
        bad = rows if bad is None else bad | rows
    if bad is None:
        raise ValueError("nonfinite_rows needs at least one tensor")
    return bad


class EnvFaults:
    """Finds envs with a non-finite action, state, observation or reward and resets them.

    Per step: :meth:`actions` before ``env.step`` (non-finite rows are replaced by zeros, in place,
    so that a stored copy of the action is finite too), :meth:`after_step` after it. No host
    sync per step: the resets are the env's ``nonfinite`` termination's, the count stays on the
    device until :meth:`pop` (once per iteration).
    """

    def __init__(self, env: Any) -> None:
        if "nonfinite" not in env.termination_manager.active_terms:
            raise ValueError("EnvFaults needs a training env (its 'nonfinite' termination)")
        self.env = env  # the mjlab ManagerBasedRlEnv (unwrapped)
        self._count = torch.zeros((), dtype=torch.long, device=env.device)  # since pop()
        self.total = 0

    def actions(self, actions: torch.Tensor) -> torch.Tensor:
        """Zero the non-finite rows of ``actions`` in place; returns their mask."""
        bad = nonfinite_rows(self.env.num_envs, actions)
        actions.masked_fill_(bad.unsqueeze(-1), 0.0)
        return bad

    def after_step(
        self, obs: Any, reward: torch.Tensor, bad_actions: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Mark the faulty envs of a step, without a host sync; returns the (num_envs,) mask.

        An env whose physics state went non-finite was already reset by this step's
        ``nonfinite`` termination (:mod:`march.env.nonfinite`): its observation is the
        post-reset one. Any other faulty env (a non-finite action, observation or reward) gets
        zeros in its observation rows and its reward, its episode ends here (the runners treat
        the mask as done) and the env is reset at the next step's termination check."""
        env = self.env
        bad = nonfinite_rows(env.num_envs, obs, reward)
        if bad_actions is not None:
            bad = bad | bad_actions
        flags = fault_flags(env)
        flags.pending |= bad & ~flags.physics
        _zero_rows(obs, bad)
        bad = bad | flags.physics
        reward.masked_fill_(bad, 0.0)
        self._count += bad.sum()
        return bad

    def pop(self) -> int:
        """Envs reset for a fault since the last call (one host read, once per iteration)."""
        n = int(self._count)
        self._count.zero_()
        self.total += n
        return n


def _zero_rows(obs: Any, bad: torch.Tensor) -> None:
    for k in list(obs.keys()):
        old = obs[k]
        if hasattr(old, "keys"):
            _zero_rows(old, bad)
            continue
        mask = bad.view(-1, *([1] * (old.dim() - 1)))
        obs[k] = old.masked_fill(mask, 0.0)


class UpdateGuard:
    """Undoes and counts updates with a non-finite loss or parameter; stops after ``limit`` in a row.

    ``snapshot`` returns a state (state_dicts) that ``restore`` puts back; it is deep-copied
    before each update (:meth:`before`), which costs one copy of the networks and the optimizer
    per iteration: small next to a rollout.
    """

    def __init__(
        self,
        stage: str,
        limit: int,
        snapshot: Callable[[], Any],
        restore: Callable[[Any], None],
        parameters: Callable[[], Any],
    ) -> None:
        self.stage, self.limit = stage, limit
        self._snapshot, self._restore, self._parameters = snapshot, restore, parameters
        self._saved: Any = None
        self.count = 0  # undone since the last pop()
        self.in_a_row = 0

    def before(self) -> None:
        self._saved = copy.deepcopy(self._snapshot())

    def finite(self, losses: Mapping[str, float]) -> bool:
        if not all(math.isfinite(float(v)) for v in losses.values()):
            return False
        flags = [torch.isfinite(p).all() for p in self._parameters()]
        return bool(torch.stack(flags).all()) if flags else True

    def after(self, losses: Mapping[str, float], iteration: int, last_ckpt: Any) -> bool:
        """True if the update is kept; else it is undone and counted, and after ``limit`` in a
        row :class:`NumericalFault` is raised (``iteration``: the one that just failed)."""
        if self.finite(losses):
            self.in_a_row = 0
            return True
        self._restore(self._saved)
        self.count += 1
        self.in_a_row += 1
        if self.in_a_row >= self.limit:
            kept = f"the last good checkpoint is {last_ckpt}" if last_ckpt else "no checkpoint yet"
            raise NumericalFault(
                f"{self.stage}: {self.in_a_row} updates in a row gave a non-finite loss or "
                f"parameter (iterations {iteration - self.in_a_row + 1}-{iteration}, each undone; "
                f"{self.stage}.max_nonfinite_updates={self.limit}); stopped, {kept}. Lower the "
                "learning rate or check the reward and observation terms"
            )
        return False

    def pop(self) -> int:
        n, self.count = self.count, 0
        return n
