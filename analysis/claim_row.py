"""One claim row: a statistic, its verdict by :func:`march.stats.judge`, the seeds behind it and
the scale of the runs it came from (``claims.csv`` columns :data:`CLAIM_COLUMNS`).

Shared by the baseline claims (:mod:`analysis.claims`) and the ablation claims
(:mod:`analysis.ablation_claims`), so that neither imports the other.
"""

from __future__ import annotations

from analysis.rundirs import Run
from march.stats import MIN_SEEDS, Estimate, judge

CLAIM_COLUMNS = [
    "claim",
    "paper",
    "measured",
    "ci_low",
    "ci_high",
    "n_seeds",
    "scale",
    "verdict",
    "why",
]


def seeds_text(est: Estimate) -> str:
    """``n_seeds``: the finite values per arm the statistic used (never the runs found)."""
    text = f"{est.n_a} vs {est.n_b}"
    return text if min(est.n_a, est.n_b) >= MIN_SEEDS else f"{text} (fewer than {MIN_SEEDS})"


def claim_row(claim, paper, est: Estimate, scale, claimed, direction, seeds=None) -> dict:
    """A ``claims.csv`` row of ``est`` against ``claimed`` (``direction`` ``le`` / ``ge``)."""
    verdict, why = judge(est, claimed, direction)
    return {
        "claim": claim,
        "paper": paper,
        "measured": est.point,
        "ci_low": est.low,
        "ci_high": est.high,
        "n_seeds": seeds or seeds_text(est),
        "scale": scale,
        "verdict": verdict,
        "why": why,
    }


def scale_text(a: list[Run], b: list[Run], start: int | None = None) -> str:
    """The ``scale`` column: the compute presets and budgets of the runs of both sides."""
    runs = a + b
    computes = sorted({str(r.compute) for r in runs})
    ta = sorted({r.teacher_budget for r in a}, key=str)
    tb = sorted({r.teacher_budget for r in b}, key=str)
    db = sorted({r.distill_budget for r in runs}, key=str)
    text = f"compute={','.join(computes)}; teacher {ta} vs {tb} it; distill {db} it"
    if start is not None:
        text += f"; rows from distill it {start} (500/1500 of the budget)"
    return text
