"""Planned walks tracked by the kinematic G1: the planner's receding-horizon loop with the
whole-body IK in place of the robot.

:func:`ik_walks` plays the loop of :func:`march.reference.walk.walk_course` (plan at each
touchdown, take step 0, stop at the goal platform or at an infeasible plan) over a batch of
courses, and at every control tick of every step poses :class:`~march.audit.kinematic_g1.KinematicG1`
for that instant's reference (:func:`march.reference.trajectory.reference_at`). As in the env
(``march.env.reference_command``), a touchdown happens at the planned duration (the first tick
with tau >= T: ideal timing), the next plan starts from where the IK's swing foot actually
landed, the new stance foot is held at its landing pose, and the new swing foot lifts off from
where it stands; so a step the G1 cannot reach moves the walk where the robot really is, and a
landing off the stones ends the walk as an infeasible plan. Each step is built as the env's
command term builds it (:func:`next_step`): the CoM reference carries the previous step's
reference CoM state at the touchdown tick (``reference.com_anchoring=continuous``, the default;
``stance`` anchors each step's orbit at the new stance foot, the earlier reference), at the
step's CoM height (``reference.com_height``), and the new swing foot's pitch at the touchdown tick
(``reference.swing_pitch_carry``, which the env reads from the site's rotation), so the audit
measures the reference the env tracks.

With ``IkCfg.stance=heel_toe`` a step whose stance foot landed toe up
(``reference.swing_heel_strike``) holds it on its heel edge while its toe comes down
(:func:`heel_landing`, :func:`toe_up_bound`); a heel strike's landing gap is the heel's, not
the raised site's.

Only a real touchdown ends a step and replans (issue 55): the swing foot must have left the
ground (risen ``lift_min`` above its lift-off height) and come down onto the planned stone top
(at most ``land_tol`` above its height at the touchdown tick; a foot below the top would have
hit the stone). A step without one ends the walk (``no_touchdown``): the env would see no
contact there and restart the step at its timeout.

Each step also records the reference at its two ends (positions and rates at tau = 0 and at
its last tick), so the report can measure how far the reference jumps at a touchdown:
y_ref of the new step at tau = 0 minus y_ref of the old step at the same instant.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

import numpy as np
import torch

from march.audit.kinematic_g1 import KinematicG1, rotation_zyx, tracking_error
from march.reference.hlip import HlipCfg
from march.reference.planner import Plan, PlannerCfg, plan_footsteps
from march.reference.trajectory import (
    ReferenceCfg,
    StepState,
    com_state,
    pelvis_state,
    reference_at,
    step_state_from_plan,
)
from march.world.footholds import Footholds

NUM_UPPER = 17


@dataclass
class WalkTrace:
    """One course walked by the kinematic G1: every tick's errors and every step's landing."""

    eta: list[np.ndarray] = field(default_factory=list)
    """Per tick (29,) y - y_ref (angles wrapped)."""
    etadot: list[np.ndarray] = field(default_factory=list)
    """Per tick (29,) the error's rate over the tick, (eta - eta_before) / dt
    (:meth:`KinematicG1.track`)."""
    v_ratio: list[float] = field(default_factory=list)
    """Per tick V / Vmax."""
    tick_step: list[int] = field(default_factory=list)
    """Per tick the index of its step."""
    qpos: list[np.ndarray] = field(default_factory=list)
    """Per tick the solved configuration (for the film)."""
    y_ref: list[np.ndarray] = field(default_factory=list)
    """Per tick the reference outputs (29,)."""
    touchdown_eta: list[np.ndarray] = field(default_factory=list)
    """Per step (29,) eta at its touchdown tick."""
    step_max_eta: list[np.ndarray] = field(default_factory=list)
    """Per step (29,) max |eta| over its ticks."""
    step_max_etadot: list[np.ndarray] = field(default_factory=list)
    """Per step (29,) max |etadot| over its ticks."""
    slide: list[float] = field(default_factory=list)
    """Per step the largest slide of the stance foot's held contact [m] (the site, or with
    ``IkCfg.stance=heel_off`` the toe edge's corners: :meth:`KinematicG1.contact`)."""
    heel_lift: list[float] = field(default_factory=list)
    """Per step the stance heel's highest lift above where it was held [m] (0: flat)."""
    heel_low: list[float] = field(default_factory=list)
    """Per step the stance heel's lowest height against where it was held [m] (< 0: into
    the ground)."""
    stance_pitch: list[float] = field(default_factory=list)
    """Per step the stance foot's largest heel-up pitch [rad]."""
    tick_heel_lift: list[float] = field(default_factory=list)
    """Per tick the stance heel's lift [m]."""
    tick_stance_pitch: list[float] = field(default_factory=list)
    """Per tick the stance foot's pitch against its held (flat) pose [rad], positive heel up,
    negative toe up (``heel_toe``'s heel phase)."""
    tick_slide: list[float] = field(default_factory=list)
    """Per tick the slide of the stance foot's held contact [m]
    (:class:`~march.audit.kinematic_g1.Tick`)."""
    landed_toe_up: list[float] = field(default_factory=list)
    """Per step the toe-up pitch its stance foot landed with [rad] (``heel_toe``; 0 for a flat
    or toe-down landing and with the other models)."""
    liftoff_pitch: list[float] = field(default_factory=list)
    """Per step the pitch [rad] (ZYX, positive toe down) of its stance foot at the touchdown
    tick: the next step's swing foot leaves the ground with it (``reference.swing_pitch_carry``
    carries it, as the env reads it from the site's rotation)."""
    lifted: list[float] = field(default_factory=list)
    """Per step the swing-foot site's highest rise above its lift-off height [m]."""
    landing_gap: list[float] = field(default_factory=list)
    """Per step the swing-foot site's height above the planned stone top (plus the reference's
    foot height offset) at the touchdown tick [m]."""
    real_touchdown: list[bool] = field(default_factory=list)
    """Per step: the swing foot left the ground and landed (module docstring)."""
    ref_start: list[np.ndarray] = field(default_factory=list)
    """Per step (58,) the reference's positions then rates (29 each) at tau = 0."""
    ref_end: list[np.ndarray] = field(default_factory=list)
    """Per step (58,) the reference's positions then rates at its last tick."""
    step_length: list[float] = field(default_factory=list)
    """Per step the planned step length: horizontal distance from the stance foot to the
    target (the planner's ``max_step`` bounds it) [m]."""
    step_rise: list[float] = field(default_factory=list)
    """Per step the planned height change from the stance foot to the target [m]."""
    duration: list[float] = field(default_factory=list)
    """Per step the planned duration [s]."""
    end: str = "max_steps"
    """Why the walk ended: goal, plan_infeasible, no_touchdown or max_steps."""

    def arrays(self) -> dict[str, np.ndarray]:
        """The per-tick and per-step lists as arrays (empty walks give (0, 29) arrays)."""
        out = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, list):
                wide = ("eta", "etadot", "y_ref", "touchdown_eta", "step_max_eta")
                wide += ("step_max_etadot",)
                width = 29 if f.name in wide else 58 if f.name.startswith("ref_") else None
                arr = np.asarray(value, dtype=np.float64)
                if arr.size == 0 and width is not None:
                    arr = arr.reshape(0, width)
                out[f.name] = arr
        return out


