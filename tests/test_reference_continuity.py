"""The continuous CoM reference (issue 55, march.reference.com_carry): no jump at touchdown over
many generated step sequences, each step ending on its planned HLIP orbit (analytic values),
bounded, the hand-derived correction, and the CoM height that fits the step."""

from __future__ import annotations

import math

import pytest
import torch

from march.reference.com_carry import step_com_height
from march.reference.fused_reference import reference_outputs
from march.reference.hlip import HlipCfg, hlip_com_state
from march.reference.trajectory import (
    ReferenceCfg,
    StepState,
    com_state,
    pelvis_state,
    reference_at,
    step_height,
)

torch.set_num_threads(1)
F64 = torch.float64
HLIP = HlipCfg()
W = HLIP.step_width


def _first_step(e: int, g: torch.Generator) -> StepState:
    """E random straight-ish courses (random heading): the left foot stands at the origin."""
    ang = (torch.rand(e, generator=g, dtype=F64) - 0.5) * 2.0
    axis = torch.stack([torch.cos(ang), torch.sin(ang)], -1)
    zero = torch.zeros(e, dtype=F64)
    stance = torch.zeros(e, 3, dtype=F64)
    return _step(stance, torch.ones(e, dtype=torch.bool), axis, g, zero)


def _planned(stance, left, axis, g):
    """A planned landing from ``stance``: 0.15-0.85 m along, the nominal width across (the
    landing foot's side) with 5 cm noise, +/-10 cm of height."""
    e = stance.shape[0]
    lat = torch.stack([-axis[:, 1], axis[:, 0]], -1)
    along = 0.15 + 0.7 * torch.rand(e, generator=g, dtype=F64)
    side = torch.where(left, -1.0, 1.0).to(F64)  # the left foot stands: the right lands
    across = side * W + 0.05 * (torch.rand(e, generator=g, dtype=F64) - 0.5)
    xy = stance[:, :2] + along[:, None] * axis + across[:, None] * lat
    z = stance[:, 2] + 0.2 * (torch.rand(e, generator=g, dtype=F64) - 0.5)
    return torch.cat([xy, z[:, None]], -1)


def _step(stance, left, axis, g, zero, com_from=None, cfg=None, pelvis_from=None):
    target = _planned(stance, left, axis, g)
    nxt = _planned(target, ~left, axis, g)
    dur = 0.45 + 0.25 * torch.rand(stance.shape[0], generator=g, dtype=F64)
    st = StepState(
        stance_pos=stance,
        stance_is_left=left,
        swing_start=stance + torch.tensor([0.0, 0.0, 0.0], dtype=F64),
        target=target,
        next_target=nxt,
        duration=dur,
        next_duration=0.45 + 0.25 * torch.rand(stance.shape[0], generator=g, dtype=F64),
        yaw0=zero,
        yaw_rate=zero,
        axis=axis,
        com_from_pos=None if com_from is None else com_from[0],
        com_from_vel=None if com_from is None else com_from[1],
        pelvis_from_pos=None if pelvis_from is None else pelvis_from[0],
        pelvis_from_vel=None if pelvis_from is None else pelvis_from[1],
    )
    if cfg is not None and cfg.com_height == "step":
        st.z0 = step_height(stance, target, axis, cfg, HLIP)
    return st


def _walk(cfg: ReferenceCfg, e: int = 32, steps: int = 30, seed: int = 0, restarts: bool = False):
    """Chain ``steps`` steps: touchdown at a random tau in [0.6 T, 1.5 T] (the command's window)
    at the planned foothold plus up to 4 cm of landing offset; yields per touchdown the old
    step, the touchdown time, the new step. ``restarts``: a third of the switches are timeout
    restarts instead (at 1.5 T, the same stance foot, the foot not moved)."""
    g = torch.Generator().manual_seed(seed)
    zero = torch.zeros(e, dtype=F64)
    step = _first_step(e, g)
    for _ in range(steps):
        td = step.duration * (0.6 + 0.9 * torch.rand(e, generator=g, dtype=F64))
        landing = step.target.clone()
        landing[:, :2] += 0.08 * (torch.rand(e, 2, generator=g, dtype=F64) - 0.5)
        left = ~step.stance_is_left
        if restarts:
            again = torch.rand(e, generator=g, dtype=F64) < 1.0 / 3.0
            td = torch.where(again, 1.5 * step.duration, td)
            landing = torch.where(again[:, None], step.stance_pos, landing)
            left = torch.where(again, step.stance_is_left, left)
        carried = com_state(step, td, cfg, HLIP)
        pelvis = pelvis_state(step, td, cfg)
        new = _step(landing, left, step.axis, g, zero, carried, cfg, pelvis)
        yield step, td, new
        step = new


