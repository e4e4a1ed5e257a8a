"""Hybrid linear inverted pendulum (HLIP), batched in plain torch (no simulator import).

State per horizontal plane: xi = [r, v], r = CoM position relative to the stance foot [m], v = CoM
velocity [m/s]. Continuous flow within a step (stance phase of duration T):

    d/dt [r, v] = A [r, v],   A = [[0, 1], [lam^2, 0]],   lam = sqrt(g / z0)

with the closed form e^{A tau} = [[cosh(lam tau), sinh(lam tau) / lam],
                                  [lam sinh(lam tau), cosh(lam tau)]].

Impact (the swing foot lands at stance + l and becomes the new stance foot): r+ = r- - l, v+ = v-,
i.e. B = [-1, 0]^T as in Xiong & Ames. The paper prints B = [0, -1]^T, which would change the
velocity at impact instead of the reference point of r; we read it as a typo (SPEC.md section 2).
Step-to-step map on pre-impact states: xi_{k+1}^- = e^{AT} (xi_k^- + B l_k).

Orbits (pre-impact state just before the impact that takes step l_0):
- period-1 (sagittal, l = v_d T every step): r- = l/2, v- = lam coth(lam T/2) l/2.
- alternating (l_k = (-1)^k a): r- = a/2, v- = lam tanh(lam T/2) a/2 (solve xi = -A_d (xi + B a)).
- period-2 (lateral): steps alternate l_0, l_1. With equal T, split l_0 = m + a, l_1 = m - a into a
  mean m (= v_y T) and an alternating part a (= -/+ nominal step width, sign by which foot lands);
  by linearity the orbit is the sum of the two closed forms above, so r- = l_0/2 and
  v- = lam coth(lam T/2) m/2 + lam tanh(lam T/2) a/2. With unequal durations T_0 (the flow that
  ends in the impact of l_0) and T_1 we solve the 2x2 fixed point exactly:
  xi = (I - E_0 E_1)^{-1} (E_0 E_1 B l_0 + E_0 B l_1),  E_i = e^{A T_i}.

Walking velocity v_y with left/right alternation: stepping from the left stance foot to the right
foot gives l_y = v_y T - w, from the right to the left l_y = v_y T + w (w = nominal step width), so
the lateral orbit is the period-2 orbit of (v_y T -/+ w) (see :func:`lateral_step_lengths`).

Reference anchoring (SPEC decision): the CoM reference of a step is the HLIP orbit for that step's
planned length and duration, anchored at the actual stance foot at touchdown, i.e. the state at
time tau is e^{-A (T - tau)} xi*^- (backward flow from the orbit's pre-impact state). Flowing the
measured touchdown state forward instead would diverge by about e^{lam T} (~7x) per step.

Late touchdown (decision, issue 10): past the planned duration the same formula holds with
tau > T, i.e. the reference keeps flowing forward from the pre-impact state (the robot is still
on the same stance foot, so the LIP keeps falling). Position and velocity stay consistent
(earlier the position froze at tau = T while the velocity kept its pre-impact value). The
command term restarts the step at 1.5 T at the latest, so the flow lasts at most 0.5 T
(cosh(lam T / 2) <= 2.1 for T <= 0.7 s).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch


@dataclass
class HlipCfg:
    """Parameters of the HLIP reduced-order model."""

    z0: float = 0.67
    """Constant CoM height above the stance foot [m] (author value for the G1)."""
    g: float = 9.81
    """Gravitational acceleration [m/s^2]."""
    step_width: float = 0.25
    """Nominal lateral distance between the feet, w [m]: the alternating part of lateral steps."""

    @property
    def lam(self) -> float:
        """Pendulum constant lambda = sqrt(g / z0) [1/s]."""
        return math.sqrt(self.g / self.z0)


def hlip_flow(
    r: torch.Tensor, v: torch.Tensor, tau: torch.Tensor | float, lam: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Closed-form intra-step flow e^{A tau} [r, v] (broadcasting; tau may be negative)."""
    tau = torch.as_tensor(tau, dtype=r.dtype, device=r.device)
    c = torch.cosh(lam * tau)
    s = torch.sinh(lam * tau)
    return r * c + v * s / lam, r * lam * s + v * c


