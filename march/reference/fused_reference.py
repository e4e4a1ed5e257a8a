"""The step reference of :mod:`march.reference.trajectory` in few torch ops (issue 41): what the
``reference`` command term evaluates every control step, for any number of instants per env.

:func:`reference_outputs` is :func:`march.reference.trajectory.reference_at` flattened
(``Reference.flatten``), the same maths rearranged; :func:`reference_at` stays the readable
definition the tests hold it to (within 1e-9 in float64). Plain torch, no simulator import.
"""

from __future__ import annotations

import math

import torch

from march.reference.hlip import HlipCfg
from march.reference.kept import kept
from march.reference.trajectory import (
    TOE_ROLL_SCALE,
    ReferenceCfg,
    StepState,
    com_orbit_height,
    heel_strike,
    step_lambda,
    swing_pitch_carry,
    swing_roll_out,
    wrap_to_pi,
)

BASIS_COLUMNS = 16
"""Polynomials of the phase s that :func:`reference_outputs` evaluates in one product: the swing
foot's xy Bezier weights of p0 and p1 (with ``ReferenceCfg.swing_xy_shape``'s inner control
points), its z Bezier weights of z0, c and z1, the three d/ds
weights (of p1 - p0, c - z0 and z1 - c), the ramp's smoothstep and its d/ds, the CoM
carry's Hermite polynomials (1 - s)^2 (1 + 2 s), s (1 - s)^2 and their d/ds
(march.reference.com_carry), and the swing foot's pitch, toe-down 64 s^3 (1 - s)^3 plus toe
roll K s^3 (1 - s)^3 (1 - 2 s) with their amplitudes, and its d/ds
(march.reference.trajectory.toe_down)."""


def reference_tables(
    cfg: ReferenceCfg, num_upper: int, dtype: torch.dtype, device: torch.device | str
) -> tuple[torch.Tensor, ...]:
    """The constant tensors of :func:`reference_outputs`, made once per (cfg, num_upper, dtype,
    device) and kept (built eagerly: pass them into a compiled call)."""
    key = (
        "reference_tables",
        cfg.swing_height,
        cfg.swing_xy_shape,
        cfg.swing_toe_down,
        cfg.swing_toe_roll,
        cfg.foot_height_offset,
        cfg.roll_amplitude,
        cfg.pitch_amplitude,
        cfg.pitch_offset,
        num_upper,
        dtype,
        torch.device(device),
    )
    return kept(key, lambda: _make_reference_tables(cfg, num_upper, dtype, device))