@pytest.mark.parametrize("height", ["fixed", "step"])
def test_no_jump_at_touchdown_and_every_step_ends_on_its_orbit(height):
    """Over 32 x 30 generated touchdowns (random lengths, heights, headings, timings, landing
    offsets): the reference right after a touchdown equals the one right before in position and
    velocity (x, y, z), the fused reference agrees, and at tau = T the position is the planned
    step's orbit pre-impact position (hlip_com_state at T: stance + l/2 along the course) at the
    height z0 above the lower stone; its distance from the orbit at a step's start (late
    touchdowns, up to 1.5 T, start far ahead) does not grow along the chain."""
    cfg = ReferenceCfg(com_height=height)
    orbit_only = ReferenceCfg(com_anchoring="stance", com_height=height)
    worst_p = worst_v = 0.0
    offsets = []
    for old, td, new in _walk(cfg):
        before = com_state(old, td, cfg, HLIP)
        after = com_state(new, torch.zeros_like(td), cfg, HLIP)
        worst_p = max(worst_p, float((after[0] - before[0]).abs().max()))
        worst_v = max(worst_v, float((after[1] - before[1]).abs().max()))
        pos, vel = reference_outputs(new, torch.zeros_like(td), cfg, HLIP, 0)
        assert torch.allclose(pos[:, :3], before[0], atol=1e-9, rtol=0)
        assert torch.allclose(vel[:, :3], before[1], atol=1e-9, rtol=0)
        # ends on the orbit of the planned step
        t_end = new.duration
        end = com_state(new, t_end, cfg, HLIP)
        lam = HLIP.lam if new.z0 is None else torch.sqrt(HLIP.g / new.z0)
        stance_xy = new.stance_pos[:, :2]
        orbit, _ = hlip_com_state(
            stance_xy,
            new.target[:, :2] - stance_xy,
            new.next_target[:, :2] - new.target[:, :2],
            new.duration,
            new.next_duration,
            t_end,
            lam,
            new.axis,
        )
        assert torch.allclose(end[0][:, :2], orbit, atol=1e-9, rtol=0)
        along = ((end[0][:, :2] - stance_xy) * new.axis).sum(-1)
        half = 0.5 * ((new.target[:, :2] - stance_xy) * new.axis).sum(-1)
        assert torch.allclose(along, half, atol=1e-9, rtol=0)  # r- = l/2
        z0 = HLIP.z0 if new.z0 is None else new.z0
        low = torch.minimum(new.stance_pos[:, 2], new.target[:, 2])
        assert torch.allclose(end[0][:, 2], low + z0, atol=1e-9, rtol=0)
        # bounded: the start's distance from the planned step's own orbit does not grow along
        # the chain (each step ends on its orbit; a reference that diverged would grow ~7x a step)
        o, _ = com_state(new, torch.zeros_like(td), orbit_only, HLIP)
        offsets.append(float((after[0] - o).norm(dim=-1).max()))
    assert worst_p < 1e-12 and worst_v < 1e-12, (worst_p, worst_v)
    assert max(offsets[-10:]) < 1.5 * max(offsets[:10]) and max(offsets) < 2.0, offsets


def test_the_stance_anchoring_jumps():
    """The earlier reference (``com_anchoring=stance``), on the same sequences, jumps by
    centimetres and tenths of m/s at touchdown: the measure above can see a jump."""
    cfg = ReferenceCfg(com_anchoring="stance")
    jumps_p, jumps_v = [], []
    for old, td, new in _walk(cfg, steps=10):
        before = com_state(old, td, cfg, HLIP)
        after = com_state(new, torch.zeros_like(td), cfg, HLIP)
        jumps_p.append((after[0] - before[0])[:, :2].norm(dim=-1))
        jumps_v.append((after[1] - before[1])[:, :2].norm(dim=-1))
    assert float(torch.cat(jumps_p).median()) > 0.02
    assert float(torch.cat(jumps_v).median()) > 0.1


