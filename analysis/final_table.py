"""The final-metrics table: each group's final evaluation over seeds and the paper's relative
differences, each with its 95% interval across seeds (or "no claim" under 3 seeds per arm).

Reads ``summary.json`` of complete runs (the final evaluation of the student: the same numbers as
the run's last ``eval.csv`` student row). One row per group (:mod:`analysis.groups`): the arm
named by its reward (plus what tells it from the other groups of that reward), the variant in its
own column. Each row carries its group's standing floor (``floor_distance_m`` and its rollout SE
``floor_se_distance_m``: the zero action on the final evaluation's rollouts, the mean over the
group's runs; NaN for runs from before the floor existed).
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from analysis.aggregate import (
    COUNT_KEYS,
    FLOOR,
    FLOOR_SE,
    METRICS,
    OWN_REWARD_METRICS,
    combine,
    combine_floors,
    format_rel,
    rel_diff,
    run_floor,
)
from analysis.arms import Comparisons
from analysis.groups import (
    GroupKey,
    not_compared,
    primary,
    series_names,
    unlike,
    variant_of_arm,
)
from analysis.rundirs import Run
from march.stats import fieller_rel

# --------------------------------------------------------------------------- final metrics


def _final_runs(runs: list[Run], notes: list[str]) -> list[Run]:
    """Complete runs whose summary.json is a student's final evaluation."""
    skipped = [r for r in runs if r.summary is not None and not r.complete]
    if skipped:
        notes.append(
            "final_metrics: summary.json of non-complete runs not used: "
            + ", ".join(r.label for r in skipped)
        )
    out = []
    for r in runs:
        if not (r.complete and r.summary is not None):
            continue
        stage = str(r.summary.get("stage", "student"))  # older summaries carry no stage
        if stage != "student":
            notes.append(f"final_metrics: {r.label} evaluates a {stage} policy; not used")
            continue
        out.append(r)
    return out


def _span(values) -> str:
    vals = sorted({int(v) for v in values if v is not None and not pd.isna(v)})
    if not vals:
        return ""
    return str(vals[0]) if len(vals) == 1 else f"{vals[0]}-{vals[-1]}"


