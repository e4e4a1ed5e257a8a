"""An evaluation over N ranks: waves of rollouts dealt to the ranks and gathered.

An evaluation of ``n`` rollouts on an eval env of ``W`` envs (``compute.eval_num_envs``) is a
sequence of waves: wave ``k`` runs rollouts ``[k W, min((k + 1) W, n))`` (the last wave keeps its
first envs). Every random number a rollout draws is keyed by (the evaluation's seed, its rollout
index) (:mod:`march.env.rollout_draws`), so a rollout's row depends on the policy, the seed and
its index only: not on ``W``, on what ran before it in its env, nor on which process runs it.

Over N ranks rank r runs waves r, r + N, r + 2N, ... on its own eval env, and the per-rollout
metrics of every wave are gathered (one ``all_gather_object``) and put back in rollout order, so
1 rank in 1 wave, 1 rank in 4 waves and 2 ranks give the same rows (tested with gloo,
tests/test_distributed.py). The evaluation's wall time falls with ranks when it has at least N
waves: a run over N ranks that evaluates ``n`` rollouts should set ``compute.eval_num_envs`` to
``n / N`` (docs/scaling.md).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

from march.learn import distributed
from march.learn.distributed import Dist

WaveFn = Callable[..., dict[str, torch.Tensor]]
"""``rollout_metrics(env, policy, count, first, seed)``: one wave's per-rollout metrics."""


def waves(num_rollouts: int, wave_size: int) -> list[tuple[int, int, int]]:
    """Every wave as (index, first rollout, rollouts)."""
    return [
        (k, first, min(wave_size, num_rollouts - first))
        for k, first in enumerate(range(0, num_rollouts, wave_size))
    ]


def rank_waves(num_rollouts: int, wave_size: int, d: Dist | None = None) -> list[tuple[int, ...]]:
    """The waves rank ``d.rank`` of ``d.world`` runs: k = rank, rank + world, ..."""
    d = d or distributed.current()
    return [w for w in waves(num_rollouts, wave_size) if w[0] % d.world == d.rank]


def sharded_rollouts(
    env: Any, policy: Any, num_rollouts: int, run_wave: WaveFn
) -> dict[str, torch.Tensor]:
    """Per-rollout metrics of all ``num_rollouts`` rollouts (rollout order) on every rank; this
    rank runs only its waves (:func:`rank_waves`)."""
    # The run's seed (rank 0's env): rank r's env carries rank r's training seed.
    seed = distributed.agree(int(env.cfg.seed or 0))
    mine = {
        k: {name: v.cpu() for name, v in run_wave(env, policy, count, first, seed).items()}
        for k, first, count in rank_waves(num_rollouts, env.num_envs)
    }
    by_wave: dict[int, dict[str, torch.Tensor]] = {}
    for part in distributed.gather_objects(mine):
        by_wave.update(part)
    order = sorted(by_wave)
    if order != list(range(len(waves(num_rollouts, env.num_envs)))):
        raise RuntimeError(f"evaluation: waves {order} gathered, not every wave once")
    keys = list(by_wave[order[0]]) if order else []
    return {name: torch.cat([by_wave[k][name] for k in order]) for name in keys}