def step_row(step: StepState, i: int, n: int) -> StepState:
    """Env ``i`` of a batched step state, repeated ``n`` times (one row per tick)."""
    values = {}
    for f in fields(step):
        value = getattr(step, f.name)
        values[f.name] = None if value is None else value[i : i + 1].expand(n, *value.shape[1:])
    return StepState(**values)


def touchdown_tick(duration: float, dt: float) -> int:
    """The tick of a step of planned ``duration`` [s] at which it touches down: the first with
    tau >= T (ideal timing), at least 1."""
    return max(1, math.ceil(duration / dt - 1e-6))


def touchdown_tau(step: StepState, dt: float) -> torch.Tensor:
    """(E,) float32 tau [s] of each env's touchdown tick in ``step``: the same value
    :func:`track_step` evaluates the step's last reference at (``arange(n + 1) * dt``'s last
    entry), so the next step carries the old reference's CoM state at that very instant."""
    ticks = [touchdown_tick(float(d), dt) for d in step.duration]
    return torch.tensor(ticks, dtype=torch.float32) * dt


def next_step(
    plan: Plan,
    swing: torch.Tensor,
    yaw0: torch.Tensor,
    axis: torch.Tensor,
    previous: StepState | None,
    dt: float,
    reference: ReferenceCfg,
    hlip: HlipCfg,
    swing_pitch: torch.Tensor | None = None,
) -> StepState:
    """The step each env takes after replanning (``plan``'s step 0), as the env's reference
    command builds it (``march.env.reference_command``): stance at ``plan.start``, the swing
    foot lifting off at ``swing`` (E, 3), the CoM reference carrying the previous step's
    reference CoM state at its touchdown tick (``reference.com_anchoring=continuous``; ignored
    with ``stance``) and the step's CoM height (``reference.com_height``); ``swing_pitch`` (E,)
    the new swing foot's pitch at lift-off (``reference.swing_pitch_carry``; None: flat).

    ``previous`` None: the walk starts standing, as an episode does: the CoM reference ramps
    from rest at the feet's midpoint and carries, at rest, the height a G1 stands at (z0 above
    the stance stone: the env carries its measured CoM, 0.672 m on the default pose)."""
    zero = torch.zeros_like(yaw0)
    if previous is None:
        ramp_from = 0.5 * (plan.start[:, :2] + swing[:, :2])
        standing = torch.cat([ramp_from, plan.start[:, 2:] + hlip.z0], dim=-1)
        com_from = (standing, torch.zeros_like(standing))
        rest = torch.zeros_like(standing[:, :2])
        rest[:, 1] = reference.pitch_offset
        pelvis_from = (rest, torch.zeros_like(rest))
    else:
        ramp_from = None
        com_from = com_state(previous, touchdown_tau(previous, dt), reference, hlip)
        pelvis_from = pelvis_state(previous, touchdown_tau(previous, dt), reference)
    return step_state_from_plan(
        plan,
        plan.start,
        swing,
        yaw0,
        zero,
        axis,
        ramp_from=ramp_from,
        com_from=com_from,
        cfg=reference,
        hlip=hlip,
        pelvis_from=pelvis_from,
        swing_from_pitch=torch.zeros_like(yaw0) if swing_pitch is None else swing_pitch,
    )


