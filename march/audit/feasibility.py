"""The reference's kinematic feasibility: `python -m march.audit reference`.

:func:`reference_report` walks planned references (the planner's receding-horizon loop, ideal
touchdown timing) on generated courses at every curriculum level with the kinematic G1
(:mod:`march.audit.ik_walk`, :mod:`march.audit.kinematic_g1`) and reports, per level:

- the **error floor** of each output: median and 90th percentile over the control ticks of
  |eta| = |y - y_ref| of the IK's best pose, per output and per group (CoM, pelvis, swing-foot
  position, swing-foot orientation, upper body);
- the **V / Vmax floor**: median, 90th percentile and saturated fraction (V >= Vmax, where
  r_clf is flat at e^-1) of V along the kinematic trajectory (etadot by finite difference), and
  of its position part alone (etadot = 0: what no timing can remove);
- **reach**: the fraction of planned steps whose touchdown tick has every output within its
  tolerance (:class:`FeasibilityCfg`), the fraction whose every tick does, and for the steps
  that miss, which output misses worst (|eta| / tolerance) and how long those steps were;
- how the walks ended (goal platform, an infeasible plan after a landing off the plan, the
  step cap).

It writes the JSON (strict: no NaN or inf; absent values are null), prints a table, draws the
PNG and films the hardest level's first course (:mod:`march.audit.feasibility_media`).
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

# The film renders offscreen; MuJoCo picks its GL backend when first imported (mjlab's choice,
# EGL, unless the user set one).
os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from march.audit.ik_walk import WalkTrace, ik_walks  # noqa: E402
from march.audit.kinematic_g1 import GROUPS, IkCfg, KinematicG1  # noqa: E402
from march.clf.lyapunov import CLF_OUTPUT_NAMES  # noqa: E402
from march.config import MarchConfig  # noqa: E402
from march.env.reference_cfg import ReferenceCommandCfg  # noqa: E402
from march.errors import ConfigError  # noqa: E402
from march.strict_json import strict  # noqa: E402
from march.world.courses import flat_course, generate_course  # noqa: E402
from march.world.footholds import footholds_from_layouts  # noqa: E402

DEFAULT_OUT = "audit_reference.json"


@dataclass
class FeasibilityCfg:
    """What :func:`reference_report` walks and how it judges a step."""

    courses_per_level: int = 3
    """Generated courses per curriculum level (seeded by the run's ``seed``); the default
    report takes ~2 minutes on one CPU core, each course ~2.5 s."""
    max_steps: int = 40
    """Steps per walk at most (a 12 m course takes 14-30)."""
    film: bool = True
    """Write the MP4 of the kinematic G1 on the hardest level's first course."""
    tol_com: float = 0.03
    """Reach tolerance on each CoM coordinate [m]."""
    tol_pelvis: float = 0.05
    """Reach tolerance on each pelvis angle [rad]."""
    tol_swing_pos: float = 0.02
    """Reach tolerance on each swing-foot coordinate [m] (half the planner's 0.04 m stone
    margin: a landing this far off the target still lies on the stone)."""
    tol_swing_ori: float = 0.1
    """Reach tolerance on each swing-foot angle [rad]."""
    tol_upper: float = 0.05
    """Reach tolerance on each upper-body joint [rad]."""

    def __post_init__(self) -> None:
        for key, value in asdict(self).items():
            if key == "film":
                continue
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ConfigError(f"audit.{key}={value} must be a positive number")
            if key in ("courses_per_level", "max_steps") and int(value) != value:
                raise ConfigError(f"audit.{key}={value} must be a whole number")

    def tolerances(self) -> np.ndarray:
        """(29,) the reach tolerance of each output."""
        tol = np.empty(29)
        for group, value in (
            ("com", self.tol_com),
            ("pelvis", self.tol_pelvis),
            ("swing_pos", self.tol_swing_pos),
            ("swing_ori", self.tol_swing_ori),
            ("upper", self.tol_upper),
        ):
            lo, hi = GROUPS[group]
            tol[lo:hi] = value
        return tol


@dataclass
class LevelWalks:
    """The walks of one curriculum level."""

    level: int
    difficulty: float
    kind: str
    """"stones" or "flat"."""
    commands: list[float]
    """Forward speed of each course's walk [m/s]."""
    traces: list[WalkTrace]
    layouts: list[Any]


def level_courses(cfg: MarchConfig, level: int, n: int, rng: np.random.Generator) -> tuple:
    """(difficulty, kind, layouts) of ``n`` courses of curriculum ``level`` as the terrain
    generator makes them: difficulty level / (levels - 1); flat_first's lowest
    ``flat_levels`` are flat ground and the stone levels above span difficulty 0..1."""
    c = cfg.curriculum
    if c.name == "flat_first" and level < c.flat_levels:
        return 0.0, "flat", [flat_course(cfg.terrain) for _ in range(n)]
    difficulty = level / (c.num_levels - 1) if c.num_levels > 1 else 0.0
    if c.name == "flat_first":
        above = c.num_levels - c.flat_levels
        difficulty = (level - c.flat_levels) / (above - 1) if above > 1 else 0.0
    return difficulty, "stones", [generate_course(difficulty, cfg.terrain, rng) for _ in range(n)]


def walk_levels(cfg: MarchConfig, options: FeasibilityCfg, kin: KinematicG1) -> list[LevelWalks]:
    """Every curriculum level's courses walked by the kinematic G1 (commands: the training
    range ``env.command_vx``, drawn per course)."""
    rng = np.random.default_rng(cfg.seed)
    command = ReferenceCommandCfg()
    levels = []
    for level in range(cfg.curriculum.num_levels):
        difficulty, kind, layouts = level_courses(cfg, level, options.courses_per_level, rng)
        lo, hi = cfg.env.command_vx
        vx = rng.uniform(lo, hi, size=len(layouts))
        footholds = footholds_from_layouts(layouts, np.stack([lay.origin for lay in layouts]))
        cmd = torch.zeros(len(layouts), 2)
        cmd[:, 0] = torch.as_tensor(vx, dtype=torch.float32)
        traces = ik_walks(
            kin,
            footholds,
            cmd,
            max_steps=options.max_steps,
            seed=cfg.seed + level,
            planner=command.planner,
            hlip=command.hlip,
            reference=command.reference,
            keep_qpos=options.film,
        )
        levels.append(LevelWalks(level, difficulty, kind, vx.tolist(), traces, layouts))
    return levels


def _quantiles(x: np.ndarray) -> dict[str, float | None]:
    if x.size == 0:
        return {"median": None, "p90": None}
    return {"median": float(np.median(x)), "p90": float(np.quantile(x, 0.9))}


def level_summary(
    walks: LevelWalks, tol: np.ndarray, p11: np.ndarray, v_max: float
) -> dict[str, Any]:
    """One level's floors, reach and misses (module docstring) as plain JSON values; ``p11``
    (29,) the P_11 entries and ``v_max`` the Vmax of the position-only V."""
    arrays = [t.arrays() for t in walks.traces]

    def cat(key: str, width: int | None = None) -> np.ndarray:
        parts = [a[key] for a in arrays if a[key].size]
        if not parts:
            return np.zeros((0, width) if width else (0,))
        return np.concatenate(parts)

    eta, etadot, v_ratio = np.abs(cat("eta", 29)), cat("etadot", 29), cat("v_ratio")
    touchdown, step_max = np.abs(cat("touchdown_eta", 29)), cat("step_max_eta", 29)
    lengths, rises, jumps = cat("step_length"), cat("step_rise"), cat("com_jump")
    kin_v = 0.5 * (eta**2 * p11).sum(1) / v_max  # V of the position errors alone
    groups = {g: _quantiles(eta[:, lo:hi].ravel()) for g, (lo, hi) in GROUPS.items()}
    outputs = {n: _quantiles(eta[:, j]) for j, n in enumerate(CLF_OUTPUT_NAMES)}
    rates = {g: _quantiles(np.abs(etadot[:, lo:hi]).ravel()) for g, (lo, hi) in GROUPS.items()}
    reached = (touchdown <= tol).all(1)
    whole = (step_max <= tol).all(1)
    worst = np.argmax(touchdown / tol, axis=1)
    misses: dict[str, int] = {}
    for j in worst[~reached]:
        misses[CLF_OUTPUT_NAMES[j]] = misses.get(CLF_OUTPUT_NAMES[j], 0) + 1
    misses = dict(sorted(misses.items(), key=lambda kv: -kv[1]))
    steps = int(reached.size)
    ends: dict[str, int] = {}
    for t in walks.traces:
        ends[t.end] = ends.get(t.end, 0) + 1
    return {
        "level": walks.level,
        "difficulty": walks.difficulty,
        "kind": walks.kind,
        "courses": len(walks.traces),
        "command_vx": walks.commands,
        "ticks": int(v_ratio.size),
        "steps": steps,
        "walk_ends": ends,
        "eta_abs": {"groups": groups, "outputs": outputs},
        "etadot_abs": {"groups": rates},
        "v_over_vmax": {
            **_quantiles(v_ratio),
            "saturated": float((v_ratio >= 1.0).mean()) if v_ratio.size else None,
        },
        "v_position_over_vmax": {
            **_quantiles(kin_v),
            "saturated": float((kin_v >= 1.0).mean()) if kin_v.size else None,
        },
        "com_reference_jump_m": {
            **_quantiles(jumps),
            "max": float(jumps.max()) if jumps.size else None,
        },
        "reach": {
            "touchdown": float(reached.mean()) if steps else None,
            "whole_step": float(whole.mean()) if steps else None,
            "misses_by_output": misses,
            "step_length_m": {
                "reached": _quantiles(lengths[reached]),
                "missed": _quantiles(lengths[~reached]),
            },
            "step_rise_m": {
                "reached": _quantiles(np.abs(rises[reached])),
                "missed": _quantiles(np.abs(rises[~reached])),
            },
        },
    }


def table(levels: list[dict[str, Any]]) -> str:
    """The per-level table printed on stdout."""

    def pct(x: float | None) -> str:
        return "  -  " if x is None else f"{100 * x:5.1f}"

    def mm(x: float | None, scale: float = 1000.0) -> str:
        return "   -" if x is None else f"{scale * x:5.1f}"

    head = (
        "level diff kind   steps reach% whole% | V/Vmax p50   p90  sat%  Vpos p90 | "
        "p90 |eta|: com mm pelvis mrad swing mm swing-ori mrad upper mrad | "
        "CoM ref jump p90 mm | missed most"
    )
    rows = [head, "-" * len(head)]
    for s in levels:
        g = s["eta_abs"]["groups"]
        v, vp = s["v_over_vmax"], s["v_position_over_vmax"]
        misses = s["reach"]["misses_by_output"]
        miss = ", ".join(f"{k} {n}" for k, n in list(misses.items())[:2]) or "-"
        rows.append(
            f"{s['level']:5d} {s['difficulty']:4.2f} {s['kind']:6s} {s['steps']:5d}  "
            f"{pct(s['reach']['touchdown'])}  {pct(s['reach']['whole_step'])} | "
            f"    {_num(v['median'])} {_num(v['p90'])} {pct(v['saturated'])}   {_num(vp['p90'])} | "
            f"          {mm(g['com']['p90'])}      {mm(g['pelvis']['p90'])}    "
            f"{mm(g['swing_pos']['p90'])}          {mm(g['swing_ori']['p90'])}      "
            f"{mm(g['upper']['p90'])} |               "
            f"{mm(s['com_reference_jump_m']['p90'])} | {miss}"
        )
    return "\n".join(rows)


def _num(x: float | None) -> str:
    return "    -" if x is None else f"{x:6.3f}"


def output_paths(out: str | None) -> tuple[Path, Path, Path]:
    """The JSON path (``out``, default ``audit_reference.json``) and the PNG and MP4 beside it
    (same stem); a name without the .json suffix is one clear error."""
    path = Path(out or DEFAULT_OUT)
    if path.suffix.lower() != ".json":
        raise ConfigError(f"out={path}: give a .json file name, e.g. out={DEFAULT_OUT}")
    return path, path.with_suffix(".png"), path.with_suffix(".mp4")


def reference_report(
    cfg: MarchConfig, out: str | None, options: FeasibilityCfg | None = None
) -> dict[str, Any]:
    """Walk, measure, write the JSON / PNG / MP4, print the table; returns the JSON's dict
    (module docstring). ``options`` sets the course count and tolerances (defaults:
    :class:`FeasibilityCfg`)."""
    options = options or FeasibilityCfg()
    json_path, png_path, mp4_path = output_paths(out)
    started = time.perf_counter()
    torch.manual_seed(cfg.seed)
    kin = KinematicG1(IkCfg())
    walks = walk_levels(cfg, options, kin)
    tol = options.tolerances()
    p11 = kin.clf.P_blocks_np[:, 0, 0]
    levels = [level_summary(w, tol, p11, kin.v_max) for w in walks]
    report = {
        "what": "kinematic feasibility of the planned reference (march.audit reference)",
        "seed": cfg.seed,
        "curriculum": cfg.curriculum.name,
        "options": asdict(options),
        "ik": asdict(kin.cfg),
        "tolerances": dict(zip(CLF_OUTPUT_NAMES, tol.tolist(), strict=True)),
        "v_max": kin.v_max,
        "levels": levels,
        "seconds": None,
        "files": {"json": str(json_path), "png": str(png_path), "mp4": None},
    }
    from march.audit.feasibility_media import draw_floors, film_walk

    json_path.parent.mkdir(parents=True, exist_ok=True)
    draw_floors(levels, png_path, options)
    if options.film:
        hardest = walks[-1]
        problem = film_walk(hardest.traces[0], hardest.layouts[0], mp4_path, kin)
        if problem is None:
            report["files"]["mp4"] = str(mp4_path)
        else:
            report["files"]["mp4_skipped"] = problem
            print(f"no film: {problem}", file=sys.stderr)
    report["seconds"] = round(time.perf_counter() - started, 1)
    report = strict(report)
    json_path.write_text(json.dumps(report, indent=1, allow_nan=False))
    print(table(levels))
    films = f", {mp4_path}" if report["files"]["mp4"] else ""
    print(f"wrote {json_path}, {png_path}{films}")
    sys.stdout.flush()
    return report