def final_table(runs: list[Run], mode: str, notes: list[str], comp: Comparisons) -> pd.DataFrame:
    """Per (reward, variant): the final evaluation (summary.json of complete runs) combined over
    seeds, and the relative differences of the chosen pairs: A/full vs B/full for each arm pair
    A:B, and every other variant of the ablation teacher vs its reference variant (columns
    ``compared_to``, ``rel_<metric>``, ``relative``). A pair the like-for-like rule refuses
    (:func:`analysis.groups.unlike`) gets no relative difference: ``relative`` says "not
    compared (differ in ...)", and a baseline row that differs from the first compared arm's
    group so says in ``not_compared``."""
    done = _final_runs(runs, notes)
    arm_rank = {n: i for i, n in enumerate(comp.arm_order)}
    var_rank = {n: i for i, n in enumerate(comp.variant_order)}
    # One row per group (analysis.groups): the arm named by its reward plus what tells it
    # from the other groups of that reward, the variant in its own column.
    arm_keys = {r.path: GroupKey.of(r).arm_part() for r in done}
    arm_name = series_names(list(dict.fromkeys(arm_keys.values())), "reward")
    key_of = {name: k for k, name in arm_name.items()}
    name_of = {p: arm_name[k] for p, k in arm_keys.items()}
    primary_name = {}
    for rw in {k.reward for k in arm_keys.values()}:
        pk = primary(list(dict.fromkeys(arm_keys.values())), rw)
        if pk is not None:
            primary_name[rw] = arm_name[pk]
    for rw in sorted({a for pair in comp.pairs for a in pair} - set(primary_name)):
        variants = [n for k, n in arm_name.items() if k.reward == rw and variant_of_arm(k)]
        if variants:
            notes.append(
                f"final_metrics: no group of {rw} is the paper's {rw} arm ({', '.join(variants)}: "
                "variants); it is compared with nothing"
            )
    groups = sorted(
        {(name_of[r.path], r.variant) for r in done},
        key=lambda g: (arm_rank.get(g[0], 999), var_rank.get(g[1], 999), g),
    )
    records = []
    per_seed: dict[tuple[str, str], dict[str, np.ndarray]] = {}
    for reward, variant in groups:
        members = [r for r in done if (name_of[r.path], r.variant) == (reward, variant)]
        rec = {"reward": reward, "variant": variant, "n_runs": len(members)}
        rec["n_rollouts"] = sum(int(r.summary.get("n_rollouts") or 0) for r in members)
        rec["iteration"] = _span(r.summary.get("iteration") for r in members)
        for count in COUNT_KEYS:  # rollouts behind torque / jerk (newer summaries only)
            vals = [r.summary.get(count) for r in members]
            vals = [int(v) for v in vals if v is not None and not pd.isna(v)]
            rec[count] = sum(vals) if vals else None
        for key in METRICS:
            means = [r.summary.get(f"mean_{key}") for r in members]
            ses = [r.summary.get(f"se_{key}") for r in members]
            means = [math.nan if v is None else v for v in means]
            ses = [math.nan if v is None else v for v in ses]
            rec[f"mean_{key}"], rec[f"se_{key}"], _ = combine(means, ses, mode)
            vals = np.asarray(means, dtype=float)
            per_seed.setdefault((reward, variant), {})[key] = vals[~np.isnan(vals)]
        floor = combine_floors([run_floor(r.summary) for r in members])
        rec[FLOOR] = math.nan if floor is None else floor.distance_m
        rec[FLOOR_SE] = math.nan if floor is None else floor.se_m
        records.append(rec)
    table = pd.DataFrame(records)
    if table.empty:
        return table
    table["compared_to"] = ""
    table["relative"] = ""
    table["not_compared"] = ""
    full, teacher = comp.reference_variant, comp.ablation_teacher
    # The one like-for-like rule (analysis.groups.unlike): the baseline rows are drawn up beside
    # the first compared arm's group; a row that differs from it outside the arms' own fields
    # is "not compared", its numbers kept apart (issue 57).
    anchor = next(
        (key_of[primary_name[a]] for pair in comp.pairs for a in pair if a in primary_name), None
    )
    for i, row in enumerate(table.itertuples()):
        if row.variant == full and anchor is not None:
            bad = unlike(anchor, key_of[row.reward], "reward")
            if bad:
                table.at[i, "not_compared"] = f"{not_compared(bad)} from {arm_name[anchor]}"
                notes.append(
                    f"final_metrics: {row.reward}/{full} vs {arm_name[anchor]}/{full}: "
                    + not_compared(bad)
                )
    for key in METRICS:
        table[f"rel_{key}"] = math.nan
    index = {(row.reward, row.variant): i for i, row in enumerate(table.itertuples())}
    pairs = [
        ((primary_name[a], full), (primary_name[b], full))
        for a, b in comp.pairs
        if a in primary_name and b in primary_name
    ]
    for a, b in comp.pairs:
        if a in primary_name and b not in primary_name:
            notes.append(
                f"final_metrics: {b}/{full} has no complete runs (or no single group); "
                f"no relative differences for {a}/{full}"
            )
    pairs += [
        ((name, v), (name, full))
        for (name, v) in index
        if name.split(" [")[0] == teacher and v != full and (name, full) in index
    ]
    for group, ref in pairs:
        if group not in index:
            continue
        if ref not in index:
            notes.append(
                f"final_metrics: {'/'.join(ref)} has no complete runs; "
                f"no relative differences for {'/'.join(group)}"
            )
            continue
        i, j = index[group], index[ref]
        parts = []
        bad = unlike(key_of[group[0]], key_of[ref[0]], "reward")
        if bad:  # never side by side: no relative difference of a refused pair
            text = not_compared(bad)
            if table.at[i, "compared_to"]:
                table.at[i, "compared_to"] += ";" + "/".join(ref)
                table.at[i, "relative"] += f"; vs {'/'.join(ref)}: {text}"
            else:
                table.at[i, "compared_to"] = "/".join(ref)
                table.at[i, "relative"] = text
            continue
        for key, (short, _) in METRICS.items():
            if key in OWN_REWARD_METRICS and group[0].split(" [")[0] != ref[0].split(" [")[0]:
                # Each arm's return is under its own teacher's reward set: clf and modelfree
                # returns are different functions, so their ratio means nothing.
                parts.append(f"{short} n/a (different reward sets)")
                continue
            rel = rel_diff(table.at[i, f"mean_{key}"], table.at[j, f"mean_{key}"])
            if not table.at[i, "compared_to"]:  # the first pair of a group fills the columns
                table.at[i, f"rel_{key}"] = rel
            a_vals, b_vals = per_seed[group].get(key), per_seed[ref].get(key)
            ci = ""
            big = a_vals is not None and b_vals is not None and min(a_vals.size, b_vals.size) >= 3
            if big and not math.isnan(rel):
                _, lo, hi = fieller_rel(a_vals, b_vals)
                ci = f" [{format_rel(lo)}, {format_rel(hi)}]"
            n_runs = (int(table.at[i, "n_runs"]), int(table.at[j, "n_runs"]))
            if a_vals is not None and b_vals is not None and (a_vals.size, b_vals.size) != n_runs:
                ci += f" (n={a_vals.size} vs {b_vals.size} with a value)"  # the seeds it used
            parts.append(f"{short} {format_rel(rel)}{ci}")
        n_a, n_b = int(table.at[i, "n_runs"]), int(table.at[j, "n_runs"])
        if min(n_a, n_b) < 3:
            parts.append(f"n={n_a} vs {n_b} seeds: fewer than 3 per arm, no claim")
        else:
            parts.append(f"n={n_a} vs {n_b} seeds, 95% CI across seeds in brackets")
        if table.at[i, "compared_to"]:  # a group compared with several references
            table.at[i, "compared_to"] += ";" + "/".join(ref)  # group names may hold commas
            table.at[i, "relative"] += f"; vs {'/'.join(ref)}: " + ", ".join(parts)
        else:
            table.at[i, "compared_to"] = "/".join(ref)
            table.at[i, "relative"] = ", ".join(parts)
    return table
