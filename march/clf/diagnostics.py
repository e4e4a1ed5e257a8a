"""What the CLF reward sees, summarised on the device: V/Vmax quantiles, saturation, dV/dt
validity and each output's share of V (issue 50: "does the CLF reward teach?").

Plain torch, no simulator. :class:`ClfStats` accumulates samples of one env step at a time
(``add``: a handful of tensor ops, no host read) and reads everything back with one device ->
host copy (``pop``), once per training iteration or evaluation.

Definitions (per sample = one env at one control step)
- ``ratio = V / Vmax``. ``r_clf = exp(-min(V, Vmax)/Vmax)`` is flat at e^-1 for ``ratio >= 1``,
  so the **saturated** fraction is the share of samples with ``V >= Vmax``: there the reward
  gives no gradient towards the reference.
- **Quantiles** ``v_p10``, ``v_p50``, ``v_p90`` of ``ratio``, read from a histogram with
  logarithmic bins (``BINS_PER_DECADE`` per decade from ``RATIO_MIN`` to ``RATIO_MAX``; below
  ``RATIO_MIN``, zero included, is one underflow bin read as 0; above ``RATIO_MAX`` one overflow
  bin read as ``inf``), linearly interpolated within the bin: a relative resolution of
  ``10 ** (1 / BINS_PER_DECADE) - 1`` (2.3 %). A histogram, not stored samples, because its size
  does not grow with envs x steps and filling it is one ``index_add_``.
- **dvdt_valid**: the share of samples whose dV/dt is defined (two or more V since the last
  reset or reference switch; :class:`march.clf.lyapunov.VHistory`) - where it is not, r_dclf
  is 0 by construction.
- **share/<output>**: the mean over samples with ``V > 0`` of ``V_i / V``, where
  ``V_i = 1/2 x_i^T P_i x_i`` (``x_i = [eta_i, etadot_i]``) is output i's term of V
  (P is block-diagonal, so the terms add up to V and the shares to 1).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

RATIO_MIN = 1e-4
"""Smallest V/Vmax resolved by the quantile histogram (below it: the underflow bin, read as 0)."""
RATIO_MAX = 1e6
"""Largest V/Vmax resolved (above it: the overflow bin, read as inf)."""
BINS_PER_DECADE = 100
"""Histogram bins per decade of V/Vmax (2.3 % relative resolution of the quantiles)."""
QUANTILES = (("v_p10", 0.10), ("v_p50", 0.50), ("v_p90", 0.90))
"""The quantiles of V/Vmax reported, by column name."""
PREFIX = "clf/"
"""Column prefix in metrics.csv / eval.csv (``clf/v_p50``, ``clf/share/com_x``, ...)."""


def output_terms(prod: torch.Tensor) -> torch.Tensor:
    """Each output's term of V (E, n) from the interleaved products ``(x @ P/2) * x`` (E, 2n).

    With P block-diagonal in ``x = [eta_1, etadot_1, eta_2, ...]``, ``V = sum(prod)`` and output
    i's term is the sum of its two columns (its block's 1/2 x_i^T P_i x_i)."""
    return prod.unflatten(-1, (-1, 2)).sum(-1)


def histogram_edges() -> torch.Tensor:
    """The interior bin edges of V/Vmax (float64, host): ``RATIO_MIN`` ... ``RATIO_MAX``."""
    decades = math.log10(RATIO_MAX / RATIO_MIN)
    n = round(decades * BINS_PER_DECADE)
    return torch.logspace(math.log10(RATIO_MIN), math.log10(RATIO_MAX), n + 1, dtype=torch.float64)


def quantiles_from_histogram(
    counts: Sequence[float], edges: torch.Tensor, qs: Sequence[float]
) -> list[float]:
    """Quantiles of a histogram with an underflow bin (value 0), ``len(edges) - 1`` interior bins
    and an overflow bin (value inf), linear within an interior bin; NaN without samples."""
    total = float(sum(counts))
    if total <= 0:
        return [math.nan for _ in qs]
    out = []
    for q in qs:
        target = q * total
        cum = 0.0
        value = math.inf
        for i, c in enumerate(counts):
            if c > 0 and cum + c >= target:
                if i == 0:
                    value = 0.0
                elif i == len(counts) - 1:
                    value = math.inf
                else:
                    lo, hi = float(edges[i - 1]), float(edges[i])
                    value = lo + (hi - lo) * (target - cum) / c
                break
            cum += c
        out.append(value)
    return out


class ClfStats:
    """Device-side sums of the CLF diagnostics of one env over an interval of steps."""

    def __init__(self, output_names: Sequence[str], v_max: float, device: torch.device | str):
        if not v_max > 0:
            raise ValueError(f"Vmax must be > 0, got {v_max}")
        self.names = list(output_names)
        self.v_max = float(v_max)
        edges = histogram_edges()
        self._edges = edges
        self._log_edges = torch.log(edges.to(device=device, dtype=torch.float32))
        # one buffer: [underflow, bins..., overflow | saturated, valid, samples, positive |
        # shares (n)] so that pop is a single host read
        self._n_bins = len(edges) + 1
        n = len(self.names)
        self._sums = torch.zeros(self._n_bins + 4 + n, dtype=torch.float64, device=device)
        self._ones: torch.Tensor | None = None

    def add(
        self,
        v: torch.Tensor,
        terms: torch.Tensor,
        valid: torch.Tensor,
        active: torch.Tensor | None = None,
    ) -> None:
        """Add one step's samples: V (E,), its per-output terms (E, n), dV/dt validity (E,);
        ``active`` (E,) bool keeps only those envs (None: all). No host read."""
        ratio = v / self.v_max
        # bin index: 0 underflow, 1..B interior, B+1 overflow (searchsorted on log edges)
        log_r = torch.log(ratio.clamp_min(1e-30).float())
        idx = torch.searchsorted(self._log_edges, log_r, right=True)
        w = torch.ones_like(v, dtype=torch.float64) if active is None else active.double()
        positive = (v > 0).double() * w
        shares = (terms / v.clamp_min(1e-30).unsqueeze(-1)).double() * positive.unsqueeze(-1)
        scalars = torch.stack(
            [
                ((v >= self.v_max).double() * w).sum(),
                (valid.double() * w).sum(),
                w.sum(),
                positive.sum(),
            ]
        )
        # straight into the one buffer's views: no per-step histogram or concatenation
        b = self._n_bins
        self._sums[:b].index_add_(0, idx, w)
        self._sums[b : b + 4] += scalars
        self._sums[b + 4 :] += shares.sum(0)

    def pop(self) -> dict[str, float]:
        """This interval's columns (``clf/...``; NaN without samples), then start over."""
        return self.row(self.pop_sums())

    def pop_sums(self) -> list[float]:
        """This interval's raw sums (histogram counts, counts, share sums), then start over: the
        sums of several processes add up to the sums of their samples pooled (:meth:`row`)."""
        values = self._sums.tolist()  # the one host read
        self._sums.zero_()
        return values

    def row(self, values: Sequence[float]) -> dict[str, float]:
        """The ``clf/...`` columns of raw sums (:meth:`pop_sums`, or several added up)."""
        b = self._n_bins
        counts = values[:b]
        saturated, valid, samples, positive = values[b : b + 4]
        shares = values[b + 4 :]
        row: dict[str, float] = {}
        qs = quantiles_from_histogram(counts, self._edges, [q for _, q in QUANTILES])
        for (name, _), value in zip(QUANTILES, qs, strict=True):
            row[PREFIX + name] = value
        row[PREFIX + "saturated"] = saturated / samples if samples else math.nan
        row[PREFIX + "dvdt_valid"] = valid / samples if samples else math.nan
        row[PREFIX + "samples"] = samples
        for name, s in zip(self.names, shares, strict=True):
            row[f"{PREFIX}share/{name}"] = s / positive if positive else math.nan
        return row


def columns(output_names: Sequence[str]) -> list[str]:
    """The diagnostic columns, in order, for these outputs."""
    return (
        [PREFIX + name for name, _ in QUANTILES]
        + [PREFIX + "saturated", PREFIX + "dvdt_valid", PREFIX + "samples"]
        + [f"{PREFIX}share/{n}" for n in output_names]
    )
