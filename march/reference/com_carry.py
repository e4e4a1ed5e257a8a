"""The continuous reference across touchdowns: carrying the previous step's reference CoM state
into the new step's HLIP orbit, and its pelvis roll and pitch into the new step's lean (issue
55; SPEC section 2, "References", revised 2026-12-06), and the CoM height a step is walked at.
Plain torch, no simulator import.

Why. Anchoring each step's orbit at the new stance foot (the earlier decision, still selectable
as ``reference.com_anchoring=stance``) restarts the CoM reference at -l_new/2 behind the new
foot while the old step ended at +l_old/2 ahead of the old one: a jump of (l_old - l_new)/2 plus
the landing offset and a timing term at every touchdown (p90 ~20 cm, most of a good tracker's
V). The paper chains pre-impact states with the step-to-step map and flows between them.

How (per plane, within a step of planned duration T, tau the time since it began). Let
(r_o, v_o)(tau) be the step's orbit reference (the HLIP orbit of the planned step, anchored at
the stance foot, flowed back from its pre-impact state), and (p0, u0) the previous reference's
CoM at the instant the step began. The reference is the orbit plus a correction

    c(tau) = e0 b(tau) + (u0 - v_o(0) - e0 b'(0)) T h(phi),      e0 = p0 - r_o(0),  phi = tau/T

- sagittal and lateral: b(tau) = sinh(lam (T - tau)) / sinh(lam T), a solution of the LIP
  (b'' = lam^2 b), so orbit + e0 b is exactly the two-point HLIP flow
  r(tau) = r0 cosh(lam tau) + c sinh(lam tau) from p0 to the orbit's pre-impact position;
  b'(0) = -lam coth(lam T);
- height: b(tau) = (1 - phi)^2 (1 + 2 phi) (cubic Hermite; the orbit's height is constant);
- h(phi) = phi (1 - phi)^2 with h(0) = 0, dh/dtau(0) = 1/T, h(1) = dh/dphi(1) = 0: it carries
  the velocity left over at tau = 0 and is gone, with its slope, at the planned touchdown.

So at tau = 0 the reference equals (p0, u0) (continuous in position and velocity), and at
tau = T its position is the orbit's pre-impact position, whatever p0 was: each step ends on the
planned step's orbit, so the reference cannot drift (the sagittal velocity at T differs from
the orbit's by -e0 lam / sinh(lam T), and the next step's h absorbs it; e0 of the next step
depends only on the plan's change and the touchdown's timing and place). Past T (a late
touchdown) the LIP part keeps flowing and h stays 0 (phi is clamped), so position and velocity
stay one C^1 curve until the touchdown or the timeout restart, which carry it on.

Pelvis roll and pitch (``hermite_carry``): the step's own lean (roll toward the stance foot,
pitch one period per step) starts at (0, pitch_offset) with a rate that depends on the stance
side and the step's duration, so a touchdown that comes early or late, a timeout restart (same
stance side) or a change of duration left a jump of 0.2-0.35 rad/s in the rates. The previous
reference's roll and pitch (position and rate) at the switch are carried by the cubic Hermite
correction e0 h00(phi) + (u0 - v_o(0)) T h10(phi), with h00 = (1 - phi)^2 (1 + 2 phi) and
h10 = phi (1 - phi)^2: continuous at tau = 0, gone with its slope at tau = T.

CoM height (``reference.com_height``): ``fixed`` walks every step at z0 (author 0.67 m, the
G1's standing CoM height); ``step`` lowers it with the step's length along the course,
z0(l) = clamp(z0 - slope (|l| - free), z_min, z0), so that long steps stay within the G1's reach
(the measured envelope, issue 55: longest step in tolerance 0.575 m at CoM height 0.67, 0.65 at
0.65, 0.775 at 0.62, 0.825 at 0.60, 0.90 at 0.57). The HLIP's lam = sqrt(g / z) then uses that
step's z.
"""

from __future__ import annotations

import math

import torch

