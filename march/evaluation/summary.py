"""What an evaluation prints and leaves as its summary: the console line, the summary block and
``summary.json`` (strict JSON), each with the standing floor beside the policy's distance.

The rows themselves are :mod:`march.evaluation.protocol`'s.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from march.evaluation.protocol import COUNTED
from march.store.checkpoint import write_json_atomic
from march.strict_json import null_because, strict


def eval_line(row: dict[str, Any]) -> str:
    """The one console line of an evaluation row: distance beside the standing floor."""
    floor = row.get("floor_distance_m", float("nan"))
    return (
        f"[eval] {row['stage']} it {row['iteration']}: distance {row['mean_distance_m']:.3g} m "
        f"(standing floor {floor:.3g} m), success {100 * row['mean_success_rate']:.0f}%, "
        f"reward {row['mean_reward']:.3g}"
    )


def write_summary(row: dict[str, Any], run_dir: Path, extra: dict[str, Any]) -> Path:
    """summary.json, strict JSON: an undefined mean or SE (no successful rollout, one rollout)
    is null, and ``null_because`` names the count that says why (march.strict_json)."""
    path = run_dir / "summary.json"
    counts = {metric: count for count, metric in COUNTED.items()}
    why = null_because(row, counts, "n_rollouts")
    write_json_atomic(strict({**row, **extra, **({"null_because": why} if why else {})}), path)
    return path


def format_summary(row: dict[str, Any]) -> str:
    def pm(name: str, unit: str = "", scale: float = 1.0) -> str:
        return f"{row[f'mean_{name}'] * scale:.3g} ± {row[f'se_{name}'] * scale:.2g}{unit}"

    n = row["n_rollouts"]
    left_out = ""
    if row.get("n_torque", n) < n or row.get("n_jerk", n) < n:
        left_out = (
            f" ({n - row.get('n_torque', n)} too short for torque, "
            f"{n - row.get('n_jerk', n)} for jerk: left out of those means)"
        )
    floor = ""
    if "floor_distance_m" in row:
        floor = (
            f"   (standing floor {row['floor_distance_m']:.3g} ± "
            f"{row['floor_se_distance_m']:.2g} m: the zero action on the same rollouts)"
        )
    return (
        f"  rollouts          {n}{left_out}\n"
        f"  distance          {pm('distance_m', ' m')}{floor}\n"
        f"  success           {pm('success_rate', ' %', 100.0)}\n"
        f"  |joint torque|    {pm('abs_torque_nm', ' N m')}\n"
        f"  |angular jerk|    {pm('abs_ang_jerk', ' rad/s^3')}\n"
        f"  teacher reward    {pm('reward')} (episode return)" + clf_summary(row)
    )


def clf_summary(row: dict[str, Any]) -> str:
    """The CLF diagnostics' summary lines (a clf-arm row; "" without them): V/Vmax quantiles,
    saturation (V >= Vmax: r_clf flat at e^-1) and the outputs with the largest share of V."""
    if "clf/v_p50" not in row:
        return ""
    shares = {k.split("/", 2)[2]: v for k, v in row.items() if k.startswith("clf/share/")}
    top = sorted(((v, k) for k, v in shares.items() if v == v), reverse=True)[:4]
    return (
        f"\n  CLF V/Vmax        p10 {row['clf/v_p10']:.3g}, p50 {row['clf/v_p50']:.3g}, "
        f"p90 {row['clf/v_p90']:.3g}; saturated {100 * row['clf/saturated']:.0f} % of steps "
        f"(r_clf flat at e^-1 there); dV/dt defined {100 * row['clf/dvdt_valid']:.0f} %"
        f"\n  share of V        " + ", ".join(f"{k} {100 * v:.0f} %" for v, k in top)
    )
