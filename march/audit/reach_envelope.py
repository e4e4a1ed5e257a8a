"""The G1's reach envelope: the longest step whose touchdown pose the kinematic G1 can take,
against the CoM height (``python -m march.audit envelope``, issue 55).

For each CoM height z0 of :class:`EnvelopeCfg` and each step length l, the reference at the
planned touchdown instant of a steady forward step (the stance foot, left, at the origin; the
swing foot landing l ahead at the step width; the HLIP orbit with that z0; the reference's own
pelvis, swing-foot and upper-body outputs) is posed by the whole-body IK
(:class:`march.audit.kinematic_g1.KinematicG1`: the stance foot a hard constraint, flat or with
``audit.stance=heel_off`` its heel free to lift about the held toe edge; the joint limits on)
from the default pose, solved to convergence and held for ``settle_ticks`` ticks.
The pose counts as reached when every output is within the feasibility audit's tolerance
(:class:`march.audit.feasibility.FeasibilityCfg`: CoM 3 cm, pelvis 0.05 rad, swing foot 2 cm,
...) and the stance foot slid at most 1 cm. The envelope at z0 is the longest l of the grid that
was reached (the JSON and the figure keep every pose: at low z0 the short steps miss too, the
CoM staying above its reference with both feet flat).

A static touchdown pose is the hardest instant of a step for reach (both legs spread the most,
the CoM half a step ahead of the stance foot); it says nothing about balance or timing.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from march.audit.feasibility import FeasibilityCfg
from march.audit.kinematic_g1 import IkCfg, KinematicG1
from march.clf.lyapunov import CLF_OUTPUT_NAMES
from march.errors import ConfigError
from march.reference.hlip import HlipCfg
from march.reference.trajectory import ReferenceCfg, StepState, reference_at
from march.strict_json import strict

DEFAULT_OUT = "outputs/audit/envelope.json"


@dataclass
class EnvelopeCfg:
    """The grid of :func:`reach_envelope`."""

    heights: tuple[float, ...] = (0.57, 0.60, 0.62, 0.65, 0.67, 0.70)
    """CoM heights z0 above the stance foot [m] (0.67: the author's, the G1's standing CoM)."""
    min_length: float = 0.40
    """Shortest step length of the grid [m]."""
    max_length: float = 1.00
    """Longest step length of the grid [m]."""
    length_step: float = 0.025
    """Grid spacing of the step lengths [m]."""
    step_width: float = 0.25
    """Lateral distance between the feet [m] (the planner's nominal)."""
    duration: float = 0.55
    """Planned step duration [s] (the middle of the planner's 0.45-0.7 s)."""
    settle_ticks: int = 10
    """Control ticks the touchdown reference is held after the converged solve (the rates
    settle to 0; the pose moves by the IK's last small steps)."""

    def __post_init__(self) -> None:
        if not self.heights or any(not (0.3 < h < 1.0) for h in self.heights):
            raise ConfigError(f"envelope heights {self.heights} must lie in (0.3, 1.0) m")
        if not 0 < self.min_length < self.max_length or self.length_step <= 0:
            raise ConfigError("envelope lengths need 0 < min_length < max_length, step > 0")

    def lengths(self) -> np.ndarray:
        n = int(math.floor((self.max_length - self.min_length) / self.length_step + 1e-9)) + 1
        return self.min_length + self.length_step * np.arange(n)


def touchdown_reference(
    length: float, height: float, cfg: EnvelopeCfg, reference: ReferenceCfg | None = None
) -> np.ndarray:
    """(29,) the reference outputs at the planned touchdown of a steady step of ``length``
    [m] at CoM height ``height`` [m] (module docstring), with the left foot standing at
    (0, w/2, 0), heading +x."""
    w, t = cfg.step_width, torch.tensor
    step = StepState(
        stance_pos=t([[0.0, 0.5 * w, 0.0]]),
        stance_is_left=t([True]),
        swing_start=t([[-length, -0.5 * w, 0.0]]),
        target=t([[length, -0.5 * w, 0.0]]),
        next_target=t([[2.0 * length, 0.5 * w, 0.0]]),
        duration=t([cfg.duration]),
        next_duration=t([cfg.duration]),
        yaw0=t([0.0]),
        yaw_rate=t([0.0]),
        axis=t([[1.0, 0.0]]),
    )
    hlip = HlipCfg(z0=height, step_width=w)
    tau = torch.tensor([cfg.duration])
    pos, _ = reference_at(step, tau, reference or ReferenceCfg(), hlip, 17).flatten()
    return pos[0].double().numpy()


def pose_reached(
    kin: KinematicG1, y_ref: np.ndarray, cfg: EnvelopeCfg, judge: FeasibilityCfg
) -> dict[str, Any]:
    """Pose the kinematic G1 for ``y_ref`` (left foot standing at (0, w/2, 0), flat) and judge
    it (module docstring): reached, the worst output and its |eta| / tolerance, the slide."""
    held = (np.array([0.0, 0.5 * cfg.step_width, 0.0]), np.eye(3))
    kin.stand(y_ref, True, *held)
    tick = None
    for _ in range(cfg.settle_ticks):
        tick = kin.track(y_ref, np.zeros(29), True, *held)
    assert tick is not None
    ratio = np.abs(tick.eta) / judge.tolerances()
    worst = int(np.argmax(ratio))
    held_foot = tick.slide <= judge.max_slide and tick.heel_lift >= -judge.max_heel_sink
    return {
        "reached": bool(ratio.max() <= 1.0 and held_foot),
        "worst_output": CLF_OUTPUT_NAMES[worst],
        "worst_ratio": float(ratio[worst]),
        "com_z_error_m": float(tick.eta[2]),
        "slide_m": float(tick.slide),
        "heel_lift_m": float(tick.heel_lift),
        "stance_pitch_rad": float(tick.stance_pitch),
    }


def longest_reached(lengths: np.ndarray, reached: list[bool]) -> float | None:
    """The longest grid length that was reached (None: none was)."""
    ok = [float(length) for length, r in zip(lengths, reached, strict=True) if r]
    return max(ok) if ok else None


def reach_envelope(
    cfg: EnvelopeCfg | None = None, judge: FeasibilityCfg | None = None, ik: IkCfg | None = None
) -> dict:
    """The envelope's JSON dict: per height the verdict of every grid length and the
    longest step reached (module docstring); ``ik``: the IK and its stance-foot model."""
    cfg, judge = cfg or EnvelopeCfg(), judge or FeasibilityCfg()
    kin = KinematicG1(ik or IkCfg())
    lengths = cfg.lengths()
    rows = []
    for height in cfg.heights:
        poses = [
            pose_reached(kin, touchdown_reference(lv, height, cfg), cfg, judge) for lv in lengths
        ]
        reached = [p["reached"] for p in poses]
        rows.append(
            {
                "com_height_m": height,
                "longest_step_m": longest_reached(lengths, reached),
                "poses": [
                    {"length_m": float(lv)} | p for lv, p in zip(lengths, poses, strict=True)
                ],
            }
        )
    return {
        "what": "the G1's reach envelope: longest step whose touchdown pose the IK takes "
        "(march.audit envelope)",
        "options": asdict(cfg),
        "ik": asdict(kin.cfg),
        "tolerances": dict(zip(CLF_OUTPUT_NAMES, judge.tolerances().tolist(), strict=True)),
        "max_slide_m": judge.max_slide,
        "rows": rows,
    }


def envelope_table(report: dict) -> str:
    """One line per CoM height: the longest step reached and what misses just beyond it."""
    ik = report.get("ik", {})
    stance = ik.get("stance", "flat")
    lines = [
        f"stance foot: {stance}"
        + (f" (heel up to {ik.get('heel_pitch_max')} rad)" if stance == "heel_off" else ""),
        "CoM height m | longest step reached m | heel-up there mm (pitch rad) | "
        "first miss beyond it (output, |eta|/tol)",
    ]
    for row in report["rows"]:
        longest = row["longest_step_m"]
        beyond_it = [p for p in row["poses"] if longest is None or p["length_m"] > longest]
        miss = next((p for p in beyond_it if not p["reached"]), None)
        beyond = "none in the grid"  # every length beyond the longest reached was reached
        if miss is not None:
            beyond = f"{miss['length_m']:.3f} m: {miss['worst_output']} {miss['worst_ratio']:.2f}"
        at = next((p for p in row["poses"] if p["length_m"] == longest), None)
        heel = (
            "-" if at is None else f"{1e3 * at['heel_lift_m']:.1f} ({at['stance_pitch_rad']:.3f})"
        )
        lines.append(
            f"{row['com_height_m']:12.3f} | {'-' if longest is None else f'{longest:.3f}':>22} | "
            f"{heel:>29} | {beyond}"
        )
    return "\n".join(lines)


def draw_envelope(report: dict, path: Path, planner_max_step: float, default_height: float) -> Path:
    """Reached (green) and missed (red) touchdown poses over step length and CoM height, the
    envelope line, the planner's step bound and the default CoM height."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5))
    for row in report["rows"]:
        h = row["com_height_m"]
        for p in row["poses"]:
            ax.plot(p["length_m"], h, "o", color="tab:green" if p["reached"] else "tab:red", ms=4)
    heights = [r["com_height_m"] for r in report["rows"]]
    longest = [
        np.nan if r["longest_step_m"] is None else r["longest_step_m"] for r in report["rows"]
    ]
    ax.plot(longest, heights, "-", color="k", lw=2, label="longest step reached (envelope)")
    ax.axvline(
        planner_max_step, color="tab:blue", ls="--", label=f"planner max step {planner_max_step} m"
    )
    ax.axhline(
        default_height, color="grey", ls=":", label=f"default CoM height z0 = {default_height} m"
    )
    ax.set(xlabel="step length [m] (forward, step width 0.25 m)", ylabel="CoM height z0 [m]")
    ax.set_title(
        "G1 reach envelope: touchdown pose by whole-body IK "
        f"(stance foot {report.get('ik', {}).get('stance', 'flat')}, held; joint limits)\n"
        "green: every output within tolerance, red: not",
        fontsize=10,
    )
    ax.legend(fontsize=8, loc="lower left")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def envelope_report(
    cfg: Any, out: str | None, options: EnvelopeCfg | None = None, ik: IkCfg | None = None
) -> dict:
    """``python -m march.audit envelope``: compute, print, write the JSON and the PNG beside it
    (``ik``: the IK and its stance-foot model, ``audit.stance``)."""
    from march.audit.feasibility import reference_command_cfg

    path = Path(out or DEFAULT_OUT)
    if path.suffix.lower() != ".json":
        raise ConfigError(f"out={path}: give a .json file name, e.g. out={DEFAULT_OUT}")
    started = time.perf_counter()
    command = reference_command_cfg(cfg)
    options = options or EnvelopeCfg(step_width=command.planner.step_width)
    report = reach_envelope(options, ik=ik)
    report["seconds"] = round(time.perf_counter() - started, 1)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(strict(report), indent=1, allow_nan=False))
    png = draw_envelope(report, path.with_suffix(".png"), command.planner.max_step, command.hlip.z0)
    print(envelope_table(report))
    print(f"wrote {path} and {png}")
    return report
