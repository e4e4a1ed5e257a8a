"""The CLF diagnostics of an env with the ``reference`` command, kept on the device.

:func:`attach` wraps the env's reward manager's ``compute`` (mjlab's own, run as before): after
each step's rewards it adds that step's V, its per-output terms and dV/dt's validity to a
:class:`march.clf.diagnostics.ClfStats` - a few tensor ops, no host read. :func:`pop_clf` reads
the interval's ``clf/...`` columns with one device -> host copy (once per training iteration, or
once per evaluation). The V read is the one the CLF reward terms use this step
(:meth:`ReferenceCommand.clf_state`, computed once per step and cached), so an arm whose reward
has no CLF term still gets V measured against the same reference.

``ClfMeter.active`` (E,) bool, when set, keeps only those envs' samples: an evaluation counts each
rollout up to its end, not the auto-reset episodes its env runs afterwards.
"""

from __future__ import annotations

from typing import Any

import torch

from march.clf.diagnostics import ClfStats, output_terms
from march.env.reference_command import reference_term
from march.env.rewards import REFERENCE_COMMAND


class ClfMeter:
    """Device-side CLF diagnostics of one env (see the module docstring)."""

    def __init__(self, env: Any) -> None:
        self.term = reference_term(env, REFERENCE_COMMAND)
        clf = self.term.clf
        self.stats = ClfStats(clf.cfg.output_names, clf.v_max, env.device)
        self.active: torch.Tensor | None = None
        rm = env.reward_manager
        reward_compute = rm.compute

        def rewards(dt: float) -> torch.Tensor:
            out = reward_compute(dt)
            v, _, valid = self.term.clf_state()
            self.stats.add(v, output_terms(self.term.v_products), valid, self.active)
            return out

        rm.compute = rewards

    def pop(self) -> dict[str, float]:
        return self.stats.pop()


def attach(env: Any) -> ClfMeter | None:
    """Put a :class:`ClfMeter` on ``env`` (``env.clf_meter``) if it has the reference command."""
    if REFERENCE_COMMAND not in env.command_manager.active_terms:
        return None
    meter = ClfMeter(env)
    env.clf_meter = meter
    return meter


def pop_clf(env: Any) -> dict[str, float]:
    """The ``clf/...`` columns of ``env`` (unwrapped or rsl-rl-wrapped), or {} without a meter."""
    meter = getattr(getattr(env, "unwrapped", env), "clf_meter", None)
    return meter.pop() if meter is not None else {}


def pop_clf_pooled(env: Any, gather: Any) -> dict[str, float]:
    """:func:`pop_clf` of the samples of every process pooled: ``gather(obj)`` returns every
    rank's ``obj`` (march.learn.distributed.gather_objects); the raw sums are added, then the
    columns computed, so N ranks give the quantiles of all their samples (not a mean of
    quantiles) and one rank gives :func:`pop_clf`'s."""
    meter = getattr(getattr(env, "unwrapped", env), "clf_meter", None)
    if meter is None:
        return {}
    parts = gather(meter.stats.pop_sums())
    return meter.stats.row([sum(values) for values in zip(*parts, strict=True)])
