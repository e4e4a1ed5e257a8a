"""Which envs the reference command plans in a step: one planner batch of a fixed size, decided
without a host sync (issues 11 and 41).

A GPU stalls whenever the host reads a device value (``if mask.any()``, ``nonzero()``), so the
reference command never branches on data; and a planner batch whose size changes from step to
step defeats CUDA graphs and ``torch.compile(mode="reduce-overhead")``, which replay one shape.
:class:`ReplanQueue` builds every update's batch (:meth:`ReplanQueue.next_batch`) as

    [ the p resets | the due envs, in env order | idle envs (padding) ],   B rows in all,

- **Episode starts** are exactly the envs mjlab reset: their ids reach the command term's
  ``_resample_command`` with a size the host already knows (mjlab synchronised to find them);
  :meth:`ReplanQueue.take_resets` hands them over in the next update, first in the batch, all of
  them. Resets never wait.
- **The batch size B** (:meth:`ReplanQueue.batch_size`) depends on the host-known p only:
  ``capacity`` (``ReferenceCommandCfg.capacity``: 1/8 of the envs, at least 8) while the resets
  fit in it, else the next power of two >= p, capped at E (p itself when p > E, which only
  repeated resets of one env cause: construction and the first reset both reset every env). The
  planner therefore sees one of at most log2(E / capacity) + 2 shapes after its first update,
  and almost always ``capacity`` (at 4096 envs: 512, 1024, 2048, 4096).
- **Touchdowns and timeouts** are masks. They fill the B - p rows after the resets, the due envs
  first in env order (a stable sort of the mask), then idle envs, which are planned and
  discarded (``apply`` False), as are due envs beyond the batch: they wait for the next update
  (20 ms), still flagged, and every waiting update is counted in ``deferred_count``. The planner
  costs ~4 ms for an 8-env batch and ~30 ms for 64 envs on one CPU thread (loaded 2-core
  machine, issue 41), so a batch of every env on every step would cost a 64-env CPU step ~7x
  more planner time than the fixed batch. The planner is called on every update (also when no
  env is due), so its random stream advances once per update.

Plain torch on the env's device; the command term owns the walking state and the planner call.
"""

from __future__ import annotations

from typing import NamedTuple

import torch


class ReplanBatch(NamedTuple):
    """One update's planner batch (module docstring), B rows."""

    ids: torch.Tensor
    """(B,) env ids: the p resets, then B - p distinct running envs."""
    apply: torch.Tensor
    """(B,) bool: the row's plan starts a new step (a reset, or a due env served now)."""
    ramp: torch.Tensor
    """(B,) bool: the row is an episode start (its CoM reference ramps from standing)."""
    num_resets: int
    """p, known on the host."""
    sel: torch.Tensor
    """(B - p,) the running envs of the batch (``ids[p:]``)."""
    serve: torch.Tensor
    """(B - p,) bool: that env is due and served now."""
    flip: torch.Tensor
    """(B - p,) bool: served for a touchdown (the others served are timeouts)."""


