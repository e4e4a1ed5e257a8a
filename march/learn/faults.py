"""Numerical faults in training: non-finite envs are reset, non-finite updates undone; both counted.

Shared by the teacher (PPO) and distillation runners, which own their loops:

- :class:`EnvFaults`: an env whose action, physics state (mjlab's ``NanGuard.detect_nans``: qpos,
  qvel, qacc, warm start, sensors), observation or reward holds a NaN or inf after a step is reset
  through mjlab's own partial reset (``env.reset(env_ids=...)``), its observation rows replaced by
  the post-reset ones, its reward zeroed and its episode ended. The run goes on; the runners log
  the count per iteration (``nonfinite_resets`` in metrics.csv).
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

from march.env.nonfinite import nonfinite_physics


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
    so that a stored copy of the action is finite too), :meth:`after_step` after it. One host
    sync per step (``any()``); mjlab's step already syncs on its own resets.
    """

    def __init__(self, env: Any) -> None:
        self.env = env  # the mjlab ManagerBasedRlEnv (unwrapped)
        self.count = 0  # envs reset since the last pop()
        self.total = 0

    def actions(self, actions: torch.Tensor) -> torch.Tensor:
        """Zero the non-finite rows of ``actions`` in place; returns their mask."""
        bad = nonfinite_rows(self.env.num_envs, actions)
        actions.masked_fill_(bad.unsqueeze(-1), 0.0)
        return bad

    def after_step(
        self, obs: Any, reward: torch.Tensor, bad_actions: torch.Tensor | None = None
    ) -> torch.Tensor | None:
        """Reset the faulty envs after a step; ``obs`` (dict or TensorDict, edited in place) gets
        their post-reset rows and ``reward`` zeros there. Returns the mask, None if none."""
        env = self.env
        bad = nonfinite_physics(env) | nonfinite_rows(env.num_envs, obs, reward)
        if bad_actions is not None:
            bad = bad | bad_actions
        if not bool(bad.any()):
            return None
        ids = bad.nonzero().squeeze(-1)
        fresh, _ = env.reset(env_ids=ids)
        _replace_rows(obs, fresh, bad)
        reward.masked_fill_(bad, 0.0)
        n = int(ids.numel())
        self.count += n
        self.total += n
        return bad

    def pop(self) -> int:
        n, self.count = self.count, 0
        return n


def _replace_rows(obs: Any, fresh: Mapping[str, Any], bad: torch.Tensor) -> None:
    for k in list(obs.keys()):
        if k not in fresh:
            continue
        old, new = obs[k], fresh[k]
        if hasattr(old, "keys"):
            _replace_rows(old, new, bad)
            continue
        mask = bad.view(-1, *([1] * (old.dim() - 1)))
        obs[k] = torch.where(mask, new.to(old.device), old)


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
