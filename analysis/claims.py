"""The paper's claims, measured on the runs with a 95% interval across seeds and a verdict.

One row per claim (``claims.csv`` / ``claims.md``; columns :data:`CLAIM_COLUMNS`):

* **sample efficiency** -- the clf teacher reaches the model-free distance with half the
  training: per seed, the teacher env steps until its evaluation distance (eval.csv teacher rows)
  first reaches ``threshold_fraction`` (default 0.9) of the better arm's final seed-mean
  distance; the ratio of the arms' mean step counts, clf / modelfree. Each crossing is known
  only to the evaluation grid (between the last evaluation below the target and the first at
  it; before the first evaluation for a seed already past it; after the last for one that never
  reaches it), and the interval covers every value inside those bounds
  (:func:`march.stats.censored_ratio_estimate`): the data give the verdict, never the grid,
  which the claim names. Paper: 10k vs 20k iterations, a ratio of 0.5; claimed "<= 0.5".
* **torque** and **angular jerk** after distillation -- "at least 12% / 39% less after 500
  distillation iterations": over the student evaluation rows from distillation iteration
  ``500 / 1500`` of the runs' distillation budget on, the LARGEST relative difference of seed
  means (clf - modelfree) / modelfree over those iterations (the weakest reduction: "at least X%
  at every iteration" <=> it is <= -X), with a simultaneous interval
  (:func:`march.stats.worst_over_iterations`). Headline: over successful rollouts only
  (``torque_success`` / ``jerk_success``: gait, not falls); the same over all rollouts follows
  as a secondary row; and, where both arms of a seed wrote ``eval_rollouts.csv``, the paired
  per-cell difference on the cells both arms completed in the final evaluation.
* **ablation** -- the full student ahead of each ablated one, by the paper's metric and two task
  metrics beside it (:mod:`analysis.ablation_claims`).
* **controls** (``+sweep=factorial``): the sample-efficiency, torque and jerk rows again with each
  other group of the reference arm (modelfree on stones at the clf budget, with the reference
  observation) in place of the paper's modelfree, so the CLF reward's own effect can be read.

Which groups are compared (:mod:`analysis.groups`): two groups only when they differ in the
compared arms' own fields (what ``conf/experiment/<arm>.yaml`` chooses) and nothing else
(:func:`analysis.groups.unlike`, the rule every output shares); the paper's arm is the arm's
config as a whole (:func:`analysis.groups.variant_of_arm`: a reward term beyond it makes a
variant); every pair refused, and every group that is not the paper's arm, is listed once with
the reason in ``claims.md`` ("Not compared").

The distances behind these claims (the sample-efficiency target, the ablation's distance row)
are read against each compared group's standing floor, the zero action's distance on the same
rollouts: ``claims.md`` lists it per group ("Standing floor"), on the teacher evaluations and the
final student evaluation, or says the runs have none (from before the floor existed).

Every verdict counts the finite per-seed values it was computed from, per arm (and per iteration
for the "every iteration" rows): ``n_seeds`` reports them; fewer than 3 on either side is
``inconclusive`` with the reason in ``why`` (:func:`march.stats.judge`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pandas as pd

from analysis.ablation_claims import ablation_rows
from analysis.aggregate import NO_FLOOR, combine_floors, run_floor
from analysis.claim_row import CLAIM_COLUMNS, claim_row, scale_text
from analysis.groups import (
    CONF_DIR,
    GroupKey,
    not_compared,
    series_names,
    shorten,
    unlike,
    variant_of_arm,
)
from analysis.rundirs import Run, stage_rows
from march.stats import (
    MIN_SEEDS,
    Estimate,
    censored_ratio_estimate,
    mean_ci,
    worst_over_iterations,
)

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
    conf_dir: Path = CONF_DIR
    refused: list[str] = field(default_factory=list)  # what was not compared, and why
    used: set = field(default_factory=set)  # the groups some claim row compared
    listed: set = field(default_factory=set)  # the groups a line of ``refused`` names
    floors: list[str] = field(default_factory=list)  # the compared groups' standing floors
    floor_warnings: list[str] = field(default_factory=list)  # distance targets at the floor


def from_iteration(distill_budget) -> int:
    """The paper's "after 500 distillation iterations" at the runs' budget (500 of 1500)."""
    try:
        budget = int(distill_budget)
    except (TypeError, ValueError):
        return PAPER_FROM_ITERATION
    return math.ceil(PAPER_FROM_ITERATION / PAPER_DISTILL_ITERATIONS * budget)


def _student_matrix(runs: list[Run], column: str, grid: list[int]) -> np.ndarray:
    """(runs, iterations of ``grid``) of eval.csv student ``column``; NaN where a run has no
    value (a metric undefined at that evaluation: no successful rollout)."""
    out = np.full((len(runs), len(grid)), np.nan)
    for i, r in enumerate(runs):
        f = stage_rows(r.evals, "student")
        if f is None or column not in f.columns:
            continue
        values = dict(zip(f["iteration"].astype(int), f[column], strict=False))
        out[i] = [values.get(it, np.nan) for it in grid]
    return out


def student_grid(runs: list[Run], start: int) -> list[int]:
    """The student evaluation iterations from ``start`` on that every one of ``runs`` has."""
    its: set[int] | None = None
    for r in runs:
        f = stage_rows(r.evals, "student")
        got = set() if f is None else {int(i) for i in f["iteration"] if i >= start}
        its = got if its is None else its & got
    return sorted(its or ())


def teacher_curve(run: Run) -> tuple[np.ndarray, np.ndarray] | None:
    """(env steps, evaluation distance) of a run's eval.csv teacher rows, or None."""
    f = stage_rows(run.evals, "teacher", "mean_distance_m")
    if f is None:
        return None
    return f["env_steps"].to_numpy(dtype=float), f["mean_distance_m"].to_numpy(dtype=float)


