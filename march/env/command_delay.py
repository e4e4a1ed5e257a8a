"""The actuator command delay as one gather per physics step (issue 41).

mjlab 1.6's actuator ``DelayBuffer`` (which :func:`march.env.dr_terms.install_control_delay`
switches on) costs ~24 torch ops per physics step, 96 per control step: every ``compute``
re-draws the lags (a ``randint``, a ``rand`` against ``hold_prob`` and two ``where``, all
discarded at ``hold_prob = 1``), and every read clamps the lags to the history length twice
before indexing. :class:`GatherDelay` is the same buffer for the configuration march uses (lags
set per episode by the ``control_delay`` event, never re-drawn), in 1 op per append and 1 per
read:

- the lags change only through ``set_lags`` / ``reset``, so the flat row of every env's delayed
  frame is kept in a table for each of the L ring positions (remade, a few ops, after a lag
  change); a read is one ``index_select`` of the current position's row of the table;
- the clamp to the history length is not needed: the first append after a reset writes its
  frame into every slot of that env (mjlab's backfill), so a lag longer than the history reads
  that first frame, which is what the clamp returns. The backfill is one ``where`` on the first
  append after a reset (a host flag says whether one happened, no sync); other appends are one
  copy.

What differs: the per-step lag draws are gone, so torch's global random stream is no longer
advanced by them (the lags were never changed by those draws: ``hold_prob = 1``). The outputs
equal mjlab's buffer step by step (tests/test_randomization.py).

:func:`use_gather_delay` puts one in place of each delayed actuator group's buffer (its state
copied over); :func:`march.env.dr_terms.sample_control_delay` calls it.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch


class GatherDelay:
    """mjlab's ``DelayBuffer`` with fixed lags (``hold_prob = 1``, ``update_period = 0``,
    ``min_lag = 0``): same interface and outputs (module docstring)."""

    def __init__(self, max_lag: int, batch_size: int, device: str | torch.device) -> None:
        self.min_lag = 0
        self.max_lag = int(max_lag)
        self.batch_size = int(batch_size)
        self.device = device
        self._len = self.max_lag + 1 if self.max_lag > 0 else 1
        self._pointer = -1
        self._ring: torch.Tensor | None = None
        """(L, E, ...) frames; slot ``_pointer`` is the newest."""
        self._lags = torch.zeros(self.batch_size, dtype=torch.long, device=device)
        self._fresh = torch.ones(self.batch_size, dtype=torch.bool, device=device)
        """(E,) the env's next append backfills its whole history (after a reset)."""
        self._any_fresh = True
        self._rows: torch.Tensor | None = None
        """(L, E) flat ring row of each env's delayed frame, per newest slot."""
        self._last_reset: Any = None
        self._arange = torch.arange(self.batch_size, device=device)

    @classmethod
    def from_buffer(cls, buffer: Any) -> GatherDelay:
        """A GatherDelay holding the state of mjlab ``DelayBuffer`` ``buffer``."""
        if buffer.min_lag != 0 or buffer.hold_prob != 1.0 or buffer.update_period != 0:
            raise ValueError(
                "GatherDelay needs min_lag 0, hold_prob 1 and update_period 0 (lags set per "
                f"episode); got {buffer.min_lag}, {buffer.hold_prob}, {buffer.update_period}"
            )
        new = cls(buffer.max_lag, buffer.batch_size, buffer.device)
        new._lags = buffer.current_lags.clone()
        circ = buffer._buffer
        if circ._buffer is not None:
            new._ring = circ._buffer.clone()
            new._pointer = int(circ._pointer)
            new._fresh = circ._num_pushes == 0
        return new

    # mjlab DelayBuffer interface ---------------------------------------------------------

    @property
    def is_initialized(self) -> bool:
        return self._ring is not None

    @property
    def current_lags(self) -> torch.Tensor:
        """Current lag per environment (E,)."""
        return self._lags

    def set_lags(
        self, lags: torch.Tensor, batch_ids: Sequence[int] | torch.Tensor | slice | None = None
    ) -> None:
        idx = slice(None) if batch_ids is None else batch_ids
        self._lags[idx] = lags.clamp(self.min_lag, self.max_lag)
        self._rows = None
        self._last_reset = None

    def reset(self, batch_ids: Sequence[int] | torch.Tensor | slice | None = None) -> None:
        """Lag 0 and an empty history (refilled by the next append) for ``batch_ids``. The
        actuators of a fused group each reset the one shared buffer with the same ids object:
        done once."""
        if batch_ids is not None and batch_ids is self._last_reset:
            return
        self._last_reset = batch_ids
        idx = slice(None) if batch_ids is None else batch_ids
        self._lags[idx] = 0
        self._fresh[idx] = True
        self._any_fresh = True
        self._rows = None

    def append(self, data: torch.Tensor) -> None:
        if data.shape[0] != self.batch_size:
            raise ValueError(f"Expected batch size {self.batch_size}, got {data.shape[0]}")
        self._last_reset = None
        if self._ring is None:
            self._ring = torch.empty((self._len, *data.shape), dtype=data.dtype, device=self.device)
        self._pointer = (self._pointer + 1) % self._len
        if self._any_fresh:
            fresh = self._fresh.view(1, self.batch_size, *([1] * (data.dim() - 1)))
            torch.where(fresh, data.unsqueeze(0), self._ring, out=self._ring)
            self._ring[self._pointer] = data
            self._fresh.zero_()
            self._any_fresh = False
        else:
            self._ring[self._pointer] = data

    def backfill(self, data: torch.Tensor, batch_ids: torch.Tensor) -> None:
        if self._ring is None:
            raise RuntimeError("Buffer not initialized. Call append() first.")
        self._ring[:, batch_ids] = data[batch_ids].unsqueeze(0)
        self._fresh[batch_ids] = False

    def compute(self) -> torch.Tensor:
        """The delayed frame of every env (the lags are fixed: nothing to advance)."""
        return self.peek()

    def peek(self) -> torch.Tensor:
        if self._ring is None:
            raise RuntimeError("Buffer not initialized. Call append() first.")
        if self._rows is None:
            slots = torch.arange(self._len, device=self._lags.device)[:, None]
            self._rows = torch.remainder(slots - self._lags, self._len) * self.batch_size
            self._rows += self._arange
        flat = self._ring.view(self._len * self.batch_size, *self._ring.shape[2:])
        return flat.index_select(0, self._rows[self._pointer])


def use_gather_delay(entity: Any) -> int:
    """Replace the delay buffer of each delayed actuator group of ``entity`` (mjlab's builtin
    and fused groups, and their actuators' aliases) by a :class:`GatherDelay` with its state;
    returns how many were replaced (0 when already done)."""
    from mjlab.utils.buffers.delay_buffer import DelayBuffer

    groups = list(getattr(entity._builtin_group, "_delayed_groups", ()))
    groups += list(getattr(entity._fused_actuator_group, "_groups", ()))
    replaced = 0
    for group in groups:
        old = getattr(group, "delay_buffer", None)
        if not isinstance(old, DelayBuffer):
            continue
        new = GatherDelay.from_buffer(old)
        group.delay_buffer = new
        for act in group.absorbed_actuators:
            act._delay_buffer = new
        replaced += 1
    for act in entity.actuators:  # custom actuators keep their own buffer
        if isinstance(act._delay_buffer, DelayBuffer):
            act._delay_buffer = GatherDelay.from_buffer(act._delay_buffer)
            replaced += 1
    return replaced
