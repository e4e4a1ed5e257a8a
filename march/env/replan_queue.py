"""Which envs the reference command plans in a step, decided without a host sync (issue 11).

A GPU stalls whenever the host reads a device value (``if mask.any()``, ``nonzero()``), so the
reference command never branches on data. :class:`ReplanQueue` keeps the two kinds of replans
apart:

- **Episode starts** are planned as exactly the envs mjlab reset: their ids reach the command
  term's ``_resample_command`` with a size the host already knows (mjlab synchronised to find
  them), and :meth:`ReplanQueue.take_resets` hands them over in the next update. Resets never
  wait.
- **Touchdowns and timeouts** are masks. They are served by one planner call of fixed size,
  ``capacity`` (``ReferenceCommandCfg.capacity``: 1/8 of the envs, at least 8): the due envs first
  in env order (a stable sort of the mask), the rest of the batch planned and discarded. The
  planner costs 4.7 ms for 1 env and 23 ms for 64 on 2 CPU threads, so planning every env on
  every step would add ~7% to a 64-env CPU step; the fixed batch adds ~2 ms. An event that does
  not fit waits for the next update (20 ms), still flagged, and is counted in
  ``deferred_count``. The planner is called on every update (also when no env is due), so its
  random stream advances once per update.

Plain torch on the env's device; the command term owns the walking state and the planner call.
"""

from __future__ import annotations

import torch


class ReplanQueue:
    """Resets to plan and due touchdowns / timeouts of ``num_envs`` envs (module docstring)."""

    def __init__(self, num_envs: int, capacity: int, device: torch.device | str) -> None:
        self.num_envs = num_envs
        self.capacity = capacity
        """Running envs (touchdowns, timeouts) served per update at most."""
        self.device = device
        self.due_touchdown = torch.zeros(num_envs, dtype=torch.bool, device=device)
        """(E,) a touchdown waits to be served."""
        self.due_timeout = torch.zeros(num_envs, dtype=torch.bool, device=device)
        """(E,) a step timeout waits to be served (a touchdown of the same env outranks it)."""
        self.deferred_count = torch.zeros(num_envs, dtype=torch.long, device=device)
        """(E,) env steps a due event waited for capacity."""
        self.is_reset = torch.zeros(num_envs, dtype=torch.bool, device=device)
        """(E,) the env is among the last :meth:`take_resets` (kept buffer, no per-step alloc)."""
        self._num_resets = 0
        self._served = torch.zeros(num_envs, dtype=torch.bool, device=device)
        self._resets: list[torch.Tensor] = [torch.arange(num_envs, device=device)]

    def add_resets(self, env_ids: torch.Tensor) -> None:
        """Envs that start an episode (host-known ids); their waiting events are dropped."""
        self._resets.append(env_ids)
        self.due_touchdown[env_ids] = False
        self.due_timeout[env_ids] = False

    def take_resets(self) -> torch.Tensor:
        """(p,) the envs reset since the last call (host-known size), and forget them; marks
        them in :attr:`is_reset`."""
        ids, self._resets = self._resets, []
        self.is_reset.zero_()
        if not ids:
            self._num_resets = 0
            return torch.zeros(0, dtype=torch.long, device=self.device)
        resets = torch.cat([i.to(device=self.device, dtype=torch.long) for i in ids])
        self.is_reset[resets] = True
        self._num_resets = resets.numel()
        return resets

    def serve(
        self,
        touchdown: torch.Tensor,
        timeout: torch.Tensor,
        active: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Queue this update's ``touchdown`` / ``timeout`` masks (E,) and take up to ``capacity``
        due envs among ``active`` (E,), never one of the p resets :meth:`take_resets` returned
        in this update (they are planned apart).

        Returns ``sel`` (c,) the env ids of the fixed-size batch (c = min(capacity, E - p), known
        on the host), ``serve`` (c,) bool: the env is due and is served now, and ``flip`` (c,)
        bool: served for a touchdown (the others served are timeouts).
        """
        e = self.num_envs
        self.due_touchdown |= touchdown
        self.due_timeout = (self.due_timeout | timeout) & ~self.due_touchdown
        due = (self.due_touchdown | self.due_timeout) & active
        order_key = (~due).to(torch.int8) + 2 * self.is_reset.to(torch.int8)  # due, idle, resets
        sel = torch.argsort(order_key, stable=True)[: min(self.capacity, e - self._num_resets)]
        serve = due[sel]
        flip = serve & self.due_touchdown[sel]
        served = self._served.zero_()
        served[sel] = serve
        self.deferred_count += (due & ~served).long()
        self.due_touchdown &= ~served
        self.due_timeout &= ~served
        return sel, serve, flip

    def waiting(self) -> torch.Tensor:
        """(E,) bool: an event waits to be served."""
        return self.due_touchdown | self.due_timeout
