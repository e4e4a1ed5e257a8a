"""The ablation claim: the full student ahead of each ablated one, by three metrics.

The paper scores its ablation by the teacher's reward on student rollouts. march reports that
metric first, per control step (``reward_per_step``: the return grows with episode length, and
under the goal termination a rollout that stands until the time-out collects more of it than one
that crosses), then two task metrics beside it that standing still cannot win: the distance
travelled and the success rate. Each row names its metric and has its own verdict, because the
teacher's reward still credits a standing robot (r_clf >= e^-1 x w_clf, full holonomic terms):
measured at smoke scale, a zero action scored 0.210 per step against trained students' 0.192
and 0.178 (issue 49). A "reproduced" by the paper's metric with the task metrics inconclusive or
against it is a student that learned to stand.

Per variant: ``(variant - full) / |full|`` of the seed means of the final student evaluation
(the last eval.csv student row), Fieller's interval across seeds, claimed "< 0" for the reward
and "> 0" reversed for none: every metric here is better when larger, so each row is
``(variant - full) / |full| <= 0``. Groups are compared only when they differ in ``student.*``
and nothing else (:func:`analysis.groups.unlike`, the one like-for-like rule); the others are
listed once as not compared.
"""

from __future__ import annotations

import numpy as np

from analysis.claim_row import claim_row, scale_text
from analysis.groups import GroupKey, not_compared, series_names, unlike
from analysis.rundirs import Run, stage_rows
from march.stats import rel_estimate

ABLATION_METRICS = (
    ("reward_per_step", "the paper's metric: teacher's reward per step on student rollouts"),
    ("distance_m", "task metric: distance traveled"),
    ("success_rate", "task metric: success rate"),
)


def final_values(runs: list[Run], column: str) -> np.ndarray:
    """Per run, ``column`` of its last eval.csv student row (NaN where it has none)."""
    out = []
    for r in runs:
        f = stage_rows(r.evals, "student", column)
        out.append(float(f[column].iloc[-1]) if f is not None else np.nan)
    return np.asarray(out, dtype=float)


def ablation_rows(inp, notes: list[str]) -> list[dict]:
    """Rows for each variant group of the ablation teacher against the ``full`` group that
    differs from it in ``student.*`` only; refusals go to ``inp.refused``."""
    rows = []
    teacher = [k for k in inp.groups if k.reward == inp.ablation_teacher]
    names = series_names(teacher, "variant", inp.conf_dir)
    fulls = [k for k in teacher if k.variant == inp.full]
    for kv in teacher:
        if kv.variant == inp.full:
            continue
        kf = _reference(kv, fulls, inp)
        if kf is None:
            near = min(
                (unlike(k, kv, "variant", inp.conf_dir) for k in fulls), key=len, default=None
            )
            why = not_compared(near) if near else f"not compared: no {inp.full} group"
            inp.refused.append(
                f"ablation {names[kv]}: {why}; only student.* may differ from the {inp.full} "
                "student of the same teacher"
            )
            inp.listed.add(kv)
            notes.append(f"claims: ablation {names[kv]} has no {inp.full} group to compare with")
            continue
        v, f = inp.groups[kv], inp.groups[kf]
        inp.used |= {kv, kf}
        stage = f" (stage {kv.stage})" if kv.stage != "student" else ""
        for column, label in ABLATION_METRICS:
            est = rel_estimate(final_values(v, f"mean_{column}"), final_values(f, f"mean_{column}"))
            rows.append(
                claim_row(
                    f"ablation: {inp.full} ahead of {names[kv]} by {label}, "
                    f"({kv.variant} - {inp.full}) / |{inp.full}|, final evaluation{stage}",
                    "< 0 (full ahead)",
                    est,
                    scale_text(v, f),
                    0.0,
                    "le",
                )
            )
    return rows


def _reference(kv: GroupKey, fulls: list[GroupKey], inp) -> GroupKey | None:
    same = [k for k in fulls if not unlike(k, kv, "variant", inp.conf_dir)]
    return same[0] if same else None
