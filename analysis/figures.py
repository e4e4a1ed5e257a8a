"""Turn MARCH run directories into the paper's figures and tables.

Usage::

    python analysis/figures.py RUN_OR_SWEEP_DIR [MORE_DIRS ...] [--out DIR]
        [--target-distance 2.0] [--smooth 20] [--se-mode seeds|pooled]

Runs are found recursively: a run is a directory holding ``config.yaml`` (the resolved config)
or ``.hydra/config.yaml``; a Hydra sweep directory (``multirun.yaml`` + ``0/``, ``1/``, ...) is
searched, never taken as a run. Every run found is listed in ``runs.md``/``runs.csv`` with its
state; failed or incomplete runs are named there and on stdout, and the figures still use
whatever rows they have.

Written into ``--out`` (default ``<first dir>/figures``):

* ``ablation.{png,pdf}`` -- teacher reward on student rollouts (``metrics.csv`` student rows,
  column ``teacher_reward``) vs distillation iteration, one line per student variant of the clf
  teacher, trailing moving average (window ``--smooth``) per run, then mean across seeds with a
  band of +-1 standard error across seeds.
* ``baseline.{png,pdf}`` -- distance, |torque| and |angular jerk| from ``eval.csv`` student rows
  vs distillation iteration, clf (blue) vs modelfree (red), student variant ``full``; error bars
  are 4 x standard error.
* ``teacher_curves.{png,pdf}`` -- teacher mean_reward, mean_episode_length, mean_distance_m vs
  env steps (iteration on the top axis when steps/iteration is the same for all runs);
  ``sample_efficiency.csv`` -- first teacher iteration at which the smoothed, seed-averaged
  mean_distance_m reaches ``--target-distance`` (or "not reached"), per reward and per run.
* ``final_metrics.{md,csv}`` -- per group (reward x student variant), the final metrics from
  ``summary.json`` of complete runs: mean +- se, n runs, and relative differences vs the
  reference group clf/full written like ``torque -12%``.
* ``runs.{md,csv}`` -- every run found, its config keys, state and problems.

Combining several seeds (``--se-mode``): with ``seeds`` (default) the mean is the mean of the
per-seed means and the standard error is the SE *across seeds*, std(ddof=1)/sqrt(n); this
includes seed-to-seed variation. A point backed by a single run keeps that run's own SE over
rollouts (``se_*`` columns). With ``pooled`` the SE is the SE of the mean of independent
per-seed means, sqrt(sum se_i^2)/n, i.e. rollout noise only. The same rule is used for the
baseline figure and the final table; the ablation and teacher curves (training logs carry no
per-run SE) use the across-seed SE, and show no band where only one run contributes.

This script reads files only: it imports pandas, numpy, matplotlib and omegaconf, never the
simulator or the ``march`` package.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import os
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

REFERENCE_REWARD = "clf"
REFERENCE_VARIANT = "full"
REWARD_COLORS = {"clf": "tab:blue", "modelfree": "tab:red"}
VARIANT_COLORS = {"full": "tab:blue", "no_transformer": "tab:orange", "no_mdn": "tab:green"}
VARIANT_ORDER = ["full", "no_transformer", "no_mdn"]
REWARD_ORDER = ["clf", "modelfree"]
# metric key in eval.csv / summary.json (mean_<key>, se_<key>) -> short name, axis label
METRICS = {
    "distance_m": ("distance", "distance traveled [m]"),
    "success_rate": ("success", "success rate"),
    "abs_torque_nm": ("torque", "mean |joint torque| [Nm]"),
    "abs_ang_jerk": ("jerk", "mean |angular jerk| [rad/s^3]"),
    "reward": ("reward", "reward"),
}
BASELINE_METRICS = ["distance_m", "abs_torque_nm", "abs_ang_jerk"]
BASELINE_ERR_MULT = 4.0
TEACHER_PANELS = [
    ("mean_reward", "mean reward"),
    ("mean_episode_length", "mean episode length [steps]"),
    ("mean_distance_m", "mean distance [m]"),
]
STRING_COLUMNS = {"stage"}
FIG_EXTS = ("png", "pdf")


# --------------------------------------------------------------------------- discovery / loading


@dataclass
class Run:
    path: Path
    label: str = ""
    reward: str = "?"
    variant: str = "?"
    curriculum: str = "?"
    seed: object = None
    stage: str = "?"
    compute: str = "?"
    state: str = "no status.json"
    error: str | None = None
    metrics: pd.DataFrame | None = None
    evals: pd.DataFrame | None = None
    summary: dict | None = None
    issues: list[str] = field(default_factory=list)
    csv_problem: bool = False

    @property
    def complete(self) -> bool:
        needs_summary = self.stage != "teacher"
        return (
            self.state == "done"
            and (self.summary is not None or not needs_summary)
            and not self.csv_problem
        )

    @property
    def status_label(self) -> str:
        if self.complete:
            return "complete"
        if self.state == "done":
            if self.stage != "teacher" and self.summary is None:
                return "incomplete (done, no summary.json)"
            return "incomplete (unreadable CSV)"
        if self.state == "failed":
            return "failed"
        if self.state == "running":
            return "incomplete (running)"
        return f"incomplete ({self.state})"


def _natural_key(name: str):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def find_run_dirs(root: Path) -> list[Path]:
    """Run dirs under ``root`` (``root`` included): dirs with config.yaml or .hydra/config.yaml.

    Sweep dirs (with multirun.yaml) are searched, not taken as runs; the search does not descend
    into a run dir, nor into hidden dirs or a ``figures`` output dir.
    """
    found: list[Path] = []
    for dirpath, dirnames, filenames in os.walk(root):
        d = Path(dirpath)
        is_sweep = "multirun.yaml" in filenames
        is_run = not is_sweep and (
            "config.yaml" in filenames or (d / ".hydra" / "config.yaml").is_file()
        )
        if is_run:
            found.append(d)
            dirnames[:] = []
            continue
        dirnames[:] = sorted(
            (n for n in dirnames if not n.startswith(".") and n != "figures"), key=_natural_key
        )
    return found


def _cfg_get(cfg, key: str):
    try:
        return OmegaConf.select(cfg, key, default=None, throw_on_resolution_failure=False)
    except Exception:  # noqa: BLE001 - a broken interpolation must not kill the analysis
        return None


def _read_csv_tolerant(path: Path) -> tuple[pd.DataFrame | None, list[str], bool]:
    """Read a CSV that may be cut off mid-write. Returns (frame or None, issues, problem)."""
    name = path.name
    if not path.is_file():
        return None, [], False
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        return None, [f"{name} unreadable ({type(exc).__name__})"], True
    lines = text.splitlines()
    if not lines or not lines[0].strip():
        return None, [f"{name} empty"], True
    header = next(csv.reader([lines[0]]))
    body = lines[1:]
    issues: list[str] = []
    problem = False
    if body and not text.endswith("\n"):
        body = body[:-1]
        issues.append(f"{name}: last line cut off (dropped)")
        problem = True
    rows = [r for r in csv.reader(body) if r]
    good = [r for r in rows if len(r) == len(header)]
    if len(good) != len(rows):
        issues.append(f"{name}: {len(rows) - len(good)} malformed row(s) dropped")
        problem = True
    df = pd.DataFrame(good, columns=header)
    for col in df.columns:
        if col in STRING_COLUMNS:
            continue
        conv = pd.to_numeric(df[col], errors="coerce")
        if conv.notna().sum() >= (df[col] != "").sum():
            df[col] = conv
    if "iteration" in df.columns:
        bad = df["iteration"].isna()
        if bad.any():
            issues.append(f"{name}: {int(bad.sum())} row(s) without iteration dropped")
            problem = True
            df = df[~bad]
    if "stage" in df.columns:
        df["stage"] = df["stage"].astype(str).str.strip()
    return df.reset_index(drop=True), issues, problem


def load_run(path: Path) -> Run:
    run = Run(path=path)
    cfg_path = path / "config.yaml"
    if not cfg_path.is_file():
        cfg_path = path / ".hydra" / "config.yaml"
    try:
        cfg = OmegaConf.load(cfg_path)
    except Exception as exc:  # noqa: BLE001
        cfg = OmegaConf.create({})
        run.issues.append(f"{cfg_path.name} unreadable ({type(exc).__name__})")
    for attr, key in [
        ("reward", "reward.name"),
        ("variant", "student.variant"),
        ("curriculum", "curriculum.name"),
        ("stage", "stage"),
        ("compute", "compute.name"),
    ]:
        val = _cfg_get(cfg, key)
        if val is not None:
            setattr(run, attr, str(val))
    run.seed = _cfg_get(cfg, "seed")

    status_path = path / "status.json"
    if status_path.is_file():
        try:
            status = json.loads(status_path.read_text())
            run.state = str(status.get("state", "unknown"))
            run.error = status.get("error")
        except (OSError, ValueError) as exc:
            run.state = "unreadable status.json"
            run.issues.append(f"status.json unreadable ({type(exc).__name__})")

    for attr, fname in [("metrics", "metrics.csv"), ("evals", "eval.csv")]:
        df, issues, problem = _read_csv_tolerant(path / fname)
        setattr(run, attr, df)
        run.issues.extend(issues)
        run.csv_problem |= problem
    if run.metrics is None and not (path / "metrics.csv").is_file():
        run.issues.append("metrics.csv missing")

    summary_path = path / "summary.json"
    if summary_path.is_file():
        try:
            run.summary = json.loads(summary_path.read_text())
        except (OSError, ValueError) as exc:
            run.issues.append(f"summary.json unreadable ({type(exc).__name__})")
    return run


def discover(dirs: list[Path]) -> list[Run]:
    seen: set[Path] = set()
    runs: list[Run] = []
    for root in dirs:
        for d in find_run_dirs(root):
            key = d.resolve()
            if key in seen:
                continue
            seen.add(key)
            run = load_run(d)
            rel = d.resolve().relative_to(root.resolve().parent)
            run.label = str(rel)
            runs.append(run)
    return runs


# --------------------------------------------------------------------------- statistics


def combine(means, ses=None, mode: str = "seeds") -> tuple[float, float, int]:
    """Combine per-run (mean, se) into (mean, se, n); see the module docstring for the rule."""
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
        se = float(s[0])
    return mean, se, n


def smooth(values: pd.Series, window: int) -> pd.Series:
    """Trailing moving average over ``window`` rows (fewer at the start)."""
    return values.rolling(max(1, int(window)), min_periods=1).mean()


def _stage_rows(df: pd.DataFrame | None, stage: str, column: str) -> pd.DataFrame | None:
    if df is None or "stage" not in df.columns or "iteration" not in df.columns:
        return None
    if column not in df.columns:
        return None
    rows = df[(df["stage"] == stage) & df[column].notna()]
    if rows.empty:
        return None
    return rows.sort_values("iteration").drop_duplicates("iteration", keep="last")


def aggregate_curves(per_run: list[pd.DataFrame], column: str) -> pd.DataFrame:
    """Per iteration: mean across runs and SE across runs (NaN where only one run)."""
    cat = pd.concat(per_run, ignore_index=True)
    g = cat.groupby("iteration")[column]
    out = pd.DataFrame({"mean": g.mean(), "n": g.count()})
    out["se"] = g.std(ddof=1) / np.sqrt(out["n"])
    if "env_steps" in cat.columns:
        out["env_steps"] = cat.groupby("iteration")["env_steps"].mean()
    return out.reset_index()


def _ordered(keys, order):
    return sorted(keys, key=lambda k: (order.index(k) if k in order else len(order), str(k)))


# --------------------------------------------------------------------------- figure data


def ablation_data(runs: list[Run], window: int, notes: list[str]) -> dict[str, pd.DataFrame]:
    cand = [r for r in runs if _stage_rows(r.metrics, "student", "teacher_reward") is not None]
    if not cand:
        notes.append("skip ablation: no run has student rows with teacher_reward in metrics.csv")
        return {}
    rewards = {r.reward for r in cand}
    if REFERENCE_REWARD in rewards:
        if len(rewards) > 1:
            others = ", ".join(sorted(rewards - {REFERENCE_REWARD}))
            notes.append(f"ablation: clf teacher only; student rows of reward {others} not used")
        cand = [r for r in cand if r.reward == REFERENCE_REWARD]
    else:
        notes.append(f"ablation: no clf runs; using reward(s) {', '.join(sorted(rewards))}")
    out: dict[str, pd.DataFrame] = {}
    for variant in _ordered({r.variant for r in cand}, VARIANT_ORDER):
        per_run = []
        for r in cand:
            if r.variant != variant:
                continue
            rows = _stage_rows(r.metrics, "student", "teacher_reward")
            per_run.append(
                pd.DataFrame(
                    {
                        "iteration": rows["iteration"].to_numpy(),
                        "teacher_reward": smooth(rows["teacher_reward"], window).to_numpy(),
                    }
                )
            )
        out[variant] = aggregate_curves(per_run, "teacher_reward")
    for variant in VARIANT_ORDER:
        if variant not in out:
            notes.append(f"ablation: variant {variant} has no student teacher_reward rows")
    return out


def baseline_data(runs: list[Run], mode: str, notes: list[str]) -> dict[str, pd.DataFrame]:
    """reward -> frame(iteration, env_steps, n, mean_<M>, se_<M>) from eval.csv student rows."""
    out: dict[str, pd.DataFrame] = {}
    full = [r for r in runs if r.variant == REFERENCE_VARIANT]
    for reward in _ordered({r.reward for r in runs} | set(REWARD_ORDER), REWARD_ORDER):
        group = [r for r in full if r.reward == reward]
        frames = []
        for r in group:
            if r.evals is None or "stage" not in r.evals.columns:
                continue
            rows = r.evals[r.evals["stage"] == "student"]
            if not rows.empty and "iteration" in rows.columns:
                frames.append(rows.drop_duplicates("iteration", keep="last"))
        if not frames:
            why = "no runs" if not group else "no eval.csv student rows"
            notes.append(f"baseline: skip {reward}/{REFERENCE_VARIANT} ({why})")
            continue
        cat = pd.concat(frames, ignore_index=True)
        records = []
        for it, rows in cat.groupby("iteration"):
            rec = {"iteration": it, "n": len(rows)}
            if "env_steps" in rows.columns:
                rec["env_steps"] = rows["env_steps"].mean()
            for key in METRICS:
                mcol, scol = f"mean_{key}", f"se_{key}"
                if mcol not in rows.columns:
                    continue
                ses = rows[scol] if scol in rows.columns else None
                rec[mcol], rec[scol], _ = combine(rows[mcol], ses, mode)
            records.append(rec)
        out[reward] = pd.DataFrame(records).sort_values("iteration").reset_index(drop=True)
    return out


def teacher_data(runs: list[Run], window: int, notes: list[str]) -> dict[str, dict]:
    """reward -> {column: aggregated smoothed curve}."""
    out: dict[str, dict] = {}
    for reward in _ordered({r.reward for r in runs}, REWARD_ORDER):
        curves = {}
        for col, _ in TEACHER_PANELS:
            per_run = []
            for r in runs:
                if r.reward != reward:
                    continue
                rows = _stage_rows(r.metrics, "teacher", col)
                if rows is None:
                    continue
                d = {
                    "iteration": rows["iteration"].to_numpy(),
                    col: smooth(rows[col], window).to_numpy(),
                }
                if "env_steps" in rows.columns:
                    d["env_steps"] = rows["env_steps"].to_numpy()
                per_run.append(pd.DataFrame(d))
            if per_run:
                curves[col] = aggregate_curves(per_run, col)
        if curves:
            out[reward] = curves
        else:
            notes.append(f"teacher_curves: skip {reward} (no teacher rows in metrics.csv)")
    return out


def _first_reach(iterations, values, target: float):
    hit = np.nonzero(np.asarray(values, dtype=float) >= target)[0]
    return None if hit.size == 0 else int(np.asarray(iterations)[hit[0]])


def sample_efficiency(
    runs: list[Run], teacher: dict[str, dict], target: float, window: int
) -> pd.DataFrame:
    """Per reward: first iteration where the smoothed seed-mean mean_distance_m >= target."""
    records = []
    for reward, curves in teacher.items():
        curve = curves.get("mean_distance_m")
        if curve is None:
            continue
        it = _first_reach(curve["iteration"], curve["mean"], target)
        steps = None
        if it is not None and "env_steps" in curve.columns:
            steps = float(curve.loc[curve["iteration"] == it, "env_steps"].iloc[0])
        per_run = []
        for r in runs:
            rows = (
                _stage_rows(r.metrics, "teacher", "mean_distance_m") if r.reward == reward else None
            )
            if rows is None:
                continue
            rit = _first_reach(rows["iteration"], smooth(rows["mean_distance_m"], window), target)
            per_run.append(f"{r.label}:{'not reached' if rit is None else rit}")
        records.append(
            {
                "reward": reward,
                "n_runs": int(curve["n"].max()),
                "target_distance_m": target,
                "iteration": it,
                "env_steps": steps,
                "result": "reached" if it is not None else "not reached",
                "per_run": " ".join(per_run),
            }
        )
    return pd.DataFrame(
        records,
        columns=[
            "reward",
            "n_runs",
            "target_distance_m",
            "iteration",
            "env_steps",
            "result",
            "per_run",
        ],
    )


def final_table(runs: list[Run], mode: str, notes: list[str]) -> pd.DataFrame:
    done = [r for r in runs if r.complete and r.summary is not None]
    skipped = [r for r in runs if r.summary is not None and not r.complete]
    if skipped:
        notes.append(
            "final_metrics: summary.json of non-complete runs not used: "
            + ", ".join(r.label for r in skipped)
        )
    records = []
    groups = sorted(
        {(r.reward, r.variant) for r in done},
        key=lambda g: (
            REWARD_ORDER.index(g[0]) if g[0] in REWARD_ORDER else 99,
            VARIANT_ORDER.index(g[1]) if g[1] in VARIANT_ORDER else 99,
            g,
        ),
    )
    for reward, variant in groups:
        members = [r for r in done if (r.reward, r.variant) == (reward, variant)]
        computes = sorted({r.compute for r in members})
        if len(computes) > 1:
            notes.append(f"final_metrics: {reward}/{variant} mixes compute {computes}")
        rec = {"reward": reward, "variant": variant, "n_runs": len(members)}
        rec["n_rollouts"] = sum(int(r.summary.get("n_rollouts") or 0) for r in members)
        for key in METRICS:
            means = [r.summary.get(f"mean_{key}", math.nan) for r in members]
            ses = [r.summary.get(f"se_{key}", math.nan) for r in members]
            means = [math.nan if v is None else v for v in means]
            ses = [math.nan if v is None else v for v in ses]
            rec[f"mean_{key}"], rec[f"se_{key}"], _ = combine(means, ses, mode)
        records.append(rec)
    table = pd.DataFrame(records)
    if table.empty:
        return table
    ref = table[(table["reward"] == REFERENCE_REWARD) & (table["variant"] == REFERENCE_VARIANT)]
    if ref.empty:
        notes.append(
            f"final_metrics: reference group {REFERENCE_REWARD}/{REFERENCE_VARIANT} has no "
            "complete runs; no relative differences"
        )
    texts = []
    for i, row in table.iterrows():
        parts = []
        for key, (short, _) in METRICS.items():
            rel = math.nan
            if not ref.empty:
                base = float(ref[f"mean_{key}"].iloc[0])
                val = float(row[f"mean_{key}"])
                if base != 0 and not math.isnan(base) and not math.isnan(val):
                    rel = (val - base) / abs(base)
            table.loc[i, f"rel_{key}"] = rel
            parts.append(f"{short} {format_rel(rel)}")
        is_ref = (row["reward"], row["variant"]) == (REFERENCE_REWARD, REFERENCE_VARIANT)
        texts.append("reference" if is_ref else ("" if ref.empty else ", ".join(parts)))
    table[f"vs_{REFERENCE_REWARD}_{REFERENCE_VARIANT}"] = texts
    return table


def format_rel(rel: float) -> str:
    """Relative difference as a whole percent with sign: -0.12 -> '-12%'."""
    if rel is None or math.isnan(rel):
        return "n/a"
    return f"{int(round(rel * 100)):+d}%"


def _fmt(x) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "n/a"
    return f"{x:.4g}"


# --------------------------------------------------------------------------- plotting


def _save(fig, out: Path, stem: str, written: list[Path]) -> None:
    for ext in FIG_EXTS:
        p = out / f"{stem}.{ext}"
        fig.savefig(p, dpi=150, bbox_inches="tight")
        written.append(p)
    plt.close(fig)


def plot_ablation(data, window: int, out: Path, written: list[Path]) -> None:
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for variant, curve in data.items():
        color = VARIANT_COLORS.get(variant)
        n = int(curve["n"].max())
        ax.plot(curve["iteration"], curve["mean"], color=color, label=f"{variant} (n={n})")
        band = curve["se"].fillna(0.0)
        ax.fill_between(
            curve["iteration"], curve["mean"] - band, curve["mean"] + band, color=color, alpha=0.25
        )
    ax.set_xlabel("distillation iteration")
    ax.set_ylabel("teacher reward on student rollouts\n(mean per step)")
    ax.set_title(f"Student ablation (moving avg {window}, band = SE across seeds)", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend()
    _save(fig, out, "ablation", written)


def plot_baseline(data, mode: str, out: Path, written: list[Path]) -> None:
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    for ax, key in zip(axes, BASELINE_METRICS, strict=True):
        for reward, frame in data.items():
            mcol, scol = f"mean_{key}", f"se_{key}"
            if mcol not in frame.columns:
                continue
            yerr = BASELINE_ERR_MULT * frame[scol].fillna(0.0) if scol in frame.columns else None
            n = int(frame["n"].max())
            ax.errorbar(
                frame["iteration"],
                frame[mcol],
                yerr=yerr,
                marker="o",
                ms=4,
                capsize=3,
                color=REWARD_COLORS.get(reward),
                label=f"{reward} (n={n})",
            )
        ax.set_xlabel("distillation iteration")
        ax.set_ylabel(METRICS[key][1])
        ax.grid(alpha=0.3)
    axes[0].legend()
    se_txt = "SE across seeds" if mode == "seeds" else "pooled SE"
    fig.suptitle(f"clf vs modelfree, student '{REFERENCE_VARIANT}' (bars = 4 x {se_txt})")
    fig.tight_layout()
    _save(fig, out, "baseline", written)


def plot_teacher(
    data,
    eff: pd.DataFrame,
    target: float,
    window: int,
    out: Path,
    written: list[Path],
    notes: list[str],
) -> None:
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    ratios = []
    for curves in data.values():
        for curve in curves.values():
            if "env_steps" in curve.columns:
                c = curve[curve["iteration"] > 0]
                ratios.extend((c["env_steps"] / c["iteration"]).dropna().tolist())
    per_iter = float(np.median(ratios)) if ratios else None
    if per_iter is not None and not np.allclose(ratios, per_iter, rtol=0.01):
        notes.append("teacher_curves: steps per iteration differ between runs; no iteration axis")
        per_iter = None
    for ax, (col, label) in zip(axes, TEACHER_PANELS, strict=True):
        for reward, curves in data.items():
            curve = curves.get(col)
            if curve is None:
                continue
            use_steps = "env_steps" in curve.columns and curve["env_steps"].notna().all()
            x = curve["env_steps"] if use_steps else curve["iteration"]
            color = REWARD_COLORS.get(reward)
            ax.plot(x, curve["mean"], color=color, label=f"{reward} (n={int(curve['n'].max())})")
            band = curve["se"].fillna(0.0)
            ax.fill_between(x, curve["mean"] - band, curve["mean"] + band, color=color, alpha=0.25)
            if col == "mean_distance_m":
                hit = eff[(eff["reward"] == reward) & eff["iteration"].notna()]
                if not hit.empty:
                    row = hit.iloc[0]
                    xv = row["env_steps"] if use_steps else row["iteration"]
                    ax.axvline(xv, color=color, ls=":", lw=1)
                    ax.annotate(
                        f"it {int(row['iteration'])}",
                        (xv, target),
                        color=color,
                        fontsize=8,
                        xytext=(3, 3),
                        textcoords="offset points",
                    )
        if col == "mean_distance_m":
            ax.axhline(target, color="gray", ls="--", lw=1, label=f"target {target:g} m")
        ax.set_xlabel("env steps")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        if per_iter:
            top = ax.secondary_xaxis(
                "top", functions=(lambda s: s / per_iter, lambda i: i * per_iter)
            )
            top.set_xlabel("iteration", fontsize=8)
            top.tick_params(labelsize=7)
    axes[2].legend(fontsize=8)
    fig.suptitle(f"Teacher training (moving avg {window}, band = SE across seeds)", y=1.02)
    fig.tight_layout()
    _save(fig, out, "teacher_curves", written)


# --------------------------------------------------------------------------- tables


def _md_table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(str(c).replace("|", "/") for c in r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def runs_frame(runs: list[Run]) -> pd.DataFrame:
    records = []
    for r in runs:
        n_student = n_teacher = 0
        if r.metrics is not None and "stage" in r.metrics.columns:
            n_teacher = int((r.metrics["stage"] == "teacher").sum())
            n_student = int((r.metrics["stage"] == "student").sum())
        records.append(
            {
                "run": r.label,
                "status": r.status_label,
                "state": r.state,
                "reward": r.reward,
                "variant": r.variant,
                "curriculum": r.curriculum,
                "seed": r.seed,
                "stage": r.stage,
                "compute": r.compute,
                "teacher_rows": n_teacher,
                "student_rows": n_student,
                "eval_rows": 0 if r.evals is None else len(r.evals),
                "summary": r.summary is not None,
                "error": r.error or "",
                "issues": "; ".join(r.issues),
            }
        )
    return pd.DataFrame(records)


def write_tables(
    out: Path,
    listing: pd.DataFrame,
    table: pd.DataFrame,
    eff: pd.DataFrame,
    mode: str,
    written: list[Path],
) -> None:
    listing.to_csv(out / "runs.csv", index=False)
    (out / "runs.md").write_text(
        "# Runs\n\n" + _md_table(list(listing.columns), listing.astype(str).values.tolist())
    )
    written += [out / "runs.csv", out / "runs.md"]
    if not table.empty:
        table.to_csv(out / "final_metrics.csv", index=False)
        vs = f"vs_{REFERENCE_REWARD}_{REFERENCE_VARIANT}"
        header = ["reward", "variant", "n runs"] + [METRICS[k][0] for k in METRICS]
        header.append(f"vs {REFERENCE_REWARD}/{REFERENCE_VARIANT}")
        rows = []
        for _, row in table.iterrows():
            cells = [row["reward"], row["variant"], str(row["n_runs"])]
            cells += [f"{_fmt(row[f'mean_{k}'])} ± {_fmt(row[f'se_{k}'])}" for k in METRICS]
            cells.append(row[vs])
            rows.append(cells)
        se_txt = (
            "SE across seeds (a single-run group keeps its rollout SE)"
            if mode == "seeds"
            else "pooled SE sqrt(sum se_i^2)/n"
        )
        units = ", ".join(f"{METRICS[k][0]} = {METRICS[k][1]}" for k in METRICS)
        (out / "final_metrics.md").write_text(
            "# Final metrics (summary.json of complete runs)\n\n"
            f"mean ± {se_txt}; relative differences vs "
            f"{REFERENCE_REWARD}/{REFERENCE_VARIANT} = (group - ref) / |ref|.\n"
            f"Units: {units}.\n\n" + _md_table(header, rows)
        )
        written += [out / "final_metrics.csv", out / "final_metrics.md"]
    if not eff.empty:
        eff.to_csv(out / "sample_efficiency.csv", index=False)
        written.append(out / "sample_efficiency.csv")


# --------------------------------------------------------------------------- main


def analyze(
    dirs: list[Path], out: Path, target: float = 2.0, window: int = 20, mode: str = "seeds"
) -> dict:
    """Load runs, write figures and tables into ``out``; returns what was computed."""
    runs = discover(dirs)
    notes: list[str] = []
    written: list[Path] = []
    if not runs:
        return {"runs": runs, "notes": notes, "written": written}
    out.mkdir(parents=True, exist_ok=True)

    abl = ablation_data(runs, window, notes)
    if abl:
        plot_ablation(abl, window, out, written)
    base = baseline_data(runs, mode, notes)
    if base:
        plot_baseline(base, mode, out, written)
    else:
        notes.append("skip baseline: no eval.csv student rows for any reward (variant full)")
    teach = teacher_data(runs, window, notes)
    eff = sample_efficiency(runs, teach, target, window)
    if teach:
        plot_teacher(teach, eff, target, window, out, written, notes)
    else:
        notes.append("skip teacher_curves: no teacher rows in any metrics.csv")
    table = final_table(runs, mode, notes)
    if table.empty:
        notes.append("skip final_metrics: no complete run with summary.json")
    listing = runs_frame(runs)
    write_tables(out, listing, table, eff, mode, written)
    return {
        "runs": runs,
        "notes": notes,
        "written": written,
        "ablation": abl,
        "baseline": base,
        "teacher": teach,
        "sample_efficiency": eff,
        "final": table,
        "listing": listing,
    }


def _report(res: dict, out: Path) -> str:
    buf = io.StringIO()
    runs: list[Run] = res["runs"]
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
    eff: pd.DataFrame = res["sample_efficiency"]
    if not eff.empty:
        print(
            f"sample efficiency (teacher distance >= {eff['target_distance_m'].iloc[0]:g} m):",
            file=buf,
        )
        for _, row in eff.iterrows():
            if row["result"] == "reached":
                steps = "" if pd.isna(row["env_steps"]) else f" ({row['env_steps']:.4g} env steps)"
                print(f"  {row['reward']}: iteration {int(row['iteration'])}{steps}", file=buf)
            else:
                print(f"  {row['reward']}: not reached", file=buf)
    table: pd.DataFrame = res["final"]
    if not table.empty:
        vs = f"vs_{REFERENCE_REWARD}_{REFERENCE_VARIANT}"
        print("final metrics:", file=buf)
        for _, row in table.iterrows():
            print(
                f"  {row['reward']}/{row['variant']} (n={row['n_runs']}): "
                f"distance {_fmt(row['mean_distance_m'])} m, "
                f"success {_fmt(row['mean_success_rate'])}; {row[vs]}",
                file=buf,
            )
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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dirs", nargs="+", type=Path, help="run dirs or Hydra sweep dirs")
    ap.add_argument("--out", type=Path, default=None, help="output dir (default <first>/figures)")
    ap.add_argument(
        "--target-distance",
        type=float,
        default=2.0,
        help="teacher sample efficiency: distance [m] to reach (default 2.0)",
    )
    ap.add_argument("--smooth", type=int, default=20, help="moving-average window (iterations)")
    ap.add_argument(
        "--se-mode",
        choices=["seeds", "pooled"],
        default="seeds",
        help="how SEs of several seeds combine (default seeds)",
    )
    args = ap.parse_args(argv)
    for d in args.dirs:
        if not d.is_dir():
            print(
                f"figures.py: {d} is not a directory (expected a run dir or a sweep dir)",
                file=sys.stderr,
            )
            return 2
    out = args.out if args.out is not None else args.dirs[0] / "figures"
    res = analyze(args.dirs, out, args.target_distance, args.smooth, args.se_mode)
    if not res["runs"]:
        where = ", ".join(str(d) for d in args.dirs)
        print(
            f"figures.py: no runs found under {where} (expected a run dir with config.yaml or "
            ".hydra/config.yaml, or a sweep dir with multirun.yaml and job subdirs 0/, 1/, ...)",
            file=sys.stderr,
        )
        return 2
    print(_report(res, out), end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
