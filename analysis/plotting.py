"""Draw the figures from tidy point tables (one row per plotted point).

Every figure is drawn from a tidy frame with the columns of ``POINT_COLUMNS``; the same frame is
written to ``figure_data.csv``, so what a figure shows can be read back number by number. A
series or metric without rows is named in a grey note above its panel instead of being left out
silently.

Every distance panel draws the standing floor (the zero action's distance on the same rollouts,
:class:`analysis.aggregate.Floor`) as a dashed horizontal line: one black line when every series
drawn has the same floor (to 3 significant digits), else one per series in its colour. Runs from
before the floor existed have none: the panel's note says so. Its value is in
``figure_data.csv`` too (``x_name`` ``standing_floor``, one row per figure, panel and series).
"""

from __future__ import annotations

import textwrap
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402

from analysis.aggregate import (  # noqa: E402
    METRICS,
    NO_FLOOR,
    TEACHER_PANELS,
    Curves,
    Floor,
)
from analysis.arms import Comparisons, Series  # noqa: E402

FIG_EXTS = ("png", "pdf")
POINT_COLUMNS = ["figure", "panel", "x_name", "series", "x", "y", "se", "yerr", "n"]
X_LABELS = {
    "student": {"iteration": "distillation iteration", "env_steps": "distillation env steps"},
    "teacher": {"iteration": "teacher iteration", "env_steps": "teacher env steps"},
}


@dataclass(frozen=True)
class FigureSpec:
    """One evaluation figure: which metric against which x per panel, error-bar multiple."""

    stem: str
    panels: tuple[tuple[str, str], ...]  # (metric key, x column)
    err_mult: float
    group: str  # "reward" (arms) or "student" (variants): whose colours and labels
    xstage: str  # "student" or "teacher": which x labels
    title: str


BASELINE_ERR_MULT = 4.0  # the paper's Fig. 4 error bars
BASELINE = FigureSpec(
    stem="baseline",
    panels=(
        ("distance_m", "iteration"),
        ("torque_success", "iteration"),
        ("jerk_success", "iteration"),
        ("success_rate", "iteration"),
        ("abs_torque_nm", "iteration"),
        ("abs_ang_jerk", "iteration"),
    ),
    err_mult=BASELINE_ERR_MULT,
    group="reward",
    xstage="student",
    title="Baseline: {pairs}, student '{full}' -- eval.csv student rows "
    "(fixed evaluation set), bars = 4 x {se}",
)
SAMPLE_EFFICIENCY = FigureSpec(
    stem="sample_efficiency",
    panels=(
        ("distance_m", "iteration"),
        ("success_rate", "iteration"),
        ("distance_m", "env_steps"),
    ),
    err_mult=1.0,
    group="reward",
    xstage="teacher",
    title="Sample efficiency: teachers on the fixed stone evaluation set -- eval.csv teacher "
    "rows, bars = 1 x {se}",
)
ABLATION = FigureSpec(
    stem="ablation",
    panels=(
        ("reward_per_step", "iteration"),
        ("distance_m", "iteration"),
        ("success_rate", "iteration"),
    ),
    err_mult=1.0,
    group="student",
    xstage="student",
    title="Student ablation ({teacher} teacher, vs '{full}') -- eval.csv student rows (fixed evaluation set), "
    "bars = 1 x {se}",
)


def se_text(mode: str) -> str:
    return "SE across seeds" if mode == "seeds" else "pooled SE"


def eval_points(spec: FigureSpec, curves: Curves) -> pd.DataFrame:
    """The tidy points of an evaluation figure: per panel and series, every iteration whose
    metric has a value; ``yerr`` = err_mult x SE (NaN where there is no SE across seeds, e.g.
    n=1: drawn without a bar, never as a zero-length one)."""
    frames = []
    for key, xcol in spec.panels:
        for name, curve in curves.series.items():
            if xcol not in curve.columns:
                continue
            rows = curve[curve[f"mean_{key}"].notna() & curve[xcol].notna()]
            if rows.empty:
                continue
            se = rows[f"se_{key}"]
            frames.append(
                pd.DataFrame(
                    {
                        "figure": spec.stem,
                        "panel": key,
                        "x_name": xcol,
                        "series": name,
                        "x": rows[xcol].to_numpy(dtype=float),
                        "y": rows[f"mean_{key}"].to_numpy(dtype=float),
                        "se": se.to_numpy(dtype=float),
                        "yerr": (spec.err_mult * se).to_numpy(dtype=float),
                        "n": rows[f"n_{key}"].to_numpy(dtype=int),
                    }
                )
            )
    if not frames:
        return pd.DataFrame(columns=POINT_COLUMNS)
    return pd.concat(frames, ignore_index=True)[POINT_COLUMNS]


