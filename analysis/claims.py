"""The paper's claims, measured on the runs with a 95% interval across seeds and a verdict.

One row per claim (``claims.csv`` / ``claims.md``; columns :data:`CLAIM_COLUMNS`):

* **sample efficiency** -- the clf teacher reaches the model-free distance with half the
  training: teacher env steps until the seed-mean evaluation distance (eval.csv teacher rows)
  first reaches ``threshold_fraction`` (default 0.9) of the better arm's final seed-mean distance,
  clf / modelfree. Paper: 10k vs 20k iterations, a ratio of 0.5; claimed "<= 0.5".
* **torque** and **angular jerk** after distillation -- "at least 12% / 39% less after 500
  distillation iterations": over the student evaluation rows from distillation iteration
  ``500 / 1500`` of the runs' distillation budget on, the LARGEST relative difference of seed
  means (clf - modelfree) / modelfree over those iterations (the weakest reduction: "at least X%
  at every iteration" <=> it is <= -X). Headline: over successful rollouts only
  (``torque_success`` / ``jerk_success``: gait, not falls); the same over all rollouts follows
  as a secondary row; and, where both arms of a seed wrote ``eval_rollouts.csv``, the paired
  per-cell difference on the cells both arms completed in the final evaluation.
* **ablation** -- the full student ahead of each ablated one: (variant - full) / |full| of the
  final reward per step (the teacher's full reward per control step of a student rollout; the
  return would pay for standing, docs/decisions.md), claimed "< 0".
* **controls** (``+sweep=factorial``): the sample-efficiency, torque and jerk rows again with each
  other group of the reference arm (modelfree on stones at the clf budget, with the reference
  observation) in place of the paper's modelfree, so the CLF reward's own effect can be read.

Intervals (95%, across seeds, :mod:`analysis.stats`): Fieller's interval with Welch's degrees of
freedom for relative differences of means (per iteration for the "every iteration from 500 on"
rows), Student's t for paired per-seed differences, the percentile bootstrap over seeds for the
sample-efficiency ratio; verdicts by :func:`analysis.stats.verdict` (``inconclusive`` with fewer
than 3 seeds per arm).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import pandas as pd

from analysis.groups import GroupKey, primary, series_names
from analysis.rundirs import Run, stage_rows
from analysis.stats import (
    MIN_SEEDS,
    bootstrap,
    fieller_rel,
    mean_interval,
    verdict,
    worst_over_iterations,
)

CLAIM_COLUMNS = ["claim", "paper", "measured", "ci_low", "ci_high", "n_seeds", "scale", "verdict"]
PAPER_DISTILL_ITERATIONS = 1500
PAPER_FROM_ITERATION = 500
PAPER_STEP_RATIO = 0.5  # 10k vs 20k teacher iterations
PAPER_TORQUE = -0.12
PAPER_JERK = -0.39
GAIT = (
    ("torque_success", "|joint torque|, successful rollouts", PAPER_TORQUE),
    ("jerk_success", "|angular jerk|, successful rollouts", PAPER_JERK),
    ("abs_torque_nm", "|joint torque|, all rollouts", PAPER_TORQUE),
    ("abs_ang_jerk", "|angular jerk|, all rollouts", PAPER_JERK),
)
PAIRED = (("torque", "|joint torque|", PAPER_TORQUE), ("jerk", "|angular jerk|", PAPER_JERK))


@dataclass
class ClaimsInput:
    groups: dict[GroupKey, list[Run]]
    arm: str = "clf"
    reference: str = "modelfree"
    full: str = "full"
    ablation_teacher: str = "clf"
    threshold_fraction: float = 0.9


def from_iteration(distill_budget) -> int:
    """The paper's "after 500 distillation iterations" at the runs' budget (500 of 1500)."""
    try:
        budget = int(distill_budget)
    except (TypeError, ValueError):
        return PAPER_FROM_ITERATION
    return math.ceil(PAPER_FROM_ITERATION / PAPER_DISTILL_ITERATIONS * budget)


def _seeds(a: list[Run], b: list[Run]) -> str:
    text = f"{len(a)} vs {len(b)}"
    return text if min(len(a), len(b)) >= MIN_SEEDS else f"{text} (fewer than {MIN_SEEDS})"


def _row(claim, paper, stat, n_a, n_b, scale, claimed, direction, seeds) -> dict:
    point, lo, hi = stat
    return {
        "claim": claim,
        "paper": paper,
        "measured": point,
        "ci_low": lo,
        "ci_high": hi,
        "n_seeds": seeds,
        "scale": scale,
        "verdict": verdict(lo, hi, claimed, direction, n_a, n_b),
    }


def _student_matrix(runs: list[Run], column: str, start: int) -> tuple[np.ndarray, list[int]]:
    """(runs, iterations) of eval.csv student ``column`` from iteration ``start`` on, over the
    iterations every run has; NaN where a run has no value."""
    frames = [stage_rows(r.evals, "student") for r in runs]
    its: set[int] | None = None
    for f in frames:
        got = set() if f is None else {int(i) for i in f["iteration"] if i >= start}
        its = got if its is None else its & got
    grid = sorted(its or ())
    out = np.full((len(runs), len(grid)), np.nan)
    for i, f in enumerate(frames):
        if f is None or column not in f.columns:
            continue
        values = dict(zip(f["iteration"].astype(int), f[column], strict=False))
        out[i] = [values.get(it, np.nan) for it in grid]
    return out, grid


def _teacher_curves(runs: list[Run]) -> tuple[np.ndarray, np.ndarray]:
    """(runs, iterations) teacher evaluation distance on the iterations every run has, and the
    mean env steps at each."""
    frames = [stage_rows(r.evals, "teacher", "mean_distance_m") for r in runs]
    if any(f is None for f in frames):
        return np.empty((len(runs), 0)), np.empty(0)
    its = set.intersection(*({int(i) for i in f["iteration"]} for f in frames))
    grid = sorted(its)
    dist = np.array(
        [
            [
                dict(zip(f["iteration"].astype(int), f["mean_distance_m"], strict=True))[i]
                for i in grid
            ]
            for f in frames
        ]
    )
    steps = np.array(
        [
            [dict(zip(f["iteration"].astype(int), f["env_steps"], strict=True))[i] for i in grid]
            for f in frames
        ]
    )
    return dist.astype(float), steps.mean(axis=0).astype(float)


def steps_to_reach(curves: np.ndarray, steps: np.ndarray, threshold: np.ndarray) -> np.ndarray:
    """(R,) env steps at which each mean curve (R, T) first reaches ``threshold`` (R,); inf
    where it never does."""
    hit = curves >= threshold[:, None]
    first = hit.argmax(axis=1)
    return np.where(hit.any(axis=1), steps[first], np.inf)


def sample_efficiency_stat(steps_a: np.ndarray, steps_b: np.ndarray, fraction: float):
    """The statistic of the sample-efficiency claim for resampled arms A (R, n_a, T_a) and B:
    steps_to_reach(A) / steps_to_reach(B) with the threshold ``fraction`` x the better final
    seed-mean distance of the two (NaN where neither reaches it)."""

    def stat(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        ma, mb = a.mean(axis=1), b.mean(axis=1)
        threshold = fraction * np.maximum(ma[:, -1], mb[:, -1])
        sa = steps_to_reach(ma, steps_a, threshold)
        sb = steps_to_reach(mb, steps_b, threshold)
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = sa / sb
        return np.where(np.isinf(sa) & np.isinf(sb), np.nan, ratio)

    return stat


def _scale(a: list[Run], b: list[Run], start: int | None = None) -> str:
    runs = a + b
    computes = sorted({str(r.compute) for r in runs})
    ta = sorted({r.teacher_budget for r in a}, key=str)
    tb = sorted({r.teacher_budget for r in b}, key=str)
    db = sorted({r.distill_budget for r in runs}, key=str)
    text = f"compute={','.join(computes)}; teacher {ta} vs {tb} it; distill {db} it"
    if start is not None:
        text += f"; rows from distill it {start} (500/1500 of the budget)"
    return text


def _paired_cells(a: list[Run], b: list[Run], metric: str) -> np.ndarray:
    """Per seed both arms ran: (mean over the cells both completed of a - b) / mean of b, from
    the final student evaluation's eval_rollouts.csv rows (the same cells and draws)."""
    by_seed = {r.seed: r for r in b}
    values = []
    for ra in a:
        rb = by_seed.get(ra.seed)
        if rb is None or ra.rollouts is None or rb.rollouts is None:
            continue
        fa, fb = (stage_rows_last(r.rollouts) for r in (ra, rb))
        if fa is None or fb is None:
            continue
        both = fa.merge(fb, on=["rollout", "level", "column"], suffixes=("_a", "_b"))
        both = both[(both["success_a"] == 1) & (both["success_b"] == 1)]
        both = both[both[f"{metric}_a"].notna() & both[f"{metric}_b"].notna()]
        if both.empty:
            continue
        ref = both[f"{metric}_b"].mean()
        values.append((both[f"{metric}_a"].mean() - ref) / abs(ref) if ref else np.nan)
    return np.asarray(values, dtype=float)


