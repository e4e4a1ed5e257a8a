"""The swing foot's shaping options of issue 55 item 5: the horizontal Bezier's inner control
points (``reference.swing_xy_shape``) and the toe roll added to the toe-down
(``reference.swing_toe_roll``): hand-derived values, rates that are the time derivatives of the
positions over generated cases, the defaults unchanged, the options on the command line.
(fused == readable for both: tests/test_reference.py.)
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from generated_steps import (
    assert_fused_is_readable,
    assert_reference_option_is_read,
    random_steps,
)

from march.reference.hlip import HlipCfg
from march.reference.trajectory import (
    TOE_ROLL_SCALE,
    ReferenceCfg,
    output_names,
    reference_at,
    swing_trajectory,
    toe_down,
)

F64 = torch.float64
NAMES = output_names(17)
SWING_X, SWING_PITCH = NAMES.index("swing_x"), NAMES.index("swing_pitch")


def _ends(n: int, g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    start = torch.rand(n, 3, generator=g, dtype=F64) - 0.5
    end = start + torch.rand(n, 3, generator=g, dtype=F64) * torch.tensor([1.2, 0.4, 0.2])
    duration = 0.3 + 0.5 * torch.rand(n, generator=g, dtype=F64)
    return start, end, duration


@pytest.mark.parametrize("a", [0.0, 0.2, 0.35, 0.5])
def test_the_xy_shape_takes_its_hand_values(a):
    """Control points (p0, p0, p0 + a D, p1 - a D, p1, p1): by hand, the share of D covered
    at s = 1/4 is (106 + 180 a) / 1024 (a = 0: 10 s^3 - 15 s^4 + 6 s^5, minimum jerk), at
    s = 1/2 exactly 1/2, at 3/4 (918 - 180 a) / 1024; the speed at s = 1/2 is (30 - 20 a) / 16
    |D| / T (1.875 |D| / T for minimum jerk); at lift-off and touchdown the foot is at p0 and
    p1 with zero velocity; the height is the shape's own (unchanged by a)."""
    g = torch.Generator().manual_seed(int(100 * a))
    start, end, duration = _ends(40, g)
    d = end[:, :2] - start[:, :2]
    share = {0.25: (106 + 180 * a) / 1024, 0.5: 0.5, 0.75: (918 - 180 * a) / 1024}
    for s, w in share.items():
        pos, vel = swing_trajectory(
            start, end, torch.full((40,), s, dtype=F64), duration, 0.1, xy_shape=a
        )
        assert torch.allclose(pos[:, :2], start[:, :2] + w * d, atol=1e-12), s
        flat, _ = swing_trajectory(start, end, torch.full((40,), s, dtype=F64), duration, 0.1)
        assert torch.equal(pos[:, 2], flat[:, 2])
        if s == 0.5:
            want = (30 - 20 * a) / 16 * d / duration[:, None]
            assert torch.allclose(vel[:, :2], want, atol=1e-12)
    for s, p in ((0.0, start), (1.0, end)):
        pos, vel = swing_trajectory(
            start, end, torch.full((40,), s, dtype=F64), duration, 0.1, xy_shape=a
        )
        assert torch.allclose(pos[:, :2], p[:, :2], atol=1e-12)
        assert torch.allclose(vel[:, :2], torch.zeros_like(vel[:, :2]), atol=1e-12)


