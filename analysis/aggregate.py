"""Turn runs' rows into the curves and tables the figures show.

Which rows feed what:

* baseline -- ``eval.csv`` rows ``stage == "student"`` of runs with the reference student variant
  (``full``), grouped by reward arm (every arm found; the compared pairs default to clf vs
  modelfree), per distillation iteration.
* sample efficiency -- ``eval.csv`` rows ``stage == "teacher"`` (each teacher evaluated on the fixed
  stone evaluation set every ``teacher.eval_interval`` iterations), grouped by reward, per teacher
  iteration.
* ablation -- ``eval.csv`` rows ``stage == "student"`` of the ablation teacher's runs (clf),
  grouped by student variant.
* teacher training diagnostic -- ``metrics.csv`` rows ``stage == "teacher"`` (training rollouts,
  each arm on its own curriculum: not a like-for-like comparison, never used for one).
* final metrics -- ``summary.json`` of complete runs (the final evaluation of the student, the
  same numbers as the run's last ``eval.csv`` student row).

The standing floor (:class:`Floor`): every evaluation row written since issue 56 also carries
the zero action's distance on the same rollouts (``floor_distance_m``, ``floor_se_distance_m``);
each series' floor is the mean of its runs' floors, drawn and printed beside its distances.
Rows from before the floor have none: the outputs say so instead of drawing one.

Several seeds combine per iteration with :func:`combine` (``--se-mode``). Relative differences
follow the paper's convention for the chosen pairs (analysis.arms.Comparisons): (A - B) / B for an
arm pair A:B (default clf:modelfree), (variant - full) / full for the ablation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from analysis.arms import Comparisons
from analysis.groups import (
    GroupKey,
    like_for_like,
    not_compared,
    primary,
    series_names,
    unlike,
)
from analysis.rundirs import Run, eval_rows, stage_rows

# metric key in eval.csv / summary.json (mean_<key>, se_<key>) -> short name, axis label
METRICS = {
    "distance_m": ("distance", "distance traveled [m]"),
    "success_rate": ("success", "success rate"),
    "abs_torque_nm": ("torque", "mean |joint torque| [Nm]"),
    "abs_ang_jerk": ("jerk", "mean |angular jerk| [rad/s^3]"),
    "reward": ("return", "episode return (teacher's full reward)"),
    "reward_per_step": (
        "reward/step",
        "teacher's reward per step\n(the paper's ablation metric)",
    ),
    "torque_success": ("torque (success)", "|joint torque|, successful rollouts [Nm]"),
    "jerk_success": ("jerk (success)", "|angular jerk|, successful rollouts [rad/s^3]"),
}
OWN_REWARD_METRICS = ("reward", "reward_per_step")  # under each arm's own reward set
COUNT_KEYS = ("n_torque", "n_jerk")  # rollouts long enough for the torque / jerk means
TEACHER_PANELS = [
    ("mean_reward", "mean reward per step"),
    ("mean_episode_length", "mean episode length [steps]"),
    ("mean_distance_m", "mean distance [m]"),
]


FLOOR = "floor_distance_m"  # eval.csv / summary.json: the zero action's distance [m]
FLOOR_SE = "floor_se_distance_m"  # its standard error over the rollouts [m]
NO_FLOOR = "no standing floor in these runs (eval.csv / summary.json from before the floor)"


@dataclass(frozen=True)
class Floor:
    """A series' standing floor: the zero action's distance on the same rollouts as its policies
    (march.evaluation.protocol.standing_floor), the mean over its runs' floors."""

    distance_m: float  # mean over runs of each run's floor [m]
    se_m: float  # rollout SE of that mean, sqrt(sum se_i^2) / n [m] (NaN: none recorded)
    n_runs: int  # runs with a floor
    n_rollouts: int  # rollouts behind it, summed over those runs (0: not recorded)

    def text(self) -> str:
        """``standing floor 0.036 ± 0.008 m (zero action, 2 runs, 32 rollouts)``."""
        se = "" if math.isnan(self.se_m) else f" ± {self.se_m:.2g}"
        runs = f"{self.n_runs} run{'s' * (self.n_runs != 1)}"
        rolls = f", {self.n_rollouts} rollouts" if self.n_rollouts else ""
        return f"standing floor {self.distance_m:.3g}{se} m (zero action, {runs}{rolls})"


