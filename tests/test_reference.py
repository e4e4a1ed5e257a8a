"""Reference trajectory: swing Bezier end points, end velocities and apex; angle wrapping; the
flattened output layout."""

import math

import pytest
import torch

from march.reference.hlip import HlipCfg, hlip_com_state
from march.reference.planner import Plan
from march.reference.trajectory import (
    ReferenceCfg,
    StepState,
    angle_mask,
    bezier,
    output_names,
    reference_at,
    step_state_from_plan,
    swing_trajectory,
    tracking_error,
    wrap_to_pi,
)

torch.set_num_threads(1)
F64 = torch.float64


def _swing_case():
    start = torch.tensor([[0.0, -0.12, 0.0], [0.1, 0.1, 0.05], [0.3, 0.0, 0.1]], dtype=F64)
    end = torch.tensor([[0.35, -0.12, 0.0], [0.5, 0.2, -0.03], [0.9, -0.1, 0.18]], dtype=F64)
    duration = torch.tensor([0.5, 0.45, 0.7], dtype=F64)
    return start, end, duration


def test_swing_end_points_and_zero_end_velocity():
    start, end, duration = _swing_case()
    for phase, point in ((0.0, start), (1.0, end)):
        pos, vel = swing_trajectory(start, end, torch.full((3,), phase, dtype=F64), duration, 0.1)
        torch.testing.assert_close(pos, point)
        assert vel.abs().max() < 1e-12
    # Past the planned duration the foot rests at the target.
    pos, vel = swing_trajectory(start, end, torch.full((3,), 1.3, dtype=F64), duration, 0.1)
    torch.testing.assert_close(pos, end)
    assert vel.abs().max() == 0.0


def test_swing_apex_height():
    start, end, duration = _swing_case()
    z_sw = 0.1
    apex = torch.maximum(start[:, 2], end[:, 2]) + z_sw
    mid, _ = swing_trajectory(start, end, torch.full((3,), 0.5, dtype=F64), duration, z_sw)
    torch.testing.assert_close(mid[:, 2], apex)
    s = torch.linspace(0, 1, 201, dtype=F64)
    z = torch.stack(
        [swing_trajectory(start, end, si.expand(3), duration, z_sw)[0][:, 2] for si in s]
    )
    # Equal heights: mid-swing is the maximum; otherwise it is at least the apex and close to it.
    assert float(z[:, 0].max()) == pytest.approx(float(apex[0]), abs=1e-9)
    assert (z.max(0).values >= apex - 1e-9).all()
    assert (z.max(0).values <= apex + 0.02).all()
    # Never below the lower end point (no scuffing into the stone edge).
    assert (z >= torch.minimum(start[:, 2], end[:, 2]) - 1e-9).all()


def test_swing_velocity_is_time_derivative():
    start, end, duration = _swing_case()
    tau, h = 0.2, 1e-6
    pa, _ = swing_trajectory(start, end, (tau - h) / duration, duration, 0.1)
    pb, _ = swing_trajectory(start, end, (tau + h) / duration, duration, 0.1)
    _, vel = swing_trajectory(start, end, tau / duration, duration, 0.1)
    torch.testing.assert_close(vel, (pb - pa) / (2 * h), atol=1e-6, rtol=0)


def test_bezier_derivative_against_finite_difference():
    ctrl = torch.randn(4, 7, 3, dtype=F64, generator=torch.Generator().manual_seed(0))
    s, h = torch.full((4,), 0.37, dtype=F64), 1e-6
    _, d = bezier(ctrl, s)
    torch.testing.assert_close(d, (bezier(ctrl, s + h)[0] - bezier(ctrl, s - h)[0]) / (2 * h))


def test_wrap_to_pi():
    x = torch.tensor([0.0, math.pi - 1e-6, math.pi + 0.1, -math.pi - 0.1, 7.0, -20.0, 3 * math.pi])
    w = wrap_to_pi(x)
    assert (w >= -math.pi).all() and (w < math.pi).all()
    torch.testing.assert_close(torch.sin(w), torch.sin(x), atol=1e-5, rtol=0)
    torch.testing.assert_close(torch.cos(w), torch.cos(x), atol=1e-5, rtol=0)
    assert float(w[2]) == pytest.approx(-math.pi + 0.1, abs=1e-6)
    assert float(w[3]) == pytest.approx(math.pi - 0.1, abs=1e-6)