def _make_reference_tables(
    cfg: ReferenceCfg, num_upper: int, dtype: torch.dtype, device: torch.device | str
) -> tuple[torch.Tensor, ...]:
    # Bernstein polynomials b^n_k = C(n, k) s^k (1 - s)^(n - k) as entries (k, n - k) of the
    # 7 x 7 products s^i (1 - s)^j, summed into the BASIS_COLUMNS polynomials.
    bern = torch.zeros(7, 7, BASIS_COLUMNS, dtype=torch.float64)

    def add(col: int, n: int, ks: range, scale: float = 1.0) -> None:
        for k in ks:
            bern[k, n - k, col] += scale * math.comb(n, k)

    # xy: ctrl p0, p0, p0 + a D, p1 - a D, p1, p1 (a = swing_xy_shape, D = p1 - p0; a = 0:
    # p0, p0, p0, p1, p1, p1): the weights of p0 and p1, and 5 (a b^4_1 + (1 - 2 a) b^4_2 +
    # a b^4_3) of D for d/ds.
    a = cfg.swing_xy_shape
    add(0, 5, range(0, 2))  # xy: weight of p0
    add(0, 5, range(2, 3), 1.0 - a)
    add(0, 5, range(3, 4), a)
    add(1, 5, range(2, 3), a)  # xy: weight of p1
    add(1, 5, range(3, 4), 1.0 - a)
    add(1, 5, range(4, 6))
    add(2, 6, range(0, 2))  # z: weight of z0 (ctrl z0, z0, c, c, c, z1, z1)
    add(3, 6, range(2, 5))  # z: weight of c
    add(4, 6, range(5, 7))  # z: weight of z1
    add(5, 4, range(2, 3), 5.0 * (1.0 - 2.0 * a))  # d/ds xy, of p1 - p0
    add(5, 4, range(1, 2), 5.0 * a)
    add(5, 4, range(3, 4), 5.0 * a)
    add(6, 5, range(1, 2), 6.0)  # d/ds z: 6 b^5_1 (c - z0)
    add(7, 5, range(4, 5), 6.0)  #        + 6 b^5_4 (z1 - c)
    add(8, 3, range(2, 4))  # smoothstep 3 s^2 - 2 s^3
    add(9, 2, range(1, 2), 3.0)  # its d/ds 6 s (1 - s)
    add(10, 3, range(0, 2))  # carry: h00 = (1 - s)^3 + 3 s (1 - s)^2 = (1 - s)^2 (1 + 2 s)
    add(11, 3, range(1, 2), 1.0 / 3.0)  # h10 = s (1 - s)^2
    add(12, 2, range(1, 2), -3.0)  # d h00 / ds = -6 s (1 - s)
    add(13, 2, range(0, 1))  # d h10 / ds = (1 - s)^2 - 2 s (1 - s)
    add(13, 2, range(1, 2), -1.0)
    # The swing-foot pitch, amplitudes included: toe-down A 64 s^3 (1 - s)^3 plus the roll
    # R K s^3 (1 - s)^3 (1 - 2 s) = R K (s^3 (1 - s)^4 - s^4 (1 - s)^3), and their d/ds
    # 192 A (s^2 (1 - s)^3 - s^3 (1 - s)^2) + R K (3 s^2 (1 - s)^4 - 8 s^3 (1 - s)^3 +
    # 3 s^4 (1 - s)^2) (march.reference.trajectory.toe_down).
    toe, roll = cfg.swing_toe_down, cfg.swing_toe_roll * TOE_ROLL_SCALE
    bern[3, 3, 14] = 64.0 * toe
    bern[3, 4, 14], bern[4, 3, 14] = roll, -roll
    bern[2, 3, 15], bern[3, 2, 15] = 192.0 * toe, -192.0 * toe
    bern[2, 4, 15], bern[3, 3, 15], bern[4, 2, 15] = 3.0 * roll, -8.0 * roll, 3.0 * roll
    # Control matrix (10 basis rows x [pos xyz, d/ds xyz]) from u = [start xyz, target xyz,
    # apex], with c = (64 apex - 7 (z0 + z1)) / 50 (the z control point of swing_trajectory).
    ctrl = torch.zeros(7, BASIS_COLUMNS, 6, dtype=torch.float64)
    c_of = torch.tensor([0, 0, -7 / 50, 0, 0, -7 / 50, 64 / 50], dtype=torch.float64)
    ctrl[0, 0, 0] = ctrl[1, 0, 1] = 1.0  # p0
    ctrl[3, 1, 0] = ctrl[4, 1, 1] = 1.0  # p1
    ctrl[2, 2, 2] = 1.0  # z0
    ctrl[:, 3, 2] = c_of  # c
    ctrl[5, 4, 2] = 1.0  # z1
    ctrl[3, 5, 3] = ctrl[4, 5, 4] = 1.0  # p1 - p0
    ctrl[0, 5, 3] = ctrl[1, 5, 4] = -1.0
    ctrl[:, 6, 5] = c_of  # c - z0
    ctrl[2, 6, 5] -= 1.0
    ctrl[:, 7, 5] = -c_of  # z1 - c
    ctrl[5, 7, 5] += 1.0
    ra, pa = cfg.roll_amplitude, cfg.pitch_amplitude
    tables = (
        torch.arange(7, dtype=torch.float64),  # exponents
        bern.reshape(49, BASIS_COLUMNS),
        ctrl.reshape(7, BASIS_COLUMNS * 6),
        torch.tensor([math.pi, 2.0 * math.pi], dtype=torch.float64),  # pelvis phase angles
        torch.tensor([[ra, pa], [-ra, pa]], dtype=torch.float64),  # [right, left stance]
        torch.tensor(
            [[ra * math.pi, 2.0 * pa * math.pi], [-ra * math.pi, 2.0 * pa * math.pi]],
            dtype=torch.float64,
        ),
        torch.tensor([0.0, cfg.pitch_offset], dtype=torch.float64),
        torch.tensor([0.0, 0.0, cfg.foot_height_offset], dtype=torch.float64),
        torch.zeros(max(2, num_upper), dtype=torch.float64),
        torch.tensor([1.0, 1.0, -1.0, 1.0], dtype=torch.float64),  # [axis; lat] from axis
        # the carry's coefficient rows from the start gap e0 (march.reference.com_carry)
        torch.tensor([[1.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]], dtype=torch.float64),
        torch.tensor([1.0, 1.0, 0.0], dtype=torch.float64),  # the LIP planes
    )
    index = (
        torch.tensor([0, 1, 1, 0]),  # the frame's entries from axis: [ax, ay, ay, ax] * sign
        torch.tensor([0, 3]),  # l1 per plane from the projected steps: [l0 sagittal, l1 lateral]
    )
    return tuple(t.to(dtype=dtype, device=device) for t in tables) + tuple(
        i.to(device=device) for i in index
    )