def test_the_xy_shape_rates_are_derivatives_and_it_starts_with_its_acceleration():
    """Over 1,000 generated swings at random instants and shapes: the velocity is the central
    difference of the position in time (1e-6), and the acceleration at lift-off (the velocity's
    difference over the first 1e-6 s) is 20 a D / T^2; the peak speed over the swing is
    (30 - 20 a) / 16 |D| / T, reached at mid-swing, for every a in [0, 0.5]."""
    g = torch.Generator().manual_seed(5)
    n, h = 1000, 1e-6
    start, end, duration = _ends(n, g)
    for a in (0.1, 0.35, 0.5):
        tau = duration * (0.01 + 0.98 * torch.rand(n, generator=g, dtype=F64))
        up, _ = swing_trajectory(start, end, (tau + h) / duration, duration, 0.1, a)
        down, _ = swing_trajectory(start, end, (tau - h) / duration, duration, 0.1, a)
        _, vel = swing_trajectory(start, end, tau / duration, duration, 0.1, a)
        assert torch.allclose(vel, (up - down) / (2 * h), atol=1e-6)
        _, v_first = swing_trajectory(start, end, h / duration, duration, 0.1, a)
        d = end[:, :2] - start[:, :2]
        accel = v_first[:, :2] / h
        assert torch.allclose(accel, 20 * a * d / duration[:, None] ** 2, rtol=1e-4, atol=1e-6)
        s = torch.linspace(0, 1, 201, dtype=F64)
        speeds = torch.stack(
            [
                swing_trajectory(start, end, si.expand(n), duration, 0.1, a)[1][:, :2].norm(dim=-1)
                for si in s
            ]
        )
        peak = (30 - 20 * a) / 16 * d.norm(dim=-1) / duration
        assert torch.allclose(speeds.max(0).values, peak, rtol=1e-9)
        assert torch.equal(speeds.argmax(0), torch.full((n,), 100))


@pytest.mark.parametrize("seed", range(6))
def test_the_toe_roll_takes_its_hand_values(seed):
    """pitch = A 64 s^3 (1 - s)^3 + R K s^3 (1 - s)^3 (1 - 2 s), K = 19208 / (27 sqrt 7):
    by hand, the roll alone is 27 R K / 8192 at s = 1/4, 0 at 1/2, -27 R K / 8192 at 3/4, R at
    s = 1/2 - sqrt(7) / 14 (its maximum) and -R at 1/2 + sqrt(7) / 14; its rate
    R K s^2 (1 - s)^2 (3 (1 - 2 s)^2 - 2 s (1 - s)) / T is 27 R K / 2048 / T at 1/4 and 3/4 and
    -R K / 32 / T at 1/2; zero pitch and rate at lift-off and touchdown and past the swing; the
    toe-down adds its own values unchanged."""
    g = torch.Generator().manual_seed(seed)
    n = 30
    amp, roll = (float(2.0 * torch.rand(1, generator=g, dtype=F64) - 1.0) for _ in range(2))
    duration = 0.3 + 0.5 * torch.rand(n, generator=g, dtype=F64)
    k = TOE_ROLL_SCALE
    assert k == pytest.approx(268.886725835601, rel=1e-12)
    peak = 0.5 - math.sqrt(7) / 14
    want = {
        0.0: (0.0, 0.0, 0.0, 0.0),
        0.25: (27 / 64, 27 / 8, 27 * k / 8192, 27 * k / 2048),
        0.5: (1.0, 0.0, 0.0, -k / 32),
        0.75: (27 / 64, -27 / 8, -27 * k / 8192, 27 * k / 2048),
        1.0: (0.0, 0.0, 0.0, 0.0),
        1.3: (0.0, 0.0, 0.0, 0.0),
    }
    for s, (p, r, pr, rr) in want.items():
        pitch, rate = toe_down(torch.full((n,), s, dtype=F64), duration, amp, roll)
        assert torch.allclose(pitch, torch.full_like(pitch, p * amp + pr * roll), atol=1e-12), s
        assert torch.allclose(rate, (r * amp + rr * roll) / duration, atol=1e-12), s
    for s, sign in ((peak, 1.0), (1.0 - peak, -1.0)):
        pitch, rate = toe_down(torch.full((n,), s, dtype=F64), duration, 0.0, roll)
        assert torch.allclose(pitch, torch.full_like(pitch, sign * roll), atol=1e-12)
        assert torch.allclose(rate, torch.zeros_like(rate), atol=1e-9)