def test_tracking_error_wraps_only_angles():
    names = output_names(2)
    mask = angle_mask(2)
    y = torch.zeros(1, len(names))
    ref = torch.zeros(1, len(names))
    yaw, com_x = names.index("pelvis_yaw"), names.index("com_x")
    y[0, yaw], ref[0, yaw] = 3.1, -3.1  # 0.083 rad apart across the seam, not 6.2
    y[0, com_x], ref[0, com_x] = 6.0, 0.0  # positions are never wrapped
    eta = tracking_error(y, ref, mask)
    assert float(eta[0, yaw]) == pytest.approx(6.2 - 2 * math.pi, abs=1e-5)
    assert float(eta[0, com_x]) == pytest.approx(6.0)


def _plan(e=2):
    feet = torch.tensor(
        [[0.35, -0.125, 0.05], [0.7, 0.125, 0.0], [1.0, -0.1, 0.0], [1.3, 0.1, 0.0]]
    )
    return Plan(
        footholds=feet.expand(e, 4, 3).clone(),
        durations=torch.tensor([0.5, 0.55, 0.6, 0.6]).expand(e, 4).clone(),
        lands_left=torch.tensor([False, True, False, True]).expand(e, 4).clone(),
        cost=torch.zeros(e),
        feasible=torch.ones(e, dtype=torch.bool),
        start=torch.tensor([0.0, 0.125, 0.0]).expand(e, 3).clone(),
    )


def _step(e=2, yaw0=0.0, yaw_rate=0.2) -> StepState:
    plan = _plan(e)
    swing = torch.tensor([-0.05, -0.125, 0.0]).expand(e, 3).clone()
    return step_state_from_plan(
        plan, plan.start, swing, torch.full((e,), yaw0), torch.full((e,), yaw_rate)
    )


def test_reference_layout_and_flatten():
    ref = reference_at(_step(), torch.tensor([0.1, 0.3]), num_upper=17)
    pos, vel = ref.flatten()
    assert pos.shape == (2, 29) and vel.shape == (2, 29)
    assert ref.names == output_names(17) and len(ref.names) == 29
    assert ref.names[:3] == ["com_x", "com_y", "com_z"] and ref.names[-1] == "upper_16"
    torch.testing.assert_close(pos[:, 6:9], ref.swing_pos)
    assert angle_mask(17).sum() == 6 and angle_mask(17)[5] and not angle_mask(17)[6]
    assert (pos[:, 12:] == 0).all() and (vel[:, 12:] == 0).all()


def test_reference_components():
    step = _step(yaw0=3.1, yaw_rate=0.2)
    tau = torch.tensor([0.0, 0.5])
    ref = reference_at(step, tau, ReferenceCfg(swing_height=0.1), HlipCfg(), num_upper=3)
    # Swing: lift-off point at touchdown, planned foothold at the planned duration.
    torch.testing.assert_close(ref.swing_pos[0], step.swing_start[0])
    torch.testing.assert_close(ref.swing_pos[1], step.target[1])
    # CoM: HLIP in x/y anchored at the stance foot, constant height z0 above it.
    xy, vxy = hlip_com_state(
        step.stance_pos[:, :2],
        step.target[:, :2] - step.stance_pos[:, :2],
        step.next_target[:, :2] - step.target[:, :2],
        step.duration,
        step.next_duration,
        tau,
        HlipCfg().lam,
    )
    torch.testing.assert_close(ref.com_pos[:, :2], xy)
    torch.testing.assert_close(ref.com_vel[:, :2], vxy)
    torch.testing.assert_close(ref.com_pos[:, 2], torch.full((2,), 0.67))
    assert (ref.com_vel[:, 2] == 0).all()
    # At the end of the step the CoM is halfway between stance and landing foot along the course
    # (period-1 orbit r- = l/2; laterally only for equal durations, not the case here).
    mid = 0.5 * (step.stance_pos[1, :2] + step.target[1, :2])
    assert float(ref.com_pos[1, 0]) == pytest.approx(float(mid[0]), abs=1e-6)
    # Yaw tracks the commanded rate and is wrapped; roll/pitch vanish at touchdown.
    assert float(ref.pelvis_ori[1, 2]) == pytest.approx(3.2 - 2 * math.pi, abs=1e-5)
    assert (ref.pelvis_rate[:, 2] == 0.2).all()
    assert ref.pelvis_ori[:, :2].abs().max() < 1e-6
    # Swing foot flat with the pelvis yaw.
    torch.testing.assert_close(ref.swing_ori[:, 2], ref.pelvis_ori[:, 2])
    assert (ref.swing_ori[:, :2] == 0).all()