def stage_rows_last(rows: pd.DataFrame) -> pd.DataFrame | None:
    """The student rollouts of the last evaluated iteration (the final evaluation)."""
    if rows is None or "stage" not in rows.columns:
        return None
    rows = rows[rows["stage"] == "student"]
    if rows.empty:
        return None
    last = rows["iteration"].max()
    rows = rows[rows["iteration"] == last].drop_duplicates("rollout", keep="last")
    return rows


def _baseline_rows(name: str, a: list[Run], b: list[Run], inp: ClaimsInput) -> list[dict]:
    """The sample-efficiency, gait and paired rows of arm runs ``a`` vs reference runs ``b``
    (stage=all runs: each trained its own teacher, whose eval.csv teacher rows it holds)."""
    rows = []
    ta, tb = a, b
    ca, sa = _teacher_curves(ta)
    cb, sb = _teacher_curves(tb)
    stat = (math.nan, math.nan, math.nan)
    if ca.shape[1] and cb.shape[1]:
        stat = bootstrap(sample_efficiency_stat(sa, sb, inp.threshold_fraction), ca, cb)
    rows.append(
        _row(
            f"{name}: teacher env steps to {inp.threshold_fraction:.0%} of the better final "
            f"distance, {inp.arm} / {inp.reference}",
            f"<= {PAPER_STEP_RATIO} (10k vs 20k it)",
            stat,
            len(ta),
            len(tb),
            _scale(ta, tb),
            PAPER_STEP_RATIO,
            "le",
            _seeds(ta, tb),
        )
    )
    start = from_iteration(next((r.distill_budget for r in a + b), None))
    for column, label, paper in GAIT:
        ma, _ = _student_matrix(a, f"mean_{column}", start)
        mb, _ = _student_matrix(b, f"mean_{column}", start)
        stat = (math.nan, math.nan, math.nan)
        if ma.shape[1] and ma.shape[1] == mb.shape[1]:
            stat = worst_over_iterations(ma, mb)
        rows.append(
            _row(
                f"{name}: {label}, worst (a - b) / b from distill it {start} on",
                f"<= {paper:+.0%}",
                stat,
                len(a),
                len(b),
                _scale(a, b, start),
                paper,
                "le",
                _seeds(a, b),
            )
        )
    for metric, label, paper in PAIRED:
        per_pair = _paired_cells(a, b, metric)
        stat = (math.nan, math.nan, math.nan)
        if per_pair.size:
            stat = mean_interval(per_pair)
        rows.append(
            _row(
                f"{name}: {label}, paired cells both arms completed (final evaluation)",
                f"<= {paper:+.0%}",
                stat,
                per_pair.size,
                per_pair.size,
                _scale(a, b) + "; per seed pair",
                paper,
                "le",
                f"{per_pair.size} seed pairs"
                + ("" if per_pair.size >= MIN_SEEDS else f" (fewer than {MIN_SEEDS})"),
            )
        )
    return rows


