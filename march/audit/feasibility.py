"""The reference's kinematic feasibility: `python -m march.audit reference`.

:func:`reference_report` walks planned references (the planner's receding-horizon loop, ideal
touchdown timing) on generated courses at every curriculum level with the kinematic G1
(:mod:`march.audit.ik_walk`, :mod:`march.audit.kinematic_g1`; the stance foot held as a hard
constraint: flat, or with ``audit.stance=heel_off`` its toe edge held and the heel free to lift,
or with ``heel_toe`` a foot landed toe up first held on its heel edge until flat)
and reports, per level:

- the **error floor** of each output: median and 90th percentile over the control ticks of
  |eta| = |y - y_ref| of the IK's best pose, per output and per group (CoM, pelvis, swing-foot
  position, swing-foot orientation, upper body);
- the **V / Vmax floor**: median, 90th percentile and saturated fraction (V >= Vmax, where
  r_clf is flat at e^-1) of V along the kinematic trajectory (etadot by finite difference), and
  of its position part alone (etadot = 0: what no timing can remove);
- **reach**, judged so that it cannot flatter (issue 55): a planned step is reached when at
  EVERY tick of it every output is within its tolerance and every output's rate within its
  rate tolerance (tolerance / ``rate_time``), the stance foot slid at most ``max_slide``, and
  the step ended in a real touchdown; beside it the old criterion (positions at the touchdown
  tick only) for comparison; for the steps that miss, what missed worst;
- the **stance-foot slide** (p50 / p90 / max over steps), the stance heel's lift and lowest
  height and the foot's pitch (a heel more than ``max_heel_sink`` below where it was held is
  not reached);
- the **jump of the reference at touchdowns**: |y_ref(new step, tau = 0) - y_ref(old step,
  same instant)| per output, positions and rates, p50 / p90 / max over the touchdowns (a
  continuous reference has 0 on the CoM and pelvis; the swing-foot outputs change feet at a
  touchdown, so theirs is the step itself);
- the **step lengths** walked, as a histogram with the reach share in each bin;
- how the walks ended (goal platform, an infeasible plan after a landing off the plan, a step
  without a real touchdown, the step cap).

The planner, HLIP and reference parameters are the env's own: read from the env config the
run's overrides build (:func:`reference_command_cfg`), so every ``reference.*`` option a run
can take is audited as the env would use it. It writes the JSON (strict: no NaN or inf; absent
values are null), prints the tables, draws the PNG and films the hardest level's first course
(:mod:`march.audit.feasibility_media`).
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

# The film renders offscreen; MuJoCo picks its GL backend when first imported (mjlab's choice,
# EGL, unless the user set one).
os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from march.audit.feasibility_tables import jump_table, length_table, table  # noqa: E402
from march.audit.ik_walk import TouchdownRule, WalkTrace, ik_walks  # noqa: E402
from march.audit.kinematic_g1 import ANGLES, GROUPS, IkCfg, KinematicG1, wrap  # noqa: E402
from march.clf.lyapunov import CLF_OUTPUT_NAMES  # noqa: E402
from march.config import MarchConfig  # noqa: E402
from march.env.reference_command import ReferenceCommandCfg  # noqa: E402
from march.errors import ConfigError  # noqa: E402
from march.stats import LEVEL, proportion_ci  # noqa: E402
from march.strict_json import strict  # noqa: E402
from march.world.courses import flat_course, generate_course  # noqa: E402
from march.world.footholds import footholds_from_layouts  # noqa: E402

DEFAULT_OUT = "audit_reference.json"
STEP_BINS = (0.0, 0.45, 0.55, 0.60, 0.65, 0.70, 0.85, math.inf)
"""Edges of the step-length histogram [m]: the G1 reaches steps up to ~0.575 m at the
default CoM height (issue 55's envelope); the planner's bound is 0.85 m."""


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
    rate_time: float = 0.1
    """Each output's rate tolerance is its position tolerance over this [s]: an error of one
    tolerance built up or removed within 5 control ticks (CoM 0.3 m/s, pelvis 0.5 rad/s,
    swing foot 0.2 m/s, swing-foot angles 1 rad/s, upper body 0.5 rad/s)."""
    max_slide: float = 0.01
    """A reached step's stance foot stays within this of its held position [m] (its site, or
    with ``audit.stance=heel_off`` its toe edge's corners, with ``heel_toe``'s heel phase its
    heel edge's)."""
    max_heel_sink: float = 0.001
    """A reached step's stance heel stays above this depth below where it was held [m]: the
    heel never goes into the ground (the IK's linearisation residual is ~1e-6 m)."""
    lift_min: float = 0.02
    """A real touchdown's swing foot rose at least this above its lift-off height [m]."""
    land_tol: float = 0.02
    """... and ends at most this above the planned stone top's height [m]."""

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

    def rate_tolerances(self) -> np.ndarray:
        """(29,) the reach tolerance of each output's rate."""
        return self.tolerances() / self.rate_time

    def touchdown_rule(self) -> TouchdownRule:
        return TouchdownRule(lift_min=self.lift_min, land_tol=self.land_tol)


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


def reference_command_cfg(cfg: MarchConfig) -> ReferenceCommandCfg:
    """The ``reference`` command's config as the env builds it from ``cfg`` (its planner,
    reference, HLIP and CLF sections, with every override of the run): taken from
    :func:`march.env.build.build_env_cfg` (no simulator is built); an arm without the
    reference is audited with it (``reward.observe_reference``)."""
    from march.env.build import build_env_cfg
    from march.env.rewards import REFERENCE_COMMAND

    with_reference = replace(cfg, reward=replace(cfg.reward, observe_reference=True))
    return build_env_cfg(with_reference, "teacher", num_envs=1).commands[REFERENCE_COMMAND]


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


def walk_levels(
    cfg: MarchConfig,
    options: FeasibilityCfg,
    kin: KinematicG1,
    command: ReferenceCommandCfg | None = None,
) -> list[LevelWalks]:
    """Every curriculum level's courses walked by the kinematic G1 (commands: the training
    range ``env.command_vx``, drawn per course; ``command``: the reference command's config,
    default :func:`reference_command_cfg`)."""
    rng = np.random.default_rng(cfg.seed)
    command = command or reference_command_cfg(cfg)
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
            rule=options.touchdown_rule(),
        )
        levels.append(LevelWalks(level, difficulty, kind, vx.tolist(), traces, layouts))
    return levels


