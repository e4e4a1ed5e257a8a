"""Mixture density network (MDN) head over actions: K diagonal Gaussians.

The student's stochastic output (paper: "MDN with 2 modes, min std 1e-3, log-std in [-3, 2],
inference = mean of the top mode"). Everything here is plain torch.

Parameters are carried as :class:`MDNParams` ``(logits (B, K), means (B, K, A), log_std (B, K, A))``.
``log_std`` is already *final*: the raw network output clamped to ``[log_std_min, log_std_max]``
and then floored at ``log(min_std)``. With the paper's values (-3, 2, 1e-3) the clamp binds first
(e^-3 ~ 0.0498 > 1e-3), so the smallest standard deviation the head can express is e^-3; the
``min_std`` floor only matters when ``log_std_min < log(min_std)``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

_LOG_2PI = math.log(2.0 * math.pi)


class MDNParams(NamedTuple):
    """Mixture parameters. B = batch, K = modes, A = action dimension."""

    logits: torch.Tensor
    """(B, K) unnormalised log mixture weights."""
    means: torch.Tensor
    """(B, K, A) per-mode action means (action units, i.e. the policy's raw action space)."""
    log_std: torch.Tensor
    """(B, K, A) per-mode log standard deviations (natural log), clamped and floored."""


def squash_log_std(
    raw: torch.Tensor, log_std_min: float, log_std_max: float, min_std: float
) -> torch.Tensor:
    """Squash a raw log-std smoothly into ``[log_std_min, log_std_max]`` (a scaled sigmoid), then
    floor it at ``log(min_std)``.

    A hard clamp would leave no gradient once the raw value passes a bound: a mode whose std hit
    e^-3 could never widen again, and its NLL on the next states the student visits explodes.
    """
    log_std = log_std_min + (log_std_max - log_std_min) * torch.sigmoid(raw)
    return log_std.clamp_min(math.log(min_std))


def unsquash_log_std(log_std: float, log_std_min: float, log_std_max: float) -> float:
    """The raw value that :func:`squash_log_std` maps to ``log_std`` (for initialisation)."""
    frac = (log_std - log_std_min) / (log_std_max - log_std_min)
    if not 0.0 < frac < 1.0:
        raise ValueError(f"log_std {log_std} must lie inside ({log_std_min}, {log_std_max})")
    return math.log(frac / (1.0 - frac))


class MDNHead(nn.Module):
    """Linear read-out from a feature vector to :class:`MDNParams`.

    Three separate linear maps (``logits``, ``means``, ``log_std``) so the mixture parameters are
    identifiable in the state_dict. The logit layer starts near zero (uniform mode weights) and the
    log-std bias at ``init_log_std``.
    """

    def __init__(
        self,
        in_dim: int,
        num_actions: int,
        num_modes: int = 2,
        min_std: float = 1e-3,
        log_std_min: float = -3.0,
        log_std_max: float = 2.0,
        init_log_std: float = 0.0,
    ) -> None:
        super().__init__()
        if num_modes < 1:
            raise ValueError(f"num_modes must be >= 1, got {num_modes}")
        if not log_std_min < log_std_max:
            raise ValueError(f"need log_std_min < log_std_max, got {log_std_min}, {log_std_max}")
        if min_std <= 0:
            raise ValueError(f"min_std must be > 0, got {min_std}")
        self.num_actions = num_actions
        self.num_modes = num_modes
        self.min_std = min_std
        self.log_std_min = log_std_min
        self.log_std_max = log_std_max
        self.logits = nn.Linear(in_dim, num_modes)
        self.means = nn.Linear(in_dim, num_modes * num_actions)
        self.log_std = nn.Linear(in_dim, num_modes * num_actions)
        nn.init.normal_(self.logits.weight, std=1e-3)
        nn.init.zeros_(self.logits.bias)
        nn.init.normal_(self.log_std.weight, std=1e-3)
        nn.init.constant_(
            self.log_std.bias, unsquash_log_std(init_log_std, log_std_min, log_std_max)
        )

    def params_from_raw(
        self, logits: torch.Tensor, means: torch.Tensor, raw_log_std: torch.Tensor
    ) -> MDNParams:
        """Reshape flat head outputs to (B, K[, A]) and squash the log-std."""
        shape = (*means.shape[:-1], self.num_modes, self.num_actions)
        log_std = squash_log_std(
            raw_log_std.reshape(shape), self.log_std_min, self.log_std_max, self.min_std
        )
        return MDNParams(logits, means.reshape(shape), log_std)

    def forward(self, x: torch.Tensor) -> MDNParams:
        return self.params_from_raw(self.logits(x), self.means(x), self.log_std(x))


def mixture_weights(params: MDNParams) -> torch.Tensor:
    """(B, K) mode probabilities (softmax of the logits)."""
    return torch.softmax(params.logits, dim=-1)


def mdn_log_prob(params: MDNParams, actions: torch.Tensor) -> torch.Tensor:
    """Log-density of ``actions`` under the mixture, by a log-sum-exp over modes.

    ``actions`` is (B, A) -> returns (B,), or (B, S, A) (S samples per batch row) -> returns (B, S).
    """
    logits, means, log_std = params
    single = actions.dim() == means.dim() - 1
    if single:
        actions = actions.unsqueeze(-2)  # (B, 1, A)
    a = actions.unsqueeze(-2)  # (B, S, 1, A)
    mu = means.unsqueeze(-3)  # (B, 1, K, A)
    ls = log_std.unsqueeze(-3)  # (B, 1, K, A)
    z = (a - mu) * torch.exp(-ls)
    num_actions = means.shape[-1]
    comp = -0.5 * z.square().sum(-1) - ls.sum(-1) - 0.5 * num_actions * _LOG_2PI  # (B, S, K)
    log_w = torch.log_softmax(logits, dim=-1).unsqueeze(-2)  # (B, 1, K)
    out = torch.logsumexp(log_w + comp, dim=-1)  # (B, S)
    return out.squeeze(-1) if single else out


def mdn_nll(params: MDNParams, teacher_actions: torch.Tensor) -> torch.Tensor:
    """Mean negative log-likelihood of teacher actions (B, S, A) (or (B, A)): scalar."""
    return -mdn_log_prob(params, teacher_actions).mean()


def mode_mean(params: MDNParams, k: int) -> torch.Tensor:
    """(B, A) mean of mode ``k`` (modes are ordered as the head emits them, not by weight)."""
    return params.means[..., k, :]


def top_mode_index(params: MDNParams) -> torch.Tensor:
    """(B,) index of the most probable mode."""
    return torch.argmax(params.logits, dim=-1)


def top_mode_mean(params: MDNParams) -> torch.Tensor:
    """(B, A) mean of the most probable mode: the student's deterministic action (inference)."""
    idx = top_mode_index(params)  # (B,)
    num_actions = params.means.shape[-1]
    gather_idx = idx.reshape(-1, 1, 1).expand(-1, 1, num_actions)
    return torch.gather(params.means, 1, gather_idx).squeeze(1)


def mdn_sample(params: MDNParams, generator: torch.Generator | None = None) -> torch.Tensor:
    """(B, A) one sample per row: a mode drawn from the weights, then its Gaussian."""
    logits, means, log_std = params
    probs = torch.softmax(logits, dim=-1)
    k = torch.multinomial(probs, 1, generator=generator)  # (B, 1)
    idx = k.reshape(-1, 1, 1).expand(-1, 1, means.shape[-1])
    mu = torch.gather(means, 1, idx).squeeze(1)
    std = torch.exp(torch.gather(log_std, 1, idx).squeeze(1))
    eps = torch.randn(mu.shape, generator=generator, device=mu.device, dtype=mu.dtype)
    return mu + std * eps


def mode_weight_entropy(params: MDNParams) -> torch.Tensor:
    """(B,) entropy of the mode weights (nats): 0 = one mode, log K = uniform. For logging."""
    log_w = F.log_softmax(params.logits, dim=-1)
    return -(log_w.exp() * log_w).sum(-1)
