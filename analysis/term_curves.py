"""``python analysis/figures.py <runs> --terms``: each run's per-term training curves.

From a run's ``metrics.csv`` (march.env.term_meter, march.learn.metrics): the teacher's
``reward/<term>`` (each term's mean contribution per env step, weighted as it enters the
reward), ``termination/<term>`` (the fraction of ended episodes each termination ended), the
curriculum level (mean +- its spread over the envs) and the distillation's ``loss/<part>``,
against env steps. One figure per run: ``<out>/terms_<run>.png`` (and ``.pdf``), titled with the
run's arm as every output names it (a variant of the paper's arm says so). No figure draws two
runs side by side. A run without per-term columns (written before they existed) is named, not
drawn.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402

from analysis.groups import GroupKey, mismatch_keys, shorten, variant_of_arm  # noqa: E402
from analysis.rundirs import Run  # noqa: E402

PANELS = (
    ("teacher", "reward/", "reward per env step (weighted)"),
    ("teacher", "termination/", "fraction of ended episodes"),
    ("student", "loss/", "distillation objective"),
    ("student", "loss/", "student diagnostics (action error, mixture weights, spread)"),
    (
        "teacher",
        "clf/v_",
        "V/Vmax quantiles over the training steps (r_clf flat above the red line)",
    ),
    ("teacher", "clf/fractions", "CLF: share of steps saturated (V >= Vmax), with dV/dt defined"),
    ("teacher", "clf/share/", "CLF: share of V by output group"),
)
OBJECTIVE_PARTS = ("loss", "nll", "huber")
"""Distillation loss parts on the objective's scale; the others (action error, mode weights,
entropy, std) are on a scale of their own, drawn in the next panel so neither flattens the other."""
MARKERS_UP_TO = 40
"""Points drawn with markers up to this many per line (a short run's 2-3 iterations, a
termination seen once, stay visible)."""


def _smooth(y: pd.Series, window: int) -> pd.Series:
    return y.rolling(max(1, window), min_periods=1).mean()


OBJECTIVE_TITLE = "distillation objective"
"""The loss panel that draws the objective's parts (the other loss panel draws the rest)."""
CLF_FRACTIONS = ("clf/saturated", "clf/dvdt_valid")
"""The CLF diagnostics drawn as shares of steps (march.clf.diagnostics)."""
SHARE_GROUPS = (
    ("CoM", ("com_",)),
    ("pelvis", ("pelvis_",)),
    ("swing position", ("swing_x", "swing_y", "swing_z")),
    ("swing orientation", ("swing_roll", "swing_pitch", "swing_yaw")),
    ("upper-body joints", ("_joint",)),
)
"""Output groups the per-output shares of V are summed into (29 lines would be unreadable)."""


def _in_group(name: str, keys: tuple[str, ...]) -> bool:
    """``com_`` is a prefix, ``_joint`` a suffix, any other key an exact output name (a
    substring test would put ``swing_yaw`` under ``swing_y`` too)."""
    return any(
        name.startswith(k)
        if k.endswith("_")
        else name.endswith(k)
        if k.startswith("_")
        else name == k
        for k in keys
    )


def share_groups(rows: pd.DataFrame) -> dict[str, pd.Series]:
    """Each output group's share of V (the sum of its outputs' ``clf/share/<output>``)."""
    out = {}
    cols = [c for c in rows.columns if c.startswith("clf/share/")]
    for name, keys in SHARE_GROUPS:
        mine = [c for c in cols if _in_group(c[len("clf/share/") :], keys)]
        if mine:
            out[name] = sum(pd.to_numeric(rows[c], errors="coerce") for c in mine)
    return out


def term_columns(metrics: pd.DataFrame, prefix: str, title: str = "") -> list[str]:
    """The columns of a panel: ``prefix``'s, the loss parts split by :data:`OBJECTIVE_PARTS`."""
    if prefix == "clf/fractions":
        return [c for c in CLF_FRACTIONS if c in metrics.columns]
    cols = [c for c in metrics.columns if c.startswith(prefix)]
    if prefix == "loss/" and title:
        objective = title == OBJECTIVE_TITLE
        cols = [c for c in cols if (c[len(prefix) :] in OBJECTIVE_PARTS) == objective]
    return cols