def hlip_reset(
    r: torch.Tensor, v: torch.Tensor, step: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Impact map xi+ = xi- + B l with B = [-1, 0]^T: the reference point moves by the step."""
    return r - step, v


def hlip_step_to_step(
    r: torch.Tensor, v: torch.Tensor, step: torch.Tensor, duration: torch.Tensor | float, lam: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pre-impact to pre-impact map xi_{k+1}^- = e^{AT} (xi_k^- + B l_k)."""
    r_plus, v_plus = hlip_reset(r, v, step)
    return hlip_flow(r_plus, v_plus, duration, lam)


def hlip_orbit(
    step: torch.Tensor, duration: torch.Tensor | float, lam: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Period-1 orbit X* = (I - A_d)^{-1} B_d l for a constant step l and duration T.

    Closed form: r- = l/2, v- = lam coth(lam T/2) l/2 (pre-impact state).
    """
    duration = torch.as_tensor(duration, dtype=step.dtype, device=step.device)
    half = 0.5 * step
    return half, lam * half / torch.tanh(0.5 * lam * duration)


def hlip_orbit_alternating(
    amplitude: torch.Tensor, duration: torch.Tensor | float, lam: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Period-2 orbit for steps +a, -a, +a, ... (pre-impact state before the +a impact).

    Closed form: r- = a/2, v- = lam tanh(lam T/2) a/2.
    """
    duration = torch.as_tensor(duration, dtype=amplitude.dtype, device=amplitude.device)
    half = 0.5 * amplitude
    return half, lam * half * torch.tanh(0.5 * lam * duration)


def hlip_orbit_p2(
    step0: torch.Tensor,
    step1: torch.Tensor,
    duration0: torch.Tensor | float,
    duration1: torch.Tensor | float,
    lam: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact period-2 orbit for alternating (step0, duration0), (step1, duration1).

    Returns the pre-impact state just before the impact of ``step0``, reached after a flow of
    ``duration0``; after that impact the flow lasts ``duration1`` and ends with the impact of
    ``step1``. Solves xi = E0 E1 xi + E0 E1 B l0 + E0 B l1 with E_i = e^{A T_i} in closed form.
    Reduces to :func:`hlip_orbit` when the two steps are equal.
    """
    d0 = torch.as_tensor(duration0, dtype=step0.dtype, device=step0.device)
    d1 = torch.as_tensor(duration1, dtype=step0.dtype, device=step0.device)
    c0, s0 = torch.cosh(lam * d0), torch.sinh(lam * d0)
    # E0 E1 = e^{A (T0 + T1)} because the flows commute.
    c01, s01 = torch.cosh(lam * (d0 + d1)), torch.sinh(lam * (d0 + d1))
    # rhs = E0 E1 [-l0, 0] + E0 [-l1, 0]
    rhs_r = -c01 * step0 - c0 * step1
    rhs_v = -lam * s01 * step0 - lam * s0 * step1
    # (I - M)^{-1} with M = [[c01, s01/lam], [lam s01, c01]]; det = (1 - c01)^2 - s01^2.
    det = (1.0 - c01) ** 2 - s01**2
    r = ((1.0 - c01) * rhs_r + (s01 / lam) * rhs_v) / det
    v = (lam * s01 * rhs_r + (1.0 - c01) * rhs_v) / det
    return r, v


def lateral_step_lengths(
    vy: torch.Tensor, duration: torch.Tensor | float, width: float, left_lands_first: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Nominal lateral steps (l_0, l_1) = v_y T -/+ w for the next two impacts.

    A left foot landing sits ``width`` to the left of the right stance foot (l = v_y T + w), a
    right foot landing ``width`` to the right (l = v_y T - w).
    """
    drift = vy * torch.as_tensor(duration, dtype=vy.dtype, device=vy.device)
    sign = torch.where(left_lands_first, 1.0, -1.0).to(vy.dtype)
    return drift + sign * width, drift - sign * width


def hlip_com_state(
    stance_xy: torch.Tensor,
    step0: torch.Tensor,
    step1: torch.Tensor,
    duration0: torch.Tensor,
    duration1: torch.Tensor,
    tau: torch.Tensor,
    lam: float,
    axis: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """CoM reference (position, velocity) in the world xy-plane at time ``tau`` into a step.

    stance_xy: (E, 2) stance foot at touchdown (the anchor); step0: (E, 2) the planned step of the
    current swing (landing - stance); step1: (E, 2) the planned step after it; duration0/1: (E,)
    their durations [s]; tau: (E,) time since touchdown [s] (clamped at 0; past duration0 - a
    late touchdown - the stance phase continues: the state flows on from the pre-impact state,
    so position and velocity stay one solution of the LIP, d pos / d tau = vel);
    axis: (E, 2) unit sagittal direction (default +x; the course direction). The sagittal plane
    follows the period-1 orbit of step0, the lateral plane the period-2 orbit of (step0, step1).
    Returns (E, 2) position and (E, 2) velocity, world frame.
    """
    if axis is None:
        axis = torch.zeros_like(stance_xy)
        axis[:, 0] = 1.0
    lat = torch.stack([-axis[:, 1], axis[:, 0]], dim=-1)
    tau = tau.clamp(min=0.0)
    l0x, l0y = (step0 * axis).sum(-1), (step0 * lat).sum(-1)
    l1y = (step1 * lat).sum(-1)
    rx, vx = hlip_orbit(l0x, duration0, lam)
    ry, vy = hlip_orbit_p2(l0y, l1y, duration0, duration1, lam)
    # Flow from the orbit's pre-impact state to the current time in the step (backward within
    # the planned duration, forward past it).
    back = tau - duration0
    rx, vx = hlip_flow(rx, vx, back, lam)
    ry, vy = hlip_flow(ry, vy, back, lam)
    pos = stance_xy + rx[:, None] * axis + ry[:, None] * lat
    vel = vx[:, None] * axis + vy[:, None] * lat
    return pos, vel