def run_floor(rows: pd.DataFrame | dict | None) -> tuple[float, float, int] | None:
    """One run's floor (distance, SE, rollouts) from its eval rows of one stage (the mean over
    the rows: one value per eval env, so the same in every row) or its summary.json; None when
    it has none (written before the floor existed)."""
    if rows is None:
        return None
    if isinstance(rows, dict):  # summary.json
        d = rows.get(FLOOR)
        if d is None or pd.isna(d):
            return None
        se = rows.get(FLOOR_SE)
        return float(d), math.nan if se is None else float(se), int(rows.get("n_rollouts") or 0)
    if FLOOR not in rows.columns:
        return None
    rows = rows[rows[FLOOR].notna()]
    if rows.empty:
        return None
    se = rows[FLOOR_SE].mean() if FLOOR_SE in rows.columns else math.nan
    n = int(rows["n_rollouts"].iloc[-1]) if "n_rollouts" in rows.columns else 0
    return float(rows[FLOOR].mean()), float(se), n


def combine_floors(per_run: list[tuple[float, float, int] | None]) -> Floor | None:
    """The floor of a series from its runs' (:func:`run_floor`); None when no run has one. The
    SE is the rollout SE of the mean (pooled): a floor is a property of the courses, not of a
    training seed."""
    got = [f for f in per_run if f is not None]
    if not got:
        return None
    mean, se, n = combine([f[0] for f in got], [f[1] for f in got], "pooled")
    return Floor(mean, se, n, sum(f[2] for f in got))


@dataclass
class Curves:
    """Aggregated curves per series (a reward or a variant) and the series that have none."""

    series: dict[str, pd.DataFrame] = field(default_factory=dict)
    missing: dict[str, str] = field(default_factory=dict)  # series -> why it has no curve
    refused: dict[str, str] = field(default_factory=dict)  # series -> "not compared (...)"
    floors: dict[str, Floor] = field(default_factory=dict)  # series -> its standing floor

    def __bool__(self) -> bool:
        return bool(self.series)


# --------------------------------------------------------------------------- statistics


def combine(means, ses=None, mode: str = "seeds") -> tuple[float, float, int]:
    """Combine per-run (mean, se) into (mean, se, n).

    ``seeds``: mean of the run means; SE across runs std(ddof=1)/sqrt(n); a single run has no
    SE across seeds (NaN: drawn without a bar, labelled n=1; never its rollout SE, another
    unit). ``pooled``: SE of the mean of independent run means, sqrt(sum se_i^2)/n.
    Runs whose mean is NaN are left out.
    """
    m = np.asarray(means, dtype=float)
    s = np.full_like(m, np.nan) if ses is None else np.asarray(ses, dtype=float)
    ok = ~np.isnan(m)
    m, s = m[ok], s[ok]
    n = int(m.size)
    if n == 0:
        return math.nan, math.nan, 0
    mean = float(m.mean())
    if mode == "pooled":
        se = float(np.sqrt(np.nansum(s**2)) / n) if not np.isnan(s).all() else math.nan
    elif n >= 2:
        se = float(m.std(ddof=1) / math.sqrt(n))
    else:
        se = math.nan
    return mean, se, n


def smooth(values: pd.Series, window: int) -> pd.Series:
    """Trailing moving average over ``window`` rows (fewer at the start)."""
    return values.rolling(max(1, int(window)), min_periods=1).mean()


def rel_diff(value: float, reference: float) -> float:
    """(value - reference) / |reference|; NaN when either is missing or the reference is 0."""
    if value is None or reference is None:
        return math.nan
    value, reference = float(value), float(reference)
    if math.isnan(value) or math.isnan(reference) or reference == 0:
        return math.nan
    return (value - reference) / abs(reference)


def format_rel(rel: float) -> str:
    """Relative difference as a whole percent with sign: -0.12 -> '-12%'."""
    if rel is None or math.isnan(rel):
        return "n/a"
    return f"{int(round(rel * 100)):+d}%"


def _ordered(keys, order):
    return sorted(keys, key=lambda k: (order.index(k) if k in order else len(order), str(k)))


