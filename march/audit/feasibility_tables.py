"""The reference audit's printed tables (``python -m march.audit reference``): per curriculum
level, reach and the error floor; the reference's jump at touchdowns; the step lengths walked
with the share reached in each bin. They read the per-level dicts of
:func:`march.audit.feasibility.level_summary` (plain JSON values).
"""

from __future__ import annotations

from typing import Any

JUMP_GROUPS = (
    ("com", "CoM pos mm", 1000.0, "position"),
    ("com", "CoM vel m/s", 1.0, "rate"),
    ("pelvis", "pelvis mrad", 1000.0, "position"),
    ("pelvis", "pelvis rate rad/s", 1.0, "rate"),
    ("swing_pos", "swing mm", 1000.0, "position"),
    ("upper", "upper mrad", 1000.0, "position"),
)
"""The jump table's columns: output group, heading, unit scale, positions or rates."""


def num(x: float | None, scale: float = 1.0, width: int = 6, digits: int = 3) -> str:
    return f"{'-':>{width}}" if x is None else f"{scale * x:{width}.{digits}f}"


def pct(x: float | None) -> str:
    return "  -  " if x is None else f"{100 * x:5.1f}"


def interval(bounds: list[float] | None) -> str:
    """A share's 95 % interval as ``[ 84-100]`` (percent), dashes when there is none."""
    if not bounds:
        return "[  -  - ]"
    lo, hi = (100 * b for b in bounds)
    return f"[{lo:3.0f}-{hi:3.0f}]"


def table(levels: list[dict[str, Any]]) -> str:
    """The per-level reach and floor table printed on stdout."""
    head = (
        "level diff kind   steps reach%  95% CI    td% | slide mm p50   p90   max |"
        " heel-up mm p90   max |"
        " V/Vmax p50   p90  "
        "sat%  Vpos p90 | p90 |eta|: com mm pelvis mrad swing mm swing-ori mrad upper mrad | "
        "missed most"
    )
    rows = [head, "-" * len(head)]
    for s in levels:
        g = s["eta_abs"]["groups"]
        v, vp, sl = s["v_over_vmax"], s["v_position_over_vmax"], s["stance_slide_m"]
        hl = s.get("stance_heel_lift_m", {})  # the stance heel's lift (audit.stance=heel_off)
        misses = s["reach"]["misses_by_cause"]
        miss = ", ".join(f"{k} {n}" for k, n in list(misses.items())[:3]) or "-"
        rows.append(
            f"{s['level']:5d} {s['difficulty']:4.2f} {s['kind']:6s} {s['steps']:5d}  "
            f"{pct(s['reach']['whole_step'])} {interval(s['reach'].get('whole_step_ci95'))} "
            f"{pct(s['reach']['touchdown_tick_positions'])} |"
            f"     {num(sl['median'], 1e3, 5, 1)} {num(sl['p90'], 1e3, 5, 1)} "
            f"{num(sl['max'], 1e3, 5, 1)} |"
            f"           {num(hl.get('p90'), 1e3, 5, 1)} {num(hl.get('max'), 1e3, 5, 1)} |"
            f"     {num(v['median'])} {num(v['p90'])} {pct(v['saturated'])}   "
            f"{num(vp['p90'])} |"
            f"          {num(g['com']['p90'], 1e3, 5, 1)}      {num(g['pelvis']['p90'], 1e3, 5, 1)}"
            f"    {num(g['swing_pos']['p90'], 1e3, 5, 1)}          "
            f"{num(g['swing_ori']['p90'], 1e3, 5, 1)}      {num(g['upper']['p90'], 1e3, 5, 1)} | "
            f"{miss}"
        )
    return "\n".join(rows)


def jump_table(levels: list[dict[str, Any]]) -> str:
    """The reference's jump at touchdown per level: p50 / p90 / max over the touchdowns of
    each group's norm (:data:`JUMP_GROUPS`)."""
    cols = [f"{name} p50/p90/max" for _, name, _, _ in JUMP_GROUPS]
    width = 31
    head = "level touchdowns | " + "".join(f"{c:>{width}}" for c in cols)
    rows = [
        "jump of the reference at touchdown: |y_ref(new step, tau=0) - y_ref(old step, same "
        "instant)|, norm over each group (swing: the output changes feet, so its jump is the step)",
        head,
        "-" * len(head),
    ]
    for s in levels:
        j = s["jump_at_touchdown"]
        cells = []
        for group, _, scale, part in JUMP_GROUPS:
            q = j[f"{part}_group_norm"][group]
            digits = 1 if scale > 1 else 3
            cells.append(
                "/".join(num(q[k], scale, 1, digits).strip() for k in ("median", "p90", "max"))
            )
        rows.append(
            f"{s['level']:5d} {j['touchdowns']:10d} | " + "".join(f"{c:>{width}}" for c in cells)
        )
    return "\n".join(rows)


def length_table(levels: list[dict[str, Any]]) -> str:
    """Steps per length bin and the share reached in each, per level."""
    bins = levels[0]["reach"]["by_step_length"] if levels else []
    labels = [
        f"{b['from_m']:.2f}-{b['to_m']:.2f}" if b["to_m"] is not None else f">={b['from_m']:.2f}"
        for b in bins
    ]
    head = "level reach% | " + "".join(f"{lab + ' m':>16}" for lab in labels)
    rows = ["planned step lengths: steps (reach %) per bin", head, "-" * len(head)]
    for s in levels:
        cells = []
        for b in s["reach"]["by_step_length"]:
            r = "  -" if b["reached"] is None else f"{100 * b['reached']:3.0f}"
            cells.append(f"{b['steps']:4d} ({r}%)")
        rows.append(
            f"{s['level']:5d}  {pct(s['reach']['whole_step'])} | "
            + "".join(f"{c:>16}" for c in cells)
        )
    return "\n".join(rows)