def test_pelvis_leans_toward_stance_and_rates_are_derivatives():
    step = _step(yaw_rate=-0.3)  # left stance
    cfg = ReferenceCfg()
    tau, h = torch.tensor([0.17, 0.25]), 1e-3
    ref = reference_at(step, tau, cfg, num_upper=0)
    assert float(ref.pelvis_ori[1, 0]) == pytest.approx(-cfg.roll_amplitude, abs=1e-6)
    a = reference_at(step, tau - h, cfg, num_upper=0)
    b = reference_at(step, tau + h, cfg, num_upper=0)
    pos_a, _ = a.flatten()
    pos_b, _ = b.flatten()
    _, vel = ref.flatten()
    fd = tracking_error(pos_b, pos_a, angle_mask(0)) / (2 * h)
    torch.testing.assert_close(vel, fd, atol=2e-3, rtol=1e-3)


# ---------------------------------------------------------------- issue 10: late touchdown, start

LAM = HlipCfg().lam
T = 0.5
L = 0.3
"""A straight walk: steps of L = 0.3 m along +x every T = 0.5 s, feet +/- 0.125 m across."""


def _straight_step(ramp_from=None, e=1) -> StepState:
    feet = torch.tensor(
        [[0.3, -0.125, 0.0], [0.6, 0.125, 0.0], [0.9, -0.125, 0.0], [1.2, 0.125, 0.0]], dtype=F64
    )
    plan = Plan(
        footholds=feet.expand(e, 4, 3).clone(),
        durations=torch.full((e, 4), T, dtype=F64),
        lands_left=torch.tensor([False, True, False, True]).expand(e, 4).clone(),
        cost=torch.zeros(e, dtype=F64),
        feasible=torch.ones(e, dtype=torch.bool),
        start=torch.tensor([[0.0, 0.125, 0.0]], dtype=F64).expand(e, 3).clone(),
    )
    swing = torch.tensor([[0.0, -0.125, 0.0]], dtype=F64).expand(e, 3).clone()
    zero = torch.zeros(e, dtype=F64)
    return step_state_from_plan(plan, plan.start, swing, zero, zero, ramp_from=ramp_from)


def _orbit_x(tau: float) -> tuple[float, float]:
    """Hand-derived sagittal HLIP reference: pre-impact r* = L/2, v* = lam coth(lam T/2) L/2,
    flowed by tau - T (x measured from the stance foot at x = 0)."""
    r, v = 0.5 * L, LAM * 0.5 * L / math.tanh(0.5 * LAM * T)
    d = tau - T
    return (
        r * math.cosh(LAM * d) + v / LAM * math.sinh(LAM * d),
        r * LAM * math.sinh(LAM * d) + v * math.cosh(LAM * d),
    )


def _com(step: StepState, tau: float) -> tuple[torch.Tensor, torch.Tensor]:
    e = step.stance_pos.shape[0]
    ref = reference_at(step, torch.full((e,), tau, dtype=F64), num_upper=0)
    return ref.com_pos[:, :2], ref.com_vel[:, :2]


def test_com_reference_keeps_flowing_after_a_late_touchdown():
    """Past the planned duration the CoM position and velocity both follow the LIP flow from the
    pre-impact state (hand formula), and the velocity is the position's time derivative."""
    step = _straight_step()
    pos_t, vel_t = _com(step, T)
    assert float(pos_t[0, 0]) == pytest.approx(0.15, abs=1e-12)  # r* = l / 2
    for tau in (T + 0.05, T + 0.2, 1.5 * T):
        pos, vel = _com(step, tau)
        x, vx = _orbit_x(tau)
        assert float(pos[0, 0]) == pytest.approx(x, abs=1e-12)
        assert float(vel[0, 0]) == pytest.approx(vx, abs=1e-12)
        h = 1e-6
        fd = (_com(step, tau + h)[0] - _com(step, tau - h)[0]) / (2 * h)
        torch.testing.assert_close(fd, vel, atol=1e-7, rtol=0)
    # It moves on: 0.2 s late the CoM is past the pre-impact point, faster than at it.
    pos, vel = _com(step, T + 0.2)
    assert float(pos[0, 0]) > float(pos_t[0, 0]) + 0.1
    assert float(vel[0, 0]) > float(vel_t[0, 0])