# --------------------------------------------------------------------------- evaluation curves


def aggregate_eval(frames: list[pd.DataFrame], mode: str) -> pd.DataFrame:
    """Per iteration over several runs' eval rows: n (runs), env_steps, n_rollouts, and
    mean_/se_/n_ of every metric in METRICS (NaN where no run has the column: older files)."""
    cat = pd.concat(frames, ignore_index=True)
    records = []
    for it, rows in cat.groupby("iteration"):
        rec = {"iteration": it, "n": len(rows)}
        rec["env_steps"] = rows["env_steps"].mean() if "env_steps" in rows.columns else math.nan
        if "n_rollouts" in rows.columns:
            rec["n_rollouts"] = rows["n_rollouts"].sum()
        for key in METRICS:
            mcol, scol = f"mean_{key}", f"se_{key}"
            if mcol not in rows.columns:
                rec[mcol], rec[scol], rec[f"n_{key}"] = math.nan, math.nan, 0
                continue
            ses = rows[scol] if scol in rows.columns else None
            rec[mcol], rec[scol], rec[f"n_{key}"] = combine(rows[mcol], ses, mode)
        records.append(rec)
    return pd.DataFrame(records).sort_values("iteration").reset_index(drop=True)


def _eval_curves(
    runs: list[Run], stage: str, key_of, series: list[str], order: list[str], mode: str, what: str
) -> Curves:
    """Group runs by ``key_of(run)`` and aggregate their ``stage`` eval rows per iteration: every
    group found, and a ``missing`` entry for each expected ``series`` without rows."""
    out = Curves()
    found = {key_of(r) for r in runs}
    # An expected arm drawn only as named groups (``clf [eval.pushes=false]``, ...) has rows.
    series = [s for s in series if not any(f.startswith(f"{s} [") for f in found)]
    for name in _ordered(set(series) | found, order):
        group = [r for r in runs if key_of(r) == name]
        frames = [f for f in (eval_rows(r, stage) for r in group) if f is not None]
        if frames:
            out.series[name] = aggregate_eval(frames, mode)
            floor = combine_floors([run_floor(f) for f in frames])
            if floor is not None:
                out.floors[name] = floor
        else:
            out.missing[name] = (
                f"no {what}runs"
                if not group
                else f"no eval.csv {stage} rows in {len(group)} run{'s' * (len(group) > 1)}"
            )
    return out


def _namer(runs: list[Run], by: str, teacher: bool = False):
    """run -> its series name: its group (:class:`analysis.groups.GroupKey`, or the teacher
    part of it) named by ``by`` plus what tells it from the other groups of that name."""
    key = (lambda r: GroupKey.of(r).teacher_part()) if teacher else GroupKey.of
    names = series_names(list(dict.fromkeys(key(r) for r in runs)), by)
    return lambda r: names[key(r)]


def arm_anchor(keys: list[GroupKey], comp: Comparisons) -> GroupKey | None:
    """The group others are drawn beside: the first compared arm's paper group, else the first."""
    for arm in [a for pair in comp.pairs for a in pair]:
        k = primary(keys, arm)
        if k is not None:
            return k
    order = {n: i for i, n in enumerate(comp.arm_order)}
    return min(keys, key=lambda k: (order.get(k.reward, 999), str(k.reward)), default=None)


def variant_anchor(keys: list[GroupKey], comp: Comparisons) -> GroupKey | None:
    """The ablation's anchor: the reference variant's (full) group, else the first."""
    fulls = [k for k in keys if k.variant == comp.reference_variant]
    return (fulls or keys or [None])[0]


def like_for_like_runs(
    runs: list[Run], key, by: str, comp: Comparisons, notes: list[str], what: str
) -> tuple[list[Run], dict[str, str]]:
    """The runs whose groups (``key``: run -> group key) may be drawn beside the anchor's
    (:func:`analysis.groups.unlike`) and {refused series: "not compared (...) from <anchor>"}."""
    keys = list(dict.fromkeys(key(r) for r in runs))
    if not keys:
        return runs, {}
    anchor = (arm_anchor if by == "reward" else variant_anchor)(keys, comp)
    kept, refused = like_for_like(keys, anchor, by)
    names = series_names(keys, by)
    out = {names[k]: f"{not_compared(bad)} from {names[anchor]}" for k, bad in refused.items()}
    for name, why in out.items():
        notes.append(f"{what}: {name} {why}; not drawn beside it")
    return [r for r in runs if key(r) in kept], out