def quantiles(x: np.ndarray, top: bool = False) -> dict[str, float | None]:
    """Median and 90th percentile of ``x`` (None when empty); ``top`` adds the maximum."""
    out: dict[str, float | None] = {"median": None, "p90": None}
    if x.size:
        out = {"median": float(np.median(x)), "p90": float(np.quantile(x, 0.9))}
    if top:
        out["max"] = float(x.max()) if x.size else None
    return out


def touchdown_jumps(traces: list[WalkTrace]) -> np.ndarray:
    """(touchdowns, 58) |y_ref(new step, tau = 0) - y_ref(old step, last tick)|: positions
    (angle columns wrapped) then rates, over every pair of consecutive steps of each walk."""
    parts = []
    for t in traces:
        a = t.arrays()
        if len(a["ref_start"]) < 2:
            continue
        d = a["ref_start"][1:] - a["ref_end"][:-1]
        d[:, :29] = np.where(ANGLES, wrap(d[:, :29]), d[:, :29])
        parts.append(np.abs(d))
    return np.concatenate(parts) if parts else np.zeros((0, 58))


def jump_summary(jumps: np.ndarray) -> dict[str, Any]:
    """The jump column's JSON: p50 / p90 / max per output (positions, rates) and per group
    of the Euclidean norm over the group's coordinates."""
    out: dict[str, Any] = {"touchdowns": int(len(jumps))}
    for part, lo in (("position", 0), ("rate", 29)):
        out[part] = {
            n: quantiles(jumps[:, lo + j], top=True) for j, n in enumerate(CLF_OUTPUT_NAMES)
        }
        out[f"{part}_group_norm"] = {
            g: quantiles(np.linalg.norm(jumps[:, lo + a : lo + b], axis=1), top=True)
            for g, (a, b) in GROUPS.items()
        }
    return out