def test_the_toe_roll_rate_is_the_derivative_and_stays_within_its_amplitude():
    """Over 2,000 random instants, amplitudes and rolls: the rate is the central difference of
    the pitch in time (1e-6); the roll alone never exceeds |R|."""
    g = torch.Generator().manual_seed(9)
    n, h = 2000, 1e-6
    duration = 0.3 + 0.5 * torch.rand(n, generator=g, dtype=F64)
    tau = duration * (0.01 + 0.98 * torch.rand(n, generator=g, dtype=F64))
    for amp, roll in ((0.5, 0.15), (-0.2, 0.4), (0.0, -0.3)):
        up, _ = toe_down((tau + h) / duration, duration, amp, roll)
        down, _ = toe_down((tau - h) / duration, duration, amp, roll)
        _, rate = toe_down(tau / duration, duration, amp, roll)
        assert torch.allclose(rate, (up - down) / (2 * h), atol=1e-6)
        alone, _ = toe_down(tau / duration, duration, 0.0, roll)
        assert float(alone.abs().max()) <= abs(roll) + 1e-12


def test_only_the_shaped_outputs_change():
    """reference_at with the shaping options against without: over 64 random steps at 5
    instants (late touchdowns included) ``swing_xy_shape`` changes only swing_x / swing_y
    (positions and rates), ``swing_toe_roll`` only the swing pitch; both 0 (the defaults) give
    the reference bit for bit."""
    g = torch.Generator().manual_seed(2)
    st = random_steps(64, g)
    base = ReferenceCfg(com_height="step", swing_toe_down=0.35)
    shaped = ReferenceCfg(com_height="step", swing_toe_down=0.35, swing_xy_shape=0.35)
    rolled = ReferenceCfg(com_height="step", swing_toe_down=0.35, swing_toe_roll=0.15)
    explicit = ReferenceCfg(swing_xy_shape=0.0, swing_toe_roll=0.0)
    for _ in range(5):
        tau = st.duration * 1.3 * torch.rand(64, generator=g, dtype=F64)
        p0, v0 = reference_at(st, tau, base, HlipCfg(), 17).flatten()
        for cfg, changed in ((shaped, [SWING_X, SWING_X + 1]), (rolled, [SWING_PITCH])):
            p1, v1 = reference_at(st, tau, cfg, HlipCfg(), 17).flatten()
            other = torch.ones(p0.shape[1], dtype=torch.bool)
            other[changed] = False
            assert torch.equal(p0[:, other], p1[:, other]) and torch.equal(
                v0[:, other], v1[:, other]
            )
            inside = (tau > 0) & (tau < st.duration)
            assert bool((p0[inside][:, changed] != p1[inside][:, changed]).any())
        d0 = reference_at(st, tau, ReferenceCfg(), HlipCfg(), 17).flatten()
        d1 = reference_at(st, tau, explicit, HlipCfg(), 17).flatten()
        assert torch.equal(d0[0], d1[0]) and torch.equal(d0[1], d1[1])


def test_the_options_reach_the_reference_term_and_bad_values_are_one_line():
    """``reference.swing_xy_shape``, ``swing_toe_roll`` and ``swing_height`` on the command line
    are the env's reference term's (and so the audit's); the defaults are 0, 0 and 0.10 m (the
    reference as before); outside their intervals they are refused naming the interval."""
    from march.audit.feasibility import reference_command_cfg
    from march.config.cli import load
    from march.config.schema import ConfigError

    cfg = load(
        [
            "compute=smoke",
            "reference.swing_xy_shape=0.35",
            "reference.swing_toe_roll=0.15",
            "reference.swing_height=0.08",
        ]
    )
    ref = reference_command_cfg(cfg).reference
    assert (ref.swing_xy_shape, ref.swing_toe_roll, ref.swing_height) == (0.35, 0.15, 0.08)
    ref = reference_command_cfg(load(["compute=smoke"])).reference
    assert (ref.swing_xy_shape, ref.swing_toe_roll, ref.swing_height) == (0.0, 0.0, 0.10)
    for key, bad, interval in (
        ("swing_xy_shape", 0.6, r"\[0.0, 0.5\]"),
        ("swing_toe_roll", -1.5, r"\[-1.0, 1.0\]"),
        ("swing_height", 0.5, r"\[0.02, 0.3\]"),
    ):
        with pytest.raises(ConfigError, match=interval):
            load(["compute=smoke", f"reference.{key}={bad}"])