def _set_refused(out: Curves, refused: dict[str, str]) -> Curves:  # named, not "missing"
    out.refused = refused
    bases = {name.split(" [")[0] for name in refused}
    for name in list(out.missing):
        if name in refused or (name in bases and name not in out.series):
            out.missing.pop(name)
    return out


def baseline_data(runs: list[Run], mode: str, notes: list[str], comp: Comparisons) -> Curves:
    """group -> eval.csv student rows of the runs with the reference student variant that
    trained their own teacher (stage all), one series per group (analysis.groups); groups the
    like-for-like rule refuses beside the anchor arm's are named, not drawn."""
    ref = comp.reference_variant
    chosen = [r for r in runs if r.variant == ref and r.stage in ("all", "?")]
    chosen, refused = like_for_like_runs(chosen, GroupKey.of, "reward", comp, notes, "baseline")
    out = _eval_curves(
        runs=chosen,
        stage="student",
        key_of=_namer(chosen, "reward"),
        series=comp.expected_arms,
        order=comp.arm_order,
        mode=mode,
        what=f"{ref}-student ",
    )
    _set_refused(out, refused)
    for name, why in out.missing.items():
        notes.append(f"baseline: {name}/{ref} has {why}")
    return out


def teacher_runs(runs: list[Run], notes: list[str] | None = None) -> list[Run]:
    """Runs with eval.csv teacher rows, one per (teacher group, seed): a second run that trained
    the same teacher again (another student variant of it) is left out and named."""
    chosen, seen = [], set()
    for r in runs:
        if eval_rows(r, "teacher") is None:
            continue
        ident = (GroupKey.of(r).teacher_part(), r.seed)
        if ident in seen:
            if notes is not None:
                notes.append(f"sample_efficiency: {r.label} repeats the teacher of seed {r.seed}")
            continue
        seen.add(ident)
        chosen.append(r)
    return chosen


def sample_efficiency_data(
    runs: list[Run], mode: str, notes: list[str], comp: Comparisons
) -> Curves:
    """teacher group -> eval.csv teacher rows (every teacher.eval_interval teacher iterations).
    Runs that share a teacher group and seed (students of one teacher) count once."""
    chosen = teacher_runs(runs, notes)
    chosen, refused = like_for_like_runs(
        chosen, lambda r: GroupKey.of(r).teacher_part(), "reward", comp, notes, "sample_efficiency"
    )
    out = _eval_curves(
        runs=chosen,
        stage="teacher",
        key_of=_namer(chosen, "reward", teacher=True),
        series=comp.expected_arms,
        order=comp.arm_order,
        mode=mode,
        what="",
    )
    _set_refused(out, refused)
    for name, why in out.missing.items():
        notes.append(f"sample_efficiency: {name} has {why}")
    return out


def ablation_data(runs: list[Run], mode: str, notes: list[str], comp: Comparisons) -> Curves:
    """variant -> eval.csv student rows of the ablation teacher's (clf's) students."""
    teacher = comp.ablation_teacher
    rewards = {r.reward for r in runs if eval_rows(r, "student") is not None}
    cand = [r for r in runs if r.reward == teacher and eval_rows(r, "student") is not None]
    if rewards - {teacher}:
        others = ", ".join(sorted(rewards - {teacher}))
        notes.append(f"ablation: {teacher} teacher only; student rows of reward {others} not used")
    # One ablation: the students of one fixed teacher (stage student, the ablation sweep) are
    # not pooled with students that trained their own teacher (stage all). The stage whose runs
    # cover the most variants is the ablation; ties go to the fixed teacher.
    stages = {r.stage for r in cand}
    if len(stages) > 1:
        chosen = max(
            sorted(stages),
            key=lambda st: (len({r.variant for r in cand if r.stage == st}), st == "student"),
        )
        notes.append(
            f"ablation: students of stage {chosen} only ({', '.join(sorted(stages - {chosen}))} "
            "left out: another teacher)"
        )
        cand = [r for r in cand if r.stage == chosen]
    cand, refused = like_for_like_runs(cand, GroupKey.of, "variant", comp, notes, "ablation")
    out = _eval_curves(
        runs=cand,
        stage="student",
        key_of=_namer(cand, "variant"),
        series=comp.expected_variants,
        order=comp.variant_order,
        mode=mode,
        what=f"{teacher} ",
    )
    _set_refused(out, refused)
    for name, why in out.missing.items():
        notes.append(f"ablation: variant {name} has {why}")
    return out


