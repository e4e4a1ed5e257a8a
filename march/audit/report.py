"""The rewards audit's outputs: the table on stdout, strict JSON and one self-explaining PNG."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from march.strict_json import dumps


def write_json(obj: Any, path: Path) -> Path:
    """Strict JSON (no NaN / Infinity tokens; json.dumps refuses them)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(dumps(obj, indent=2) + "\n")
    return path


def _ci(d: dict[str, Any], fmt: str = "{:.3g}") -> str:
    if d["ci_low"] is None:
        return fmt.format(d["mean"])
    return f"{fmt.format(d['mean'])} [{fmt.format(d['ci_low'])}, {fmt.format(d['ci_high'])}]"


def table(arm: dict[str, Any]) -> str:
    """The arm's audit as a text table (one row per behaviour, then the terms, then verdicts)."""
    rows = arm["behaviours"]
    head = (
        f"reward audit: reward={arm['reward']}, {arm['num_envs']} rollouts x "
        f"{arm['horizon_steps']} steps ({arm['horizon_steps'] * arm['step_dt']:.1f} s), "
        f"seed {arm['seed']}; means with 95 % t intervals over rollouts"
    )
    lines = [head]
    fmt = "{:<19}{:>27}{:>28}{:>22}{:>7}{:>7}{:>22}{:>6}{:>22}{:>11}{:>6}"
    lines.append(
        fmt.format(
            "behaviour",
            "return",
            "return/step",
            "progress m",
            "steps",
            "ended",
            "V/Vmax p10/50/90",
            "sat",
            "no-upper p10/50/90",
            "sat no-up",
            "TDs",
        )
    )
    for r in rows:
        v, vn = r.get("v_over_vmax"), r.get("v_over_vmax_no_upper")
        vq = f"{v['p10']:.2f}/{v['p50']:.2f}/{v['p90']:.2f}" if v else "n/a"
        vnq = f"{vn['p10']:.2f}/{vn['p50']:.2f}/{vn['p90']:.2f}" if vn else "n/a"
        sat = f"{100 * r['saturated']:.0f}%" if "saturated" in r else "n/a"
        sat_n = f"{100 * r['saturated_no_upper']:.0f}%" if "saturated_no_upper" in r else "n/a"
        lines.append(
            fmt.format(
                r["behaviour"],
                _ci(r["return"]),
                _ci(r["return_per_step"]),
                _ci(r["distance_m"], "{:.2f}"),
                f"{r['steps']:.0f}",
                f"{100 * r['ended_early']:.0f}%",
                vq,
                sat,
                vnq,
                sat_n,
                str(r.get("touchdowns", "n/a")),
            )
        )
    lines.append(
        "  (no-upper: V without the 17 upper-body outputs' terms; TDs: touchdowns the reference "
        "command counted over the rollouts, while alive; standing must have 0)"
    )
    for r in rows:
        by = ", ".join(f"{k} {100 * v:.0f}%" for k, v in r["ended_by"].items() if v > 0)
        if by:
            lines.append(f"  {r['behaviour']} ended by: {by}")
    names = list(rows[0]["terms"])
    lines.append("per-term return over the horizon (weighted, as it enters the reward):")
    width = max(len(n) for n in names) + 2
    col = max(12, *(len(r["behaviour"]) + 2 for r in rows))
    lines.append(" " * width + "".join(f"{r['behaviour']:>{col}}" for r in rows))
    for n in names:
        lines.append(f"{n:<{width}}" + "".join(f"{r['terms'][n]:>{col}.4g}" for r in rows))
    for v in arm["verdicts"]:
        d, c = v["difference"], v["common_steps"]
        lines.append(
            f"verdict: {v['verdict']} per step at equal time since reset (reward per step over "
            f"the first min(survivals) steps, {c['min']}-{c['max']}, mean {c['mean']:.0f}: "
            f"{v['candidate']} {_ci(v['candidate_per_step'])} vs zero "
            f"{_ci(v['standing_per_step'])}, paired difference {_ci(d)}, "
            f"{100 * v['relative']:+.0f} % of standing's, n={d['n']})"
        )
    for v in arm.get("total_return_differences", []):
        d = v["difference"]
        lines.append(
            f"  not the verdict: total return {v['candidate']} - zero = {_ci(d)} "
            f"({100 * v['relative']:+.0f} %): it pays survival, a behaviour that lives longer "
            "collects more steps"
        )
    if not arm["verdicts"]:
        lines.append("verdict: none (no reference for this arm and no teacher_ckpt= given)")
    for note in arm.get("notes", []):
        lines.append(f"note: {note}")
    return "\n".join(lines)