def steps_to_target(a: list[Run], b: list[Run], fraction: float) -> tuple[Estimate, float, str]:
    """The sample-efficiency statistic: per seed, the env steps at which its teacher's
    evaluation distance first reaches ``fraction`` x the better arm's final seed-mean distance,
    and the ratio of the arms' mean step counts (a / b). Returns the estimate, the target [m]
    and a note naming the evaluation grid and the censored seeds.

    The evaluations see a crossing only on their grid: a seed first at or above the target at
    the evaluation at step s_k (the one before it, s_{k-1}, below) crossed it somewhere in
    (s_{k-1}, s_k]; one already past it at its first evaluation, in (0, s_0] (an upper bound,
    not a point); one that never reaches it, after its last evaluated step (a lower bound).
    The interval is :func:`march.stats.censored_ratio_estimate` over those intervals, so a
    verdict comes only when the data decide wherever in its interval each crossing lies, never
    from the grid (every seed past the target at its first evaluation: no verdict)."""
    ca = [c for c in (teacher_curve(r) for r in a) if c is not None]
    cb = [c for c in (teacher_curve(r) for r in b) if c is not None]
    finals = [
        float(np.mean(x))
        for x in ([c[1][-1] for c in ca], [c[1][-1] for c in cb])
        if len(x) and np.isfinite(x).all()
    ]
    if len(finals) < 2:
        return Estimate.none("no eval.csv teacher rows", len(ca), len(cb)), math.nan, ""
    target = fraction * max(finals)

    def reach(curves) -> tuple[np.ndarray, np.ndarray, int, int]:
        low, high, first, never = [], [], 0, 0
        for steps, dist in curves:
            hit = np.nonzero(dist >= target)[0]
            if hit.size == 0:
                never += 1
                low.append(steps[-1])
                high.append(math.inf)
            elif hit[0] == 0:
                first += 1
                low.append(0.0)
                high.append(steps[0])
            else:
                low.append(steps[hit[0] - 1])
                high.append(steps[hit[0]])
        return np.asarray(low, float), np.asarray(high, float), first, never

    (la, ha, fa, na), (lb, hb, fb, nb) = reach(ca), reach(cb)
    est = censored_ratio_estimate(la, ha, lb, hb)
    why = []
    for n, arm in ((fa, "arm"), (fb, "reference")):
        if n:
            why.append(f"{n} seed(s) of the {arm} past the target at the first evaluation")
    for n, arm in ((na, "arm"), (nb, "reference")):
        if n:
            why.append(f"{n} seed(s) of the {arm} never reach it (a lower bound)")
    note = f"crossings known to the evaluation grid: {grid_text(ca)} vs {grid_text(cb)}"
    note += "".join(f"; {w}" for w in why)
    return replace(est, why="; ".join(filter(None, [est.why, *why]))), target, note