def first_reach(iterations, values, target: float):
    """Index of the first value >= target, or None."""
    hit = np.nonzero(np.asarray(values, dtype=float) >= target)[0]
    return None if hit.size == 0 else int(hit[0])


SE_COLUMNS = [
    "reward",
    "n_runs",
    "target_distance_m",
    "iteration",
    "env_steps",
    "result",
    "compared_to",
    "relative",
    "per_run",
    "source",
    "floor_distance_m",  # the arm's standing floor on the teacher evaluations (NaN: none)
]


def relative_target(curves: Curves, fraction: float, among: list[str] | None = None) -> float:
    """``fraction`` x the better final seed-mean evaluation distance of the series ``among``
    (the compared pair, as the claims take it; every series when None or none of them has
    one); NaN if none."""
    finals = {
        name: float(c["mean_distance_m"].dropna().iloc[-1])
        for name, c in curves.series.items()
        if c["mean_distance_m"].notna().any()
    }
    chosen = [v for k, v in finals.items() if among and k in among] or list(finals.values())
    return fraction * max(chosen) if chosen else math.nan


def sample_efficiency(
    runs: list[Run],
    curves: Curves,
    target: float | None,
    notes: list[str],
    comp: Comparisons,
    fraction: float = 0.9,
) -> pd.DataFrame:
    """Per teacher group: first teacher iteration (and env steps) at which the seed-mean
    evaluation distance (eval.csv teacher rows, no smoothing) reaches the target: ``target``
    [m] if given, else ``fraction`` x the better group's final distance (the paper's "reaches
    the model-free distance"); per run the same. Pairs compare each arm's primary group."""
    chosen = teacher_runs(runs)
    name_of = _namer(chosen, "reward", teacher=True) if chosen else None
    keys = list(dict.fromkeys(GroupKey.of(r).teacher_part() for r in chosen))
    names = series_names(keys, "reward")
    if target is None:
        # The claims' target: the better of the first compared pair's arms, not of the controls.
        pair = comp.pairs[0] if comp.pairs else ()
        among = [names[k] for k in (primary(keys, a) for a in pair) if k is not None]
        target = relative_target(curves, fraction, among)
        source = f"{fraction:.0%} of the better final distance of {' and '.join(among) or 'all'}"
    else:
        source = "--target-distance"
    records = []
    for series, curve in curves.series.items():
        idx = first_reach(curve["iteration"], curve["mean_distance_m"], target)
        it = None if idx is None else int(curve["iteration"].iloc[idx])
        steps = None if idx is None else float(curve["env_steps"].iloc[idx])
        per_run = []
        for r in chosen:
            if name_of(r) != series:
                continue
            rows = eval_rows(r, "teacher")
            if "mean_distance_m" not in rows.columns:
                continue
            j = first_reach(rows["iteration"], rows["mean_distance_m"], target)
            per_run.append(f"{r.label}:{'not reached' if j is None else int(rows['iteration'][j])}")
        records.append(
            {
                "reward": series,
                "n_runs": int(curve["n"].max()),
                "target_distance_m": target,
                "iteration": it,
                "env_steps": steps,
                "result": "reached" if it is not None else "not reached",
                "compared_to": "",
                "relative": "",
                "per_run": " ".join(per_run),
                "source": f"eval.csv teacher rows (fixed stone evaluation set); target {source}",
                "floor_distance_m": (
                    curves.floors[series].distance_m if series in curves.floors else math.nan
                ),
            }
        )
    eff = pd.DataFrame(records, columns=SE_COLUMNS)
    under = {n: f.distance_m for n, f in curves.floors.items() if f.distance_m >= target}
    if under:  # reaching it takes no walking: the zero action scores as much
        floors = ", ".join(f"{n} {d:.3g} m" for n, d in under.items())
        notes.append(
            f"sample_efficiency: the target {target:.3g} m is at or below the standing floor "
            f"({floors}): reaching it is no progress"
        )
    by = {row["reward"]: row for _, row in eff.iterrows()}
    for a, b in comp.pairs:
        ka, kb = primary(keys, a), primary(keys, b)
        if ka is None or kb is None:
            continue
        arm, ref = by.get(names[ka]), by.get(names[kb])
        bad = unlike(ka, kb, "reward")
        if arm is None or (ref is None and not bad):
            continue
        if bad:  # the one like-for-like rule: no relative difference of a refused pair
            text = not_compared(bad)
        elif arm["result"] == ref["result"] == "reached":
            rel_it = rel_diff(arm["iteration"], ref["iteration"])
            rel_steps = rel_diff(arm["env_steps"], ref["env_steps"])
            text = f"iterations {format_rel(rel_it)}, env steps {format_rel(rel_steps)}"
        else:
            text = "n/a (target not reached by both)"
        row = eff["reward"] == names[ka]
        if eff.loc[row, "compared_to"].iloc[0]:  # several references: one line each
            text = f"{eff.loc[row, 'relative'].iloc[0]}; vs {names[kb]}: {text}"
            eff.loc[row, "compared_to"] = eff.loc[row, "compared_to"] + f";{names[kb]}"
        else:
            eff.loc[row, "compared_to"] = names[kb]
        eff.loc[row, "relative"] = text
    if not eff.empty and (eff["result"] == "not reached").all():
        notes.append(f"sample_efficiency: no arm reaches {target:g} m ({source})")
    return eff