def test_carry_correction_hand_values():
    """One straight step (l = 0.4 m along +x, T = 0.5 s, flat) whose start state is off the orbit
    by e0 = (0.1, -0.03, 0.05) m and u0 - v_o(0) = (0.2, 0.1, -0.3) m/s. By hand: in x and y the
    correction is e0 sinh(lam (T - tau)) / sinh(lam T) + (du + e0 lam coth(lam T)) tau
    (1 - tau / T)^2, in z e0 (1 - phi)^2 (1 + 2 phi) + du T phi (1 - phi)^2."""
    T, L = 0.5, 0.4
    lam = HLIP.lam
    st = StepState(
        stance_pos=torch.tensor([[0.0, W / 2, 0.0]], dtype=F64),
        stance_is_left=torch.tensor([True]),
        swing_start=torch.tensor([[0.0, -W / 2, 0.0]], dtype=F64),
        target=torch.tensor([[L, -W / 2, 0.0]], dtype=F64),
        next_target=torch.tensor([[2 * L, W / 2, 0.0]], dtype=F64),
        duration=torch.tensor([T], dtype=F64),
        next_duration=torch.tensor([T], dtype=F64),
        yaw0=torch.zeros(1, dtype=F64),
        yaw_rate=torch.zeros(1, dtype=F64),
        axis=torch.tensor([[1.0, 0.0]], dtype=F64),
    )
    stance = ReferenceCfg(com_anchoring="stance")
    o0 = com_state(st, torch.zeros(1, dtype=F64), stance, HLIP)
    e0 = torch.tensor([0.1, -0.03, 0.05], dtype=F64)
    du = torch.tensor([0.2, 0.1, -0.3], dtype=F64)
    st.com_from_pos, st.com_from_vel = o0[0] + e0, o0[1] + du
    cfg = ReferenceCfg()
    for tau in (0.0, 0.1, T / 3, 0.37, T, 0.6):
        t = torch.tensor([tau], dtype=F64)
        got_p, got_v = com_state(st, t, cfg, HLIP)
        orb_p, orb_v = com_state(st, t, stance, HLIP)
        for i in range(3):
            phi = min(tau / T, 1.0)
            h = T * phi * (1 - phi) ** 2
            hd = (1 - phi) * (1 - 3 * phi)
            if i < 2:
                b = math.sinh(lam * (T - tau)) / math.sinh(lam * T)
                bd = -lam * math.cosh(lam * (T - tau)) / math.sinh(lam * T)
                left = float(du[i]) + float(e0[i]) * lam / math.tanh(lam * T)
            else:
                b = (1 - phi) ** 2 * (1 + 2 * phi)
                bd = -6 * phi * (1 - phi) / T
                left = float(du[i])
            want_p = float(e0[i]) * b + left * h
            want_v = float(e0[i]) * bd + left * hd
            assert float(got_p[0, i] - orb_p[0, i]) == pytest.approx(want_p, abs=1e-12)
            assert float(got_v[0, i] - orb_v[0, i]) == pytest.approx(want_v, abs=1e-12)
        # velocity is the position's time derivative
        hstep = 1e-6
        fd = (com_state(st, t + hstep, cfg, HLIP)[0] - com_state(st, t - hstep, cfg, HLIP)[0]) / (
            2 * hstep
        )
        if tau not in (0.0, T):  # (C^1 but not C^2 at the ends of the Hermite part)
            torch.testing.assert_close(fd, got_v, atol=1e-7, rtol=0)


