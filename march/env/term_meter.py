"""Per-term training logs kept on the device: what each reward term adds to the return, what
fraction of episodes each termination ends, and the curriculum level's spread.

:func:`attach` wraps the env's reward and termination managers' ``compute`` (mjlab's own, run
as before) so that each step adds, on the device, every reward term's contribution (weight *
value * dt, as it enters the reward) summed over the envs, and every termination term's count of
ended episodes. :meth:`TermMeter.pop` reads all of it with one device -> host copy, once per
iteration, and starts over: no host sync inside the step.

Columns (metrics.csv; ``Episode_Reward/<term>`` / ``Episode_Termination/<term>`` in tensorboard
and wandb, as mjlab names them):

* ``reward/<term>``: mean per env step of the term's contribution to the step reward (the terms
  add up to the mean step reward);
* ``termination/<term>``: the fraction of the iteration's ended episodes that the term ended
  (several terms can end one episode; NaN when no episode ended);
* ``terrain_level_std``: the spread of the curriculum levels over the envs (its mean is
  ``mean_terrain_level``).
"""

from __future__ import annotations

from typing import Any

import torch

from march.env.clf_meter import pop_clf

REWARD_PREFIX = "reward/"
TERMINATION_PREFIX = "termination/"


class TermMeter:
    """Device-side sums of per-term rewards and terminations for one env."""

    def __init__(self, env: Any) -> None:
        self.env = env
        rm, tm = env.reward_manager, env.termination_manager
        self.rewards = list(rm.active_terms)
        self.terminations = list(tm.active_terms)
        dev = env.device
        self._reward = torch.zeros(len(self.rewards), device=dev)
        self._ended = torch.zeros(len(self.terminations), device=dev)
        self._episodes = torch.zeros(1, device=dev)
        self._steps = 0  # env steps (a Python count: no device read)
        reward_compute, term_compute = rm.compute, tm.compute

        def rewards(dt: float) -> torch.Tensor:
            out = reward_compute(dt)
            scale = dt if getattr(rm, "_scale_by_dt", True) else 1.0
            self._reward += rm._step_reward.sum(0) * scale
            self._steps += out.shape[0]
            return out

        def terminations() -> torch.Tensor:
            done = term_compute()
            if self.terminations:
                per_term = torch.stack([tm._term_dones[k] for k in self.terminations])
                self._ended += per_term.sum(1)
            self._episodes += done.sum()
            return done

        rm.compute, tm.compute = rewards, terminations

    def pop(self) -> dict[str, float]:
        """This interval's per-term columns (one device read), then start over."""
        steps = max(self._steps, 1)
        parts = [self._reward / steps, self._ended, self._episodes]
        levels = _levels(self.env)
        if levels is not None:
            levels = levels.float()
            parts.append(levels.std(correction=0).reshape(1))
        values = torch.cat(parts).tolist()  # the one host read
        n_r, n_t = len(self.rewards), len(self.terminations)
        episodes = values[n_r + n_t]
        row = {f"{REWARD_PREFIX}{k}": v for k, v in zip(self.rewards, values[:n_r], strict=True)}
        for k, v in zip(self.terminations, values[n_r : n_r + n_t], strict=True):
            row[f"{TERMINATION_PREFIX}{k}"] = v / episodes if episodes else float("nan")
        row["terrain_level_std"] = values[-1] if levels is not None else float("nan")
        self._reward.zero_()
        self._ended.zero_()
        self._episodes.zero_()
        self._steps = 0
        return row


def _levels(env: Any) -> torch.Tensor | None:
    terrain = getattr(env.scene, "terrain", None)
    levels = getattr(terrain, "terrain_levels", None)
    return levels if isinstance(levels, torch.Tensor) else None


def attach(env: Any) -> TermMeter:
    """Put a :class:`TermMeter` on ``env`` (``env.term_meter``). (The CLF diagnostics are
    attached beside it by march.env.build, :func:`march.env.clf_meter.attach`.)"""
    meter = TermMeter(env)
    env.term_meter = meter
    return meter


def pop_terms(env: Any) -> dict[str, float]:
    """The meter's columns of ``env`` (unwrapped or rsl-rl-wrapped), or {} without one, and the
    CLF diagnostics (``clf/...``, :mod:`march.env.clf_meter`) where the env has them."""
    meter = getattr(getattr(env, "unwrapped", env), "term_meter", None)
    row = meter.pop() if meter is not None else {}
    return {**row, **pop_clf(env)}
