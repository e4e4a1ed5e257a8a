"""Reference outputs y_ref(t) for the current step, batched in plain torch (no simulator import).

Outputs, in this order (``output_names``), each with a position and a velocity:

    com_x, com_y, com_z                  CoM [m]: HLIP orbit of the planned step in x/y, height z0;
                                         continuous across touchdowns (march.reference.com_carry)
    pelvis_roll, pelvis_pitch, pelvis_yaw  pelvis Euler angles [rad]: yaw = yaw0 + yaw_rate tau
                                         (the command term holds it at the course heading,
                                         yaw_rate 0); small roll/pitch oscillations per step
    swing_x, swing_y, swing_z            swing foot [m]: Bezier from lift-off to the planned foothold
    swing_roll, swing_pitch, swing_yaw   swing foot orientation [rad]: flat (or toed down at
                                         mid-swing, ``swing_toe_down``, and rolled toe down
                                         then up, ``swing_toe_roll``), yaw = pelvis yaw
    upper_0 ... upper_{U-1}              upper-body joints relative to default [rad]: zero

Velocities of the angle outputs are Euler-angle rates [rad/s]. Angle outputs are wrapped to
[-pi, pi); errors on them must be taken with :func:`tracking_error` (wrapped differences), never as
raw Euler differences.

Swing foot: horizontal part is a 5th-degree Bezier with control points (p0, p0, p0, p1, p1, p1),
i.e. zero velocity and acceleration at lift-off and touchdown (``swing_xy_shape`` a moves the
inner two to p0 + a (p1 - p0) and p1 - a (p1 - p0): zero velocity, a flatter speed); vertical part a 6th-degree Bezier
(z0, z0, c, c, c, z1, z1) with c chosen so that the height at mid-swing is the apex
max(z0, z1) + z_sw (when z0 != z1 the maximum lies slightly past mid-swing and is slightly higher).

Start from standing (decision, issue 10): the first step of an episode (``StepState.ramp``) does
not begin on the steady-state orbit (about 0.7 m/s of CoM velocity while the robot stands still,
a jump in V at every reset). Its CoM reference blends from rest at the measured CoM
(``ramp_from``) into that step's HLIP orbit reference with a smoothstep s = 3 phi^2 - 2 phi^3,
phi = tau / T:

    p = p0 + s (p_orbit - p0),   v = s v_orbit + (ds/dtau) (p_orbit - p0),

so it starts at the measured CoM with zero velocity, v is the exact time derivative of p, and at
the planned touchdown (s = 1, ds/dtau = 0) it is on the orbit's pre-impact state, where the
following steps continue as before. Past the planned duration every step's CoM reference keeps
flowing along the HLIP (:func:`march.reference.hlip.hlip_com_state`).

Continuity across touchdowns (issue 55, ``ReferenceCfg.com_anchoring``): with ``continuous``
(default) a step that carries the previous reference's CoM state (``StepState.com_from_pos``,
``com_from_vel``) adds :func:`march.reference.com_carry.carry_correction` to its orbit, so the
CoM reference is continuous in position and velocity and ends each step on the planned orbit; its
height blends from the previous reference's to z0 above the lower of the stance and landing
stones. With ``stance`` (or a step without ``com_from_*``) the orbit is anchored at the stance
foot and the height is z0 above it (the earlier reference, which jumps at every touchdown).
The pelvis roll and pitch carry the same way (``StepState.pelvis_from_pos``, ``_vel``;
:func:`march.reference.com_carry.hermite_carry`): their rates no longer jump at a touchdown that
comes early or late, at a restart or where the duration changes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch

from march.reference.com_carry import (
    COM_ANCHORINGS,
    COM_HEIGHTS,
    carry_correction,
    hermite_carry,
    pendulum_lambda,
    step_com_height,
)
from march.reference.hlip import HlipCfg, hlip_com_state
from march.reference.kept import kept
from march.reference.planner import Plan

ANGLE_OUTPUTS = (
    "pelvis_roll",
    "pelvis_pitch",
    "pelvis_yaw",
    "swing_roll",
    "swing_pitch",
    "swing_yaw",
)
"""Names of the outputs that are angles (wrapped differences)."""


@dataclass
class ReferenceCfg:
    """Parameters of the reference trajectory."""

    swing_height: float = 0.10
    """z_sw: apex clearance of the swing foot above the higher of lift-off and landing [m]."""
    foot_height_offset: float = 0.0
    """Height of the tracked swing-foot point above the sole [m]; added to the planned footholds'
    z (the stone top). Lift-off positions are measured, so they already include it."""
    roll_amplitude: float = 0.03
    """Pelvis roll oscillation amplitude [rad]; the pelvis leans toward the stance foot."""
    pitch_amplitude: float = 0.02
    """Pelvis pitch oscillation amplitude [rad] (one period per step)."""
    pitch_offset: float = 0.0
    """Constant forward pelvis pitch [rad]."""
    com_anchoring: str = "continuous"
    """``continuous``: the CoM reference carries the previous reference's CoM state across a
    touchdown (continuous position and velocity, each step ending on its orbit); ``stance``:
    each step's HLIP orbit is anchored at the new stance foot (the earlier reference; jumps by
    about (l_old - l_new)/2 at every touchdown). march.reference.com_carry."""
    com_height: str = "fixed"
    """``fixed``: CoM height z0 (HlipCfg.z0, author 0.67 m) for every step; ``step``: lowered
    with the step length (:attr:`com_height_free_step`, ``_slope``, ``_min``) so that long
    steps are within the G1's reach; the HLIP's lambda uses the height of the step."""
    com_height_free_step: float = 0.5
    """``com_height=step``: steps up to this long along the course keep z0 [m]."""
    com_height_slope: float = 0.35
    """``com_height=step``: CoM height lowered per metre of step beyond the free length [m/m]."""
    com_height_min: float = 0.57
    """``com_height=step``: the lowest CoM height [m] (the measured envelope reaches 0.90 m
    steps at 0.57 m)."""
    swing_toe_down: float = 0.0
    """Swing-foot pitch reference at mid-swing [rad], positive toe down (:func:`toe_down`:
    swing_toe_down 64 s^3 (1 - s)^3 of the swing phase s, flat with zero rate at lift-off and
    touchdown). 0 (default): the foot flat all swing. Issue 55: at the apex of short steps the
    G1's swing ankle is at its dorsiflexion limit (-0.873 rad) and cannot hold the foot flat;
    ``0.35`` asks for what the ankle can do."""
    swing_toe_roll: float = 0.0
    """Swing-foot pitch added to the toe-down [rad]: swing_toe_roll K s^3 (1 - s)^3 (1 - 2 s),
    K = :data:`TOE_ROLL_SCALE`: toe down by up to swing_toe_roll at s = 0.311 (after
    lift-off, the foot still behind the hip), toe up by as much at s = 0.689 (reaching for the
    landing), flat with zero rate at lift-off, mid-swing and touchdown. 0 (default): none."""
    swing_xy_shape: float = 0.0
    """a in [0, 0.5]: the swing foot's horizontal 5th-degree Bezier has control points (p0,
    p0, p0 + a D, p1 - a D, p1, p1), D = p1 - p0 [-]. 0 (default): (p0, p0, p0, p1, p1, p1),
    minimum jerk, zero velocity and acceleration at lift-off and touchdown, peak speed
    1.875 |D| / T at mid-swing. a > 0 keeps zero velocity at both ends, starts and stops with
    an acceleration of 20 a |D| / T^2 and flattens the speed: (30 - 20 a) / 16 |D| / T at
    mid-swing (1.5625 at a = 0.25, 1.25 at 0.5). Issue 55: the foot leaves with the hip
    that drags a nearly straight trailing leg, and the swing leg swings slower at
    mid-swing."""

    swing_pitch_carry: float = 0.0
    """c in [0, 1]: the swing foot's pitch reference starts at the pitch the foot has at
    lift-off (``StepState.swing_from_pitch``, measured like ``swing_start``) and blends into
    the flat / toe-down profile with the Hermite carry p0 (1 - phi)^2 (1 + 2 phi),
    phi = tau / (c T) (zero rate at lift-off, gone with its slope at tau = c T;
    :func:`swing_pitch_carry`). 0 (default): none, the reference starts flat whatever the foot
    does. Issue 55: a stance foot that lifts its heel in late stance (the audit's
    ``audit.stance=heel_off``) leaves the ground pitched toe down; a flat lift-off reference
    charges that pitch as an error and its removal in one tick as a rate."""

    swing_roll_out: float = 0.0
    """Swing-foot roll reference at mid-swing [rad], rolled toward the swing foot's own side
    (+ for the left foot, - for the right: :func:`swing_roll_out`): swing_roll_out
    64 s^3 (1 - s)^3 of the swing phase s, level with zero rate at lift-off and touchdown.
    0 (default): level all swing, as the author's. Issue 55: at mid-swing the foot passes
    0.13-0.23 m beside the CoM with the knee bent, the leg abducted beyond what the G1's ankle
    roll range (0.262 rad) can level; the foot rolls with the leg and lands level."""

    swing_heel_strike: float = 0.0
    """Swing-foot toe-up pitch at touchdown [rad] (heel strike): the pitch reference adds
    -swing_heel_strike q(u), q(u) = u^3 (10 - 15 u + 6 u^2), u = 2 s - 1 clamped to [0, 1]
    (none in the first half of the swing; zero rate and acceleration at mid-swing and at
    touchdown), and the swing-foot position the offset that keeps the heel where a flat
    landing puts it (:func:`heel_strike`: the site ``swing_heel_back`` ahead of the heel,
    raised by swing_heel_back sin and drawn back by swing_heel_back (1 - cos) of that pitch).
    0 (default): the foot lands flat, as the author's. Issue 55: on the longest steps a flat
    landing needs the front ankle at its plantarflexion limit (+0.524 rad) while the rear one
    is at its dorsiflexion limit; landing on the heel relieves the front ankle (the audit's
    ``audit.stance=heel_toe`` holds the landed heel while the toe comes down)."""
    swing_heel_back: float = 0.094
    """Distance from the tracked swing-foot point back to the heel's edge [m] (mjlab's G1: the
    foot site to the rearmost end of the sole's capsules, ``march.audit.kinematic_g1.foot_sole``,
    0.094 m); the pivot of ``swing_heel_strike``."""

    def __post_init__(self) -> None:
        if self.com_anchoring not in COM_ANCHORINGS:
            raise ValueError(f"com_anchoring must be one of {COM_ANCHORINGS}")
        if self.com_height not in COM_HEIGHTS:
            raise ValueError(f"com_height must be one of {COM_HEIGHTS}")
        if self.com_height_slope < 0.0 or self.com_height_min <= 0.0:
            raise ValueError("need com_height_slope >= 0 and com_height_min > 0")
        if not -1.0 <= self.swing_toe_down <= 1.0:
            raise ValueError("swing_toe_down must lie in [-1, 1] rad")
        if not 0.0 <= self.swing_xy_shape <= 0.5:
            raise ValueError("swing_xy_shape must lie in [0, 0.5]")
        if not 0.0 <= self.swing_pitch_carry <= 1.0:
            raise ValueError("swing_pitch_carry must lie in [0, 1]")
        if not -0.5 <= self.swing_roll_out <= 0.5:
            raise ValueError("swing_roll_out must lie in [-0.5, 0.5] rad")
        if not 0.0 <= self.swing_heel_strike <= 0.5:
            raise ValueError("swing_heel_strike must lie in [0, 0.5] rad")
        if not 0.0 < self.swing_heel_back <= 0.3:
            raise ValueError("swing_heel_back must lie in (0, 0.3] m")


def wrap_to_pi(angle: torch.Tensor) -> torch.Tensor:
    """Wrap angles to [-pi, pi)."""
    return torch.remainder(angle + math.pi, 2.0 * math.pi) - math.pi


def output_names(num_upper: int) -> list[str]:
    """Ordered names of the reference outputs (12 + num_upper)."""
    base = ["com_x", "com_y", "com_z", "pelvis_roll", "pelvis_pitch", "pelvis_yaw"]
    base += ["swing_x", "swing_y", "swing_z", "swing_roll", "swing_pitch", "swing_yaw"]
    return base + [f"upper_{j}" for j in range(num_upper)]


def angle_mask(num_upper: int, device: torch.device | str = "cpu") -> torch.Tensor:
    """(12 + num_upper,) bool: which outputs are angles whose errors must be wrapped."""
    names = output_names(num_upper)
    return torch.tensor([n in ANGLE_OUTPUTS for n in names], device=device)


def tracking_error(y: torch.Tensor, y_ref: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """eta = y - y_ref with angle outputs (``mask``) wrapped to [-pi, pi)."""
    diff = y - y_ref
    return torch.where(mask, wrap_to_pi(diff), diff)


def bezier(ctrl: torch.Tensor, s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Bezier curve and its derivative with respect to s.

    ctrl: (..., K+1, D) control points; s: (...) in [0, 1]. Returns (..., D) point and d/ds.
    """
    deg = ctrl.shape[-2] - 1
    s = s[..., None]
    k, binom = _bezier_table(deg, ctrl.dtype, ctrl.device)
    basis = binom * s**k * (1.0 - s) ** (deg - k)  # (..., K+1)
    pos = (basis[..., None] * ctrl).sum(-2)
    diff = deg * (ctrl[..., 1:, :] - ctrl[..., :-1, :])
    km, binom_d = _bezier_table(deg - 1, ctrl.dtype, ctrl.device)
    basis_d = binom_d * s**km * (1.0 - s) ** (deg - 1 - km)
    return pos, (basis_d[..., None] * diff).sum(-2)


