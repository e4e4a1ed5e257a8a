"""``python analysis/signal.py <runs...> [--standing <audit json>] [--out <dir>]``: the
learning-signal study (``+sweep=signal``, issue 50): does the CLF reward teach tracking at this
scale?

The criteria are fixed here, before the runs are read (the unit of replication is the seed; every
interval is a 95 % t interval across seeds, n stated; "signal" needs the interval to exclude 0 in
the claimed direction, otherwise "no signal at this scale"):

* **C1 clf: V falls.** Per clf seed, the median V/Vmax of the training steps (``clf/v_p50``)
  averaged over the last ``WINDOW`` iterations minus the first ``WINDOW``. Signal: upper < 0.
* **C2 clf: saturation falls.** The same on ``clf/saturated`` (the share of steps with
  V >= Vmax, where r_clf is flat). Signal: upper < 0.
* **C3 clf tracks better than its control.** Last-window ``clf/v_p50`` of clf minus that of
  modelfree_ref (same stones, budget and reference observation; only the reward differs),
  Welch interval. Signal: upper < 0.
* **C4 clf tracks better than standing.** Last-window ``clf/v_p50`` of clf against the zero-action
  behaviour's median V/Vmax in the same training env (``--standing``: the JSON of
  ``python -m march.audit rewards`` at the same preset). Signal: upper < standing's value. The
  training steps are the stochastic policy's (exploration noise adds to V), so this is the
  harder test.
* **C5 both arms: they survive and move.** Per arm, last-window minus first-window episode length
  and training distance (``mean_episode_length``, ``mean_distance_m``), and the evaluation
  distance at the last evaluation minus the first. Signal: lower > 0.

Added after the runs were read (reported beside the criteria above, which stay as declared):
the same changes with the first window after the start-up transient (:data:`TRANSIENT`), and
C1e, the median V/Vmax of the deterministic policy's evaluation rollouts, last evaluation minus
first (eval.csv).

PPO's health is reported beside them (no criterion): the learning rate the adaptive schedule ends
at, the action std, and ``kl_normaliser`` (the KL the schedule sees before any gradient step).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
import pandas as pd

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from analysis.rundirs import discover  # noqa: E402
from march.stats import mean_summary as t_interval  # noqa: E402
from march.stats import welch_summary as welch_interval  # noqa: E402
from march.strict_json import dumps  # noqa: E402

WINDOW = 5
"""Iterations averaged at the start and at the end of a run."""
TRANSIENT = 5
"""Iterations the start-up transient lasts at the cpu preset (added after reading the runs, and
reported beside the criteria as declared, not instead of them): every env starts standing at
t = 0 and falls or times out over the first few iterations, so the ended episodes' length and
the pooled V/Vmax (more steps late in an episode, where V is large) rise over iterations 1-4
whatever the policy learns. The "after the transient" rows take their first window from
iteration TRANSIENT + 1 on."""
CURVES = (
    ("mean_reward", "episode return (training)"),
    ("clf/v_p50", "median V/Vmax (training steps)"),
    ("clf/saturated", "share of steps with V >= Vmax"),
    ("mean_episode_length", "episode length [steps]"),
    ("mean_distance_m", "distance per episode [m] (training)"),
    ("learning_rate", "learning rate (adaptive schedule)"),
)
ARM_COLOURS = {"clf": "tab:blue", "modelfree_ref": "tab:orange", "modelfree": "tab:red"}


def arm_of(run) -> str:
    if run.reward == "clf":
        return "clf"
    return f"{run.reward}_ref" if run.observe_reference else str(run.reward)


def teacher_metrics(run) -> pd.DataFrame | None:
    df = run.metrics
    if df is None or "stage" not in df:
        return None
    df = df[df["stage"] == "teacher"].sort_values("iteration")
    return df if len(df) >= 2 * WINDOW else None


def window_change(df: pd.DataFrame, col: str, skip: int = 0) -> float:
    """Mean of the last WINDOW iterations minus the mean of WINDOW iterations from ``skip``."""
    if col not in df:
        return math.nan
    y = pd.to_numeric(df[col], errors="coerce").to_numpy()
    if len(y) < skip + 2 * WINDOW:
        return math.nan
    return float(np.nanmean(y[-WINDOW:]) - np.nanmean(y[skip : skip + WINDOW]))


def eval_column_change(run, col: str) -> float:
    ev = run.evals
    if ev is None or col not in ev:
        return math.nan
    ev = ev[ev["stage"] == "teacher"].sort_values("iteration")
    y = pd.to_numeric(ev[col], errors="coerce").to_numpy()
    return float(y[-1] - y[0]) if len(y) >= 2 else math.nan


def last_window(df: pd.DataFrame, col: str) -> float:
    if col not in df:
        return math.nan
    return float(np.nanmean(pd.to_numeric(df[col], errors="coerce").to_numpy()[-WINDOW:]))


def eval_change(run) -> float:
    ev = run.evals
    if ev is None or "mean_distance_m" not in ev:
        return math.nan
    ev = ev[ev["stage"] == "teacher"].sort_values("iteration")
    if len(ev) < 2:
        return math.nan
    d = pd.to_numeric(ev["mean_distance_m"], errors="coerce").to_numpy()
    return float(d[-1] - d[0])


def last_eval(run, col: str = "mean_distance_m") -> float:
    ev = run.evals
    if ev is None or col not in ev:
        return math.nan
    ev = ev[ev["stage"] == "teacher"].sort_values("iteration")
    return float(pd.to_numeric(ev[col], errors="coerce").to_numpy()[-1]) if len(ev) else math.nan


def verdict(ci: dict, direction: str, threshold: float = 0.0) -> str:
    lo, hi = ci["low"], ci["high"]
    if lo is None:
        return f"inconclusive (n={ci['n']})"
    if direction == "down":
        return "signal" if hi < threshold else "no signal at this scale"
    return "signal" if lo > threshold else "no signal at this scale"


def study(runs: list, standing: float | None) -> dict:
    by_arm: dict[str, list] = {}
    for run in runs:
        df = teacher_metrics(run)
        if df is not None:
            by_arm.setdefault(arm_of(run), []).append((run, df))
    rows = []

    def add(name: str, arm: str, ci: dict, direction: str, threshold: float = 0.0) -> None:
        rows.append(
            {"criterion": name, "arm": arm, **ci, "verdict": verdict(ci, direction, threshold)}
        )

    clf = by_arm.get("clf", [])
    ctrl = by_arm.get("modelfree_ref", [])
    if clf:
        add(
            "C1 median V/Vmax, last - first",
            "clf",
            t_interval([window_change(d, "clf/v_p50") for _, d in clf]),
            "down",
        )
        add(
            "C2 saturated share, last - first",
            "clf",
            t_interval([window_change(d, "clf/saturated") for _, d in clf]),
            "down",
        )
    if clf:
        for col, label in (("clf/v_p50", "median V/Vmax"), ("clf/saturated", "saturated share")):
            after = [window_change(d, col, TRANSIENT) for _, d in clf]
            add(f"C1/C2 {label}, after the transient", "clf", t_interval(after), "down")
        evals = [eval_column_change(r, "clf/v_p50") for r, _ in clf]
        add(
            "C1e median V/Vmax of evaluation rollouts, last - first",
            "clf",
            t_interval(evals),
            "down",
        )
    if clf and ctrl:
        add(
            "C3 median V/Vmax, clf - modelfree_ref (last)",
            "clf vs ctrl",
            welch_interval(
                [last_window(d, "clf/v_p50") for _, d in clf],
                [last_window(d, "clf/v_p50") for _, d in ctrl],
            ),
            "down",
        )
    if clf and standing is not None:
        ci = t_interval([last_window(d, "clf/v_p50") for _, d in clf])
        add(f"C4 median V/Vmax (last) vs standing's {standing:.3g}", "clf", ci, "down", standing)
    for arm, items in sorted(by_arm.items()):
        add(
            "C5 episode length, last - first",
            arm,
            t_interval([window_change(d, "mean_episode_length") for _, d in items]),
            "up",
        )
        after = [window_change(d, "mean_episode_length", TRANSIENT) for _, d in items]
        add("C5 episode length, after the transient", arm, t_interval(after), "up")
        add(
            "C5 training distance [m], last - first",
            arm,
            t_interval([window_change(d, "mean_distance_m") for _, d in items]),
            "up",
        )
        add(
            "C5 eval distance [m], last eval - first",
            arm,
            t_interval([eval_change(r) for r, _ in items]),
            "up",
        )
    health = {
        arm: {
            "seeds": [r.seed for r, _ in items],
            "env_steps": int(pd.to_numeric(items[0][1]["env_steps"]).max()),
            "final_eval_distance_m": t_interval([last_eval(r) for r, _ in items]),
            "final_learning_rate": t_interval([last_window(d, "learning_rate") for _, d in items]),
            "final_action_std": t_interval([last_window(d, "action_std") for _, d in items]),
            "kl_normaliser": t_interval([last_window(d, "kl_normaliser") for _, d in items]),
        }
        for arm, items in sorted(by_arm.items())
    }
    return {"criteria": rows, "arms": health, "window": WINDOW, "standing_v_p50": standing}


def _fmt(x) -> str:
    return "n/a" if x is None else f"{x:.3g}"


def markdown(result: dict) -> str:
    lines = [
        "| criterion | arm | mean | 95 % CI | n | verdict |",
        "|---|---|---|---|---|---|",
    ]
    for r in result["criteria"]:
        ci = f"[{_fmt(r['low'])}, {_fmt(r['high'])}]"
        lines.append(
            f"| {r['criterion']} | {r['arm']} | {_fmt(r['mean'])} | {ci} | {r['n']} | {r['verdict']} |"
        )
    lines.append("")
    lines.append(
        "| arm | seeds | env steps | final eval distance [m] | final lr | action std | kl_normaliser |"
    )
    lines.append("|---|---|---|---|---|---|---|")
    for arm, h in result["arms"].items():
        d = h["final_eval_distance_m"]
        lines.append(
            f"| {arm} | {len(h['seeds'])} | {h['env_steps']} | {_fmt(d['mean'])} "
            f"[{_fmt(d['low'])}, {_fmt(d['high'])}] | {_fmt(h['final_learning_rate']['mean'])} | "
            f"{_fmt(h['final_action_std']['mean'])} | {_fmt(h['kl_normaliser']['mean'])} |"
        )
    return "\n".join(lines)


def figure(runs: list, out: Path, title: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(15, 8))
    by_arm: dict[str, list[pd.DataFrame]] = {}
    for run in runs:
        df = teacher_metrics(run)
        if df is not None:
            by_arm.setdefault(arm_of(run), []).append(df)
    for ax, (col, label) in zip(axes.ravel(), CURVES, strict=True):
        for arm, dfs in sorted(by_arm.items()):
            dfs = [d for d in dfs if col in d]
            if not dfs:
                continue
            n = min(len(d) for d in dfs)
            x = pd.to_numeric(dfs[0]["env_steps"]).to_numpy()[:n]
            y = np.stack([pd.to_numeric(d[col], errors="coerce").to_numpy()[:n] for d in dfs])
            m = np.nanmean(y, 0)
            c = ARM_COLOURS.get(arm, "tab:gray")
            for row in y:
                ax.plot(x, row, color=c, alpha=0.25, lw=0.8)
            ax.plot(x, m, color=c, lw=2, label=f"{arm} (mean of {len(dfs)} seeds; thin: each seed)")
            if len(dfs) >= 2:
                from scipy import stats

                h = stats.t.ppf(0.975, len(dfs) - 1) * np.nanstd(y, 0, ddof=1) / math.sqrt(len(dfs))
                ax.fill_between(x, m - h, m + h, color=c, alpha=0.15)
        if col == "clf/v_p50":
            ax.axhline(1.0, color="tab:red", ls="--", lw=1)
            ax.text(x[0], 1.0, " V = Vmax: r_clf flat", color="tab:red", fontsize=8, va="bottom")
        if col == "learning_rate":
            ax.set_yscale("log")
        ax.set_title(label, fontsize=10)
        ax.set_xlabel("env steps")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(title + " (bands: 95 % t interval across seeds)", fontsize=11)
    fig.tight_layout(rect=(0, 0, 1, 0.95))
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("dirs", nargs="+", type=Path, help="sweep or run directories")
    p.add_argument("--standing", type=Path, help="march.audit rewards JSON (reward=clf)")
    p.add_argument("--out", type=Path, help="output directory (default: the first dir)")
    args = p.parse_args(argv)
    for d in args.dirs:
        if not d.is_dir():
            p.exit(2, f"error: {d} is not a directory\n")
    runs = discover(list(args.dirs))
    if not runs:
        p.exit(2, f"error: no run directories under {', '.join(map(str, args.dirs))}\n")
    standing = None
    if args.standing:
        audit = json.loads(args.standing.read_text())
        zero = [b for b in audit["behaviours"] if b["behaviour"] == "zero"]
        if not zero or "v_over_vmax" not in zero[0]:
            p.exit(2, f"error: {args.standing} has no zero-action V/Vmax (audit reward=clf)\n")
        standing = float(zero[0]["v_over_vmax"]["p50"])
    result = study(runs, standing)
    out = args.out or args.dirs[0]
    out.mkdir(parents=True, exist_ok=True)
    md = markdown(result)
    print(md)
    (out / "signal.md").write_text(md + "\n")
    (out / "signal.json").write_text(dumps(result, indent=2, default=str))
    steps = {a: h["env_steps"] for a, h in result["arms"].items()}
    png = figure(runs, out / "signal.png", f"learning-signal study, env steps per run {steps}")
    print(f"wrote {out / 'signal.md'}, {out / 'signal.json'} and {png}")


if __name__ == "__main__":
    main()
