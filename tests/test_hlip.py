"""HLIP closed forms against numerical integration, and the orbits as fixed points."""

import math

import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp

from march.reference.hlip import (
    HlipCfg,
    hlip_com_state,
    hlip_flow,
    hlip_orbit,
    hlip_orbit_alternating,
    hlip_orbit_p2,
    hlip_reset,
    hlip_step_to_step,
    lateral_step_lengths,
)

torch.set_num_threads(1)
LAM = HlipCfg().lam
F64 = torch.float64


def test_lam_from_cfg():
    assert HlipCfg().lam == pytest.approx(math.sqrt(9.81 / 0.67))


@pytest.mark.parametrize(
    ("r0", "v0", "tau"), [(0.1, 0.3, 0.4), (-0.12, 0.5, 0.7), (0.0, -0.2, 0.05)]
)
def test_flow_matches_ode(r0, v0, tau):
    sol = solve_ivp(
        lambda t, x: [x[1], LAM**2 * x[0]], (0.0, tau), [r0, v0], rtol=1e-12, atol=1e-14
    )
    r, v = hlip_flow(torch.tensor(r0, dtype=F64), torch.tensor(v0, dtype=F64), tau, LAM)
    assert abs(float(r) - sol.y[0, -1]) < 1e-6
    assert abs(float(v) - sol.y[1, -1]) < 1e-6


def test_flow_batched_matches_ode_over_envs_and_planes():
    gen = torch.Generator().manual_seed(0)
    r0 = torch.rand(5, 2, generator=gen, dtype=F64) - 0.5
    v0 = torch.rand(5, 2, generator=gen, dtype=F64) - 0.5
    tau = torch.rand(5, 1, generator=gen, dtype=F64) * 0.7
    r, v = hlip_flow(r0, v0, tau, LAM)
    for e in range(5):
        for p in range(2):
            sol = solve_ivp(
                lambda t, x: [x[1], LAM**2 * x[0]],
                (0.0, float(tau[e, 0])),
                [float(r0[e, p]), float(v0[e, p])],
                rtol=1e-12,
                atol=1e-14,
            )
            np.testing.assert_allclose([r[e, p], v[e, p]], sol.y[:, -1], atol=1e-6)


def test_reset_moves_position_not_velocity():
    r, v = hlip_reset(torch.tensor(0.2), torch.tensor(0.5), torch.tensor(0.3))
    assert float(r) == pytest.approx(-0.1) and float(v) == pytest.approx(0.5)


def test_period1_orbit_is_fixed_point_and_matches_matrix_form():
    step = torch.tensor([0.0, 0.2, 0.35, -0.1], dtype=F64)
    T = torch.tensor([0.45, 0.5, 0.6, 0.7], dtype=F64)
    r, v = hlip_orbit(step, T, LAM)
    r1, v1 = hlip_step_to_step(r, v, step, T, LAM)
    torch.testing.assert_close(r1, r, atol=1e-9, rtol=0)
    torch.testing.assert_close(v1, v, atol=1e-9, rtol=0)
    # X* = (I - A_d)^{-1} B_d l with A_d = e^{AT} (scipy expm), B_d = A_d [-1, 0]^T.
    from scipy.linalg import expm

    for i in range(4):
        a_d = expm(np.array([[0.0, 1.0], [LAM**2, 0.0]]) * float(T[i]))
        x = np.linalg.solve(np.eye(2) - a_d, a_d @ np.array([-1.0, 0.0]) * float(step[i]))
        np.testing.assert_allclose([r[i], v[i]], x, atol=1e-9)
    # The symmetric orbit: CoM halfway between the feet at impact, v = lam coth(lam T/2) l/2.
    torch.testing.assert_close(r, step / 2)


def test_period2_orbit_is_fixed_point_of_two_steps():
    l0 = torch.tensor([-0.25, 0.3, 0.05], dtype=F64)
    l1 = torch.tensor([0.25, -0.1, 0.4], dtype=F64)
    T0 = torch.tensor([0.5, 0.45, 0.7], dtype=F64)
    T1 = torch.tensor([0.5, 0.6, 0.55], dtype=F64)
    r, v = hlip_orbit_p2(l0, l1, T0, T1, LAM)
    ra, va = hlip_step_to_step(r, v, l0, T1, LAM)
    rb, vb = hlip_step_to_step(ra, va, l1, T0, LAM)
    torch.testing.assert_close(rb, r, atol=1e-9, rtol=0)
    torch.testing.assert_close(vb, v, atol=1e-9, rtol=0)
    # Not a period-1 orbit: the intermediate state differs.
    assert (ra - r).abs().max() > 1e-3