class ReplanQueue:
    """Resets to plan and due touchdowns / timeouts of ``num_envs`` envs (module docstring)."""

    def __init__(self, num_envs: int, capacity: int, device: torch.device | str) -> None:
        self.num_envs = num_envs
        self.capacity = min(capacity, num_envs)
        """The batch size while the resets fit in it."""
        self.device = device
        self.due_touchdown = torch.zeros(num_envs, dtype=torch.bool, device=device)
        """(E,) a touchdown waits to be served."""
        self.due_timeout = torch.zeros(num_envs, dtype=torch.bool, device=device)
        """(E,) a step timeout waits to be served (a touchdown of the same env outranks it)."""
        self.deferred_count = torch.zeros(num_envs, dtype=torch.long, device=device)
        """(E,) env steps a due event waited for room in the batch."""
        self.is_reset = torch.zeros(num_envs, dtype=torch.bool, device=device)
        """(E,) the env is among the last :meth:`take_resets` (kept buffer, no per-step alloc)."""
        self._num_resets = 0
        self._last_resets = torch.zeros(0, dtype=torch.long, device=device)
        self._batch = self.capacity
        self._served = torch.zeros(num_envs, dtype=torch.bool, device=device)
        self._ones = torch.ones(num_envs, dtype=torch.bool, device=device)
        self._zeros = torch.zeros(num_envs, dtype=torch.bool, device=device)
        self._resets: list[torch.Tensor] = [torch.arange(num_envs, device=device)]

    def batch_size(self, num_resets: int) -> int:
        """B for ``num_resets`` = p resets: ``capacity`` while p <= capacity, else the next power
        of two >= p capped at E (p itself beyond E: repeated resets of one env)."""
        capacity = min(self.capacity, self.num_envs)  # (tools set capacity directly)
        if num_resets <= capacity:
            return capacity
        if num_resets > self.num_envs:
            return num_resets
        return min(self.num_envs, 1 << (num_resets - 1).bit_length())

    def add_resets(self, env_ids: torch.Tensor) -> None:
        """Envs that start an episode (host-known ids); their waiting events are dropped."""
        self._resets.append(env_ids)
        self.due_touchdown[env_ids] = False
        self.due_timeout[env_ids] = False

    def take_resets(self) -> torch.Tensor:
        """(p,) the envs reset since the last call (host-known size), and forget them; marks
        them in :attr:`is_reset` and sets this update's batch size."""
        ids, self._resets = self._resets, []
        self.is_reset.zero_()
        if not ids:
            resets = torch.zeros(0, dtype=torch.long, device=self.device)
        else:
            resets = torch.cat([i.to(device=self.device, dtype=torch.long) for i in ids])
            self.is_reset[resets] = True
        self._last_resets = resets
        self._num_resets = resets.numel()
        self._batch = self.batch_size(self._num_resets)
        return resets

    def serve(
        self,
        touchdown: torch.Tensor,
        timeout: torch.Tensor,
        active: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Queue this update's ``touchdown`` / ``timeout`` masks (E,) and take the B - p rows
        after the resets: the due envs among ``active`` (E,) first, in env order, then idle
        envs; never one of the p resets :meth:`take_resets` returned in this update.

        Returns ``sel`` (B - p,) the env ids (size known on the host), ``serve`` (B - p,) bool:
        the env is due and is served now, and ``flip`` (B - p,) bool: served for a touchdown (the
        others served are timeouts). Due envs left out wait, counted in ``deferred_count``.
        """
        self.due_touchdown |= touchdown
        self.due_timeout = (self.due_timeout | timeout) & ~self.due_touchdown
        due = (self.due_touchdown | self.due_timeout) & active
        order_key = (~due).to(torch.int8).masked_fill_(self.is_reset, 2)  # due, idle, resets
        sel = torch.argsort(order_key, stable=True)[: self._batch - self._num_resets]
        serve = due[sel]
        flip = serve & self.due_touchdown[sel]
        served = self._served.zero_()
        served[sel] = serve
        waiting = ~served
        self.deferred_count += due & waiting
        self.due_touchdown &= waiting
        self.due_timeout &= waiting
        return sel, serve, flip

    def next_batch(
        self, touchdown: torch.Tensor, timeout: torch.Tensor, active: torch.Tensor
    ) -> ReplanBatch:
        """This update's batch: the resets of the last :meth:`take_resets` (call it first), then
        :meth:`serve`'s rows. ``ramp`` (and ``apply`` without resets) may be views of kept
        buffers: read them, do not write into them."""
        p = self._num_resets
        sel, serve, flip = self.serve(touchdown, timeout, active)
        if p > self._ones.numel():  # (an env reset twice since the last update)
            self._ones = torch.ones(p, dtype=torch.bool, device=self.device)
        starts = self._ones[:p]
        return ReplanBatch(
            ids=torch.cat([self._last_resets, sel]) if p else sel,
            apply=torch.cat([starts, serve]) if p else serve,
            ramp=torch.cat([starts, self._zeros[: sel.numel()]])
            if p
            else self._zeros[: sel.numel()],
            num_resets=p,
            sel=sel,
            serve=serve,
            flip=flip,
        )

    def waiting(self) -> torch.Tensor:
        """(E,) bool: an event waits to be served."""
        return self.due_touchdown | self.due_timeout