def draw_run(run: Run, out: Path, smooth: int = 1) -> Path | None:
    """Write the run's per-term figure (png + pdf); None when its metrics have no per-term
    columns."""
    fig = term_figure(run, smooth)
    if fig is None:
        return None
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"terms_{run.path.name}.png"
    fig.savefig(path, dpi=120)
    fig.savefig(path.with_suffix(".pdf"))
    plt.close(fig)
    return path


def term_figure(run: Run, smooth: int = 1) -> plt.Figure | None:
    """The run's per-term figure (one panel per :data:`PANELS` entry with data, then the
    curriculum level), or None when its metrics have no per-term columns."""
    m = run.metrics
    if m is None or not any(term_columns(m, p) for _, p, _ in PANELS):
        return None
    panels = [(s, p, t) for s, p, t in PANELS if term_columns(m[m["stage"] == s], p, t)]
    teacher = m[m["stage"] == "teacher"]
    levels = "mean_terrain_level" in m and teacher["mean_terrain_level"].notna().any()
    n = len(panels) + int(bool(levels))
    fig, axes = plt.subplots(n, 1, figsize=(7.0, 2.6 * n), sharex=False, squeeze=False)
    for ax, (stage, prefix, title) in zip(axes[:, 0], panels, strict=False):
        rows = m[m["stage"] == stage]
        if prefix == "clf/share/":
            series = share_groups(rows)
        else:
            series = {
                c[len(prefix) :] if prefix.endswith("/") or prefix == "clf/v_" else c: rows[c]
                for c in term_columns(rows, prefix, title)
            }
        if prefix == "clf/v_":
            ax.set_yscale("log")
            ax.axhline(1.0, color="tab:red", ls="--", lw=1)
        for label, col in series.items():
            y = pd.to_numeric(col, errors="coerce")
            seen = y.notna()
            if seen.any():  # an iteration where no episode ended has no termination value
                few = int(seen.sum()) <= MARKERS_UP_TO
                ax.plot(
                    rows["env_steps"][seen],
                    _smooth(y[seen], smooth),
                    label=label,
                    marker="o" if few else None,
                    markersize=3,
                )
        x = pd.to_numeric(rows["env_steps"], errors="coerce")
        if x.notna().any() and x.max() > x.min():
            pad = 0.03 * (x.max() - x.min())  # the stage's whole span, also for a sparse
            ax.set_xlim(x.min() - pad, x.max() + pad)  # column; points at the ends not clipped
        ax.set_title(f"{stage}: {title}", fontsize=9)
        ax.legend(fontsize=7, ncol=2)
        ax.grid(alpha=0.3)
    if levels:
        ax = axes[-1, 0]
        mean = pd.to_numeric(teacher["mean_terrain_level"], errors="coerce")
        ax.plot(teacher["env_steps"], mean, color="k", label="mean")
        if "terrain_level_std" in teacher:
            std = pd.to_numeric(teacher["terrain_level_std"], errors="coerce")
            ax.fill_between(teacher["env_steps"], mean - std, mean + std, alpha=0.3, label="± std")
        ax.set_title("teacher: curriculum level", fontsize=9)
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("env steps")
    fig.suptitle(f"{run.path.name}: {arm_label(run)} / {run.variant}", fontsize=10)
    fig.tight_layout()
    return fig


def arm_label(run: Run) -> str:
    """The run's arm as every output names it: ``clf``, or ``clf [variant: <what differs>]``
    when its config is not the paper's arm as a whole (analysis.groups.variant_of_arm)."""
    key = GroupKey.of(run)
    why = variant_of_arm(key)
    return f"{run.reward} [variant: {shorten(mismatch_keys(why), 3)}]" if why else str(run.reward)


def draw(runs: list[Run], out: Path, smooth: int = 1) -> list[str]:
    """One figure per run; the lines to print."""
    lines = []
    for run in runs:
        path = draw_run(run, out, smooth)
        if path is None:
            lines.append(f"{run.path}: no per-term columns in metrics.csv (an older run)")
        else:
            lines.append(f"wrote {path} ({arm_label(run)} / {run.variant})")
    return lines