def _bezier_table(deg: int, dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, ...]:
    """(deg+1,) exponents 0..deg and binomial coefficients C(deg, j), on ``device``: made once
    per (degree, dtype, device) (:func:`march.reference.kept.kept`), so a step copies nothing
    from the host."""

    def make() -> tuple[torch.Tensor, torch.Tensor]:
        k = torch.arange(deg + 1, dtype=dtype, device=device)
        # C(deg, j) from lgamma, rounded: exact integers, made on the device
        log_binom = math.lgamma(deg + 1) - torch.lgamma(k + 1) - torch.lgamma(deg - k + 1)
        return k, torch.round(torch.exp(log_binom))

    return kept(("bezier", deg, dtype, torch.device(device)), make)


def swing_trajectory(
    start: torch.Tensor,
    end: torch.Tensor,
    phase: torch.Tensor,
    duration: torch.Tensor,
    swing_height: float,
    xy_shape: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Swing-foot position and velocity (E, 3) at ``phase`` = tau / T in [0, 1].

    start/end: (E, 3) lift-off point and landing point; duration: (E,) swing time T [s];
    ``xy_shape`` a (:attr:`ReferenceCfg.swing_xy_shape`): the horizontal Bezier's inner control
    points at p0 + a (p1 - p0) and p1 - a (p1 - p0) (0: p0, p0, p0, p1, p1, p1).
    """
    s = phase.clamp(0.0, 1.0)
    p0, p1 = start[:, None, :2], end[:, None, :2]
    if xy_shape == 0.0:
        ctrl_xy = torch.cat([p0, p0, p0, p1, p1, p1], dim=1)
    else:
        d = xy_shape * (p1 - p0)
        ctrl_xy = torch.cat([p0, p0, p0 + d, p1 - d, p1, p1], dim=1)
    z0, z1 = start[:, 2], end[:, 2]
    apex = torch.maximum(z0, z1) + swing_height
    # Height at s = 1/2 is (7 z0 + 50 c + 7 z1) / 64; choose c to make it the apex.
    c = (64.0 * apex - 7.0 * (z0 + z1)) / 50.0
    ctrl_z = torch.stack([z0, z0, c, c, c, z1, z1], dim=1)[..., None]
    xy, dxy = bezier(ctrl_xy, s)
    zz, dz = bezier(ctrl_z, s)
    pos = torch.cat([xy, zz], dim=-1)
    # d/dt = d/ds / T inside the swing; the foot rests once the swing time is over.
    active = (phase < 1.0).to(pos.dtype)[:, None]
    vel = torch.cat([dxy, dz], dim=-1) / duration[:, None] * active
    return pos, vel


TOE_ROLL_SCALE = 19208.0 / (27.0 * math.sqrt(7.0))
"""1 / max of s^3 (1 - s)^3 (1 - 2 s) on [0, 1] (at s = 1/2 - sqrt(7)/14 = 0.311): the toe
roll's normalisation (:func:`toe_down`)."""


def toe_down(
    phase: torch.Tensor, duration: torch.Tensor, amplitude: float, roll: float = 0.0
) -> tuple[torch.Tensor, torch.Tensor]:
    """Swing-foot pitch [rad] and its rate [rad/s] (E,) at ``phase`` = tau / T: amplitude
    64 s^3 (1 - s)^3 with s = phase clamped to [0, 1] (``amplitude`` at s = 1/2; zero pitch,
    rate and acceleration at lift-off and touchdown) and rate amplitude 192 s^2 (1 - s)^2
    (1 - 2 s) / T inside the swing, 0 once it is over (the foot rests). ``roll`` R adds
    R K s^3 (1 - s)^3 (1 - 2 s) (K = :data:`TOE_ROLL_SCALE`: toe down by R at s = 0.311, up
    by R at 0.689, zero at 0, 1/2 and 1) and its rate R K s^2 (1 - s)^2 (3 (1 - 2 s)^2 -
    2 s (1 - s)) / T."""
    s = phase.clamp(0.0, 1.0)
    r = 1.0 - s
    pitch = amplitude * 64.0 * (s * r) ** 3
    active = (phase < 1.0).to(phase.dtype)
    rate = amplitude * 192.0 * (s * r) ** 2 * (1.0 - 2.0 * s) / duration * active
    if roll != 0.0:
        k = roll * TOE_ROLL_SCALE
        pitch = pitch + k * (s * r) ** 3 * (1.0 - 2.0 * s)
        # d/ds s^3 (1 - s)^3 (1 - 2 s) = s^2 (1 - s)^2 (3 (1 - 2 s)^2 - 2 s (1 - s))
        shape = (s * r) ** 2 * (3.0 * (1.0 - 2.0 * s) ** 2 - 2.0 * s * r)
        rate = rate + k * shape / duration * active
    return pitch, rate


def swing_roll_out(
    phase: torch.Tensor, duration: torch.Tensor, stance_is_left: torch.Tensor, amplitude: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Swing-foot roll [rad] and its rate [rad/s] (matching ``phase``'s shape, ``duration`` and
    ``stance_is_left`` broadcast against it): side A 64 s^3 (1 - s)^3, s = phase clamped to
    [0, 1], side = +1 when the left foot swings (the right one stands) and -1 when the right
    foot swings, so that the foot rolls toward its own side; its rate side A 192 s^2 (1 - s)^2
    (1 - 2 s) / T inside the swing, 0 once it is over (``ReferenceCfg.swing_roll_out``): the
    toe-down's bump (:func:`toe_down`) signed by the swinging foot."""
    side = 1.0 - 2.0 * stance_is_left.to(phase.dtype)
    bump, rate = toe_down(phase, duration, amplitude)
    return side * bump, side * rate


def swing_pitch_carry(
    pitch0: torch.Tensor, tau: torch.Tensor, duration: torch.Tensor, share: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """The swing foot's lift-off pitch carried into its reference (E,) [rad] and its rate
    [rad/s] (``ReferenceCfg.swing_pitch_carry``): p0 h00(phi), phi = tau / (share T) clamped
    to [0, 1], h00 = (1 - phi)^2 (1 + 2 phi) (p0 at lift-off with zero rate, 0 with zero rate
    from tau = share T on); the toe-down profile is 0 with zero rate at lift-off, so the sum
    starts at the foot's pitch."""
    span = share * duration
    phi = (tau / span).clamp(0.0, 1.0)
    one = 1.0 - phi
    return pitch0 * (one * one * (1.0 + 2.0 * phi)), pitch0 * (-6.0 * phi * one / span)


def heel_strike(
    phase: torch.Tensor,
    duration: torch.Tensor,
    yaw: torch.Tensor,
    yaw_rate: torch.Tensor,
    amplitude: float,
    heel_back: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The heel strike (``ReferenceCfg.swing_heel_strike``) H = ``amplitude``: the swing-foot
    pitch p = -H q(u) [rad] and its rate [rad/s] (E,), q(u) = u^3 (10 - 15 u + 6 u^2),
    u = 2 s - 1 clamped to [0, 1] (s = ``phase``), rate -H 30 u^2 (1 - u)^2 2 / T inside the
    swing's second half, 0 once it is over; and the foot site's offset (E, 3) [m] and its
    rate [m/s] that hold the heel, d = ``heel_back`` behind the site along the foot's heading
    f = (cos yaw, sin yaw, 0), where a flat foot would have it: site = heel + d (cos p f,
    -sin p), so the offset is d ((cos p - 1) f, -sin p), its rate d (-sin p p' f +
    (cos p - 1) f', -cos p p') with f' = yaw_rate (-sin yaw, cos yaw, 0). Lift-off: p = 0,
    no offset; touchdown: toe up by H with the heel on the landing stone."""
    s = phase.clamp(0.0, 1.0)
    u = (2.0 * s - 1.0).clamp(0.0, 1.0)
    q = u**3 * (10.0 - 15.0 * u + 6.0 * u * u)
    active = (phase < 1.0).to(phase.dtype)
    pitch = -amplitude * q
    rate = -amplitude * 30.0 * (u * (1.0 - u)) ** 2 * 2.0 / duration * active
    cos_p, sin_p = torch.cos(pitch), torch.sin(pitch)
    fx, fy = torch.cos(yaw), torch.sin(yaw)
    offset = heel_back * torch.stack([(cos_p - 1.0) * fx, (cos_p - 1.0) * fy, -sin_p], dim=-1)
    turn = (cos_p - 1.0) * yaw_rate
    offset_rate = heel_back * torch.stack(
        [-sin_p * rate * fx - turn * fy, -sin_p * rate * fy + turn * fx, -cos_p * rate], dim=-1
    )
    return pitch, rate, offset, offset_rate


@dataclass
class StepState:
    """What the reference needs to know about the current step (held by the command term)."""

    stance_pos: torch.Tensor
    """(E, 3) actual stance foot at touchdown: xy and ground (stone top) height [m]."""
    stance_is_left: torch.Tensor
    """(E,) bool: the stance foot is the left one."""
    swing_start: torch.Tensor
    """(E, 3) swing foot (tracked point) at lift-off [m]."""
    target: torch.Tensor
    """(E, 3) planned landing foothold of this step (stone top) [m]."""
    next_target: torch.Tensor
    """(E, 3) planned foothold of the step after (for the lateral period-2 orbit) [m]."""
    duration: torch.Tensor
    """(E,) planned duration of this step [s]."""
    next_duration: torch.Tensor
    """(E,) planned duration of the step after [s]."""
    yaw0: torch.Tensor
    """(E,) pelvis-yaw reference at touchdown [rad] (the command term integrates it)."""
    yaw_rate: torch.Tensor
    """(E,) commanded yaw rate [rad/s]."""
    axis: torch.Tensor
    """(E, 2) unit sagittal direction for the HLIP planes (the course direction)."""
    ramp: torch.Tensor | None = None
    """(E,) bool: this step starts the episode from standing; its CoM reference ramps from rest
    at ``ramp_from`` (module docstring). None = no env ramps."""
    ramp_from: torch.Tensor | None = None
    """(E, 2) measured CoM xy at the start of a ramping step [m] (read where ``ramp``)."""
    com_from_pos: torch.Tensor | None = None
    """(E, 3) the previous reference's CoM position at the instant this step began [m], world
    (``com_anchoring=continuous``; None: the orbit alone, anchored at the stance foot)."""
    com_from_vel: torch.Tensor | None = None
    """(E, 3) the previous reference's CoM velocity then [m/s]."""
    z0: torch.Tensor | None = None
    """(E,) CoM height of this step [m] (``com_height=step``; None or ``fixed``: HlipCfg.z0)."""
    pelvis_from_pos: torch.Tensor | None = None
    """(E, 2) the previous reference's pelvis roll and pitch at the instant this step began
    [rad] (``com_anchoring=continuous``; None: the step's own lean from its start)."""
    pelvis_from_vel: torch.Tensor | None = None
    """(E, 2) their rates then [rad/s]."""
    swing_from_pitch: torch.Tensor | None = None
    """(E,) the swing foot's measured pitch at lift-off [rad] (ZYX, positive toe down), the
    start of its pitch reference with ``ReferenceCfg.swing_pitch_carry`` > 0 (None: none)."""


def step_state_from_plan(
    plan: Plan,
    stance_pos: torch.Tensor,
    swing_start: torch.Tensor,
    yaw0: torch.Tensor,
    yaw_rate: torch.Tensor,
    axis: torch.Tensor | None = None,
    ramp_from: torch.Tensor | None = None,
    com_from: tuple[torch.Tensor, torch.Tensor] | None = None,
    cfg: ReferenceCfg | None = None,
    hlip: HlipCfg | None = None,
    pelvis_from: tuple[torch.Tensor, torch.Tensor] | None = None,
    swing_from_pitch: torch.Tensor | None = None,
) -> StepState:
    """The step state right after a touchdown and replan: step 0 of ``plan`` is being taken.

    ``ramp_from`` (E, 2): the measured CoM of envs that start from standing (episode start); the
    step's CoM reference then ramps from rest there. None: every env continues a walk.
    ``com_from``: (E, 3) position and velocity of the previous reference's CoM at this instant
    (:func:`com_state`), carried into the step (``com_anchoring=continuous``). ``cfg`` and
    ``hlip`` give the step's CoM height (:func:`step_height`). ``pelvis_from``: (E, 2) the
    previous reference's pelvis roll and pitch and their rates (:func:`pelvis_state`), carried
    the same way. ``swing_from_pitch`` (E,): the new swing foot's measured pitch [rad]
    (``ReferenceCfg.swing_pitch_carry``).
    """
    if axis is None:
        axis = torch.zeros_like(stance_pos[:, :2])
        axis[:, 0] = 1.0
    e = stance_pos.shape[0]
    ramp = torch.full((e,), ramp_from is not None, dtype=torch.bool, device=stance_pos.device)
    if ramp_from is None:
        ramp_from = torch.zeros_like(stance_pos[:, :2])
    target = plan.footholds[:, 0]
    return StepState(
        ramp=ramp,
        ramp_from=ramp_from,
        com_from_pos=None if com_from is None else com_from[0],
        com_from_vel=None if com_from is None else com_from[1],
        pelvis_from_pos=None if pelvis_from is None else pelvis_from[0],
        pelvis_from_vel=None if pelvis_from is None else pelvis_from[1],
        swing_from_pitch=swing_from_pitch,
        z0=step_height(stance_pos, target, axis, cfg or ReferenceCfg(), hlip or HlipCfg()),
        stance_pos=stance_pos,
        stance_is_left=~plan.lands_left[:, 0],
        swing_start=swing_start,
        target=target,
        next_target=plan.footholds[:, 1],
        duration=plan.durations[:, 0],
        next_duration=plan.durations[:, 1],
        yaw0=yaw0,
        yaw_rate=yaw_rate,
        axis=axis,
    )


def step_height(
    stance_pos: torch.Tensor,
    target: torch.Tensor,
    axis: torch.Tensor,
    cfg: ReferenceCfg,
    hlip: HlipCfg,
) -> torch.Tensor:
    """(E,) CoM height [m] of the steps from ``stance_pos`` to ``target`` (E, 3): z0 with
    ``com_height=fixed``, lowered with the step's length along ``axis`` (E, 2) with ``step``
    (:func:`march.reference.com_carry.step_com_height`)."""
    if cfg.com_height == "fixed":
        return torch.full_like(stance_pos[:, 0], hlip.z0)
    along = ((target[:, :2] - stance_pos[:, :2]) * axis).sum(-1)
    return step_com_height(
        along, hlip.z0, cfg.com_height_free_step, cfg.com_height_slope, cfg.com_height_min
    )


def step_lambda(step: StepState, cfg: ReferenceCfg, hlip: HlipCfg) -> torch.Tensor | float:
    """The HLIP's lambda of each step: sqrt(g / z) of the height it is walked at (a float with
    ``com_height=fixed``, (E,) with ``step``)."""
    if cfg.com_height == "fixed" or step.z0 is None:
        return hlip.lam
    return pendulum_lambda(step.z0, hlip.g)


def com_orbit_height(step: StepState, cfg: ReferenceCfg, hlip: HlipCfg) -> torch.Tensor:
    """(E,) the height [m] the step's CoM orbit ends at: z0 above the stance stone
    (``com_anchoring=stance``, the earlier reference), or above the lower of the stance and
    landing stones (``continuous``: on a step down the CoM comes down with the foot, on a step
    up it stays low until the new stance, within both legs' reach)."""
    z0 = hlip.z0 if cfg.com_height == "fixed" or step.z0 is None else step.z0
    if cfg.com_anchoring == "stance":
        return step.stance_pos[:, 2] + z0
    return torch.minimum(step.stance_pos[:, 2], step.target[:, 2]) + z0


def com_state(
    step: StepState,
    tau: torch.Tensor,
    cfg: ReferenceCfg | None = None,
    hlip: HlipCfg | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(E, 3) CoM reference position and velocity at ``tau`` into ``step``: what the next step
    carries (``step_state_from_plan``'s ``com_from``)."""
    ref = reference_at(step, tau, cfg, hlip, num_upper=0)
    return ref.com_pos, ref.com_vel


def pelvis_state(
    step: StepState, tau: torch.Tensor, cfg: ReferenceCfg | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """(E, 2) pelvis roll and pitch reference [rad] and their rates [rad/s] at ``tau`` into
    ``step``: what the next step carries (``step_state_from_plan``'s ``pelvis_from``)."""
    ori, rate = pelvis_reference(step, tau, cfg or ReferenceCfg())
    return ori[:, :2], rate[:, :2]


@dataclass
class Reference:
    """Reference outputs at one instant; positions and velocities (E, .) per output group."""

    com_pos: torch.Tensor
    """(E, 3) CoM position [m]."""
    com_vel: torch.Tensor
    """(E, 3) CoM velocity [m/s]."""
    pelvis_ori: torch.Tensor
    """(E, 3) pelvis roll, pitch, yaw [rad] (yaw wrapped)."""
    pelvis_rate: torch.Tensor
    """(E, 3) pelvis Euler-angle rates [rad/s]."""
    swing_pos: torch.Tensor
    """(E, 3) swing foot position [m]."""
    swing_vel: torch.Tensor
    """(E, 3) swing foot velocity [m/s]."""
    swing_ori: torch.Tensor
    """(E, 3) swing foot roll, pitch, yaw [rad]."""
    swing_rate: torch.Tensor
    """(E, 3) swing foot Euler-angle rates [rad/s]."""
    upper_pos: torch.Tensor
    """(E, U) upper-body joint positions relative to default [rad]."""
    upper_vel: torch.Tensor
    """(E, U) upper-body joint velocities [rad/s]."""

    @property
    def names(self) -> list[str]:
        return output_names(self.upper_pos.shape[1])

    def flatten(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(E, n_outputs) positions and velocities in ``names`` order."""
        pos = [self.com_pos, self.pelvis_ori, self.swing_pos, self.swing_ori, self.upper_pos]
        vel = [self.com_vel, self.pelvis_rate, self.swing_vel, self.swing_rate, self.upper_vel]
        return torch.cat(pos, dim=-1), torch.cat(vel, dim=-1)

    def index(self, env_ids: torch.Tensor) -> Reference:
        return Reference(**{f.name: getattr(self, f.name)[env_ids] for f in fields(self)})


def smoothstep(tau: torch.Tensor, duration: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """s = 3 phi^2 - 2 phi^3 with phi = tau / duration clamped to [0, 1], and ds/dtau [1/s]."""
    phi = (tau / duration).clamp(0.0, 1.0)
    return phi * phi * (3.0 - 2.0 * phi), 6.0 * phi * (1.0 - phi) / duration


def ramp_from_rest(
    pos: torch.Tensor,
    vel: torch.Tensor,
    start: torch.Tensor,
    ramp: torch.Tensor,
    tau: torch.Tensor,
    duration: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Blend the orbit reference (pos, vel) (E, D) from rest at ``start`` (E, D) where ``ramp``
    (E,): p = start + s (pos - start), v = s vel + ds/dtau (pos - start) (module docstring)."""
    s, ds = smoothstep(tau, duration)
    gap = pos - start
    blend_pos = start + s[:, None] * gap
    blend_vel = s[:, None] * vel + ds[:, None] * gap
    on = ramp[:, None]
    return torch.where(on, blend_pos, pos), torch.where(on, blend_vel, vel)


def pelvis_reference(
    step: StepState, tau: torch.Tensor, cfg: ReferenceCfg
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pelvis (roll, pitch, yaw) and their rates (E, 3) at time ``tau`` into the step: the
    step's own lean plus, with ``com_anchoring=continuous``, the carry of the previous
    reference's roll and pitch (:func:`march.reference.com_carry.hermite_carry`)."""
    active = (tau < step.duration).to(tau.dtype)
    phase = (tau / step.duration).clamp(0.0, 1.0)
    w = math.pi / step.duration
    # Lean toward the stance foot: a positive roll lifts the left side, so left stance -> negative.
    lean = torch.where(step.stance_is_left, -1.0, 1.0).to(tau.dtype) * cfg.roll_amplitude
    roll = lean * torch.sin(math.pi * phase)
    roll_rate = lean * w * torch.cos(math.pi * phase) * active
    pitch = cfg.pitch_offset + cfg.pitch_amplitude * torch.sin(2.0 * math.pi * phase)
    pitch_rate = cfg.pitch_amplitude * 2.0 * w * torch.cos(2.0 * math.pi * phase) * active
    if cfg.com_anchoring == "continuous" and step.pelvis_from_pos is not None:
        # The previous reference's roll and pitch minus the step's own at tau = 0.
        own_pos = torch.stack([torch.zeros_like(lean), torch.full_like(lean, cfg.pitch_offset)], -1)
        own_vel = torch.stack([lean * w, cfg.pitch_amplitude * 2.0 * w], -1)
        dp, dv = hermite_carry(
            step.pelvis_from_pos - own_pos, step.pelvis_from_vel - own_vel, tau, step.duration
        )
        roll, pitch = roll + dp[:, 0], pitch + dp[:, 1]
        roll_rate, pitch_rate = roll_rate + dv[:, 0], pitch_rate + dv[:, 1]
    yaw = wrap_to_pi(step.yaw0 + step.yaw_rate * tau)
    ori = torch.stack([roll, pitch, yaw], dim=-1)
    return ori, torch.stack([roll_rate, pitch_rate, step.yaw_rate], dim=-1)


def reference_at(
    step: StepState,
    tau: torch.Tensor,
    cfg: ReferenceCfg | None = None,
    hlip: HlipCfg | None = None,
    num_upper: int = 17,
) -> Reference:
    """The full reference at time ``tau`` (E,) [s] since the touchdown that began ``step``.

    Past the planned duration (a late touchdown) the swing foot rests at the target and the CoM
    keeps flowing along the HLIP from the orbit's pre-impact state (position and velocity stay
    consistent). A ramping step (``step.ramp``) blends from rest (module docstring).
    """
    cfg = cfg or ReferenceCfg()
    hlip = hlip or HlipCfg()
    e = tau.shape[0]
    target = step.target.clone()
    target[:, 2] = target[:, 2] + cfg.foot_height_offset
    phase = tau / step.duration
    swing_pos, swing_vel = swing_trajectory(
        step.swing_start, target, phase, step.duration, cfg.swing_height, cfg.swing_xy_shape
    )
    stance_xy = step.stance_pos[:, :2]
    lam = step_lambda(step, cfg, hlip)

    def orbit(at: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return hlip_com_state(
            stance_xy,
            step.target[:, :2] - stance_xy,
            step.next_target[:, :2] - step.target[:, :2],
            step.duration,
            step.next_duration,
            at,
            lam,
            step.axis,
        )

    com_xy, com_vxy = orbit(tau)
    if step.ramp is not None and step.ramp_from is not None:
        com_xy, com_vxy = ramp_from_rest(
            com_xy, com_vxy, step.ramp_from, step.ramp, tau, step.duration
        )
    com_z = com_orbit_height(step, cfg, hlip)[:, None]
    com_vz = torch.zeros_like(com_z)
    if cfg.com_anchoring == "continuous" and step.com_from_pos is not None:
        # The previous reference's CoM state minus the orbit's at tau = 0; the ramp of an
        # episode start already begins at the measured CoM at rest (its xy gap is not carried).
        xy0, vxy0 = orbit(torch.zeros_like(tau))
        keep = 1.0 if step.ramp is None else (~step.ramp).to(tau.dtype)[:, None]
        gap_pos = torch.cat(
            [(step.com_from_pos[:, :2] - xy0) * keep, step.com_from_pos[:, 2:] - com_z], -1
        )
        gap_vel = torch.cat(
            [(step.com_from_vel[:, :2] - vxy0) * keep, step.com_from_vel[:, 2:]], -1
        )
        lam_e = lam if isinstance(lam, float) else lam[:, None]
        dp, dv = carry_correction(
            gap_pos[:, None], gap_vel[:, None], tau[:, None], step.duration[:, None], lam_e
        )
        com_xy, com_vxy = com_xy + dp[:, 0, :2], com_vxy + dv[:, 0, :2]
        com_z, com_vz = com_z + dp[:, 0, 2:], com_vz + dv[:, 0, 2:]
    pelvis_ori, pelvis_rate = pelvis_reference(step, tau, cfg)
    zeros = torch.zeros_like(pelvis_ori)
    swing_ori = torch.cat([zeros[:, :2], pelvis_ori[:, 2:3]], dim=-1)
    swing_rate = torch.cat([zeros[:, :2], pelvis_rate[:, 2:3]], dim=-1)
    if cfg.swing_toe_down != 0.0 or cfg.swing_toe_roll != 0.0:
        swing_ori[:, 1], swing_rate[:, 1] = toe_down(
            phase, step.duration, cfg.swing_toe_down, cfg.swing_toe_roll
        )
    if cfg.swing_pitch_carry > 0.0 and step.swing_from_pitch is not None:
        dp, dv = swing_pitch_carry(step.swing_from_pitch, tau, step.duration, cfg.swing_pitch_carry)
        swing_ori[:, 1], swing_rate[:, 1] = swing_ori[:, 1] + dp, swing_rate[:, 1] + dv
    if cfg.swing_roll_out != 0.0:
        swing_ori[:, 0], swing_rate[:, 0] = swing_roll_out(
            phase, step.duration, step.stance_is_left, cfg.swing_roll_out
        )
    if cfg.swing_heel_strike != 0.0:
        dp, dv, off, off_rate = heel_strike(
            phase,
            step.duration,
            pelvis_ori[:, 2],
            pelvis_rate[:, 2],
            cfg.swing_heel_strike,
            cfg.swing_heel_back,
        )
        swing_ori[:, 1], swing_rate[:, 1] = swing_ori[:, 1] + dp, swing_rate[:, 1] + dv
        swing_pos, swing_vel = swing_pos + off, swing_vel + off_rate
    upper = torch.zeros(e, num_upper, dtype=tau.dtype, device=tau.device)
    return Reference(
        com_pos=torch.cat([com_xy, com_z], dim=-1),
        com_vel=torch.cat([com_vxy, com_vz], dim=-1),
        pelvis_ori=pelvis_ori,
        pelvis_rate=pelvis_rate,
        swing_pos=swing_pos,
        swing_vel=swing_vel,
        swing_ori=swing_ori,
        swing_rate=swing_rate,
        upper_pos=upper,
        upper_vel=upper.clone(),
    )