def test_lateral_orbit_closed_form_superposition():
    vy = torch.tensor([0.0, 0.1, -0.1], dtype=F64)
    T, w = 0.55, 0.25
    left_first = torch.tensor([True, False, True])
    l0, l1 = lateral_step_lengths(vy, T, w, left_first)
    torch.testing.assert_close(l0 - l1, torch.tensor([2 * w, -2 * w, 2 * w], dtype=F64))
    r, v = hlip_orbit_p2(l0, l1, T, T, LAM)
    rm, vm = hlip_orbit(0.5 * (l0 + l1), T, LAM)
    ra, va = hlip_orbit_alternating(0.5 * (l0 - l1), T, LAM)
    torch.testing.assert_close(r, rm + ra)
    torch.testing.assert_close(v, vm + va)
    torch.testing.assert_close(r, l0 / 2)
    # Equal steps reduce to the period-1 orbit.
    r2, v2 = hlip_orbit_p2(l0, l0, T, T, LAM)
    r1, v1 = hlip_orbit(l0, T, LAM)
    torch.testing.assert_close(r2, r1)
    torch.testing.assert_close(v2, v1)


def test_com_state_is_continuous_across_steady_steps():
    """A steady walk (constant forward step, alternating width) has a continuous CoM reference
    in the world frame across touchdowns: this fixes B = [-1, 0]^T."""
    T, lx, w = 0.55, 0.3, 0.25
    stance = torch.tensor([[0.0, 0.125]], dtype=F64)
    steps = [torch.tensor([[lx, -w if k % 2 == 0 else w]], dtype=F64) for k in range(5)]
    dur = torch.tensor([T], dtype=F64)
    for k in range(3):
        end_pos, end_vel = hlip_com_state(stance, steps[k], steps[k + 1], dur, dur, dur, LAM)
        stance = stance + steps[k]
        beg_pos, beg_vel = hlip_com_state(
            stance, steps[k + 1], steps[k + 2], dur, dur, torch.zeros(1, dtype=F64), LAM
        )
        torch.testing.assert_close(beg_pos, end_pos, atol=1e-9, rtol=0)
        torch.testing.assert_close(beg_vel, end_vel, atol=1e-9, rtol=0)
    # Mean forward velocity over a step equals l / T (the orbit walks at v_d).
    end, _ = hlip_com_state(stance, steps[0], steps[1], dur, dur, dur, LAM)
    start, _ = hlip_com_state(stance, steps[0], steps[1], dur, dur, torch.zeros(1, dtype=F64), LAM)
    assert float(end[0, 0] - start[0, 0]) == pytest.approx(lx)


def test_com_state_follows_the_lip_ode_within_a_step():
    stance = torch.tensor([[0.3, -0.1]], dtype=F64)
    s0, s1 = torch.tensor([[0.4, 0.2]], dtype=F64), torch.tensor([[0.3, -0.3]], dtype=F64)
    T0, T1 = torch.tensor([0.5], dtype=F64), torch.tensor([0.6], dtype=F64)
    p0, v0 = hlip_com_state(stance, s0, s1, T0, T1, torch.zeros(1, dtype=F64), LAM)
    p1, v1 = hlip_com_state(stance, s0, s1, T0, T1, torch.tensor([0.3], dtype=F64), LAM)
    for ax in range(2):
        x0 = [float(p0[0, ax] - stance[0, ax]), float(v0[0, ax])]
        sol = solve_ivp(lambda t, x: [x[1], LAM**2 * x[0]], (0, 0.3), x0, rtol=1e-12, atol=1e-14)
        assert abs(sol.y[0, -1] + float(stance[0, ax]) - float(p1[0, ax])) < 1e-6
        assert abs(sol.y[1, -1] - float(v1[0, ax])) < 1e-6


def test_com_state_keeps_following_the_lip_past_the_planned_duration():
    """A late touchdown: from tau = T0 on, the reference integrates the LIP ODE onward (both
    planes), so position and velocity stay one trajectory (issue 10: no frozen position)."""
    stance = torch.tensor([[0.3, -0.1]], dtype=F64)
    s0, s1 = torch.tensor([[0.4, 0.2]], dtype=F64), torch.tensor([[0.3, -0.3]], dtype=F64)
    T0, T1 = torch.tensor([0.5], dtype=F64), torch.tensor([0.6], dtype=F64)
    pt, vt = hlip_com_state(stance, s0, s1, T0, T1, T0, LAM)
    late = 0.25
    p1, v1 = hlip_com_state(stance, s0, s1, T0, T1, T0 + late, LAM)
    for ax in range(2):
        x0 = [float(pt[0, ax] - stance[0, ax]), float(vt[0, ax])]
        sol = solve_ivp(lambda t, x: [x[1], LAM**2 * x[0]], (0, late), x0, rtol=1e-12, atol=1e-14)
        assert abs(sol.y[0, -1] + float(stance[0, ax]) - float(p1[0, ax])) < 1e-6
        assert abs(sol.y[1, -1] - float(v1[0, ax])) < 1e-6
    assert float(p1[0, 0] - pt[0, 0]) > 0.1  # the position moves on, it does not freeze