def figure(arm: dict[str, Any], path: Path) -> Path:
    """One PNG: return per behaviour split by term, V/Vmax spread, distance; verdict in the title."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = arm["behaviours"]
    names = [r["behaviour"] for r in rows]
    terms = list(rows[0]["terms"])
    has_v = any("v_over_vmax" in r for r in rows)
    fig, axes = plt.subplots(1, 3 if has_v else 2, figsize=(15 if has_v else 10, 4.8))
    ax = axes[0]
    y = np.arange(len(rows))
    cmap = plt.get_cmap("tab20")
    pos_left = np.zeros(len(rows))
    neg_left = np.zeros(len(rows))
    for j, t in enumerate(terms):
        vals = np.array([r["terms"][t] for r in rows])
        left = np.where(vals >= 0, pos_left, neg_left)
        ax.barh(y, vals, left=left, color=cmap(j % 20), label=t, height=0.6)
        pos_left += np.maximum(vals, 0)
        neg_left += np.minimum(vals, 0)
    for i, r in enumerate(rows):
        d = r["return"]
        if d["ci_low"] is not None:
            ax.errorbar(
                d["mean"],
                i,
                xerr=[[d["mean"] - d["ci_low"]], [d["ci_high"] - d["mean"]]],
                fmt="kD",
                ms=5,
                capsize=4,
            )
    ax.set_yticks(y, names)
    ax.axvline(0, color="k", lw=0.8)
    ax.set_xlabel(f"return over {arm['horizon_steps']} steps (bars: each term; ◆ total, 95 % CI)")
    ax.legend(fontsize=6, loc="lower right", ncol=2)
    ax.set_title("what the reward pays each behaviour", fontsize=10)
    k = 1
    if has_v:
        ax = axes[1]
        for i, r in enumerate(rows):
            by = r.get("v_p50_by_step")
            if not by:
                continue
            t = np.arange(1, len(by) + 1) * arm["step_dt"]
            yv = np.array([np.nan if x is None else x for x in by], float)
            ax.plot(
                t,
                yv,
                color=cmap(2 * i % 20),
                lw=1.8,
                label=f"{r['behaviour']} (pooled median {r['v_over_vmax']['p50']:.2f}, "
                f"{100 * r['saturated']:.0f}% saturated)",
            )
        ax.axhline(1.0, color="tab:red", ls="--")
        ax.text(
            0.0,
            1.0,
            " V = Vmax: r_clf flat at e^-1 above",
            color="tab:red",
            fontsize=8,
            va="bottom",
        )
        ax.set_yscale("log")
        ax.set_xlabel("time since reset [s] (median over the rollouts still running)")
        ax.set_ylabel("V / Vmax")
        ax.legend(fontsize=7)
        ax.set_title("how far each behaviour is from the reference, over time", fontsize=10)
        k = 2
    ax = axes[k]
    for i, r in enumerate(rows):
        d = r["distance_m"]
        lo = d["ci_low"] if d["ci_low"] is not None else d["mean"]
        hi = d["ci_high"] if d["ci_high"] is not None else d["mean"]
        ax.barh(i, d["mean"], color="tab:green", height=0.6)
        ax.errorbar(d["mean"], i, xerr=[[d["mean"] - lo], [hi - d["mean"]]], fmt="none", ecolor="k")
        ax.text(
            max(hi, 0) + 0.01,
            i,
            f"ended early {100 * r['ended_early']:.0f}%",
            fontsize=8,
            va="center",
        )
    ax.set_yticks(y, names)
    ax.set_xlabel("progress along the course over the rollout [m] (mean, 95 % CI)")
    ax.set_title("what each behaviour achieved", fontsize=10)
    verdict = "; ".join(v["verdict"] for v in arm["verdicts"]) or "no tracking behaviour to judge"
    if arm["verdicts"]:
        verdict += " (per step, equal time since reset)"
    fig.suptitle(
        f"reward={arm['reward']}: {verdict}  (n={arm['num_envs']} rollouts x "
        f"{arm['horizon_steps'] * arm['step_dt']:.1f} s, same seeds)",
        fontsize=11,
    )
    fig.tight_layout(rect=(0, 0, 1, 0.94))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
