"""The heel strike (``reference.swing_heel_strike``, issue 55) and the audit's ``heel_toe``
stance model: the reference's toe-up pitch against hand-derived values, its rates the time
derivatives of its pitch and offset over generated cases, the heel landing where a flat foot's
lands (by the G1's own sole), the fused reference equal to the readable one, the default
unchanged bit for bit, the option on the command line; and in the kinematic walk, a foot that
landed toe up held on its heel edge, the toe coming down within its bound, flat from the
``heel_flat_by`` tick on."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from generated_steps import (
    assert_fused_is_readable,
    assert_only_these_change,
    assert_reference_option_is_read,
    random_steps,
    shaped_and_plain,
)

from march.audit.ik_walk import heel_landing, ik_walks, toe_up_bound
from march.audit.kinematic_g1 import IkCfg, KinematicG1, foot_sole, rotation_zyx
from march.env.g1 import g1_mjcf_spec
from march.reference.trajectory import ReferenceCfg, heel_strike, output_names

F64 = torch.float64
NAMES = output_names(17)
SWING_POS = [NAMES.index(n) for n in ("swing_x", "swing_y", "swing_z")]
SWING_PITCH = NAMES.index("swing_pitch")


def test_hand_derived_pitch_offset_and_rates():
    """H = 0.2, d = 0.1, T = 0.5 s, heading +x: nothing in the first half of the swing; at
    s = 3/4 (u = 1/2) q = 1/2, the pitch -H/2 and its rate -H 30 (1/16) 2 / T = -3.75 H / T;
    at and after touchdown the pitch -H with zero rate and the site offset d (cos H - 1, 0,
    sin H) (raised by d sin H, drawn back by d (1 - cos H))."""
    dur, yaw, still = (torch.full((1,), v, dtype=F64) for v in (0.5, 0.0, 0.0))
    for s in (0.0, 0.3, 0.5):
        p, r, off, off_rate = heel_strike(torch.full((1,), s, dtype=F64), dur, yaw, still, 0.2, 0.1)
        assert float(p) == 0.0 and float(r) == 0.0
        assert torch.equal(off, torch.zeros(1, 3, dtype=F64))
        assert torch.equal(off_rate, torch.zeros(1, 3, dtype=F64))
    p, r, off, _ = heel_strike(torch.full((1,), 0.75, dtype=F64), dur, yaw, still, 0.2, 0.1)
    assert float(p) == pytest.approx(-0.1, abs=1e-15)
    assert float(r) == pytest.approx(-3.75 * 0.2 / 0.5, abs=1e-12)
    assert off[0].tolist() == pytest.approx([0.1 * (math.cos(0.1) - 1), 0.0, 0.1 * math.sin(0.1)])
    for s in (1.0, 1.4):
        p, r, off, off_rate = heel_strike(torch.full((1,), s, dtype=F64), dur, yaw, still, 0.2, 0.1)
        assert float(p) == pytest.approx(-0.2, abs=1e-15) and float(r) == 0.0
        assert off[0].tolist() == pytest.approx(
            [0.1 * (math.cos(0.2) - 1), 0.0, 0.1 * math.sin(0.2)], abs=1e-15
        )
        assert torch.equal(off_rate, torch.zeros(1, 3, dtype=F64))


def test_the_rates_are_the_time_derivatives_of_pitch_and_offset():
    """Over 2,000 random instants inside the swing, durations, headings, yaw rates and
    amplitudes: the pitch rate and the offset's rate equal the central differences of the
    pitch and the offset along time (the heading turning at the yaw rate; h = 1e-6 s)."""
    g = torch.Generator().manual_seed(11)
    n, h = 2000, 1e-6
    dur = 0.3 + 0.5 * torch.rand(n, generator=g, dtype=F64)
    tau = dur * (0.001 + 0.998 * torch.rand(n, generator=g, dtype=F64))
    yaw = (torch.rand(n, generator=g, dtype=F64) - 0.5) * 6.0
    yaw_rate = (torch.rand(n, generator=g, dtype=F64) - 0.5) * 2.0
    amp = 0.5 * torch.rand(1, generator=g, dtype=F64).item()

    def at(dt: float) -> tuple[torch.Tensor, ...]:
        return heel_strike((tau + dt) / dur, dur, yaw + yaw_rate * dt, yaw_rate, amp, 0.094)

    up, down, now = at(h), at(-h), at(0.0)
    assert torch.allclose(now[1], (up[0] - down[0]) / (2 * h), atol=1e-6)
    assert torch.allclose(now[3], (up[2] - down[2]) / (2 * h), atol=1e-6)
    assert bool((now[0][tau > 0.6 * dur].abs() > 0).all())


def test_the_heel_lands_where_a_flat_foots_heel_would():
    """At touchdown, over 500 generated headings and amplitudes: the site offset by the heel
    strike, turned toe up by its pitch (ZYX, the outputs' convention), puts the point d behind
    it exactly where a flat foot at the planned site has it; the G1's own heel edge (0.094 m
    behind the site and 2 mm above it, ``foot_sole``) misses by the 2 mm's turn, 2 z sin(H / 2)
    (under 1 mm). The default pivot distance is the G1's."""
    sole = foot_sole(g1_mjcf_spec().compile(), "left_foot")
    assert ReferenceCfg().swing_heel_back == pytest.approx(-sole.heel_x, abs=1e-6)
    rng = np.random.default_rng(4)
    one = torch.ones(1, dtype=F64)
    for _ in range(500):
        yaw, amp = rng.uniform(-math.pi, math.pi), rng.uniform(0.0, 0.5)
        pitch, _, off, _ = heel_strike(
            one, one, torch.tensor([yaw], dtype=F64), 0 * one, amp, 0.094
        )
        landed = rotation_zyx(0.0, float(pitch), yaw)
        flat = rotation_zyx(0.0, 0.0, yaw)
        back = np.array([-0.094, 0.0, 0.0])
        np.testing.assert_allclose(off[0].numpy() + landed @ back, flat @ back, atol=1e-12)
        # the sole's 2 mm above the site turns with the foot: |R(p) z - z| = 2 z sin(p / 2)
        heel = sole.heel_offset()
        miss = np.linalg.norm(off[0].numpy() + landed @ heel - flat @ heel)
        assert miss == pytest.approx(2 * sole.sole_z * math.sin(amp / 2), abs=1e-12)