def length_histogram(lengths: np.ndarray, reached: np.ndarray) -> list[dict[str, Any]]:
    """Steps per length bin (:data:`STEP_BINS`) and the share reached in each."""
    rows = []
    for lo, hi in zip(STEP_BINS[:-1], STEP_BINS[1:], strict=True):
        inside = (lengths >= lo) & (lengths < hi)
        n = int(inside.sum())
        rows.append(
            {
                "from_m": lo,
                "to_m": None if math.isinf(hi) else hi,
                "steps": n,
                "reached": float(reached[inside].mean()) if n else None,
            }
        )
    return rows


def judge_steps(arrays: dict[str, np.ndarray], options: FeasibilityCfg) -> dict[str, np.ndarray]:
    """Per step of the concatenated ``arrays``: ``reached`` (every tick, rates, slide, real
    touchdown: module docstring), ``at_touchdown`` (positions at the touchdown tick only: the
    old criterion) and ``cause``, the index of what missed worst (0-28 an output's position,
    29-57 its rate, 58 the slide, 59 no real touchdown, 60 the heel in the ground)."""
    tol, rate_tol = options.tolerances(), options.rate_tolerances()
    pos = arrays["step_max_eta"] / tol
    rate = arrays["step_max_etadot"] / rate_tol
    slide = arrays["slide"][:, None] / options.max_slide
    real = arrays["real_touchdown"].astype(bool)
    low = arrays.get("heel_low", np.zeros(len(slide)))
    sink = np.maximum(-low, 0.0)[:, None] / options.max_heel_sink
    ratios = np.concatenate([pos, rate, slide, np.where(real, 0.0, 1.5)[:, None], sink], axis=1)
    reached = (ratios <= 1.0).all(1)
    return {
        "reached": reached,
        "at_touchdown": (np.abs(arrays["touchdown_eta"]) <= tol).all(1),
        "cause": np.argmax(ratios, axis=1),
    }


CAUSES = [
    *CLF_OUTPUT_NAMES,
    *(f"{n} rate" for n in CLF_OUTPUT_NAMES),
    "slide",
    "no_touchdown",
    "heel_sink",
]
"""What :func:`judge_steps`' cause index names."""


