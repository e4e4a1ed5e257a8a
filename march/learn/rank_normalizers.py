"""Observation normalisers shared by the N ranks of a run, synchronised once per iteration.

rsl-rl's ``EmpiricalNormalization`` learns from each batch it is shown, per process. On N ranks
:func:`sync_normalizers` takes every normaliser of a network over: during a rollout each rank
adds its batches' moments to a running (count, mean, M2) on its device, reading nothing back
and sending nothing; :func:`flush_normalizers` (once per iteration, before the returns and the
update) gathers every normaliser's moments from every rank in one collective and applies them
in rank order, so every rank holds the same bits. The old per-step scheme cost one all-gather
and one host read per normaliser per env step (48 per PPO iteration); this one costs one
all-gather per iteration and no host read (``tests/test_distributed.py`` counts both).

The normalisers stay as the last flush left them during a rollout (rsl-rl's own per-step
update would have moved them within the rollout): the same statistics on every rank while it
acts, and the same statistics as per-step updates by the time the networks learn.
"""

from __future__ import annotations

import types
from typing import Any

import torch

from march.learn.distributed import collective_device, current, on_leave

_NORMALIZERS: list[Any] = []
"""The normalisers :func:`sync_normalizers` took over, in the same order on every rank."""


def _deferred_update(norm: Any, x: torch.Tensor) -> None:
    """rsl-rl's ``EmpiricalNormalization.update`` on N ranks: the batch's moments are added to
    this rank's running (count, mean, M2) on the device (Chan et al.'s pairwise combination;
    the count is the host's: batch sizes are known there) and nothing is read back or
    communicated. :func:`flush_normalizers` combines every rank's once per iteration."""
    if not norm.training:
        return
    x = x.reshape(-1, x.shape[-1]).double()
    n_b = x.shape[0]
    if n_b == 0:
        return
    mean_b = x.mean(0)
    m2_b = ((x - mean_b) ** 2).sum(0)
    acc = norm._march_acc
    if acc[0] == 0:
        norm._march_acc = [n_b, mean_b, m2_b]
        return
    n_a, mean_a, m2_a = acc
    n = n_a + n_b
    delta = mean_b - mean_a
    norm._march_acc = [n, mean_a + delta * (n_b / n), m2_a + m2_b + delta**2 * (n_a * n_b / n)]


def flush_normalizers() -> int:
    """Every normaliser learns the batches all ranks saw since the last flush: one all-gather of
    every normaliser's (count, mean, M2) per call, combined in rank order (the same bits on every
    rank), applied as one rsl-rl update (exact: a running mean / variance over the batches in
    one step equals the per-batch updates). Call it once per iteration, where rsl-rl's
    per-step updates would have been complete (before the returns and the update); on the
    device throughout, no host read. Returns the number of collectives issued (0 or 1)."""
    if not current().active or not _NORMALIZERS:
        return 0
    import torch.distributed as td

    dev = collective_device()
    parts = []
    for norm in _NORMALIZERS:
        n, mean, m2 = norm._march_acc
        dim = norm._mean.shape[-1]
        if n == 0:
            mean = m2 = torch.zeros(dim, dtype=torch.float64)
        count = torch.full((1,), float(n), dtype=torch.float64, device=mean.device)
        parts.append(torch.cat([count, mean, m2]).to(dev))
        norm._march_acc = [0, None, None]
    local = torch.cat(parts)
    rows = [torch.empty_like(local) for _ in range(current().world)]
    td.all_gather(rows, local)
    gathered = torch.stack(rows)  # (world, ...), rank order
    offset = 0
    for norm in _NORMALIZERS:
        dim = norm._mean.shape[-1]
        block = gathered[:, offset : offset + 1 + 2 * dim].to(norm._mean.device)
        offset += 1 + 2 * dim
        _apply_moments(norm, block[:, 0], block[:, 1 : 1 + dim], block[:, 1 + dim :])
    return 1


def _apply_moments(norm: Any, counts: torch.Tensor, means: torch.Tensor, m2s: torch.Tensor) -> None:
    """rsl-rl's update with the union of the ranks' batches (rank order), on the device. A
    normaliser past ``until`` (a host read of its count, once per flush) learns nothing more."""
    if norm.until is not None and int(norm.count) >= norm.until:
        return
    n = counts.sum()
    safe = torch.clamp(n, min=1.0)
    mean_x = (counts[:, None] * means).sum(0) / safe
    m2 = m2s.sum(0) + (counts[:, None] * (means - mean_x) ** 2).sum(0)
    var_x = m2 / safe
    dtype = norm._mean.dtype
    mean_x, var_x = mean_x.to(dtype).unsqueeze(0), var_x.to(dtype).unsqueeze(0)
    count = norm.count + n.to(norm.count.dtype)
    rate = (n / torch.clamp(count, min=1)).to(dtype)  # 0 when no rank saw a batch
    norm.count.copy_(count)
    delta_mean = mean_x - norm._mean
    norm._mean += rate * delta_mean
    norm._var += rate * (var_x - norm._var + delta_mean * (mean_x - norm._mean))
    norm._std = torch.sqrt(norm._var)


def sync_normalizers(*modules: torch.nn.Module) -> int:
    """Make every rsl-rl ``EmpiricalNormalization`` inside ``modules`` learn from all ranks'
    batches, once per iteration (:func:`_deferred_update`, :func:`flush_normalizers`): during a
    rollout the normalisers stay as the last flush left them, the same on every rank. Returns
    how many were found. No-op for one process (rsl-rl's per-step updates)."""
    if not current().active:
        return 0
    from rsl_rl.modules.normalization import EmpiricalNormalization

    on_leave(reset)  # the process group gone, the normalisers taken over are forgotten
    found = 0
    for module in modules:
        for sub in module.modules():
            if isinstance(sub, EmpiricalNormalization):
                sub.update = types.MethodType(_deferred_update, sub)  # type: ignore[method-assign]
                sub._march_acc = [0, None, None]
                _NORMALIZERS.append(sub)
                found += 1
    return found


def reset() -> None:
    """Forget the normalisers taken over (the process group is gone)."""
    _NORMALIZERS.clear()