def _final(runs: list[Run], column: str) -> np.ndarray:
    out = []
    for r in runs:
        f = stage_rows(r.evals, "student", column)
        out.append(float(f[column].iloc[-1]) if f is not None else np.nan)
    return np.asarray(out, dtype=float)


def claims(inp: ClaimsInput, notes: list[str]) -> pd.DataFrame:
    """Every claim row the groups allow (module docstring); what is missing goes to ``notes``."""
    keys = [k for k in inp.groups if k.variant == inp.full and k.stage == "all"]
    rows: list[dict] = []
    ka, kb = primary(keys, inp.arm), primary(keys, inp.reference)
    names = series_names(keys, "reward")
    if ka is None or kb is None:
        notes.append(
            f"claims: no single {inp.arm} and {inp.reference} group of {inp.full} students "
            f"(groups: {', '.join(names.values()) or 'none'}); baseline claims not measured"
        )
    else:
        a, b = inp.groups[ka], inp.groups[kb]
        rows += _baseline_rows("baseline", a, b, inp)
        for kc in keys:
            if kc.reward == inp.reference and kc != kb:
                control = _baseline_rows(
                    f"control {inp.arm} vs {names[kc]}", a, inp.groups[kc], inp
                )
                for r in control:
                    r["paper"] = f"(control) {r['paper']}"
                rows += [r for r in control if "paired" not in r["claim"]]
    rows += _ablation_rows(inp, notes)
    return pd.DataFrame(rows, columns=CLAIM_COLUMNS)