def grid_text(curves) -> str:
    """The teacher evaluation grid of one arm's seeds: where the first evaluation is and how
    far apart they are, in env steps (e.g. ``first at 98.3k, every 983k env steps``)."""
    firsts = sorted({float(s[0]) for s, _ in curves})
    gaps = sorted({float(g) for s, _ in curves for g in np.diff(s)})
    first = "/".join(_steps(x) for x in firsts) or "none"
    if not gaps:
        return f"one evaluation at {first} env steps"
    every = _steps(gaps[0]) if len(gaps) == 1 else f"{_steps(gaps[0])}-{_steps(gaps[-1])}"
    return f"first at {first}, every {every} env steps"


def _steps(x: float) -> str:
    for div, unit in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(x) >= div:
            return f"{x / div:.3g}{unit}"
    return f"{x:.0f}"


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
    est, target, grid = steps_to_target(a, b, inp.threshold_fraction)
    where = f" ({target:.3g} m)" if np.isfinite(target) else ""
    floors = [
        combine_floors([run_floor(stage_rows(r.evals, "teacher")) for r in g]) for g in (a, b)
    ]
    top = max((f.distance_m for f in floors if f is not None), default=math.nan)
    if np.isfinite(target) and top >= target:  # claims.md's floor section says so
        inp.floor_warnings.append(
            f"{name}: the sample-efficiency target {target:.3g} m is at or below a compared "
            f"arm's standing floor ({top:.3g} m on the teacher evaluations): reaching it is "
            "no progress"
        )
    grid = grid.split("; ")[0] if grid else "no evaluation grid"
    rows = [
        claim_row(
            f"{name}: teacher env steps to {inp.threshold_fraction:.0%} of the better final "
            f"distance{where}, mean over seeds, {inp.arm} / {inp.reference} ({grid})",
            f"<= {PAPER_STEP_RATIO} (10k vs 20k it)",
            est,
            scale_text(a, b),
            PAPER_STEP_RATIO,
            "le",
        )
    ]
    start = from_iteration(next((r.distill_budget for r in a + b), None))
    grid = student_grid(a + b, start)
    for column, label, paper in GAIT:
        ma = _student_matrix(a, f"mean_{column}", grid)
        mb = _student_matrix(b, f"mean_{column}", grid)
        rows.append(
            claim_row(
                f"{name}: {label}, worst (a - b) / b from distill it {start} on "
                f"({len(grid)} evaluations, simultaneous)",
                f"<= {paper:+.0%}",
                worst_over_iterations(ma, mb, names=grid),
                scale_text(a, b, start),
                paper,
                "le",
            )
        )
    for metric, label, paper in PAIRED:
        per_pair = _paired_cells(a, b, metric)
        n = int(np.isfinite(per_pair).sum())
        point, lo, hi = mean_ci(per_pair) if n else (math.nan,) * 3
        rows.append(
            claim_row(
                f"{name}: {label}, paired cells both arms completed (final evaluation)",
                f"<= {paper:+.0%}",
                Estimate(
                    point, lo, hi, n, n, "" if n else "no seed pair with a cell both arms completed"
                ),
                scale_text(a, b) + "; per seed pair",
                paper,
                "le",
                f"{n} seed pairs" + ("" if n >= MIN_SEEDS else f" (fewer than {MIN_SEEDS})"),
            )
        )
    return rows