def test_step_height_and_lambda_follow_the_step():
    """``com_height=step``: z = clamp(0.67 - 0.35 (|l| - 0.5), 0.57, 0.67) by hand, and the
    orbit's pre-impact velocity lam coth(lam T / 2) l / 2 uses lam = sqrt(g / z) of that z."""
    cfg = ReferenceCfg(com_height="step")
    lengths = torch.tensor([0.3, 0.5, 0.7, 0.8, 1.0], dtype=F64)
    z = step_com_height(
        lengths, HLIP.z0, cfg.com_height_free_step, cfg.com_height_slope, cfg.com_height_min
    )
    want = [0.67, 0.67, 0.67 - 0.35 * 0.2, 0.57, 0.57]  # 0.565 at 0.8 m: clamped
    assert z.tolist() == pytest.approx(want, abs=1e-12)
    # Every step of the measured envelope (longest step in tolerance at a CoM height)
    # is walked at or below that height.
    for length, height in ((0.575, 0.67), (0.65, 0.65), (0.775, 0.62), (0.825, 0.60)):
        got = step_com_height(torch.tensor([length]), 0.67, 0.5, 0.35, 0.57)
        assert float(got) <= height + 1e-9
    T = 0.55
    stance = ReferenceCfg(com_anchoring="stance", com_height="step")
    for length in (0.3, 0.7, 0.9):
        st = StepState(
            stance_pos=torch.zeros(1, 3, dtype=F64),
            stance_is_left=torch.tensor([True]),
            swing_start=torch.zeros(1, 3, dtype=F64),
            target=torch.tensor([[length, -W, 0.0]], dtype=F64),
            next_target=torch.tensor([[2 * length, 0.0, 0.0]], dtype=F64),
            duration=torch.tensor([T], dtype=F64),
            next_duration=torch.tensor([T], dtype=F64),
            yaw0=torch.zeros(1, dtype=F64),
            yaw_rate=torch.zeros(1, dtype=F64),
            axis=torch.tensor([[1.0, 0.0]], dtype=F64),
        )
        zs = step_com_height(torch.tensor([length], dtype=F64), 0.67, 0.5, 0.35, 0.57)
        st.z0 = zs
        lam = math.sqrt(HLIP.g / float(zs))
        p, v = com_state(st, torch.tensor([T], dtype=F64), stance, HLIP)
        assert float(v[0, 0]) == pytest.approx(lam / math.tanh(lam * T / 2) * length / 2, 1e-12)
        assert float(p[0, 2]) == pytest.approx(float(zs), abs=1e-12)
        assert float(p[0, 0]) == pytest.approx(length / 2, abs=1e-12)


@pytest.mark.parametrize("pitch_offset", [0.0, 0.05])
def test_pelvis_roll_and_pitch_do_not_jump_at_a_switch(pitch_offset):
    """Over 32 x 30 generated switches (touchdowns early and late, a third of them timeout
    restarts on the same stance side, durations 0.45-0.7 s): the pelvis roll and pitch
    reference and their rates right after a switch equal those right before (the step's own
    lean alone jumps by ~0.1-0.4 rad/s in rate there), the fused reference agrees, and at
    tau = T each step is back on its own lean: roll 0, pitch the offset, the rates the lean's
    (roll -lean pi / T, pitch 2 pi A / T: analytic)."""
    cfg = ReferenceCfg(pitch_offset=pitch_offset)
    worst_p = worst_v = 0.0
    own_jumps = []
    for old, td, new in _walk(cfg, restarts=True):
        before = pelvis_state(old, td, cfg)
        after = pelvis_state(new, torch.zeros_like(td), cfg)
        worst_p = max(worst_p, float((after[0] - before[0]).abs().max()))
        worst_v = max(worst_v, float((after[1] - before[1]).abs().max()))
        pos, vel = reference_outputs(new, torch.zeros_like(td), cfg, HLIP, 0)
        assert torch.allclose(pos[:, 3:5], before[0], atol=1e-9, rtol=0)
        assert torch.allclose(vel[:, 3:5], before[1], atol=1e-9, rtol=0)
        bare = StepState(**{**new.__dict__, "pelvis_from_pos": None, "pelvis_from_vel": None})
        own = pelvis_state(bare, torch.zeros_like(td), cfg)
        own_jumps.append((own[1] - before[1]).abs().amax(-1))
        # back on its own lean just before the planned touchdown
        t_end = new.duration * (1.0 - 1e-9)
        end_p, end_v = pelvis_state(new, t_end, cfg)
        lean = torch.where(new.stance_is_left, -1.0, 1.0).to(F64) * cfg.roll_amplitude
        w = math.pi / new.duration
        assert torch.allclose(end_p[:, 0], torch.zeros_like(td), atol=1e-7)
        assert torch.allclose(end_p[:, 1], torch.full_like(td, pitch_offset), atol=1e-7)
        assert torch.allclose(end_v[:, 0], -lean * w, atol=1e-6)
        assert torch.allclose(end_v[:, 1], cfg.pitch_amplitude * 2.0 * w, atol=1e-6)
    assert worst_p < 1e-12 and worst_v < 1e-12, (worst_p, worst_v)
    assert float(torch.cat(own_jumps).median()) > 0.05  # the measure can see a jump