def site_pose(kin: KinematicG1, left: bool) -> tuple[np.ndarray, np.ndarray]:
    """(3,) position and (3, 3) rotation of the left / right foot site in the last measured
    state (``kin.data``)."""
    sid = kin.site_ids[0 if left else 1]
    return kin.data.site_xpos[sid].copy(), kin.data.site_xmat[sid].reshape(3, 3).copy()


@dataclass
class TouchdownRule:
    """When a step's end is a real touchdown (module docstring)."""

    lift_min: float = 0.02
    """The swing-foot site must rise this far above its lift-off height [m]."""
    land_tol: float = 0.02
    """... and end at most this above the planned stone top's height [m] (the swing-foot reach
    tolerance: higher, no contact)."""


def heel_landing(
    kin: KinematicG1, left: bool, held: tuple[np.ndarray, np.ndarray]
) -> tuple[tuple[np.ndarray, np.ndarray], float]:
    """A stance foot landed at ``held`` (site position, rotation) as the ``heel_toe`` model
    holds it: the flat pose it comes down to about its heel edge (the landed rotation turned
    about the foot's own y axis until its x axis is horizontal, the heel edge's midpoint where
    it landed) and the landed toe-up pitch [rad] (> 0: toe up; <= 0: the foot landed flat or
    toe down, held as landed and 0 returned)."""
    pos, rot = (np.asarray(a, dtype=np.float64) for a in held)
    # R Ry(a) has a horizontal x axis for tan a = R31 / R33 (a > 0: the foot turns toe down)
    a = float(np.arctan2(rot[2, 0], rot[2, 2]))
    if a <= 0.0:
        return (pos, rot), 0.0
    c, s = np.cos(a), np.sin(a)
    flat = rot @ np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    heel = kin.soles[0 if left else 1].heel_offset()
    return (pos + rot @ heel - flat @ heel, flat), a


def toe_up_bound(toe_up: float, tick: int, n: int, flat_by: float) -> float | None:
    """``heel_toe``: the largest toe-up pitch [rad] at ``tick`` (1..n) of a step whose foot
    landed ``toe_up`` up: toe_up (1 - tick / m), m = ceil(flat_by n), while tick < m; None
    from then on (the heel phase over: the flat foot's toe edge held, as ``heel_off``)."""
    m = max(1, math.ceil(flat_by * n - 1e-9))
    if toe_up <= 0.0 or tick >= m:
        return None
    return toe_up * (1.0 - tick / m)