COM_ANCHORINGS = ("continuous", "stance")
"""``reference.com_anchoring``: carry the previous reference's CoM state (default), or anchor
each step's orbit at the new stance foot (the earlier reference, which jumps at touchdown)."""
COM_HEIGHTS = ("fixed", "step")
"""``reference.com_height``: z0 everywhere (default), or z0 lowered with the step length."""


def step_com_height(
    step_along: torch.Tensor, z0: float, free_step: float, slope: float, z_min: float
) -> torch.Tensor:
    """(E,) CoM height [m] of steps ``step_along`` (E,) [m] long along the course:
    clamp(z0 - slope (|l| - free_step), z_min, z0) (module docstring)."""
    lowered = z0 - slope * (step_along.abs() - free_step)
    return lowered.clamp(min=z_min, max=z0)


def pendulum_lambda(z: torch.Tensor | float, g: float) -> torch.Tensor | float:
    """lam = sqrt(g / z) [1/s] of the CoM height ``z`` actually used (float or per env)."""
    if isinstance(z, torch.Tensor):
        return torch.sqrt(g / z)
    return math.sqrt(g / z)


def hermite_carry(
    gap_pos: torch.Tensor, gap_vel: torch.Tensor, tau: torch.Tensor, duration: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The correction e0 h00(phi) + v0 T h10(phi) and its tau-derivative (module docstring, the
    pelvis): ``gap_pos`` e0 and ``gap_vel`` v0 (E, D), ``tau`` and ``duration`` (E,) [s].
    At tau = 0 it is (e0, v0); from tau = T on it is (0, 0)."""
    phi = (tau / duration).clamp(0.0, 1.0)[:, None]
    one = 1.0 - phi
    t = duration[:, None]
    pos = gap_pos * (one * one * (1.0 + 2.0 * phi)) + gap_vel * (t * phi * one * one)
    vel = gap_pos * (-6.0 * phi * one / t) + gap_vel * (one * (1.0 - 3.0 * phi))
    return pos, vel


def carry_correction(
    gap_pos: torch.Tensor,
    gap_vel: torch.Tensor,
    tau: torch.Tensor,
    duration: torch.Tensor,
    lam: torch.Tensor | float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The correction c(tau) and dc/dtau added to the orbit reference (module docstring).

    gap_pos, gap_vel: (E, 1, 3) [m, m/s] the previous reference's CoM state minus the orbit's at
    tau = 0, columns (sagittal-or-x, lateral-or-y, z) (any frame for the first two: the map is
    the same per plane); tau: (E, K) [s]; duration: (E, 1) [s]; lam: float or (E, 1) [1/s].
    Returns (E, K, 3) position and velocity corrections.
    """
    phi = (tau / duration).clamp(0.0, 1.0)
    one = 1.0 - phi
    lam_t = torch.as_tensor(lam * duration, dtype=tau.dtype, device=tau.device)  # (E, 1)
    inv_sinh = 1.0 / torch.sinh(lam_t)
    ahead = lam * (duration - tau.clamp(min=0.0))  # (E, K): lam (T - tau)
    lip = torch.sinh(ahead) * inv_sinh
    lip_rate = -lam * torch.cosh(ahead) * inv_sinh
    hermite = one * one * (1.0 + 2.0 * phi)
    hermite_rate = -6.0 * phi * one / duration
    basis = torch.stack([lip, lip, hermite], dim=-1)  # (E, K, 3)
    basis_rate = torch.stack([lip_rate, lip_rate, hermite_rate], dim=-1)
    # b'(0) per column: -lam coth(lam T) in the two LIP planes, 0 in height.
    coth = -lam * torch.cosh(lam_t) * inv_sinh  # (E, 1)
    slope0 = torch.stack([coth, coth, torch.zeros_like(coth)], dim=-1)  # (E, 1, 3)
    left = gap_vel - gap_pos * slope0  # the velocity the LIP part leaves at tau = 0
    # T h(phi) and its tau-derivative h'(phi) = (1 - phi)(1 - 3 phi): 0 from phi = 1 on.
    pos = gap_pos * basis + left * (duration * phi * one * one)[..., None]
    vel = gap_pos * basis_rate + left * (one * (1.0 - 3.0 * phi))[..., None]
    return pos, vel