def claims(inp: ClaimsInput, notes: list[str]) -> pd.DataFrame:
    """Every claim row the groups allow (module docstring); what is missing goes to ``notes``,
    what was not compared and why to ``inp.refused`` (each group listed once: ``inp.listed``)."""
    keys = [k for k in inp.groups if k.variant == inp.full and k.stage == "all"]
    names = series_names(keys, "reward", inp.conf_dir)
    arm_keys = [k for k in keys if k.reward == inp.arm]
    ref_keys = [k for k in keys if k.reward == inp.reference]
    paper_arm = [k for k in arm_keys if not variant_of_arm(k, inp.conf_dir)]
    paper_ref = [k for k in ref_keys if not variant_of_arm(k, inp.conf_dir)]
    for k in arm_keys:
        if k not in paper_arm:
            inp.refused.append(
                f"{names[k]} ({len(inp.groups[k])} seeds): not the paper's {inp.arm} arm, a "
                f"variant ({shorten(variant_of_arm(k, inp.conf_dir))}); a separate series"
            )
            inp.listed.add(k)
    rows: list[dict] = []
    pairs = []
    for ka in paper_arm:
        for kb in paper_ref:
            bad = unlike(ka, kb, "reward", inp.conf_dir)
            if bad:
                inp.refused.append(
                    f"{names[ka]} vs {names[kb]}: {not_compared(bad)}; only the arms' own "
                    "fields (conf/experiment/<arm>.yaml) may differ"
                )
                inp.listed |= {ka, kb}
            else:
                pairs.append((ka, kb))
    if not pairs:
        notes.append(
            f"claims: no {inp.arm} and {inp.reference} groups of {inp.full} students that differ "
            f"only in the arms' own fields (groups: {', '.join(names.values()) or 'none'}); "
            "baseline claims not measured"
        )
    for ka, kb in pairs:
        label = "baseline" if len(pairs) == 1 else f"baseline {names[ka]} vs {names[kb]}"
        rows += _baseline_rows(label, inp.groups[ka], inp.groups[kb], inp)
        inp.used |= {ka, kb}
        for kc in ref_keys:
            if kc in paper_ref:
                continue
            bad = unlike(ka, kc, "reward", inp.conf_dir)
            if bad:
                inp.refused.append(f"control {names[ka]} vs {names[kc]}: {not_compared(bad)}")
                inp.listed.add(kc)
                continue
            control = _baseline_rows(
                f"control {names[ka]} vs {names[kc]}", inp.groups[ka], inp.groups[kc], inp
            )
            for r in control:
                r["paper"] = f"(control) {r['paper']}"
            rows += [r for r in control if "paired" not in r["claim"]]
            inp.used.add(kc)
    rows += ablation_rows(inp, notes)
    _unused(inp)
    inp.floors = floor_lines(inp) + inp.floor_warnings
    return pd.DataFrame(rows, columns=CLAIM_COLUMNS)


def floor_lines(inp: ClaimsInput) -> list[str]:
    """Per group a claim compared: its standing floor on the teacher evaluations (eval.csv
    teacher rows) and on the final student evaluation (summary.json), mean over its runs, or
    that it has none; one line saying there is none when no such group has one (runs from
    before the floor)."""
    used = [k for k in inp.groups if k in inp.used]
    arms = list(dict.fromkeys(k.arm_part() for k in used))  # named as final_metrics names them
    names = series_names(arms, "reward", inp.conf_dir) if used else {}
    lines, older = [], []
    for k in used:
        runs = inp.groups[k]
        parts = []
        for where, per_run in (
            ("teacher evaluations", [run_floor(stage_rows(r.evals, "teacher")) for r in runs]),
            ("final student evaluation", [run_floor(r.summary) for r in runs]),
        ):
            floor = combine_floors(per_run)
            if floor is not None:
                parts.append(f"{where}: {floor.text()}")
        if parts:
            lines.append(f"{names[k.arm_part()]} / {k.variant}: " + "; ".join(parts))
        else:
            name = f"{names[k.arm_part()]} / {k.variant}"
            older.append(f"{name}: no standing floor (from before the floor)")
    return lines + older if lines else ([NO_FLOOR] if used else [])