def level_summary(
    walks: LevelWalks, options: FeasibilityCfg, p11: np.ndarray, v_max: float
) -> dict[str, Any]:
    """One level's floors, reach, misses, slide, jumps and step lengths (module docstring) as
    plain JSON values; ``p11`` (29,) the P_11 entries and ``v_max`` the Vmax of the
    position-only V."""
    arrays = [t.arrays() for t in walks.traces]

    def cat(key: str, width: int | None = None) -> np.ndarray:
        parts = [a[key] for a in arrays if a[key].size]
        if not parts:
            return np.zeros((0, width) if width else (0,))
        return np.concatenate(parts)

    eta, etadot, v_ratio = np.abs(cat("eta", 29)), cat("etadot", 29), cat("v_ratio")
    per_step = ("slide", "real_touchdown", "heel_low")
    steps_arrays = {
        k: cat(k, None if k in per_step else 29)
        for k in ("step_max_eta", "step_max_etadot", "touchdown_eta", *per_step)
    }
    lengths, rises = cat("step_length"), cat("step_rise")
    gaps, lifted = cat("landing_gap"), cat("lifted")
    fake = ~steps_arrays["real_touchdown"].astype(bool)
    kin_v = 0.5 * (eta**2 * p11).sum(1) / v_max  # V of the position errors alone
    groups = {g: quantiles(eta[:, lo:hi].ravel()) for g, (lo, hi) in GROUPS.items()}
    outputs = {n: quantiles(eta[:, j]) for j, n in enumerate(CLF_OUTPUT_NAMES)}
    rates = {g: quantiles(np.abs(etadot[:, lo:hi]).ravel()) for g, (lo, hi) in GROUPS.items()}
    judged = judge_steps(steps_arrays, options)
    reached = judged["reached"]
    misses: dict[str, int] = {}
    for j in judged["cause"][~reached]:
        misses[CAUSES[j]] = misses.get(CAUSES[j], 0) + 1
    misses = dict(sorted(misses.items(), key=lambda kv: -kv[1]))
    steps = int(reached.size)
    ends: dict[str, int] = {}
    for t in walks.traces:
        ends[t.end] = ends.get(t.end, 0) + 1
    slide = steps_arrays["slide"]

    def share(x: np.ndarray) -> float | None:
        return float(x.mean()) if steps else None

    return {
        "level": walks.level,
        "difficulty": walks.difficulty,
        "kind": walks.kind,
        "courses": len(walks.traces),
        "command_vx": walks.commands,
        "ticks": int(v_ratio.size),
        "steps": steps,
        "no_touchdown_steps": int(fake.sum()),
        "no_touchdown": {
            "landing_gap_m": quantiles(gaps[fake], top=True),
            "lifted_m": quantiles(lifted[fake]),
            "step_rise_m": quantiles(rises[fake]),
        },
        "walk_ends": ends,
        "eta_abs": {"groups": groups, "outputs": outputs},
        "etadot_abs": {"groups": rates},
        "v_over_vmax": {
            **quantiles(v_ratio),
            "saturated": float((v_ratio >= 1.0).mean()) if v_ratio.size else None,
        },
        "v_position_over_vmax": {
            **quantiles(kin_v),
            "saturated": float((kin_v >= 1.0).mean()) if kin_v.size else None,
        },
        "stance_slide_m": quantiles(slide, top=True),
        "stance_heel_lift_m": quantiles(cat("heel_lift"), top=True),
        "stance_heel_low_m": {"min": float(steps_arrays["heel_low"].min()) if steps else None},
        "stance_pitch_rad": quantiles(cat("stance_pitch"), top=True),
        "landed_toe_up_rad": quantiles(cat("landed_toe_up"), top=True),
        "jump_at_touchdown": jump_summary(touchdown_jumps(walks.traces)),
        "reach": {
            "whole_step": share(reached),
            "reached_steps": int(reached.sum()),
            "whole_step_ci95": list(proportion_ci(int(reached.sum()), steps)[1:])
            if steps
            else None,
            "touchdown_tick_positions": share(judged["at_touchdown"]),
            "misses_by_cause": misses,
            "step_length_m": {
                "reached": quantiles(lengths[reached]),
                "missed": quantiles(lengths[~reached]),
            },
            "step_rise_m": {
                "reached": quantiles(np.abs(rises[reached])),
                "missed": quantiles(np.abs(rises[~reached])),
            },
            "by_step_length": length_histogram(lengths, reached),
        },
    }