# --------------------------------------------------------------------------- training diagnostic


def aggregate_curves(per_run: list[pd.DataFrame], column: str) -> pd.DataFrame:
    """Per iteration: mean across runs and SE across runs (NaN where only one run)."""
    cat = pd.concat(per_run, ignore_index=True)
    g = cat.groupby("iteration")[column]
    out = pd.DataFrame({"mean": g.mean(), "n": g.count()})
    out["se"] = g.std(ddof=1) / np.sqrt(out["n"])
    if "env_steps" in cat.columns:
        out["env_steps"] = cat.groupby("iteration")["env_steps"].mean()
    return out.reset_index()


def teacher_training_data(
    runs: list[Run], window: int, notes: list[str], comp: Comparisons
) -> dict[str, dict]:
    """reward -> {metrics.csv column: smoothed curve, mean and SE across runs} (diagnostic)."""
    out: dict[str, dict] = {}
    runs, _ = teacher_refused(runs, comp, notes)
    name_of = _namer(runs, "reward", teacher=True) if runs else None
    for reward in _ordered({name_of(r) for r in runs}, comp.arm_order):
        curves = {}
        for col, _ in TEACHER_PANELS:
            per_run = []
            for r in runs:
                rows = stage_rows(r.metrics, "teacher", col) if name_of(r) == reward else None
                if rows is None:
                    continue
                d = {"iteration": rows["iteration"].to_numpy(), col: smooth(rows[col], window)}
                if "env_steps" in rows.columns:
                    d["env_steps"] = rows["env_steps"].to_numpy()
                per_run.append(pd.DataFrame(d))
            if per_run:
                curves[col] = aggregate_curves(per_run, col)
        if curves:
            out[reward] = curves
        else:
            notes.append(
                f"teacher_curves: skip {reward} (no metrics.csv teacher rows with reward, "
                "episode length or distance: no training episode ended?)"
            )
    return out


def teacher_refused(
    runs: list[Run], comp: Comparisons, notes: list[str] | None = None
) -> tuple[list[Run], dict[str, str]]:
    """:func:`like_for_like_runs` of the training diagnostic (teacher part of the key)."""
    return like_for_like_runs(
        runs,
        lambda r: GroupKey.of(r).teacher_part(),
        "reward",
        comp,
        [] if notes is None else notes,
        "teacher_curves",
    )