def reference_outputs(
    step: StepState,
    tau: torch.Tensor,
    cfg: ReferenceCfg | None = None,
    hlip: HlipCfg | None = None,
    num_upper: int = 17,
    tables: tuple[torch.Tensor, ...] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`reference_at` flattened (``Reference.flatten``: positions and velocities in
    ``output_names`` order) in about 80 torch ops for any number of instants: ``tau`` (E,) or
    (E, K) [s] gives (E, n) or (E, K, n) each. The same maths rearranged (values equal within
    float32 rounding, tests/test_reference.py):

    - the swing foot's two Bezier curves, their s-derivatives and the ramp's smoothstep are
      polynomials of one phase s: one product of the powers s^i (1 - s)^j with a constant
      Bernstein table, then one batched product with each env's control points (a linear map
      of lift-off, landing and apex);
    - the HLIP orbits of both planes in one pass, in the closed form of
      :func:`march.reference.hlip.hlip_orbit_p2` simplified with cosh^2 - sinh^2 = 1
      (r = l0/2 + (cosh a0 - cosh a1) l1 / (2 (cosh A - 1)),
      v = lam (sinh A l0 + (sinh a0 + sinh a1) l1) / (2 (cosh A - 1)), a_i = lam T_i,
      A = a0 + a1; the sagittal plane is the period-1 case l1 = l0, T1 = T0), turned into the
      world frame once per env and flowed to every instant by one 2x2 product;
    - the pelvis roll and pitch oscillations as one sin / cos of (pi s, 2 pi s), plus the
      carry of the previous reference's (the same Hermite basis as the CoM's height).
    ``tables``: :func:`reference_tables` (looked up when None; pass them into a compiled call).
    """
    cfg = cfg or ReferenceCfg()
    hlip = hlip or HlipCfg()
    if tables is None:
        tables = reference_tables(cfg, num_upper, tau.dtype, tau.device)
    exps, bern, ctrl_map, pelvis_angles, lean, lean_rate, pitch_off, foot_off, zeros, sign = tables[
        :10
    ]
    carry_rows, lip_planes = tables[10:12]
    frame_idx, l1_idx = tables[12:]
    single = tau.dim() == 1
    t = tau[:, None] if single else tau  # (E, K)
    e, k = t.shape
    lam = step_lambda(step, cfg, hlip)
    lam = lam if isinstance(lam, float) else lam[:, None]  # float, or (E, 1) (com_height=step)
    carry = cfg.com_anchoring == "continuous" and step.com_from_pos is not None
    dur = step.duration[:, None]
    phase = t / dur
    s = phase.clamp(0.0, 1.0)
    # Bernstein basis: every polynomial of s the reference needs, (E, K, 10).
    powers = torch.stack([s, 1.0 - s], dim=-1)[..., None] ** exps  # (E, K, 2, 7)
    products = powers[..., 0, :, None] * powers[..., 1, None, :]  # (E, K, 7, 7)
    basis = products.reshape(e, k, 49) @ bern
    # Swing foot: positions and d/ds, (E, K, 6).
    target = step.target if cfg.foot_height_offset == 0.0 else step.target + foot_off
    apex = torch.maximum(step.swing_start[:, 2], target[:, 2]) + cfg.swing_height
    u = torch.cat([step.swing_start, target, apex[:, None]], dim=-1)
    swing = basis @ (u @ ctrl_map).view(e, BASIS_COLUMNS, 6)
    # HLIP: both planes' orbits (pre-impact), columns [sagittal, lateral].
    frame = (step.axis.index_select(1, frame_idx) * sign).view(e, 2, 2)  # rows: axis, lat
    feet = torch.stack([step.stance_pos, step.target, step.next_target], dim=1)[..., :2]
    steps = (feet[:, 1:] - feet[:, :-1]) @ frame.transpose(1, 2)  # (E, step 0|1, plane)
    l0, l1 = steps[:, 0], steps.flatten(1).index_select(1, l1_idx)  # l1: l0x (sag.), l1y (lat.)
    durs = torch.stack([step.duration, step.next_duration], dim=-1)
    args = lam * torch.cat([durs, durs + dur], dim=-1)
    ch, sh = torch.cosh(args), torch.sinh(args)  # a0, a1 (lateral), A (sagittal, lateral)
    den = ch[:, 2:] - 1.0
    r = (l0 + (ch[:, 0:1] - ch[:, 0:2]) * l1 / den) * 0.5
    v = (sh[:, 2:] * l0 + (sh[:, 0:1] + sh[:, 0:2]) * l1) * (0.5 * lam) / den
    orbit = torch.stack([r, v], dim=1) @ frame  # (E, [r, v], xy), world frame
    # flow from the pre-impact state to t (and to 0 first when the step carries a CoM state)
    t_flow = torch.cat([torch.zeros_like(t[:, :1]), t], dim=1) if carry else t
    kf = t_flow.shape[1]
    back = lam * (t_flow.clamp(min=0.0) - dur)
    cb, sb = torch.cosh(back), torch.sinh(back)
    flow = torch.stack([cb, sb / lam, lam * sb, cb], dim=-1).view(e, 2 * kf, 2)
    com = (flow @ orbit).view(e, kf, 2, 2)
    com_pos = com[:, kf - k :, 0, :] + step.stance_pos[:, None, :2]
    com_vel = com[:, kf - k :, 1, :]
    com_z = com_orbit_height(step, cfg, hlip)[:, None, None].expand(e, k, 1)
    com_vz = zeros[:1].expand(e, k, 1)
    if step.ramp is not None and step.ramp_from is not None:
        gap = com_pos - step.ramp_from[:, None]
        smooth, dsmooth = basis[..., 8:9], basis[..., 9:10] / dur[..., None]
        on = step.ramp[:, None, None]
        com_vel = torch.where(on, smooth * com_vel + dsmooth * gap, com_vel)
        com_pos = torch.where(on, step.ramp_from[:, None] + smooth * gap, com_pos)
    if carry:
        # march.reference.com_carry's correction c = F @ C in one product per env: F (K, [pos,
        # vel], 3) the basis [LIP part, h00, T h10] and its rates at every instant, C (3, xyz)
        # the coefficients [e0 in the LIP planes; e0 in height; the velocity left at 0].
        # sinh(lam (T - t)) = -sinh(back), cosh(lam (T - t)) = cosh(back); sinh(lam T) = sh0.
        neg_inv = -1.0 / sh[:, 0:1]
        herm = basis[..., 10:14]
        f = torch.stack(
            [
                sb[:, 1:] * neg_inv,
                herm[..., 0],
                herm[..., 1] * dur,
                cb[:, 1:] * (lam * neg_inv),
                herm[..., 2] / dur,
                herm[..., 3],
            ],
            dim=-1,
        )
        # e0 and the velocity gap: the previous reference's CoM state minus the orbit's at 0
        # (the ramp of an episode start excepted in xy: it starts at the measured CoM).
        gap = torch.stack([step.com_from_pos, step.com_from_vel], 1)  # (E, [p, v], 3)
        gap = gap - torch.cat([com[:, 0], zeros[:2, None].expand(e, 2, 1)], -1)
        gap[:, 0] -= torch.cat([step.stance_pos[:, :2], com_z[:, 0]], -1)
        if step.ramp is not None:
            gap[..., :2] *= (~step.ramp)[:, None, None]
        coef = gap[:, :1] * carry_rows  # (E, 3, 3): rows e0 (LIP planes), e0 (height), 0
        coef[:, 2] = gap[:, 1] - gap[:, 0] * (lam * ch[:, 0:1] * neg_inv) * lip_planes
        corr = (f.view(e, 2 * k, 3) @ coef).view(e, k, 2, 3)
        com_pos, com_vel = com_pos + corr[..., 0, :2], com_vel + corr[..., 1, :2]
        com_z, com_vz = com_z + corr[..., 0, 2:], com_vz + corr[..., 1, 2:]
    # Pelvis roll / pitch (lean toward the stance foot) and yaw.
    angles = s[..., None] * pelvis_angles
    left = step.stance_is_left.long()
    roll_pitch = torch.sin(angles) * lean[left][:, None] + pitch_off
    rate_scale = (t < dur) / dur
    roll_pitch_rate = torch.cos(angles) * lean_rate[left][:, None] * rate_scale[..., None]
    if cfg.com_anchoring == "continuous" and step.pelvis_from_pos is not None:
        # The carry of the previous reference's roll and pitch, e0 h00 + v0 T h10
        # (march.reference.com_carry.hermite_carry): e0, v0 the gap to the step's own at 0.
        herm, d = basis[..., 10:14], dur[..., None]
        e0 = (step.pelvis_from_pos - pitch_off)[:, None]
        v0 = (step.pelvis_from_vel - lean_rate[left] / dur)[:, None]
        roll_pitch = roll_pitch + e0 * herm[..., 0:1] + v0 * (herm[..., 1:2] * d)
        roll_pitch_rate = roll_pitch_rate + e0 * (herm[..., 2:3] / d) + v0 * herm[..., 3:4]
    yaw = wrap_to_pi(step.yaw0[:, None] + step.yaw_rate[:, None] * t)[..., None]
    yaw_rate = step.yaw_rate[:, None, None].expand(e, k, 1)
    per_s = ((phase < 1.0) / dur)[..., None]  # d/dt = d/ds / T inside the swing, 0 after
    swing_vel = swing[..., 3:] * per_s
    z1, zu = zeros[:1].expand(e, k, 1), zeros[:num_upper].expand(e, k, num_upper)
    # The swing foot's roll and pitch (and rates), (E, K, 1) each: flat unless shaped.
    roll, pitch, roll_rate, pitch_rate = z1, z1, z1, z1
    if cfg.swing_toe_down != 0.0 or cfg.swing_toe_roll != 0.0:
        # toed down (and rolled) in the swing (march.reference.trajectory.toe_down): the
        # table's columns 14 and 15 carry the amplitudes
        pitch, pitch_rate = basis[..., 14:15], basis[..., 15:16] * per_s
    if cfg.swing_pitch_carry > 0.0 and step.swing_from_pitch is not None:
        # the lift-off pitch carried (march.reference.trajectory.swing_pitch_carry)
        carried, rate = swing_pitch_carry(
            step.swing_from_pitch[:, None], t, dur, cfg.swing_pitch_carry
        )
        pitch, pitch_rate = pitch + carried[..., None], pitch_rate + rate[..., None]
    if cfg.swing_roll_out != 0.0:
        # rolled toward the swing foot's side (march.reference.trajectory.swing_roll_out)
        rolled, rate = swing_roll_out(phase, dur, step.stance_is_left[:, None], cfg.swing_roll_out)
        roll, roll_rate = rolled[..., None], rate[..., None]
    swing_pos = swing[..., :3]
    if cfg.swing_heel_strike != 0.0:
        # toe up at touchdown, the heel where a flat foot's lands
        # (march.reference.trajectory.heel_strike)
        toe_up, rate, offset, offset_rate = heel_strike(
            phase, dur, yaw[..., 0], yaw_rate[..., 0], cfg.swing_heel_strike, cfg.swing_heel_back
        )
        pitch, pitch_rate = pitch + toe_up[..., None], pitch_rate + rate[..., None]
        swing_pos, swing_vel = swing_pos + offset, swing_vel + offset_rate
    pos = torch.cat([com_pos, com_z, roll_pitch, yaw, swing_pos, roll, pitch, yaw, zu], dim=-1)
    vel = torch.cat(
        [
            com_vel,
            com_vz,
            roll_pitch_rate,
            yaw_rate,
            swing_vel,
            roll_rate,
            pitch_rate,
            yaw_rate,
            zu,
        ],
        -1,
    )
    if single:
        return pos[:, 0], vel[:, 0]
    return pos, vel
