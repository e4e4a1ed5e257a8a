"""Student networks (plain torch, no simulator import)."""

from march.policies.mdn import (
    MDNHead,
    MDNParams,
    mdn_log_prob,
    mdn_nll,
    mdn_sample,
    mixture_weights,
    mode_mean,
    mode_weight_entropy,
    squash_log_std,
    top_mode_index,
    top_mode_mean,
)
from march.policies.student import StudentPolicy

__all__ = [
    "MDNHead",
    "MDNParams",
    "StudentPolicy",
    "mdn_log_prob",
    "mdn_nll",
    "mdn_sample",
    "mixture_weights",
    "mode_mean",
    "mode_weight_entropy",
    "squash_log_std",
    "top_mode_index",
    "top_mode_mean",
]