def track_step(
    kin: KinematicG1,
    trace: WalkTrace,
    step: StepState,
    k: int,
    held: tuple[np.ndarray, np.ndarray],
    first: bool,
    reference: ReferenceCfg,
    hlip: HlipCfg,
    keep_qpos: bool = False,
    rule: TouchdownRule | None = None,
) -> tuple[tuple[np.ndarray, np.ndarray], np.ndarray, bool]:
    """Track one step (``step``: a one-env ``StepState``, step index ``k``) from the kinematic
    G1's current pose with the stance foot ``held`` (position, rotation), one tick per
    ``IkCfg.dt`` until the planned duration (the touchdown tick: the first with tau >= T);
    ``first``: the walk starts here, standing (:meth:`KinematicG1.stand` at tau = 0).
    Appends the ticks and the step's summary to ``trace``; returns the new stance foot's pose
    (the swing foot where it landed), the new swing foot's lift-off position and whether the
    step ended in a real touchdown (``rule``)."""
    rule = rule or TouchdownRule()
    dt = kin.cfg.dt
    is_left = bool(step.stance_is_left[0])
    toe_up = 0.0
    if kin.heels:  # heel_toe: a foot that landed toe up is held on its heel until flat
        held, toe_up = heel_landing(kin, is_left, held)
    duration = float(step.duration[0])
    n = touchdown_tick(duration, dt)
    tau = torch.arange(0, n + 1, dtype=torch.float32) * dt
    ref = reference_at(step_row(step, 0, n + 1), tau, reference, hlip, NUM_UPPER)
    ref_pos, ref_vel = (x.double().numpy() for x in ref.flatten())
    if first:
        kin.stand(ref_pos[0], is_left, *held)
    # kin.data may hold another walk's last tick; the error at tau = 0 with this step's labels
    # starts the finite difference of the error (the rate judged, KinematicG1.track)
    eta = tracking_error(kin.measure(kin.qpos, None, is_left)[0], ref_pos[0])
    lift_z = site_pose(kin, not is_left)[0][2]
    top = lift_z
    slide, heel_hi, heel_lo, pitch = 0.0, -math.inf, math.inf, -math.inf
    for j in range(1, n + 1):
        bound = toe_up_bound(toe_up, j, n, kin.cfg.heel_flat_by)
        tick = kin.track(ref_pos[j], ref_vel[j], is_left, *held, eta_before=eta, toe_up=bound)
        eta = tick.eta
        trace.eta.append(tick.eta)
        trace.etadot.append(tick.etadot)
        trace.v_ratio.append(tick.v_ratio)
        trace.tick_step.append(k)
        trace.y_ref.append(ref_pos[j])
        if keep_qpos:
            trace.qpos.append(tick.qpos)
        slide = max(slide, tick.slide)
        heel_hi, heel_lo = max(heel_hi, tick.heel_lift), min(heel_lo, tick.heel_lift)
        pitch = max(pitch, tick.stance_pitch)
        trace.tick_heel_lift.append(tick.heel_lift)
        trace.tick_stance_pitch.append(tick.stance_pitch)
        trace.tick_slide.append(tick.slide)
        top = max(top, float(site_pose(kin, not is_left)[0][2]))
    trace.touchdown_eta.append(trace.eta[-1])
    trace.step_max_eta.append(np.abs(np.asarray(trace.eta[-n:])).max(0))
    trace.step_max_etadot.append(np.abs(np.asarray(trace.etadot[-n:])).max(0))
    trace.ref_start.append(np.concatenate([ref_pos[0], ref_vel[0]]))
    trace.ref_end.append(np.concatenate([ref_pos[n], ref_vel[n]]))
    trace.slide.append(slide)
    trace.heel_lift.append(heel_hi)
    trace.heel_low.append(heel_lo)
    trace.stance_pitch.append(pitch)
    trace.landed_toe_up.append(toe_up)
    anchor, target = step.stance_pos[0], step.target[0]
    trace.step_length.append(float(torch.linalg.norm(target[:2] - anchor[:2])))
    trace.step_rise.append(float(target[2] - anchor[2]))
    trace.duration.append(duration)
    # Touchdown: the swing foot is the new stance foot where it landed; the old stance foot
    # lifts off from where it stood.
    old_stance, old_rot = site_pose(kin, is_left)
    # its ZYX pitch, as the env's euler_from_matrix reads it: asin(-R31)
    trace.liftoff_pitch.append(float(np.arcsin(np.clip(-old_rot[2, 0], -1.0, 1.0))))
    landed = site_pose(kin, not is_left)
    gap = float(landed[0][2] - (float(target[2]) + reference.foot_height_offset))
    if reference.swing_heel_strike > 0.0:
        # a heel strike lands on the heel, the site raised by the toe-up pitch: the gap is the
        # heel's (its height above where a flat foot on the target would have it)
        heel = kin.soles[0 if not is_left else 1].heel_offset()
        gap = float((landed[0] + landed[1] @ heel)[2]) - (
            float(target[2]) + reference.foot_height_offset + float(heel[2])
        )
    # A foot at or below the stone top touches it (the IK ignores collisions: below the top it
    # would have hit the stone); only a foot left above it has no contact.
    real = top - lift_z >= rule.lift_min and gap <= rule.land_tol
    trace.lifted.append(float(top - lift_z))
    trace.landing_gap.append(gap)
    trace.real_touchdown.append(bool(real))
    return landed, old_stance, bool(real)