def test_reference_at_and_the_fused_reference_carry_it_and_the_default_is_unchanged():
    """reference_at with swing_heel_strike = 0.3 against 0 over 48 random steps at 4
    instants: only the swing foot's position, pitch and their rates change, by heel_strike(...)
    of the step; the fused reference (the env's) equals reference_at to 1e-9 in float64 with
    the option and other shapings on; 0 (the default) gives the reference of before bit for
    bit."""
    g = torch.Generator().manual_seed(5)
    st = random_steps(48, g)
    changed = [*SWING_POS, SWING_PITCH]
    for frac in (0.3, 0.7, 0.95, 1.2):
        tau = st.duration * frac
        hs, plain = shaped_and_plain(st, tau, "swing_heel_strike", 0.3)
        yaw = plain[0][:, NAMES.index("pelvis_yaw")]
        yaw_rate = plain[1][:, NAMES.index("pelvis_yaw")]
        pitch, rate, shift, shift_rate = heel_strike(
            tau / st.duration, st.duration, yaw, yaw_rate, 0.3, 0.094
        )
        assert torch.allclose(hs[0][:, SWING_PITCH] - plain[0][:, SWING_PITCH], pitch, atol=1e-6)
        assert torch.allclose(hs[1][:, SWING_PITCH] - plain[1][:, SWING_PITCH], rate, atol=1e-5)
        assert torch.allclose(hs[0][:, SWING_POS] - plain[0][:, SWING_POS], shift, atol=1e-6)
        assert torch.allclose(hs[1][:, SWING_POS] - plain[1][:, SWING_POS], shift_rate, atol=1e-5)
        assert_only_these_change(hs, plain, changed)
        if frac > 0.6:
            assert bool((pitch < -1e-3).all())
    for seed in range(4):
        cfg = ReferenceCfg(
            com_height=("fixed", "step")[seed % 2],
            swing_toe_down=(0.0, 0.7)[seed % 2],
            swing_roll_out=(0.0, 0.15)[seed % 2],
            swing_heel_strike=(0.2, 0.45)[seed % 2],
        )
        gs = torch.Generator().manual_seed(80 + seed)
        assert_fused_is_readable(random_steps(31, gs), cfg, gs, seed)


def test_the_option_reaches_the_reference_term_and_bad_values_are_one_line():
    assert_reference_option_is_read("swing_heel_strike", 0.2, -0.1, "[0.0, 0.5]")