def _ablation_rows(inp: ClaimsInput, notes: list[str]) -> list[dict]:
    rows = []
    teacher = [k for k in inp.groups if k.reward == inp.ablation_teacher]
    for kv in teacher:
        if kv.variant == inp.full:
            continue
        kf = next((k for k in teacher if k.variant == inp.full and _same_but_variant(k, kv)), None)
        if kf is None:
            notes.append(f"claims: ablation {kv.variant} has no {inp.full} group to compare with")
            continue
        column = "mean_reward_per_step"
        fv, ff = _final(inp.groups[kv], column), _final(inp.groups[kf], column)
        v = [r for r, x in zip(inp.groups[kv], fv, strict=True) if np.isfinite(x)]
        f = [r for r, x in zip(inp.groups[kf], ff, strict=True) if np.isfinite(x)]
        fv, ff = fv[np.isfinite(fv)], ff[np.isfinite(ff)]
        if not v or not f:
            notes.append(f"claims: ablation {kv.variant} (stage {kv.stage}): no {column} rows")
            continue
        stat = fieller_rel(fv, ff)
        rows.append(
            _row(
                f"ablation: {inp.full} ahead of {kv.variant}: reward per step, "
                f"({kv.variant} - {inp.full}) / |{inp.full}|, final evaluation"
                + (f" (stage {kv.stage})" if kv.stage != "student" else ""),
                "< 0 (full ahead)",
                stat,
                len(v),
                len(f),
                _scale(v, f),
                0.0,
                "le",
                _seeds(v, f),
            )
        )
    return rows


def _same_but_variant(a: GroupKey, b: GroupKey) -> bool:
    return replace(a, variant="") == replace(b, variant="")


def _pct(x) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "n/a"
    if isinstance(x, float) and math.isinf(x):
        return "not reached"
    return f"{x:+.1%}"


def claims_markdown(table: pd.DataFrame) -> str:
    """claims.md: the table (relative values in percent, ratios as numbers) and how to read it."""
    lines = [
        "# The paper's claims, measured",
        "",
        "Each row: the paper's figure, march's value with a 95% interval across seeds (relative "
        "differences of means: Fieller's interval with Welch's degrees of freedom, per iteration "
        "for the 'from iteration 500 on' rows, combined as [max low, max high]; paired rows: "
        "Student's t over seed pairs; the sample-efficiency ratio: percentile bootstrap over "
        "seeds, 10,000 resamples), the seeds behind it and the scale of the runs. Verdict: `reproduced` when the whole interval satisfies the claim, "
        "`not reproduced` when the whole interval violates it, `inconclusive` otherwise or with "
        f"fewer than {MIN_SEEDS} seeds per arm (a smoke-scale run measures plumbing, not the "
        "paper).",
        "",
        "| claim | paper | measured | 95% CI | n seeds | scale | verdict |",
        "|---|---|---|---|---|---|---|",
    ]

    def cell(text) -> str:
        return str(text).replace("|", "\\|")

    for _, r in table.iterrows():
        ratio = "env steps" in r["claim"]
        show = (lambda x: "n/a" if pd.isna(x) else f"{x:.3g}") if ratio else _pct
        lines.append(
            f"| {cell(r['claim'])} | {cell(r['paper'])} | {show(r['measured'])} | "
            f"[{show(r['ci_low'])}, {show(r['ci_high'])}] | {r['n_seeds']} | {r['scale']} | "
            f"**{r['verdict']}** |"
        )
    return "\n".join(lines) + "\n"