def test_the_xy_shape_lets_the_dragged_trailing_foot_follow_on_the_kinematic_g1(monkeypatch):
    """On the kinematic G1 (stance foot held, the audit's walk), hand-planned steps (0.4 s each,
    flat ground). 0.5, 0.5, 0.3 m: after a 0.5 m step the trailing leg is nearly straight and
    drags its foot ahead of a minimum-jerk reference that has not started; with
    swing_xy_shape = 0.35 the swing foot's worst error over steps 1-2 falls from 12.2 to 7.6 mm
    in x and 19.1 to 14.1 mm in z, and its worst x rate error (the error's own rate over the
    tick, as the audit judges it) from 0.46 to 0.38 m/s (measured). 0.35 m steps: with the foot
    on its reference to 0.4 mm, its swing z rate error is 0.02 m/s with either shape, a tenth
    of the 0.2 m/s tolerance (the end-of-tick tangent the audit judged until 2026-12-07 read
    0.236 and 0.190 m/s there: dt/2 times the foot's acceleration, tests/test_feasibility.py)."""
    from march.audit.feasibility import FeasibilityCfg
    from march.audit.kinematic_g1 import KinematicG1
    from tests.test_feasibility import hand_planned_walk

    kin = KinematicG1()
    swing_z = NAMES.index("swing_z")

    def worst(trace, key: str, col: int, steps: tuple[int, ...]) -> float:
        values = np.abs(np.asarray(getattr(trace, key))[:, col])
        return float(values[np.isin(np.asarray(trace.tick_step), steps)].max())

    runs = {
        a: hand_planned_walk(kin, (0.5, 0.5, 0.3), ReferenceCfg(swing_xy_shape=a), monkeypatch)
        for a in (0.0, 0.35)
    }
    for col, share in ((SWING_X, 0.7), (swing_z, 0.8)):
        assert worst(runs[0.35], "eta", col, (1, 2)) < share * worst(runs[0.0], "eta", col, (1, 2))
    assert worst(runs[0.35], "etadot", SWING_X, (1, 2)) < 0.9 * worst(
        runs[0.0], "etadot", SWING_X, (1, 2)
    )
    tol = FeasibilityCfg().rate_tolerances()[swing_z]
    assert tol == pytest.approx(0.2)
    flat, shaped = (
        hand_planned_walk(kin, (0.35,) * 3, ReferenceCfg(swing_xy_shape=a), monkeypatch)
        for a in (0.0, 0.35)
    )
    assert max(worst(t, "eta", swing_z, (1, 2)) for t in (flat, shaped)) < 1e-3
    assert max(worst(t, "etadot", swing_z, (1, 2)) for t in (flat, shaped)) < 0.25 * tol


OPTION_SET = [
    "reference.com_height=step",
    "reference.com_height_free_step=0.4",
    "reference.com_height_slope=0.25",
    "reference.swing_height=0.08",
    "reference.swing_xy_shape=0.35",
    "reference.swing_toe_down=0.4",
    "reference.swing_toe_roll=0.15",
]
"""docs/audit.md's option set (issue 55 item 5)."""


def _option_env(*extra: str):
    """The teacher env with the option set and ``extra`` (compute=smoke, dr=none, 4 envs), reset:
    (env, its reference term, a generator seeded 0, the action dimension)."""
    from march.config.cli import load
    from march.env.build import make_env
    from march.env.reference_command import reference_term

    env = make_env(load(["compute=smoke", "dr=none", *OPTION_SET, *extra]), "teacher", num_envs=4)
    term = reference_term(env)
    env.reset()
    return env, term, torch.Generator().manual_seed(0), env.action_manager.total_action_dim