def _unused(inp: ClaimsInput) -> None:
    """Name every group no claim compared and no line above lists, with why (once each)."""
    rest = [k for k in inp.groups if k not in inp.used and k not in inp.listed]
    names = series_names(rest, "reward", inp.conf_dir) if rest else {}
    for k in rest:
        if k.reward not in (inp.arm, inp.reference, inp.ablation_teacher):
            why = f"reward {k.reward} is neither {inp.arm}, {inp.reference} nor the ablation's"
        elif k.variant != inp.full and k.reward != inp.ablation_teacher:
            why = f"student {k.variant} of reward {k.reward}: no claim compares it"
        elif k.stage == "all":
            why = "no comparable group to pair it with"
        else:
            why = f"stage {k.stage} {k.variant} student: no comparable group"
        inp.refused.append(f"{names[k]} ({len(inp.groups[k])} seeds): not compared: {why}")
        inp.listed.add(k)


def _pct(x) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "n/a"
    if isinstance(x, float) and math.isinf(x):
        return "not reached"
    return f"{x:+.1%}"


def claims_markdown(table: pd.DataFrame, refused: list[str] = (), floors: list[str] = ()) -> str:
    """claims.md: the table (relative values in percent, ratios as numbers), how to read it, the
    compared groups' standing floors, and what was not compared and why."""
    lines = [
        "# The paper's claims, measured",
        "",
        "Each row: the paper's figure, march's value with a 95% interval across seeds, the seeds "
        "behind it (finite values per arm: a seed whose metric is undefined, e.g. no successful "
        "rollout, does not count) and the scale of the runs. Intervals: relative differences "
        "of means, Fieller's interval with Welch's degrees of freedom; the 'worst from "
        "iteration 500 on' rows, a simultaneous interval for the largest difference over the "
        "evaluations (upper end: the largest per-iteration upper end; lower end: the largest "
        "Bonferroni-corrected lower end); the sample-efficiency ratio, Fieller's interval for "
        "the ratio of the arms' mean step counts over every value the evaluation grid leaves "
        "each seed's crossing (a seed past the target at its first evaluation is only bounded "
        "above: the grid is named beside the ratio); paired rows, Student's t over seed pairs. "
        "Verdict: `reproduced` when the whole interval satisfies the claim, `not reproduced` "
        "when the whole interval violates it, `inconclusive` otherwise, with fewer than "
        f"{MIN_SEEDS} seeds with a value per arm, or with no interval (column 'why'); a "
        "smoke-scale run measures plumbing, not the paper. Two groups are compared only when "
        "they differ in the compared arms' own fields and nothing else, in every output.",
        "",
        "| claim | paper | measured | 95% CI | n seeds | scale | verdict | why |",
        "|---|---|---|---|---|---|---|---|",
    ]

    def cell(text) -> str:
        return str(text).replace("|", "\\|")

    for _, r in table.iterrows():
        ratio = "env steps" in r["claim"]
        show = (lambda x: "n/a" if pd.isna(x) else f"{x:.3g}") if ratio else _pct
        lines.append(
            f"| {cell(r['claim'])} | {cell(r['paper'])} | {show(r['measured'])} | "
            f"[{show(r['ci_low'])}, {show(r['ci_high'])}] | {r['n_seeds']} | {cell(r['scale'])} | "
            f"**{r['verdict']}** | {cell(r['why'])} |"
        )
    if floors:
        lines += [
            "",
            "## Standing floor",
            "",
            "The zero action's distance on the same rollouts as each compared group's "
            "evaluations (mean over its runs ± rollout SE): a distance, or a distance target, at "
            "or below it is no progress.",
            "",
        ]
        lines += [f"- {cell(line)}" for line in floors]
    lines += ["", "## Not compared", ""]
    lines += [f"- {cell(line)}" for line in refused] or ["- (every group found was compared)"]
    return "\n".join(lines) + "\n"