def overall_reach(levels: list[dict[str, Any]], target: float = 0.99) -> str:
    """One line: the steps reached over every level with the 95 % Clopper-Pearson interval
    (steps of one walk are not independent trials, so the interval is if anything too narrow),
    what a level's steps without a miss would show, and how many steps without a miss would
    show ``target`` (the lower end of the interval of n of n: ((1 - LEVEL) / 2)^(1/n) >=
    target, 0.025^(1/n) at 95 %)."""
    k = sum(s["reach"].get("reached_steps", 0) for s in levels)
    n = sum(s["steps"] for s in levels)
    if n == 0:
        return "all levels: no step walked"
    p, lo, hi = proportion_ci(k, n)
    per_level = max(1, round(n / len(levels)))
    floor = proportion_ci(per_level, per_level)[1]
    needed = math.ceil(math.log((1.0 - LEVEL) / 2.0) / math.log(target))
    return (
        f"all levels: {k} of {n} steps reached, {100 * p:.1f} % [{100 * lo:.1f}, {100 * hi:.1f}]"
        f" (95 % Clopper-Pearson); {per_level} steps without a miss show >= {100 * floor:.0f} %,"
        f" {100 * target:.0f} % needs {needed} without a miss"
    )


def output_paths(out: str | None) -> tuple[Path, Path, Path]:
    """The JSON path (``out``, default ``audit_reference.json``) and the PNG and MP4 beside it
    (same stem); a name without the .json suffix is one clear error."""
    path = Path(out or DEFAULT_OUT)
    if path.suffix.lower() != ".json":
        raise ConfigError(f"out={path}: give a .json file name, e.g. out={DEFAULT_OUT}")
    return path, path.with_suffix(".png"), path.with_suffix(".mp4")


def reference_report(
    cfg: MarchConfig,
    out: str | None,
    options: FeasibilityCfg | None = None,
    ik: IkCfg | None = None,
) -> dict[str, Any]:
    """Walk, measure, write the JSON / PNG / MP4, print the tables; returns the JSON's dict
    (module docstring). ``options`` sets the course count and tolerances (defaults:
    :class:`FeasibilityCfg`), ``ik`` the IK and its stance-foot model (``audit.stance``)."""
    options = options or FeasibilityCfg()
    json_path, png_path, mp4_path = output_paths(out)
    started = time.perf_counter()
    torch.manual_seed(cfg.seed)
    command = reference_command_cfg(cfg)
    kin = KinematicG1(ik or IkCfg(), clf=command.clf, command=command)
    walks = walk_levels(cfg, options, kin, command)
    p11 = kin.clf.P_blocks_np[:, 0, 0]
    levels = [level_summary(w, options, p11, kin.v_max) for w in walks]
    report = {
        "what": "kinematic feasibility of the planned reference (march.audit reference)",
        "seed": cfg.seed,
        "curriculum": cfg.curriculum.name,
        "options": asdict(options),
        "ik": asdict(kin.cfg),
        "reference": {
            "hlip": asdict(command.hlip),
            "reference": asdict(command.reference),
            "planner_max_step": command.planner.max_step,
        },
        "tolerances": dict(zip(CLF_OUTPUT_NAMES, options.tolerances().tolist(), strict=True)),
        "rate_tolerances": dict(
            zip(CLF_OUTPUT_NAMES, options.rate_tolerances().tolist(), strict=True)
        ),
        "v_max": kin.v_max,
        "levels": levels,
        "seconds": None,
        "files": {"json": str(json_path), "png": str(png_path), "mp4": None},
    }
    from march.audit.feasibility_media import draw_floors, film_walk

    json_path.parent.mkdir(parents=True, exist_ok=True)
    draw_floors(levels, png_path, options.tol_com, options.tol_swing_pos)
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
    print(
        f"stance foot: {kin.cfg.stance}"
        + (
            f" (toe edge held, heel up to {kin.cfg.heel_pitch_max} rad)"
            if kin.toes
            else " (its whole pose held)"
        )
        + (
            f"; a foot landed toe up is held on its heel edge until flat at"
            f" {kin.cfg.heel_flat_by:g} of the step"
            if kin.heels
            else ""
        )
    )
    print(table(levels))
    print(overall_reach(levels))
    print()
    print(jump_table(levels))
    print()
    print(length_table(levels))
    films = f", {mp4_path}" if report["files"]["mp4"] else ""
    print(f"wrote {json_path}, {png_path}{films}")
    sys.stdout.flush()
    return report