@pytest.mark.sim
def test_the_env_tracks_the_shaped_reference():
    """The teacher env built with the option set (compute=smoke, 4 envs, dr=none), walked 30
    steps under 0.4 N(0, 1) actions: the reference term's y_ref (the fused reference, at the
    term's own tau) is reference_at of the term's step state with the option set, to float32
    rounding, and its swing pitch differs from the same step's reference without the shapings
    wherever a swing is under way (phase 0.1-0.9: the options reach the env)."""
    env, term, gen, n_act = _option_env()
    try:
        ref = term.cfg.reference
        assert (ref.swing_xy_shape, ref.swing_toe_roll, ref.swing_height) == (0.35, 0.15, 0.08)
        plain = ReferenceCfg(com_height="step", com_height_free_step=0.4, com_height_slope=0.25)
        differ = 0
        for _ in range(30):
            env.step(0.4 * torch.randn(env.num_envs, n_act, generator=gen))
            want = reference_at(term.step, term.tau, ref, term.cfg.hlip, 17).flatten()
            assert torch.allclose(term.y_ref_pos, want[0], atol=1e-4)
            assert torch.allclose(term.y_ref_vel, want[1], atol=1e-3)
            other = reference_at(term.step, term.tau, plain, term.cfg.hlip, 17).flatten()[0]
            phase = term.tau / term.step.duration
            inside = (phase > 0.1) & (phase < 0.9)  # the shapings are ~0 near the ends
            changed = (other[:, SWING_PITCH] - want[0][:, SWING_PITCH]).abs() > 1e-3
            assert bool((changed | ~inside).all())
            differ += int(inside.sum())
        assert differ >= 20, differ
    finally:
        env.close()


def _with_liftoff_pitch(st, g: torch.Generator):
    """``st`` with a random measured lift-off pitch in [-0.5, 0.5] rad per env."""
    from dataclasses import replace

    return replace(
        st, swing_from_pitch=torch.rand(st.duration.shape[0], generator=g, dtype=F64) - 0.5
    )


def test_the_liftoff_pitch_carry_takes_its_hand_values():
    """``reference.swing_pitch_carry`` c (with the toe-down 0.4 and roll 0.15 of the option
    set): the swing pitch reference is the toe-down's plus p0 h00(tau / (c T)),
    h00(phi) = (1 - phi)^2 (1 + 2 phi): by hand p0 at lift-off with the toe-down's zero rate,
    p0 / 2 plus the toe-down at tau = c T / 2 with the rate -1.5 p0 / (c T) added, the
    toe-down alone from tau = c T on; the rate is the time derivative of the pitch (central
    differences); no other output changes, and c = 0 (the default) leaves the reference bit for
    bit whatever the measured pitch."""
    from march.reference.trajectory import swing_pitch_carry

    g = torch.Generator().manual_seed(5)
    st = _with_liftoff_pitch(random_steps(48, g), g)
    p0, dur = st.swing_from_pitch, st.duration
    for c in (0.3, 0.5, 1.0):
        base = ReferenceCfg(swing_toe_down=0.4, swing_toe_roll=0.15)
        carried = ReferenceCfg(swing_toe_down=0.4, swing_toe_roll=0.15, swing_pitch_carry=c)
        for tau, add_pos, add_rate in (
            (torch.zeros_like(dur), p0, torch.zeros_like(p0)),
            (0.5 * c * dur, 0.5 * p0, -1.5 * p0 / (c * dur)),
            (c * dur, torch.zeros_like(p0), torch.zeros_like(p0)),
            (c * dur + 0.3 * (1.0 - c) * dur, torch.zeros_like(p0), torch.zeros_like(p0)),
        ):
            b_pos, b_vel = reference_at(st, tau, base, HlipCfg(), 17).flatten()
            c_pos, c_vel = reference_at(st, tau, carried, HlipCfg(), 17).flatten()
            assert torch.allclose(
                c_pos[:, SWING_PITCH], b_pos[:, SWING_PITCH] + add_pos, atol=1e-12
            )
            assert torch.allclose(
                c_vel[:, SWING_PITCH], b_vel[:, SWING_PITCH] + add_rate, atol=1e-9
            )
            other = torch.ones(b_pos.shape[1], dtype=torch.bool)
            other[SWING_PITCH] = False
            assert torch.equal(b_pos[:, other], c_pos[:, other])
            assert torch.equal(b_vel[:, other], c_vel[:, other])
        tau = c * dur * torch.rand(48, generator=g, dtype=F64)
        h = 1e-6
        up, _ = swing_pitch_carry(p0, tau + h, dur, c)
        down, _ = swing_pitch_carry(p0, tau - h, dur, c)
        _, rate = swing_pitch_carry(p0, tau, dur, c)
        assert torch.allclose(rate, (up - down) / (2 * h), atol=1e-5)
    tau = dur * 1.2 * torch.rand(48, generator=g, dtype=F64)
    off = reference_at(st, tau, ReferenceCfg(), HlipCfg(), 17).flatten()
    plain = reference_at(
        random_steps(48, torch.Generator().manual_seed(5)), tau, ReferenceCfg(), HlipCfg(), 17
    ).flatten()
    assert torch.equal(off[0], plain[0]) and torch.equal(off[1], plain[1])