def ik_walks(
    kin: KinematicG1,
    footholds: Footholds,
    command: torch.Tensor,
    max_steps: int = 30,
    seed: int = 0,
    planner: PlannerCfg | None = None,
    hlip: HlipCfg | None = None,
    reference: ReferenceCfg | None = None,
    keep_qpos: bool = False,
    rule: TouchdownRule | None = None,
) -> list[WalkTrace]:
    """Walk every course of ``footholds`` (E envs) at ``command`` (E, 2|3) [m/s] with the
    kinematic G1 (module docstring); one :class:`WalkTrace` per env. ``keep_qpos`` keeps each
    tick's configuration (the film needs it); ``rule`` says what a real touchdown is."""
    planner = planner or PlannerCfg()
    hlip = hlip or HlipCfg()
    reference = reference or ReferenceCfg()
    gen = torch.Generator().manual_seed(seed)
    e = footholds.num_envs
    axis = footholds.direction
    lat = torch.stack([-axis[:, 1], axis[:, 0]], dim=-1)
    yaw0 = torch.atan2(axis[:, 1], axis[:, 0])
    stance = footholds.start_xy + 0.3 * axis + 0.5 * planner.step_width * lat
    left = torch.ones(e, dtype=torch.bool)
    active = torch.ones(e, dtype=torch.bool)
    swing: torch.Tensor | None = None
    qpos: list[np.ndarray | None] = [None] * e
    held: list[tuple[np.ndarray, np.ndarray] | None] = [None] * e
    traces = [WalkTrace() for _ in range(e)]
    step: StepState | None = None
    liftoff_pitch = torch.zeros(e)  # the walk starts standing, both feet flat
    for k in range(max_steps):
        plan = plan_footsteps(stance, left, command[:, :2], footholds, planner, gen)
        for i in torch.nonzero(active & ~plan.feasible).flatten().tolist():
            traces[i].end = "plan_infeasible"
        active = active & plan.feasible
        if not bool(active.any()):
            break
        if swing is None:
            swing = plan.start.clone()
            swing[:, :2] -= planner.step_width * lat
        step = next_step(
            plan, swing, yaw0, axis, step, kin.cfg.dt, reference, hlip, liftoff_pitch.clone()
        )
        next_swing = swing.clone()
        for i in torch.nonzero(active).flatten().tolist():
            is_left = bool(step.stance_is_left[i])
            if held[i] is None:  # the walk starts standing, both feet flat, course heading
                start_pose = step.stance_pos[i].double().numpy()
                held[i] = (start_pose, rotation_zyx(0.0, 0.0, float(yaw0[i])))
            else:
                kin.reset(qpos[i])
            first = k == 0
            held[i], old_stance, real = track_step(
                kin,
                traces[i],
                step_row(step, i, 1),
                k,
                held[i],
                first,
                reference,
                hlip,
                keep_qpos,
                rule,
            )
            if not real:  # no contact: the env would not replan here (module docstring)
                traces[i].end = "no_touchdown"
                active[i] = False
            qpos[i] = kin.qpos
            stance[i] = torch.as_tensor(held[i][0][:2], dtype=stance.dtype)
            next_swing[i] = torch.as_tensor(old_stance, dtype=swing.dtype)
            liftoff_pitch[i] = traces[i].liftoff_pitch[-1]
            left[i] = not is_left
        swing = next_swing
        reached = footholds.progress(stance) >= footholds.goal_distance + 0.3
        for i in torch.nonzero(active & reached).flatten().tolist():
            traces[i].end = "goal"
        active = active & ~reached
        if not bool(active.any()):
            break
    return traces
