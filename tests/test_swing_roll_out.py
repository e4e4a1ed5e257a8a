"""The swing foot's roll toward its own side (``reference.swing_roll_out``, issue 55): the
profile against hand-derived values, its rate the time derivative of its roll over generated
cases, the sign by the swinging foot, the fused reference equal to the readable one, the
default unchanged bit for bit, the option on the command line."""

from __future__ import annotations

import torch
from generated_steps import (
    assert_fused_is_readable,
    assert_only_these_change,
    assert_reference_option_is_read,
    random_steps,
    shaped_and_plain,
)

from march.reference.trajectory import ReferenceCfg, output_names, swing_roll_out

F64 = torch.float64
NAMES = output_names(17)
SWING_ROLL = NAMES.index("swing_roll")


def test_hand_derived_roll_and_sign():
    """A = 0.2, T = 0.5 s: at s = 1/2 the roll is +A when the left foot swings (the right one
    stands) and -A when the right foot swings, rate 0; at s = 1/4, 64 (3/16)^3 A = 27/64 A and
    rate 192 (3/16)^2 (1/2) A / T = 27/8 A / T; 0 and rate 0 at lift-off, touchdown and after."""
    dur = torch.full((2,), 0.5, dtype=F64)
    right_stands = torch.tensor([False, True])  # env 0: the left foot swings; env 1: the right
    for s, roll_want, rate_want in ((0.5, 1.0, 0.0), (0.25, 27 / 64, 27 / 8 / 0.5)):
        roll, rate = swing_roll_out(torch.full((2,), s, dtype=F64), dur, right_stands, 0.2)
        assert torch.allclose(roll, 0.2 * roll_want * torch.tensor([1.0, -1.0], dtype=F64))
        assert torch.allclose(rate, 0.2 * rate_want * torch.tensor([1.0, -1.0], dtype=F64))
    for s in (0.0, 1.0, 1.3):
        roll, rate = swing_roll_out(torch.full((2,), s, dtype=F64), dur, right_stands, 0.2)
        assert torch.equal(roll, torch.zeros(2, dtype=F64))
        assert torch.equal(rate, torch.zeros(2, dtype=F64))


def test_the_rate_is_the_time_derivative_of_the_roll():
    """Over 2,000 random instants, durations, amplitudes and sides inside the swing: the rate
    equals the central difference of the roll (h = 1e-6 s)."""
    g = torch.Generator().manual_seed(7)
    n, h = 2000, 1e-6
    duration = 0.3 + 0.5 * torch.rand(n, generator=g, dtype=F64)
    tau = duration * (0.001 + 0.998 * torch.rand(n, generator=g, dtype=F64))
    left = torch.rand(n, generator=g) < 0.5
    amp = float(torch.empty(1).uniform_(-0.5, 0.5, generator=g))
    up, _ = swing_roll_out((tau + h) / duration, duration, left, amp)
    down, _ = swing_roll_out((tau - h) / duration, duration, left, amp)
    _, rate = swing_roll_out(tau / duration, duration, left, amp)
    assert torch.allclose(rate, (up - down) / (2 * h), atol=1e-6)


def test_reference_at_and_the_fused_reference_carry_it_and_the_default_is_unchanged():
    """reference_at with swing_roll_out = 0.25 against 0 over 48 random steps at 4 instants:
    only the swing roll and its rate change, by swing_roll_out(...) of the step; the fused
    reference (the env's) equals reference_at to 1e-9 in float64 with the option and other
    shapings on; 0 (the default) gives the reference of before bit for bit."""
    g = torch.Generator().manual_seed(3)
    st = random_steps(48, g)
    for frac in (0.1, 0.4, 0.77, 1.2):
        tau = st.duration * frac
        rolled, plain = shaped_and_plain(st, tau, "swing_roll_out", 0.25)
        want_roll, want_rate = swing_roll_out(
            tau / st.duration, st.duration, st.stance_is_left, 0.25
        )
        assert torch.allclose(rolled[0][:, SWING_ROLL], want_roll, atol=1e-12)
        assert torch.allclose(rolled[1][:, SWING_ROLL], want_rate, atol=1e-12)
        assert_only_these_change(rolled, plain, [SWING_ROLL])
        if frac < 1.0:
            assert bool((want_roll.abs() > 1e-3).all())
    for seed in range(4):
        cfg = ReferenceCfg(
            com_height=("fixed", "step")[seed % 2],
            swing_toe_down=(0.0, 0.7)[seed % 2],
            swing_roll_out=(0.2, -0.1)[seed % 2],
        )
        gs = torch.Generator().manual_seed(60 + seed)
        assert_fused_is_readable(random_steps(31, gs), cfg, gs, seed)


def test_the_option_reaches_the_reference_term_and_bad_values_are_one_line():
    assert_reference_option_is_read("swing_roll_out", 0.15, 0.8, "[-0.5, 0.5]")
