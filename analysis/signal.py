"""``python analysis/signal.py <runs...> [--standing <audit json>] [--out <dir>]``: the
learning-signal study (``+sweep=signal``, issue 50): does the CLF reward teach tracking at this
scale?

The criteria are fixed here, before the runs are read (the unit of replication is the seed; every
interval is a 95 % t interval across seeds, n stated). Three verdicts (issue 56): "signal" when
the interval lies wholly on the claimed side of the threshold, "adverse" when it lies wholly on
the other side (the change goes the wrong way), otherwise "no signal at this scale":

* **C1 clf: V falls.** Per clf seed, the median V/Vmax of the training steps (``clf/v_p50``)
  averaged over the last ``WINDOW`` iterations minus the first ``WINDOW``. Signal: upper < 0.
* **C2 clf: saturation falls.** The same on ``clf/saturated`` (the share of steps with
  V >= Vmax, where r_clf is flat). Signal: upper < 0.
* **C3 clf tracks better than its control.** Last-window ``clf/v_p50`` of clf minus that of
  modelfree_ref (same stones, budget and reference observation; only the reward differs),
  Welch interval. Signal: upper < 0.
* **C4 clf tracks better than standing.** Like with like (issue 56): the deterministic policy's
  median V/Vmax on its last evaluation's rollouts (eval.csv ``clf/v_p50``) minus the zero
  action's on the same rollouts (``floor_clf/v_p50``, the standing floor of that row), per seed.
  Signal: upper < 0. Rows written before the floor existed fall back to standing's value from
  ``--standing`` (the JSON of ``python -m march.audit rewards`` at the same preset; signal:
  upper < that value). (Until issue 56 C4 compared the *training* steps' V - the stochastic
  policy's, std ~1 - with deterministic standing: it could not pass while the std is ~1: the
  same teacher rolled with its mean action had V/Vmax p50 0.97, with its training noise 3.9.)
* **C5 both arms: they survive and move.** Per arm, last-window minus first-window episode length
  and training distance (``mean_episode_length``, ``mean_distance_m``), and the evaluation
  distance at the last evaluation minus the first. Signal: lower > 0.

* **C6 (declared for the 300-iteration study, issue 56, before its runs were read): the paper's
  sample-efficiency claim at this scale.** clf / modelfree ratio of the mean env steps to first
  reach 90 % of the better arm's final evaluation distance (:func:`sample_efficiency`, the claims
  table's statistic with its censoring): "reproduced (CPU scale)" when the interval is wholly at
  or below 0.5 (the paper: half the env steps), "not reproduced" when wholly above.

Added after the runs were read (reported beside the criteria above, which stay as declared):
the same changes with the first window after the start-up transient (:data:`TRANSIENT`), and
C1e, the median V/Vmax of the deterministic policy's evaluation rollouts, last evaluation minus
first (eval.csv).

PPO's health is reported beside them (no criterion), means of the last window: the learning rate
over each iteration's mini-batches (``lr_mean``, ``lr_min``, ``lr_max``; older runs: the last
mini-batch's ``learning_rate``), the KL the update moved the policy by (``kl_update``) and its
normaliser's part (``kl_normaliser``), the clip fraction, and the action std by joint group
(march.learn.update_readout). Every evaluation distance and success rate is printed and drawn
beside the standing floor's (the zero action on the same rollouts, ``floor_distance_m``,
``floor_success_rate``); success is a reported outcome, not a criterion (issue 56 asks for its
curve; it was added before the study's modelfree arms were read).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from analysis.claims import ClaimsInput, steps_to_target  # noqa: E402
from analysis.rundirs import discover  # noqa: E402
from march.stats import mean_summary as t_interval  # noqa: E402
from march.stats import welch_summary as welch_interval  # noqa: E402
from march.store.bounded_read import FileRefused, read_json  # noqa: E402
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
    ("mean_distance_m", "distance per episode [m] (training; feet)"),
    ("eval:mean_distance_m", "evaluation distance [m] (deterministic; feet)"),
    ("eval:mean_success_rate", "evaluation success rate (deterministic)"),
    ("lr_mean", "learning rate: mean over mini-batches (band: min-max)"),
    ("kl_update", "KL of the update (dashed: normaliser's part)"),
    ("action_std_groups", "action std by joint group"),
)
"""The figure's panels: a metrics.csv column, ``eval:<column>`` of eval.csv (teacher rows), or a
composite panel drawn by :func:`figure`."""
EVAL_FLOORS = {"mean_distance_m": "floor_distance_m", "mean_success_rate": "floor_success_rate"}
"""The standing floor's eval.csv column drawn beside each evaluation panel's."""
GROUP_STYLES = {"legs": "-", "waist": "--", "arms": ":"}
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
    """signal: the interval wholly on the claimed side of ``threshold`` (below it for "down",
    above for "up"); adverse: wholly on the other side; else no signal at this scale."""
    lo, hi = ci["low"], ci["high"]
    if lo is None:
        return f"inconclusive (n={ci['n']})"
    good, bad = (
        (hi < threshold, lo > threshold)
        if direction == "down"
        else (
            lo > threshold,
            hi < threshold,
        )
    )
    if good:
        return "signal"
    return "adverse" if bad else "no signal at this scale"


PAPER_STEP_RATIO = 0.5
"""The paper's sample-efficiency claim: the clf teacher reaches the model-free teacher's distance
with half its env steps (C6)."""


def sample_efficiency(clf: list, modelfree: list) -> dict:
    """C6, the paper's sample-efficiency claim read at this scale: the ratio of the arms' mean
    env steps to first reach :attr:`ClaimsInput.threshold_fraction` of the better arm's final
    evaluation distance (clf / modelfree; analysis.claims.steps_to_target, the claims table's
    statistic: crossings known to the evaluation grid, censored seeds bounded, Fieller's
    interval over every corner). "reproduced" when the whole interval is at or below
    :data:`PAPER_STEP_RATIO`, "not reproduced" when it is wholly above, else inconclusive."""
    est, target, note = steps_to_target(clf, modelfree, ClaimsInput.threshold_fraction)

    def num(x: float) -> float | None:  # the JSON's None: undefined, or unbounded (inf)
        return float(x) if math.isfinite(x) else None

    lo, hi = num(est.low), num(est.high)
    if math.isnan(est.low) or math.isnan(est.high):
        word = f"inconclusive ({est.why or 'no interval'})"
    elif est.high <= PAPER_STEP_RATIO:
        word = "reproduced (CPU scale)"
    elif est.low > PAPER_STEP_RATIO:
        word = "not reproduced (CPU scale)"
    else:
        word = "inconclusive at this scale"
    if math.isinf(est.high):
        word += "; the interval is unbounded above (a seed never reached the target)"
    return {
        "mean": num(est.point),
        "low": lo,
        "high": hi,
        "n": f"{est.n_a} vs {est.n_b}",
        "verdict": word,
        "target_m": num(target),
        "note": note,
    }


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
    if clf:
        paired = [last_eval(r, "clf/v_p50") - last_eval(r, "floor_clf/v_p50") for r, _ in clf]
        if any(math.isfinite(v) for v in paired):
            add(
                "C4 median V/Vmax of evaluation rollouts (last), policy - standing on them",
                "clf",
                t_interval(paired),
                "down",
            )
        elif standing is not None:
            ci = t_interval([last_eval(r, "clf/v_p50") for r, _ in clf])
            add(
                f"C4 median V/Vmax of evaluation rollouts (last) vs standing's {standing:.3g}",
                "clf",
                ci,
                "down",
                standing,
            )
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

    if clf and by_arm.get("modelfree"):
        c6 = sample_efficiency([r for r, _ in clf], [r for r, _ in by_arm["modelfree"]])
        target, note = c6.pop("target_m"), c6.pop("note")
        rows.append(
            {
                "criterion": (
                    f"C6 env steps to {ClaimsInput.threshold_fraction:.0%} of the better final "
                    f"eval distance ({_fmt(target)} m), clf / modelfree "
                    f"(paper: <= {PAPER_STEP_RATIO}); {note}"
                ),
                "arm": "clf vs modelfree",
                **c6,
            }
        )

    def lasts(items: list, col: str) -> dict:
        return t_interval([last_window(d, col) for _, d in items])

    health = {
        arm: {
            "seeds": [r.seed for r, _ in items],
            "env_steps": int(pd.to_numeric(items[0][1]["env_steps"]).max()),
            "final_eval_distance_m": t_interval([last_eval(r) for r, _ in items]),
            "standing_floor_m": t_interval([last_eval(r, "floor_distance_m") for r, _ in items]),
            "final_eval_success": t_interval([last_eval(r, "mean_success_rate") for r, _ in items]),
            "standing_floor_success": t_interval(
                [last_eval(r, "floor_success_rate") for r, _ in items]
            ),
            "final_learning_rate": lasts(items, "learning_rate"),
            "lr_mean": lasts(items, "lr_mean"),
            "lr_min": lasts(items, "lr_min"),
            "lr_max": lasts(items, "lr_max"),
            "kl_update": lasts(items, "kl_update"),
            "kl_normaliser": lasts(items, "kl_normaliser"),
            "clip_fraction": lasts(items, "clip_fraction"),
            "final_action_std": lasts(items, "action_std"),
            **{f"action_std_{g}": lasts(items, f"action_std_{g}") for g in GROUP_STYLES},
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
        "| arm | seeds | env steps | final eval distance [m] | standing floor [m] | "
        "final eval success (standing) | "
        "lr mean (min-max) | KL update (normaliser) | clip | std legs / waist / arms |"
    )
    lines.append("|---|---|---|---|---|---|---|---|---|---|")
    for arm, h in result["arms"].items():
        d, f = h["final_eval_distance_m"], h["standing_floor_m"]
        ok, ok_floor = h["final_eval_success"], h["standing_floor_success"]
        m = {k: (v["mean"] if isinstance(v, dict) else None) for k, v in h.items()}
        lr = (
            f"{_fmt(m['lr_mean'])} ({_fmt(m['lr_min'])}-{_fmt(m['lr_max'])})"
            if m["lr_mean"] is not None
            else f"{_fmt(m['final_learning_rate'])} (last mini-batch)"
        )
        std = " / ".join(_fmt(m[f"action_std_{g}"]) for g in GROUP_STYLES)
        if m["action_std_legs"] is None:
            std = f"{_fmt(m['final_action_std'])} (all joints)"
        lines.append(
            f"| {arm} | {len(h['seeds'])} | {h['env_steps']} | {_fmt(d['mean'])} "
            f"[{_fmt(d['low'])}, {_fmt(d['high'])}] | {_fmt(f['mean'])} | "
            f"{_fmt(ok['mean'])} [{_fmt(ok['low'])}, {_fmt(ok['high'])}] "
            f"({_fmt(ok_floor['mean'])}) | {lr} | "
            f"{_fmt(m['kl_update'])} ({_fmt(m['kl_normaliser'])}) | {_fmt(m['clip_fraction'])} | "
            f"{std} |"
        )
    return "\n".join(lines)


def _series(frames: list[pd.DataFrame], col: str) -> tuple[np.ndarray, np.ndarray] | None:
    """(x env steps, y (seeds, n)) of ``col`` over the common length of ``frames``."""
    frames = [d for d in frames if col in d and len(d)]
    if not frames:
        return None
    n = min(len(d) for d in frames)
    x = pd.to_numeric(frames[0]["env_steps"]).to_numpy()[:n]
    y = np.stack([pd.to_numeric(d[col], errors="coerce").to_numpy()[:n] for d in frames])
    return x, y


def _band(ax, x: np.ndarray, y: np.ndarray, colour: str, label: str, style: str = "-") -> None:
    """Each seed thin, the mean thick, the 95 % t band across seeds."""
    m = np.nanmean(y, 0)
    for row in y:
        ax.plot(x, row, color=colour, alpha=0.25, lw=0.8, ls=style)
    ax.plot(x, m, color=colour, lw=2, ls=style, label=label)
    if len(y) >= 2:
        from scipy import stats

        h = stats.t.ppf(0.975, len(y) - 1) * np.nanstd(y, 0, ddof=1) / math.sqrt(len(y))
        ax.fill_between(x, m - h, m + h, color=colour, alpha=0.15)


def _teacher_evals(run) -> pd.DataFrame | None:
    ev = run.evals
    if ev is None or "stage" not in ev:
        return None
    return ev[ev["stage"] == "teacher"].sort_values("iteration")


def figure(runs: list, out: Path, title: str) -> Path:
    """The study's curves per arm (:data:`CURVES`); every evaluation-distance panel draws the
    standing floor (the zero action on the same rollouts, eval.csv ``floor_distance_m``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(4, 3, figsize=(16, 16))
    by_arm: dict[str, list[tuple[Any, pd.DataFrame]]] = {}
    for run in runs:
        df = teacher_metrics(run)
        if df is not None:
            by_arm.setdefault(arm_of(run), []).append((run, df))
    for ax in axes.ravel()[len(CURVES) :]:
        ax.set_visible(False)
    for ax, (col, label) in zip(axes.ravel(), CURVES, strict=False):
        for arm, items in sorted(by_arm.items()):
            c = ARM_COLOURS.get(arm, "tab:gray")
            frames = [d for _, d in items]
            what = f"{arm} ({len(items)} seeds)"
            if col.startswith("eval:"):
                evals = [e for e in (_teacher_evals(r) for r, _ in items) if e is not None]
                got = _series(evals, col[5:])
                if got is not None:
                    _band(ax, *got, c, what)
                floor = _series(evals, EVAL_FLOORS.get(col[5:], ""))
                if floor is not None and np.isfinite(floor[1]).any():
                    ax.plot(floor[0], np.nanmean(floor[1], 0), color=c, lw=1.2, ls=":",
                            label=f"{arm}: standing floor (zero action, same rollouts)")  # fmt: skip
            elif col == "lr_mean":
                got = _series(frames, "lr_mean") or _series(frames, "learning_rate")
                if got is not None:
                    _band(ax, *got, c, what)
                lo, hi = _series(frames, "lr_min"), _series(frames, "lr_max")
                if lo is not None and hi is not None:
                    ax.fill_between(lo[0], np.nanmean(lo[1], 0), np.nanmean(hi[1], 0),
                                    color=c, alpha=0.1, hatch="//")  # fmt: skip
                ax.set_yscale("log")
            elif col == "kl_update":
                for name, style in (("kl_update", "-"), ("kl_normaliser", "--")):
                    got = _series(frames, name)
                    if got is not None:
                        _band(ax, *got, c, f"{what}: {name}", style)
                ax.set_yscale("log")
            elif col == "action_std_groups":
                for g, style in GROUP_STYLES.items():
                    got = _series(frames, f"action_std_{g}")
                    if got is not None:
                        _band(ax, *got, c, f"{arm}: {g}", style)
            else:
                got = _series(frames, col)
                if got is not None:
                    _band(ax, *got, c, f"{what}; thin: each seed")
        if col == "clf/v_p50":
            ax.axhline(1.0, color="tab:red", ls="--", lw=1)
            ax.text(0.01, 1.0, " V = Vmax: r_clf flat", color="tab:red", fontsize=8,
                    va="bottom", transform=ax.get_yaxis_transform())  # fmt: skip
        ax.set_title(label, fontsize=10)
        ax.set_xlabel("env steps")
        if ax.lines:
            ax.legend(fontsize=6)
    fig.suptitle(title + " (bands: 95 % t interval across seeds)", fontsize=11)
    fig.tight_layout(rect=(0, 0, 1, 0.96))
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
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
        try:
            audit = read_json(args.standing, str(args.standing), wanted="the audit's JSON")
        except FileRefused as err:
            p.exit(2, f"error: {err}\n")
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