FLOOR_X = "standing_floor"  # figure_data.csv x_name of a floor row (x is NaN)
FLOOR_GID = "standing_floor"  # the floor lines' gid (svg id; how a test finds them)
FLOOR_DASHES = (0, (5, 2))  # dashed, denser than the grey "--" target line


def floor_points(figure: str, panel: str, floors: dict[str, Floor]) -> pd.DataFrame:
    """figure_data.csv rows of the floors drawn in ``panel``: one per series, y = its floor."""
    if not floors:
        return pd.DataFrame(columns=POINT_COLUMNS)
    return pd.DataFrame(
        {
            "figure": figure,
            "panel": panel,
            "x_name": FLOOR_X,
            "series": list(floors),
            "x": np.nan,
            "y": [f.distance_m for f in floors.values()],
            "se": [f.se_m for f in floors.values()],
            "yerr": np.nan,
            "n": [f.n_runs for f in floors.values()],
        }
    )[POINT_COLUMNS]


def draw_floor(
    ax,
    floors: dict[str, Floor],
    names: list[str],
    styles: dict[str, Series],
    legend: dict[str, object],
    notes: list[str],
    where: str = "",
) -> None:
    """The standing floor of the series ``names`` drawn in a distance panel (module docstring);
    the series without one are named in ``notes``. ``where``: " on <the rollouts it was
    measured on>" when not the panel's own (the training diagnostic)."""
    have = {n: floors[n] for n in names if n in floors}
    lacking = [n for n in names if n not in floors]
    if not have:
        if names:
            notes.append(NO_FLOOR)
        return
    if lacking:
        notes.append(f"no standing floor for {', '.join(lacking)} (eval.csv from before it)")
    if len({f"{f.distance_m:.3g}" for f in have.values()}) == 1:
        y = float(np.mean([f.distance_m for f in have.values()]))
        runs = sum(f.n_runs for f in have.values())
        line = ax.axhline(y, color="black", ls=FLOOR_DASHES, lw=1.2, gid=FLOOR_GID)
        legend.setdefault(
            f"standing floor {y:.3g} m (zero action{where or ' on the same rollouts'}, "
            f"{runs} run{'s' * (runs != 1)})",
            line,
        )
        ax.annotate(
            "standing floor",
            xy=(1.0, y),
            xycoords=("axes fraction", "data"),
            xytext=(-2, 2),
            textcoords="offset points",
            ha="right",
            va="bottom",
            fontsize=7,
        )
        return
    for name, floor in have.items():  # the floors differ: one line per series, in its colour
        color, label = _style(styles, name)
        line = ax.axhline(floor.distance_m, color=color, ls=FLOOR_DASHES, lw=1.2, gid=FLOOR_GID)
        legend.setdefault(f"{label}: {floor.text()}{where.replace(' on', ',', 1)}", line)


def _note(ax, lines: list[str]) -> None:
    """The panel's grey notes as its title: above the axes, never over a data point."""
    if lines:
        ax.set_title(
            "\n".join(textwrap.fill(line, 60) for line in lines),
            loc="left",
            fontsize=7,
            color="dimgray",
        )


def _steps_label(x: float) -> str:
    """An env-step count as a tick label: 64, 98k, 1.2M."""
    for div, unit in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(x) >= div:
            return f"{x / div:.3g}{unit}"
    return f"{x:.0f}"


def _legend_below(fig, legend: dict[str, object]) -> None:
    """One legend for the figure, below the panels: never over a data point."""
    if legend:
        fig.legend(
            list(legend.values()),
            list(legend),
            loc="upper center",
            bbox_to_anchor=(0.5, 0.0),
            ncol=min(4, len(legend)),
            fontsize=8,
            frameon=False,
        )


def save(fig, out: Path, stem: str, written: list[Path]) -> None:
    for ext in FIG_EXTS:
        p = out / f"{stem}.{ext}"
        fig.savefig(p, dpi=150, bbox_inches="tight")
        written.append(p)
    plt.close(fig)