def test_toe_up_bound_by_hand():
    """0.2 rad landed, a 35-tick step, flat by 0.3: m = ceil(10.5) = 11; the bound 0.2 (1 -
    j / 11) at ticks 1..10, None (the heel phase over) from tick 11; no bound at all for a
    foot that landed flat or toe down."""
    assert toe_up_bound(0.2, 1, 35, 0.3) == pytest.approx(0.2 * 10 / 11)
    assert toe_up_bound(0.2, 10, 35, 0.3) == pytest.approx(0.2 / 11)
    assert toe_up_bound(0.2, 11, 35, 0.3) is None
    assert toe_up_bound(0.0, 1, 35, 0.3) is None
    assert toe_up_bound(-0.1, 1, 35, 0.3) is None


@pytest.fixture(scope="module")
def heel_toe() -> KinematicG1:
    return KinematicG1(IkCfg(stance="heel_toe"))


def test_a_foot_landed_toe_up_comes_down_about_its_heel_edge(heel_toe):
    """``heel_landing`` over 300 generated landings (heading, toe-up 0.02-0.5 rad, roll up to
    0.05 rad, position): the flat pose keeps the heel edge's midpoint where it landed, its x
    axis is horizontal, it differs from the landed pose by a turn about the foot's own y axis
    only, by the returned pitch; a foot landed toe down is held as it landed."""
    rng = np.random.default_rng(9)
    sole = heel_toe.soles[0]
    heel = sole.heel_offset()
    for _ in range(300):
        rot = rotation_zyx(rng.uniform(-0.05, 0.05), -rng.uniform(0.02, 0.5), rng.uniform(-3, 3))
        pos = rng.uniform(-2, 2, 3)
        (flat_pos, flat), up = heel_landing(heel_toe, True, (pos, rot))
        np.testing.assert_allclose(flat_pos + flat @ heel, pos + rot @ heel, atol=1e-12)
        assert abs(flat[2, 0]) < 1e-12
        turn = flat.T @ rot
        c, s = math.cos(up), math.sin(up)
        np.testing.assert_allclose(turn, [[c, 0, -s], [0, 1, 0], [s, 0, c]], atol=1e-12)
        assert up > 0
    down = rotation_zyx(0.0, 0.2, 0.4)
    (same_pos, same), up = heel_landing(heel_toe, False, (np.ones(3), down))
    assert up == 0.0 and np.array_equal(same, down) and np.array_equal(same_pos, np.ones(3))


def test_the_walk_holds_the_landed_heel_until_the_foot_is_flat(heel_toe):
    """A 4-step walk over a generated stepping-stone course with the heel strike (0.25 rad)
    and ``heel_toe``: every step after the first starts on a foot landed toe up by 0.2-0.3 rad;
    in the heel phase the heel edge's corners stay within 1 mm of where it landed and the
    pitch within [-bound, 0] (never the toe into the stone) tick by tick; from the
    ``heel_flat_by`` tick on the foot is flat or heel up (pitch >= 0, the toe edge held)."""
    from march.world.courses import CourseCfg, generate_course
    from march.world.footholds import footholds_from_layouts

    layouts = [generate_course(0.5, CourseCfg(size=(6.0, 4.0)), np.random.default_rng(3))]
    footholds = footholds_from_layouts(layouts, np.stack([lay.origin for lay in layouts]))
    reference = ReferenceCfg(swing_heel_strike=0.25, swing_toe_down=0.5)
    trace = ik_walks(heel_toe, footholds, torch.tensor([[0.5, 0.0]]), 4, reference=reference)[0]
    steps = np.asarray(trace.tick_step)
    assert len(trace.landed_toe_up) == 4 and trace.landed_toe_up[0] == 0.0
    checked = 0
    for k in range(1, 4):
        up = trace.landed_toe_up[k]
        assert 0.2 < up < 0.3, up
        ticks = np.flatnonzero(steps == k)
        n = len(ticks)
        for j, i in enumerate(ticks, start=1):
            bound = toe_up_bound(up, j, n, heel_toe.cfg.heel_flat_by)
            pitch, slide = trace.tick_stance_pitch[i], trace.tick_slide[i]
            assert slide < 1e-3, (k, j, slide)
            if bound is None:
                assert pitch > -1e-4, (k, j, pitch)
            else:
                assert -bound - 1e-4 < pitch < 1e-4, (k, j, pitch, bound)
                checked += 1
    assert checked >= 12