def test_the_fused_reference_carries_the_liftoff_pitch_as_reference_at_does():
    """reference_outputs (the env's few-op reference) equals reference_at flattened with the
    lift-off pitch carried, to 1e-9 in float64, over random steps and (E, K) instants (late
    touchdowns included), for several carry shares and with and without the toe-down."""
    for seed in range(6):
        g = torch.Generator().manual_seed(40 + seed)
        st = _with_liftoff_pitch(random_steps(31, g), g)
        cfg = ReferenceCfg(
            com_height=("fixed", "step")[seed % 2],
            swing_toe_down=(0.0, 0.4)[seed % 2],
            swing_toe_roll=(0.0, 0.15, 0.0)[seed % 3],
            swing_pitch_carry=(0.5, 0.3, 1.0)[seed % 3],
        )
        assert_fused_is_readable(st, cfg, g, seed)


def test_the_pitch_carry_option_reaches_the_reference_term_and_bad_values_are_one_line():
    assert_reference_option_is_read("swing_pitch_carry", 0.5, 1.5, "[0.0, 1.0]")


def test_the_env_carries_the_swing_foots_measured_pitch():
    """The teacher env with ``reference.swing_pitch_carry=0.5`` (compute=smoke, 4 envs, dr=none,
    30 steps under 0.4 N(0, 1) actions, every env replanned every 5th step as at a touchdown):
    the new step state's lift-off pitch is the ZYX pitch of its swing foot's site as MuJoCo
    has it (asin(-R31)), the term's y_ref is reference_at of its step state with the carry
    at every step, and the carried pitches are not all 0 (the feet do not stay flat)."""
    from march.env.step_cache import site_xmat

    env, term, gen, n_act = _option_env("reference.swing_pitch_carry=0.5")
    try:
        ref = term.cfg.reference
        assert ref.swing_pitch_carry == 0.5
        pitches = []
        for k in range(30):
            env.step(0.4 * torch.randn(env.num_envs, n_act, generator=gen))
            want = reference_at(term.step, term.tau, ref, term.cfg.hlip, 17).flatten()
            assert torch.allclose(term.y_ref_pos, want[0], atol=1e-4)
            assert torch.allclose(term.y_ref_vel, want[1], atol=1e-3)
            if k % 5 == 4:  # a replan of every env (as at a touchdown), the feet where they are
                term.replan(torch.arange(env.num_envs, device=env.device))
                mats = site_xmat(env, tuple(term.cfg.foot_sites), term.cfg.entity_name)
                for i in range(env.num_envs):
                    mat = mats[i, 1 if bool(term.step.stance_is_left[i]) else 0]
                    pitch = math.asin(max(-1.0, min(1.0, -float(mat[2, 0]))))
                    got = float(term.step.swing_from_pitch[i])
                    assert got == pytest.approx(pitch, abs=1e-5), (i, got, pitch)
                    pitches.append(got)
        assert len(pitches) == 24 and max(abs(p) for p in pitches) > 1e-3, pitches
    finally:
        env.close()