def plot_eval_figure(
    spec: FigureSpec,
    points: pd.DataFrame,
    curves: Curves,
    mode: str,
    out: Path,
    written: list[Path],
    comp: Comparisons,
    target: float | None = None,
    reach: pd.DataFrame | None = None,
) -> dict[str, list[str]]:
    """Draw ``points`` (from :func:`eval_points`) panel by panel; name what has no data.

    ``target``/``reach``: a dashed target-distance line on distance panels and a dotted vertical
    line where each series first reaches it (sample efficiency). Colours and labels come from
    ``comp`` (the arms' or variants' registry). Returns the grey notes written on each panel
    (metric key -> lines).
    """
    styles = comp.arms if spec.group == "reward" else comp.variants
    n_panels = len(spec.panels)
    ncols = min(3, n_panels)
    nrows = -(-n_panels // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(4.6 * ncols, 3.6 * nrows), squeeze=False)
    for ax in axes.flat[n_panels:]:
        ax.set_visible(False)
    names = list(curves.series) + [m for m in curves.missing if m not in curves.series]
    panel_notes: dict[str, list[str]] = {}
    legend: dict[str, object] = {}
    for ax, (key, xcol) in zip(axes.flat, spec.panels, strict=False):
        notes = [f"no data: {m} ({why})" for m, why in curves.missing.items()]
        notes += [f"{m}: {why}; not drawn" for m, why in curves.refused.items()]
        sel = points[(points["panel"] == key) & (points["x_name"] == xcol)]
        xs = np.unique(sel["x"].to_numpy(dtype=float))
        if xs.size > 1:
            step = float(np.min(np.diff(xs)))
        else:  # one evaluation: spread the arms by a fifth of its env steps (1 iteration)
            step = 1.0 if xcol == "iteration" or not xs.size else max(0.2 * abs(xs[0]), 1.0)
        drawn = [n for n in names if not sel[sel["series"] == n].empty]
        empty = [n for n in names if n in curves.series and n not in drawn]
        if empty:
            notes.append(
                f"no mean_{key} for {', '.join(empty)} (no rollout defines it, e.g. none "
                "succeeded; or an older eval.csv)"
            )
        for name in names:
            pts = sel[sel["series"] == name]
            if pts.empty:
                continue
            color, label = _style(styles, name)
            # Arms side by side: each series shifted by a fraction of the x spacing (iterations
            # and env steps alike: two arms at one x would hide each other's bars).
            k = drawn.index(name)
            shift = (k - (len(drawn) - 1) / 2) * 0.12 * step
            n = int(pts["n"].max())
            text = f"{label} (n={n}{', no SE bar' if n < 2 and spec.err_mult else ''})"
            handle = ax.errorbar(
                pts["x"] + shift,
                pts["y"],
                yerr=pts["yerr"],
                marker="o",
                ms=4,
                capsize=3,
                color=color,
                label=text,
            )
            legend.setdefault(text, handle)
            if target is not None and key == "distance_m" and reach is not None:
                hit = reach[(reach["reward"] == name) & reach["iteration"].notna()]
                if not hit.empty and not pd.isna(hit.iloc[0][xcol]):
                    ax.axvline(float(hit.iloc[0][xcol]), color=color, ls=":", lw=1)
        if key == "distance_m":
            draw_floor(ax, curves.floors, drawn, styles, legend, notes)
        if target is not None and key == "distance_m" and not np.isnan(target):
            line = ax.axhline(target, color="gray", ls="--", lw=1)
            legend.setdefault(f"target {target:.3g} m (reach: dotted lines)", line)
        ax.set_xlabel(X_LABELS[spec.xstage].get(xcol, xcol))
        if 0 < xs.size <= 8:  # few evaluations: a tick at each, none in between
            ax.set_xticks(xs)
            show = (lambda x: f"{int(x)}") if xcol == "iteration" else _steps_label
            ax.set_xticklabels([show(x) for x in xs])
            ax.set_xlim(xs[0] - 0.6 * step, xs[-1] + 0.6 * step)
        else:
            ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_ylabel(METRICS[key][1])
        ax.grid(alpha=0.3)
        _note(ax, notes)
        panel_notes[key] = notes
    title = spec.title.format(
        se=se_text(mode),
        pairs=comp.title,
        full=comp.reference_variant,
        teacher=comp.ablation_teacher,
    )
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    _legend_below(fig, legend)
    save(fig, out, spec.stem, written)
    return panel_notes


EXTRA_COLORS = ("tab:green", "tab:orange", "tab:purple", "tab:brown", "tab:olive", "tab:cyan")
_EXTRA_ASSIGNED: dict[str, str] = {}  # series name -> colour, stable across one run's figures


def _style(styles: dict[str, Series], name: str) -> tuple[str | None, str]:
    """(colour, legend label) of a series. A group series (``modelfree [stones, 2 it]``, a
    control) keeps its arm's label with the bracket and gets a colour no arm has."""
    info = styles.get(name)
    if info is not None:
        return info.color, name if info.label == name else f"{info.label} [{name}]"
    base, _, rest = name.partition(" [")
    base_info = styles.get(base)
    if name not in _EXTRA_ASSIGNED:  # the next colour no arm and no earlier series has
        used = {s.color for s in styles.values()} | set(_EXTRA_ASSIGNED.values())
        free = [c for c in EXTRA_COLORS if c not in used] or list(EXTRA_COLORS)
        _EXTRA_ASSIGNED[name] = free[0]
    color = _EXTRA_ASSIGNED[name]
    if base_info is None:
        return color, name
    return color, f"{base_info.label} [{rest}" if rest else base_info.label


def teacher_points(data: dict[str, dict]) -> pd.DataFrame:
    """Tidy points of the training diagnostic (x = env steps where every row has them)."""
    frames = []
    for reward, curves in data.items():
        for col, curve in curves.items():
            use_steps = "env_steps" in curve.columns and curve["env_steps"].notna().all()
            xcol = "env_steps" if use_steps else "iteration"
            frames.append(
                pd.DataFrame(
                    {
                        "figure": "teacher_curves",
                        "panel": col,
                        "x_name": xcol,
                        "series": reward,
                        "x": curve[xcol].to_numpy(dtype=float),
                        "y": curve["mean"].to_numpy(dtype=float),
                        "se": curve["se"].to_numpy(dtype=float),
                        "yerr": curve["se"].fillna(0.0).to_numpy(dtype=float),
                        "n": curve["n"].to_numpy(dtype=int),
                    }
                )
            )
    if not frames:
        return pd.DataFrame(columns=POINT_COLUMNS)
    return pd.concat(frames, ignore_index=True)[POINT_COLUMNS]


def _steps_per_iteration(data: dict[str, dict]) -> float | None:
    ratios = []
    for curves in data.values():
        for curve in curves.values():
            if "env_steps" in curve.columns:
                c = curve[curve["iteration"] > 0]
                ratios.extend((c["env_steps"] / c["iteration"]).dropna().tolist())
    if not ratios:
        return None
    per_iter = float(np.median(ratios))
    return per_iter if np.allclose(ratios, per_iter, rtol=0.01) else None


def plot_teacher_training(
    data: dict[str, dict],
    points: pd.DataFrame,
    window: int,
    out: Path,
    written: list[Path],
    notes: list[str],
    comp: Comparisons,
    refused: dict[str, str] | None = None,
    floors: dict[str, Floor] | None = None,
) -> list[str]:
    """Training diagnostic from metrics.csv teacher rows; says on its face it is no comparison.
    ``floors``: each arm's standing floor on its teacher evaluations (eval.csv), drawn in the
    distance panel with a label saying where it was measured. Returns the distance panel's
    notes."""
    fig, axes = plt.subplots(1, len(TEACHER_PANELS), figsize=(13, 3.8))
    per_iter = _steps_per_iteration(data)
    if per_iter is None and points["x_name"].eq("env_steps").any():
        notes.append("teacher_curves: steps per iteration differ between runs; no iteration axis")
    legend: dict[str, object] = {}
    panel_notes: list[str] = []
    for ax, (col, ylabel) in zip(axes, TEACHER_PANELS, strict=True):
        sel = points[points["panel"] == col]
        for reward in data:
            pts = sel[sel["series"] == reward]
            if pts.empty:
                continue
            color, series_label = _style(comp.arms, reward)
            text = f"{series_label} (n={int(pts['n'].max())})"
            (line,) = ax.plot(pts["x"], pts["y"], color=color, label=text)
            legend.setdefault(text, line)
            ax.fill_between(
                pts["x"], pts["y"] - pts["yerr"], pts["y"] + pts["yerr"], color=color, alpha=0.25
            )
        if col == "mean_distance_m":
            drawn = [reward for reward in data if not sel[sel["series"] == reward].empty]
            where = " on the teacher evaluation set, not these training levels"
            draw_floor(ax, floors or {}, drawn, comp.arms, legend, panel_notes, where)
            _note(ax, panel_notes)
        xname = sel["x_name"].iloc[0] if not sel.empty else "env_steps"
        ax.set_xlabel("teacher env steps" if xname == "env_steps" else "teacher iteration")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        if per_iter and xname == "env_steps":
            top = ax.secondary_xaxis(
                "top", functions=(lambda s: s / per_iter, lambda i: i * per_iter)
            )
            top.set_xlabel("teacher iteration", fontsize=8)
            top.xaxis.set_major_locator(MaxNLocator(integer=True))  # no iteration 1.5
            top.tick_params(labelsize=7)
    _legend_below(fig, legend)
    apart = "".join(f"\n{name}: {why}; not drawn" for name, why in (refused or {}).items())
    fig.suptitle(
        f"DIAGNOSTIC, not a comparison: teacher TRAINING rollouts (metrics.csv; each arm on its "
        f"own curriculum), moving avg {window}, band = SE across seeds" + apart,
        y=1.04 + 0.03 * apart.count("\n"),
        fontsize=10,
    )
    fig.tight_layout()
    save(fig, out, "teacher_curves", written)
    return panel_notes