def test_first_step_ramps_from_rest():
    """Episode start: the CoM reference begins at the measured CoM with zero velocity, blends
    with a smoothstep into the orbit and is on the orbit's pre-impact state at touchdown."""
    p0 = torch.tensor([[0.02, 0.01]], dtype=F64)
    ramp = _straight_step(ramp_from=p0)
    plain = _straight_step()
    # Without the ramp the step begins on the orbit: about 0.7 m/s from standing.
    _, v_orbit0 = _com(plain, 0.0)
    assert float(v_orbit0[0, 0]) == pytest.approx(_orbit_x(0.0)[1], abs=1e-12)
    assert float(v_orbit0[0, 0]) > 0.5
    pos, vel = _com(ramp, 0.0)
    torch.testing.assert_close(pos, p0, atol=1e-12, rtol=0)
    assert vel.abs().max() < 1e-12
    # Mid-step: s = 1/2, ds/dtau = 6 * 1/4 / T = 3 / s.
    x_orb, vx_orb = _orbit_x(0.5 * T)
    pos, vel = _com(ramp, 0.5 * T)
    assert float(pos[0, 0]) == pytest.approx(0.02 + 0.5 * (x_orb - 0.02), abs=1e-12)
    assert float(vel[0, 0]) == pytest.approx(0.5 * vx_orb + 3.0 * (x_orb - 0.02), abs=1e-12)
    # At the planned touchdown and after it: exactly the orbit reference.
    for tau in (T, T + 0.1):
        torch.testing.assert_close(_com(ramp, tau)[0], _com(plain, tau)[0], atol=1e-12, rtol=0)
        torch.testing.assert_close(_com(ramp, tau)[1], _com(plain, tau)[1], atol=1e-12, rtol=0)
    # v is the time derivative of p throughout the ramp.
    h = 1e-6
    for tau in (0.05, 0.2, 0.37, 0.49):
        fd = (_com(ramp, tau + h)[0] - _com(ramp, tau - h)[0]) / (2 * h)
        torch.testing.assert_close(fd, _com(ramp, tau)[1], atol=1e-7, rtol=0)


def test_ramp_is_per_env():
    """In a batch only the envs flagged ``ramp`` blend; the others keep the orbit reference."""
    step = _straight_step(e=2)
    step.ramp = torch.tensor([True, False])
    step.ramp_from = torch.tensor([[0.0, 0.0], [0.0, 0.0]], dtype=F64)
    pos, vel = _com(step, 0.0)
    assert vel[0].abs().max() < 1e-12
    assert float(vel[1, 0]) == pytest.approx(_orbit_x(0.0)[1], abs=1e-12)


def _random_step_state(e: int, g: torch.Generator, dtype: torch.dtype) -> StepState:
    """Random steps: world positions over a few metres, both stance feet, ramps, yaw rates."""

    def r(*shape):
        return torch.rand(*shape, generator=g, dtype=dtype)

    return StepState(
        stance_pos=4 * r(e, 3) - 2,
        stance_is_left=r(e) > 0.5,
        swing_start=4 * r(e, 3) - 2,
        target=4 * r(e, 3) - 1.7,
        next_target=4 * r(e, 3) - 1.4,
        duration=0.3 + 0.5 * r(e),
        next_duration=0.3 + 0.5 * r(e),
        yaw0=8 * r(e) - 4,
        yaw_rate=r(e) - 0.5,
        axis=torch.nn.functional.normalize(r(e, 2) - 0.5, dim=-1),
        ramp=r(e) > 0.6,
        ramp_from=4 * r(e, 2) - 2,
        com_from_pos=4 * r(e, 3) - 2,
        com_from_vel=2 * r(e, 3) - 1,
        pelvis_from_pos=0.2 * r(e, 2) - 0.1,
        pelvis_from_vel=r(e, 2) - 0.5,
        z0=0.57 + 0.1 * r(e),
        swing_from_pitch=torch.zeros(e, dtype=dtype),  # its carry: tests/test_swing_shape.py
    )