def test_pelvis_carry_hand_values_and_rates_are_derivatives():
    """One step (T = 0.5 s, left stance) entered with roll 0.02 rad at -0.1 rad/s and pitch
    -0.01 rad at 0.3 rad/s. By hand: roll = -a sin(pi phi) + e0 h00 + v0 T h10 with e0 the
    entry minus the own value at 0 (0, and the pitch offset) and v0 the entry rate minus the
    own rate at 0 (-a pi / T, 2 pi A / T); the rates are the finite differences of the angles."""
    T = 0.5
    cfg = ReferenceCfg()
    st = StepState(
        stance_pos=torch.zeros(1, 3, dtype=F64),
        stance_is_left=torch.tensor([True]),
        swing_start=torch.tensor([[0.0, -W, 0.0]], dtype=F64),
        target=torch.tensor([[0.4, -W, 0.0]], dtype=F64),
        next_target=torch.tensor([[0.8, 0.0, 0.0]], dtype=F64),
        duration=torch.tensor([T], dtype=F64),
        next_duration=torch.tensor([T], dtype=F64),
        yaw0=torch.zeros(1, dtype=F64),
        yaw_rate=torch.zeros(1, dtype=F64),
        axis=torch.tensor([[1.0, 0.0]], dtype=F64),
        pelvis_from_pos=torch.tensor([[0.02, -0.01]], dtype=F64),
        pelvis_from_vel=torch.tensor([[-0.1, 0.3]], dtype=F64),
    )
    a, amp = cfg.roll_amplitude, cfg.pitch_amplitude
    e0 = (0.02, -0.01)
    v0 = (-0.1 - (-a * math.pi / T), 0.3 - 2 * math.pi * amp / T)
    for tau in (0.0, 0.05, 0.17, 0.25, 0.41, T, 0.6):
        phi = min(tau / T, 1.0)
        h00, h10 = (1 - phi) ** 2 * (1 + 2 * phi), phi * (1 - phi) ** 2
        own = (-a * math.sin(math.pi * phi), amp * math.sin(2 * math.pi * phi))
        t = torch.tensor([tau], dtype=F64)
        got, _ = pelvis_state(st, t, cfg)
        for i in range(2):
            want = own[i] + e0[i] * h00 + v0[i] * T * h10
            assert float(got[0, i]) == pytest.approx(want, abs=1e-12), (tau, i)
        if 0.0 < tau < T:
            hs = 1e-6
            fd = (pelvis_state(st, t + hs, cfg)[0] - pelvis_state(st, t - hs, cfg)[0]) / (2 * hs)
            assert torch.allclose(pelvis_state(st, t, cfg)[1], fd, atol=1e-6)
    full = reference_at(st, torch.tensor([0.0], dtype=F64), cfg, HLIP, 0)
    assert torch.allclose(full.pelvis_rate[0, :2], st.pelvis_from_vel[0], atol=1e-12)


def test_the_stance_anchoring_keeps_the_old_pelvis():
    """``com_anchoring=stance`` ignores the carried pelvis state (the earlier reference: its
    roll rate restarts at the new step's own, a jump), so the old figures are reproduced."""
    cfg = ReferenceCfg(com_anchoring="stance")
    jumps = []
    for old, td, new in _walk(cfg, steps=10, restarts=True):
        before = pelvis_state(old, td, cfg)
        after = pelvis_state(new, torch.zeros_like(td), cfg)
        jumps.append((after[1] - before[1]).abs().amax(-1))
    assert float(torch.cat(jumps).median()) > 0.05
