"""Write the tables (runs, final metrics, sample efficiency, figure data) and the stdout summary.

Every distance printed has the standing floor beside it (the zero action's distance on the same
rollouts: ``distance 4 m (standing floor 0.035 m)``, a ``standing floor`` column in
final_metrics.md); runs from before the floor existed are said to have none."""

from __future__ import annotations

import io
import math
from pathlib import Path

import pandas as pd

from analysis.aggregate import FLOOR, FLOOR_SE, METRICS, NO_FLOOR
from analysis.arms import Comparisons

UNITS = {"distance_m": " m", "abs_torque_nm": " Nm", "abs_ang_jerk": " rad/s^3"}


def fmt(x) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "n/a"
    return f"{x:.4g}"


def md_table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(str(c).replace("|", "/") for c in r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def _rule(row, ref: str, comp: Comparisons) -> str:
    full = comp.reference_variant
    if row["variant"] == full:
        return f"({row['reward']} - {ref}) / {ref}, student {full}"
    return f"(variant - {full}) / {full}, {comp.ablation_teacher} teacher"


def comparisons(table: pd.DataFrame, comp: Comparisons) -> list[str]:
    """One line per relative comparison in the final table, e.g.
    'baseline clf vs modelfree ((clf - modelfree) / modelfree, student full): torque -12%, ...'."""
    lines = []
    if table.empty:
        return lines
    for _, row in table[table["compared_to"] != ""].iterrows():
        kind = "baseline" if row["variant"] == comp.reference_variant else "ablation"
        who = row["reward"] if kind == "baseline" else row["variant"]
        refs = row["compared_to"].split(";")
        texts = row["relative"].split("; vs ")
        for k, (ref, text) in enumerate(zip(refs, texts, strict=False)):
            if k:
                text = text.split(": ", 1)[-1]
            name = ref.rsplit("/", 1)[0 if kind == "baseline" else 1]
            lines.append(f"{kind} {who} vs {name} ({_rule(row, name, comp)}): {text}")
    return lines


def _has_floor(row) -> bool:
    return FLOOR in row.index and not pd.isna(row[FLOOR])


def _floor_cell(row) -> str:
    if not _has_floor(row):
        return "none (older run)"
    se = row[FLOOR_SE] if FLOOR_SE in row.index else math.nan
    return fmt(row[FLOOR]) + ("" if pd.isna(se) else f" ± {fmt(se)}")


def _floor_line(table: pd.DataFrame) -> str:
    """final_metrics.md's sentence on the standing floor column."""
    if FLOOR not in table.columns or table[FLOOR].isna().all():
        return f"Standing floor: {NO_FLOOR}.\n\n"
    return (
        "Standing floor: the zero action's distance on the same rollouts as the final "
        "evaluation (summary.json `floor_distance_m`, mean over the group's runs ± rollout SE); "
        "a distance at or below it is no progress.\n\n"
    )


def _final_md(table: pd.DataFrame, mode: str, comp: Comparisons) -> str:
    names = [METRICS[k][0] for k in METRICS]
    at = names.index(METRICS["distance_m"][0]) + 1  # the floor beside the distance
    header = ["reward", "variant", "n runs", "iteration"] + names[:at] + ["standing floor"]
    header += names[at:] + ["compared to", "relative difference"]
    rows, apart = [], []
    for _, row in table.iterrows():
        cells = [row["reward"], row["variant"], str(row["n_runs"]), str(row["iteration"])]
        values = [f"{fmt(row[f'mean_{k}'])} ± {fmt(row[f'se_{k}'])}" for k in METRICS]
        cells += values[:at] + [_floor_cell(row)] + values[at:]
        if _refused(row):  # its own table: never beside the groups it may not be compared with
            apart.append(cells + [row["not_compared"]])
            continue
        cells += [row["compared_to"] or "-", row["relative"] or "-"]
        rows.append(cells)
    se_txt = (
        "SE across seeds (a single-run group keeps its rollout SE)"
        if mode == "seeds"
        else "pooled SE sqrt(sum se_i^2)/n"
    )
    units = ", ".join(f"{METRICS[k][0]} = {METRICS[k][1]}" for k in METRICS)
    lines = comparisons(table, comp)
    pairs = "; ".join(f"({a} - {b}) / {b}" for a, b in comp.pairs)
    full = comp.reference_variant
    rel = "\n".join(f"- {ln}" for ln in lines) if lines else "- none (a reference group is missing)"
    return (
        "# Final metrics (final evaluation: summary.json of complete runs)\n\n"
        f"mean ± {se_txt}. Relative differences in the paper's convention: "
        f"{pairs} for the arm comparison (student {full}; chosen by {comp.source}), "
        f"(variant - {full}) / {full} for the ablation ({comp.ablation_teacher} teacher)."
        f"\nUnits: {units}.\n\n"
        + _floor_line(table)
        + md_table(header, rows)
        + "\n## Relative differences\n\n"
        + rel
        + "\n"
        + (
            "\n## Not compared\n\nGroups that differ from the compared arms' group in more "
            "than the arms' own fields (the like-for-like rule of claims.md): their final "
            "evaluation, kept apart.\n\n" + md_table(header[:-2] + ["why"], apart)
            if apart
            else ""
        )
    )


def _refused(row) -> bool:
    return bool(row.get("not_compared", "")) if hasattr(row, "get") else False


def write_tables(
    out: Path,
    listing: pd.DataFrame,
    table: pd.DataFrame,
    eff: pd.DataFrame,
    points: pd.DataFrame,
    mode: str,
    written: list[Path],
    comp: Comparisons,
) -> None:
    listing.to_csv(out / "runs.csv", index=False)
    (out / "runs.md").write_text(
        "# Runs\n\n" + md_table(list(listing.columns), listing.astype(str).values.tolist())
    )
    written += [out / "runs.csv", out / "runs.md"]
    if not table.empty:
        table.to_csv(out / "final_metrics.csv", index=False)
        (out / "final_metrics.md").write_text(_final_md(table, mode, comp))
        written += [out / "final_metrics.csv", out / "final_metrics.md"]
    if not eff.empty:
        eff.to_csv(out / "sample_efficiency.csv", index=False)
        written.append(out / "sample_efficiency.csv")
    if not points.empty:
        points.to_csv(out / "figure_data.csv", index=False)
        written.append(out / "figure_data.csv")


def _values(row, keys) -> str:
    """``distance 4 m (standing floor 0.035 m), success 80%, ...`` of a final-table row."""
    parts = []
    for k in keys:
        v = row[f"mean_{k}"]
        if k == "success_rate" and not pd.isna(v):
            parts.append(f"success {100 * v:.0f}%")
        else:
            floor = f" (standing floor {fmt(row[FLOOR])} m)" if k == "distance_m" else ""
            floor = floor if _has_floor(row) else ""
            parts.append(f"{METRICS[k][0]} {fmt(v)}{UNITS.get(k, '')}{floor}")
    return ", ".join(parts)


def _no_floor(rows: pd.DataFrame, name, buf) -> None:
    """One line for the printed rows without a standing floor (older runs): all, or which
    (``name``: row -> how its line names it)."""
    if FLOOR not in rows.columns or rows[FLOOR].isna().all():
        print(f"  {NO_FLOOR}", file=buf)
    elif rows[FLOOR].isna().any():
        older = ", ".join(name(row) for _, row in rows[rows[FLOOR].isna()].iterrows())
        print(f"  no standing floor for {older} (from before the floor)", file=buf)


def report(res: dict, out: Path) -> str:
    """The short stdout summary: notes, incomplete runs, final comparisons, sample efficiency."""
    buf = io.StringIO()
    runs = res["runs"]
    listing: pd.DataFrame = res["listing"]
    n_ok = sum(r.complete for r in runs)
    n_failed = sum(r.state == "failed" for r in runs)
    for note in res["notes"]:
        print(f"note: {note}", file=buf)
    bad = listing[listing["status"] != "complete"]
    if not bad.empty:
        print("not complete:", file=buf)
        for _, row in bad.iterrows():
            extra = "; ".join(x for x in [row["error"], row["issues"]] if x)
            print(f"  {row['run']}: {row['status']}" + (f" -- {extra}" if extra else ""), file=buf)
    table: pd.DataFrame = res["final"]
    comp: Comparisons = res["comparisons"]
    full, teacher = comp.reference_variant, comp.ablation_teacher
    pairs = "; ".join(f"({a} - {b}) / {b}" for a, b in comp.pairs)
    if not table.empty:
        base = table[table["variant"] == full]
        if not base.empty:
            print(
                f"baseline, final evaluation (student {full}; relative = {pairs}):",
                file=buf,
            )
            for _, row in base.iterrows():
                if _refused(row):  # named, its numbers not printed beside the others
                    print(f"  {row['reward']}: {row['not_compared']}", file=buf)
                    continue
                print(
                    f"  {row['reward']} (n={row['n_runs']}, it {row['iteration']}): "
                    + _values(row, ["distance_m", "success_rate", "abs_torque_nm", "abs_ang_jerk"]),
                    file=buf,
                )
            _no_floor(base[base["not_compared"] == ""], lambda row: row["reward"], buf)
            for _, row in base[base["compared_to"] != ""].iterrows():
                ref = row["compared_to"].split(";")[0].rsplit("/", 1)[0]
                print(f"  {row['reward']} vs {ref}: {row['relative']}", file=buf)
        abl = table[table["reward"].str.split(" [", regex=False).str[0] == teacher]
        if (abl["variant"] != full).any():
            print(
                f"ablation, final evaluation ({teacher} teacher; relative = "
                f"(variant - {full}) / {full}):",
                file=buf,
            )
            for _, row in abl.iterrows():
                own = row["variant"] != full and row["compared_to"]
                vs = f"; vs {full}: {row['relative']}" if own else ""
                print(
                    f"  {row['variant']} ({row['reward']}, n={row['n_runs']}): "
                    + _values(row, ["reward_per_step", "distance_m", "success_rate"])
                    + vs,
                    file=buf,
                )
            _no_floor(abl, lambda row: f"{row['variant']} ({row['reward']})", buf)
    eff: pd.DataFrame = res["sample_efficiency"]
    if not eff.empty:
        print(
            f"sample efficiency (teacher evaluation distance >= "
            f"{eff['target_distance_m'].iloc[0]:g} m, eval.csv teacher rows):",
            file=buf,
        )
        for _, row in eff.iterrows():
            floor = f"; standing floor {fmt(row[FLOOR])} m" if _has_floor(row) else ""
            if row["result"] == "reached":
                steps = "" if pd.isna(row["env_steps"]) else f" ({row['env_steps']:.4g} env steps)"
                print(
                    f"  {row['reward']}: iteration {int(row['iteration'])}{steps}{floor}", file=buf
                )
            else:
                print(f"  {row['reward']}: not reached{floor}", file=buf)
        _no_floor(eff, lambda row: row["reward"], buf)
        for _, row in eff[eff["compared_to"] != ""].iterrows():
            print(f"  {row['reward']} vs {row['compared_to']}: {row['relative']}", file=buf)
    print(
        f"runs found: {len(runs)} ({n_ok} complete, {n_failed} failed, "
        f"{len(runs) - n_ok - n_failed} other incomplete)",
        file=buf,
    )
    print(
        f"wrote {len(res['written'])} files to {out}: " + ", ".join(p.name for p in res["written"]),
        file=buf,
    )
    return buf.getvalue()