def test_reference_outputs_equal_reference_at():
    """Issue 41: the few-op reference (reference_outputs, every instant of (E, K) times in one
    call) is reference_at flattened: to 1e-9 in float64 over many random steps and times (late
    touchdowns and ramps included), and in float32 as close to the float64 values as
    reference_at's own float32 rounding allows."""
    from march.reference.fused_reference import reference_outputs, reference_tables

    worst_new = worst_old = 0.0
    for seed in range(25):
        g = torch.Generator().manual_seed(seed)
        cfg = ReferenceCfg(
            foot_height_offset=0.01 * (seed % 2),
            pitch_offset=0.03 * (seed % 3),
            com_anchoring=("continuous", "stance")[int(seed % 3 == 2)],
            com_height=("fixed", "step")[seed % 2],
            swing_toe_down=(0.0, 0.35, -0.2)[(seed // 2) % 3],
            swing_xy_shape=(0.0, 0.35, 0.5, 0.12)[seed % 4],
            swing_height=(0.1, 0.065)[(seed // 3) % 2],
            swing_toe_roll=(0.0, 0.15, -0.3, 0.0, 0.2)[seed % 5],
        )
        st = _random_step_state(31, g, F64)
        tau = st.duration[:, None] * 1.6 * torch.rand(31, 3, generator=g, dtype=F64)
        pos, vel = reference_outputs(st, tau, cfg, HlipCfg(), 17)
        one_pos, one_vel = reference_outputs(st, tau[:, 1], cfg, HlipCfg(), 17)
        assert torch.allclose(one_pos, pos[:, 1], atol=1e-12) and torch.allclose(
            one_vel, vel[:, 1], atol=1e-12
        )
        st32 = StepState(
            **{
                f: v.float() if v.is_floating_point() else v
                for f, v in ((f, getattr(st, f)) for f in st.__dataclass_fields__)
            }
        )
        tables = reference_tables(cfg, 17, torch.float32, "cpu")
        pos32, vel32 = reference_outputs(st32, tau.float(), cfg, HlipCfg(), 17, tables)
        for j in range(3):
            want_pos, want_vel = reference_at(st, tau[:, j], cfg, HlipCfg(), 17).flatten()
            assert torch.allclose(pos[:, j], want_pos, atol=1e-9, rtol=0.0), seed
            assert torch.allclose(vel[:, j], want_vel, atol=1e-9, rtol=0.0), seed
            old_pos, old_vel = reference_at(st32, tau[:, j].float(), cfg, HlipCfg(), 17).flatten()
            new_err = max(
                float((pos32[:, j].double() - want_pos).abs().max()),
                float((vel32[:, j].double() - want_vel).abs().max()),
            )
            old_err = max(
                float((old_pos.double() - want_pos).abs().max()),
                float((old_vel.double() - want_vel).abs().max()),
            )
            worst_new, worst_old = max(worst_new, new_err), max(worst_old, old_err)
    assert worst_new < 1e-4 and worst_new <= worst_old, (worst_new, worst_old)


def test_reference_outputs_take_few_ops():
    """Both instants of a step (the command term's refresh) in under 90 ops with the stance
    anchoring, under 130 with the continuous CoM and pelvis (issue 55: the CoM's correction is
    one batched product, ~32 ops; the pelvis roll and pitch carry ~10 more); reference_at on the step state copied twice took ~200 (and the copy ~24
    more)."""
    from march.bench.ops import OpCounter
    from march.reference.fused_reference import reference_outputs, reference_tables

    g = torch.Generator().manual_seed(0)
    st = _random_step_state(16, g, torch.float32)
    tables = reference_tables(ReferenceCfg(), 17, torch.float32, "cpu")
    tau = torch.rand(16, 2, generator=g)
    stance = ReferenceCfg(com_anchoring="stance")
    with torch.inference_mode(), OpCounter() as carry:
        reference_outputs(st, tau, ReferenceCfg(), HlipCfg(), 17, tables)
    assert carry.total < 130, carry.total
    with torch.inference_mode(), OpCounter() as ops:
        reference_outputs(st, tau, stance, HlipCfg(), 17, tables)
    both = StepState(**{f: torch.cat([getattr(st, f)] * 2) for f in st.__dataclass_fields__})
    with torch.inference_mode(), OpCounter() as old:
        reference_at(both, tau.T.flatten()).flatten()
    assert ops.total < 90 < 2 * ops.total < old.total, (ops.total, old.total)
