"""What one PPO update did: the learning rate over its mini-batches, the KL it moved the
policy by, its clip fraction and the action std per joint group (issue 56).

rsl-rl's ``PPO.update`` adapts the learning rate at every mini-batch and logs none of it; the
value left in ``alg.learning_rate`` at the end of an iteration is the last mini-batch's, which
says nothing about how far the policy moved. :class:`UpdateReadout` watches an update from
outside rsl-rl, without copying its loop: it sees each mini-batch as the storage's generator
yields it and each optimiser step through a step pre-hook (where the actor still holds that
mini-batch's distribution). Everything per mini-batch stays on the device or is a Python float
rsl-rl already keeps (the learning rate): one host read per iteration, in :meth:`pop`.

The KL columns are measured on the whole rollout, against the distributions the rollout's
actions were drawn from (``storage.distribution_params``):

- ``kl_normaliser``: before any gradient step, the same weights with the observation
  normaliser as the rollout left it (the drift no learning caused);
- ``kl_update``: after the update, the updated policy (weights and normaliser): the total KL
  the iteration moved the policy by, ``kl_normaliser`` included.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from typing import Any

import torch
from rsl_rl.algorithms import PPO
from rsl_rl.models import MLPModel
from rsl_rl.storage import RolloutStorage

from march.env.joint_groups import JOINT_GROUPS, group_index, group_means


def set_initial_std(actor: MLPModel, std: torch.Tensor) -> None:
    """Set the actor's state-independent action std per action (``std`` (A,)), as rsl-rl's
    ``GaussianDistribution`` stores it (``std_param``, or ``log_std_param`` for std_type log).
    rsl-rl builds it with one scalar for every action; this replaces the values in place (the
    optimiser keeps the same parameter)."""
    dist = actor.distribution
    with torch.no_grad():
        if hasattr(dist, "std_param"):
            dist.std_param.copy_(std.to(dist.std_param))
        elif hasattr(dist, "log_std_param"):
            dist.log_std_param.copy_(std.log().to(dist.log_std_param))
        else:
            raise ValueError(f"{type(dist).__name__} has no state-independent std to set")


def rollout_kl(actor: MLPModel, storage: RolloutStorage) -> torch.Tensor:
    """Mean over the rollout's samples of KL(rollout policy || ``actor`` now), summed over the
    action dims: the stored distributions the actions were drawn from against the actor's
    distribution on the same stored observations, normalised by its current normaliser. One
    forward pass, no sampling (the random stream is untouched); a 0-d device tensor."""
    with torch.inference_mode():
        obs = storage.observations.flatten(0, 1)
        actor.distribution.update(actor.mlp(actor.get_latent(obs)))
        new = actor.output_distribution_params
        old = tuple(p.flatten(0, 1) for p in storage.distribution_params)
        return actor.get_kl_divergence(old, new).mean()


def action_std(actor: MLPModel) -> torch.Tensor:
    """(A,) the actor's current state-independent action std (clamped as rsl-rl samples it)."""
    dist = actor.distribution
    if hasattr(dist, "std_param"):
        return dist.std_param.detach().clamp(*dist.std_range)
    return dist.log_std_param.detach().clamp(*dist.log_std_range).exp()


class UpdateReadout:
    """Watches ``alg.update()`` (:meth:`watching`) and reads what it did (:meth:`pop`).

    ``joint_names``: the action's joints in action order (:mod:`march.env.joint_groups`), for
    the std per group."""

    def __init__(self, alg: PPO, joint_names: Sequence[str]) -> None:
        self.alg = alg
        self.group = group_index(joint_names, device=alg.device)
        self.lrs: list[float] = []  # the learning rate of each optimiser step (Python floats)
        self.clipped: torch.Tensor | None = None  # on the device: sum of clip fractions
        self.batch: RolloutStorage.Batch | None = None
        self.kl_normaliser: torch.Tensor | None = None

    def _batches(self, generator: Iterator[Any]) -> Iterator[Any]:
        for batch in generator:
            self.batch = batch
            yield batch

    def _before_step(self, optimizer: torch.optim.Optimizer, *_: Any) -> None:
        # The lr rsl-rl's schedule set for this step (a float it keeps: no device read).
        self.lrs.append(float(optimizer.param_groups[0]["lr"]))
        batch, actor = self.batch, self.alg.actor
        if batch is None:
            return
        with torch.no_grad():  # the actor still holds this mini-batch's distribution
            n = batch.old_actions_log_prob.shape[0]
            new_log_prob = actor.get_output_log_prob(batch.actions)[:n]
            ratio = torch.exp(new_log_prob - batch.old_actions_log_prob.squeeze(-1))
            frac = ((ratio - 1.0).abs() > self.alg.clip_param).float().mean()
        self.clipped = frac if self.clipped is None else self.clipped + frac

    def update(self) -> dict[str, float]:
        """``alg.update()`` watched: its losses (rsl-rl's) with :meth:`pop`'s columns."""
        alg, st = self.alg, self.alg.storage
        self.lrs, self.clipped, self.batch = [], None, None
        self.kl_normaliser = rollout_kl(alg.actor, st)
        real = st.mini_batch_generator
        st.mini_batch_generator = lambda *a, **k: self._batches(real(*a, **k))  # type: ignore[method-assign]
        hook = alg.optimizer.register_step_pre_hook(self._before_step)
        try:
            losses = alg.update()
        finally:
            hook.remove()
            del st.mini_batch_generator  # the class's method again
        return {**losses, **self.pop()}

    def pop(self) -> dict[str, float]:
        """This update's columns (one host read): ``lr_mean``, ``lr_min``, ``lr_max`` over its
        optimiser steps; ``kl_update`` and ``kl_normaliser`` (module docstring);
        ``clip_fraction``, the mean over mini-batches of the share of samples whose probability
        ratio left [1 - clip, 1 + clip] at that mini-batch's step; ``action_std_<group>``, the
        mean std of each joint group after the update, and ``action_std`` over every joint."""
        alg = self.alg
        std = action_std(alg.get_policy())
        kl_norm = self.kl_normaliser if self.kl_normaliser is not None else torch.tensor(math.nan)
        clipped = self.clipped if self.clipped is not None else torch.tensor(math.nan)
        steps = max(len(self.lrs), 1)
        values = torch.cat(
            [
                torch.stack(
                    [
                        rollout_kl(alg.actor, alg.storage),
                        kl_norm.to(std),
                        clipped.to(std) / steps,
                        std.mean(),
                    ]
                ),
                group_means(std, self.group),
            ]
        ).tolist()  # the one host read of the iteration
        kl_update, kl_normaliser, clip_fraction, std_all, *by_group = values
        lrs = self.lrs or [float(alg.learning_rate)]
        return {
            "lr_mean": sum(lrs) / len(lrs),
            "lr_min": min(lrs),
            "lr_max": max(lrs),
            "kl_update": kl_update,
            "kl_normaliser": kl_normaliser,
            "clip_fraction": clip_fraction,
            "action_std": std_all,
            **{f"action_std_{g}": v for g, v in zip(JOINT_GROUPS, by_group, strict=True)},
        }
