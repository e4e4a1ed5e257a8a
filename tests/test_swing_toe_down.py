"""The swing foot's toe-down at mid-swing (``reference.swing_toe_down``, issue 55): its profile
against hand-derived values, its rate against the derivative of its pitch, the reference with it
against the one without (only the swing pitch changes), its way from the command line into the
env's reference term, and on the kinematic G1 the ankle-limit miss it removes.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from generated_steps import random_steps

from march.reference.hlip import HlipCfg
from march.reference.trajectory import (
    ReferenceCfg,
    output_names,
    reference_at,
    toe_down,
)

F64 = torch.float64
SWING_PITCH = output_names(17).index("swing_pitch")


@pytest.mark.parametrize("seed", range(8))
def test_the_profile_takes_its_hand_values(seed):
    """pitch = A 64 s^3 (1 - s)^3 and rate = A 192 s^2 (1 - s)^2 (1 - 2 s) / T, by hand at
    s = 0, 1/4, 1/2, 3/4, 1: 0, 27/64 A, A, 27/64 A, 0 and 0, 27/8 A / T, 0, -27/8 A / T, 0;
    past the swing (s = 1.3) the foot rests flat (0, 0). Random amplitudes and durations."""
    g = torch.Generator().manual_seed(seed)
    n = 50
    amp = float(2.0 * torch.rand(1, generator=g, dtype=F64) - 1.0)
    duration = 0.3 + 0.5 * torch.rand(n, generator=g, dtype=F64)
    want = {
        0.0: (0.0, 0.0),
        0.25: (27 / 64, 27 / 8),
        0.5: (1.0, 0.0),
        0.75: (27 / 64, -27 / 8),
        1.0: (0.0, 0.0),
        1.3: (0.0, 0.0),
    }
    for s, (p, r) in want.items():
        pitch, rate = toe_down(torch.full((n,), s, dtype=F64), duration, amp)
        assert torch.allclose(pitch, torch.full_like(pitch, p * amp), atol=1e-12), s
        assert torch.allclose(rate, r * amp / duration, atol=1e-12), s


def test_the_rate_is_the_time_derivative_of_the_pitch():
    """Over 2,000 random instants inside the swing, the rate equals the central difference of
    the pitch in time (d/dtau = d/ds / T) to 1e-6; the pitch never leaves [0, A] for A > 0."""
    g = torch.Generator().manual_seed(3)
    n = 2000
    duration = 0.3 + 0.5 * torch.rand(n, generator=g, dtype=F64)
    tau = duration * (0.01 + 0.98 * torch.rand(n, generator=g, dtype=F64))
    amp, h = 0.35, 1e-6
    up, _ = toe_down((tau + h) / duration, duration, amp)
    down, _ = toe_down((tau - h) / duration, duration, amp)
    pitch, rate = toe_down(tau / duration, duration, amp)
    assert torch.allclose(rate, (up - down) / (2 * h), atol=1e-6)
    assert float(pitch.min()) >= 0.0 and float(pitch.max()) <= amp + 1e-12


@pytest.mark.parametrize("height", ["fixed", "step"])
def test_only_the_swing_pitch_changes_and_by_the_profile(height):
    """reference_at with ``swing_toe_down`` = 0.35 against 0: over 64 random steps at 5 random
    instants (late touchdowns included) every output but the swing pitch is identical, and the
    swing pitch and its rate are the profile of the step's phase and duration."""
    g = torch.Generator().manual_seed(11)
    st = random_steps(64, g)
    flat, toed = (
        ReferenceCfg(com_height=height),
        ReferenceCfg(com_height=height, swing_toe_down=0.35),
    )
    for _ in range(5):
        tau = st.duration * 1.3 * torch.rand(64, generator=g, dtype=F64)
        p0, v0 = reference_at(st, tau, flat, HlipCfg(), 17).flatten()
        p1, v1 = reference_at(st, tau, toed, HlipCfg(), 17).flatten()
        other = torch.ones(p0.shape[1], dtype=torch.bool)
        other[SWING_PITCH] = False
        assert torch.equal(p0[:, other], p1[:, other]) and torch.equal(v0[:, other], v1[:, other])
        assert torch.equal(p0[:, SWING_PITCH], torch.zeros(64, dtype=F64))
        s = (tau / st.duration).clamp(0.0, 1.0)
        inside = tau < st.duration
        want = 0.35 * 64.0 * (s * (1 - s)) ** 3
        want_rate = 0.35 * 192.0 * (s * (1 - s)) ** 2 * (1 - 2 * s) / st.duration * inside
        assert torch.allclose(p1[:, SWING_PITCH], want, atol=1e-12)
        assert torch.allclose(v1[:, SWING_PITCH], want_rate, atol=1e-12)


def test_the_option_reaches_the_reference_term_and_a_bad_value_is_one_line():
    """``reference.swing_toe_down`` on the command line is the env's reference term's (and so
    the audit's); the default keeps the foot flat; outside [-1, 1] rad it is refused naming
    the interval."""
    from march.audit.feasibility import reference_command_cfg
    from march.config.cli import load
    from march.config.schema import ConfigError

    cfg = load(["compute=smoke", "reference.swing_toe_down=0.35"])
    assert reference_command_cfg(cfg).reference.swing_toe_down == 0.35
    assert reference_command_cfg(load(["compute=smoke"])).reference.swing_toe_down == 0.0
    with pytest.raises(ConfigError, match=r"\[-1.0, 1.0\]"):
        load(["compute=smoke", "reference.swing_toe_down=1.5"])


def test_toe_down_removes_the_ankle_limit_miss_of_a_short_step_after_a_longer_one(monkeypatch):
    """On the kinematic G1 (stance foot held), hand-planned steps of 0.45, 0.2 and 0.2 m (0.4 s
    each, flat ground): with the foot flat all swing, the 0.2 m step after the 0.45 m one
    misses on the swing pitch rate (the ankle at its dorsiflexion limit near the apex; 1.36
    rad/s measured, the error's own rate over the tick, against the audit's 1 rad/s) and its
    pitch error is 36 mrad; with swing_toe_down = 0.35 every step's swing pitch rate error stays
    within 1 rad/s (0.70 measured) and that step's pitch error falls by more than half
    (14 mrad)."""
    from march.audit.feasibility import FeasibilityCfg
    from march.audit.kinematic_g1 import KinematicG1
    from tests.test_feasibility import hand_planned_walk

    kin = KinematicG1()
    rate_tol = FeasibilityCfg().rate_tolerances()[SWING_PITCH]
    assert rate_tol == pytest.approx(1.0)
    lengths = (0.45, 0.2, 0.2)
    flat = hand_planned_walk(kin, lengths, ReferenceCfg(), monkeypatch)
    toed = hand_planned_walk(kin, lengths, ReferenceCfg(swing_toe_down=0.35), monkeypatch)

    def worst(trace, key: str, k: int) -> float:
        values = np.abs(np.asarray(getattr(trace, key))[:, SWING_PITCH])
        return float(values[np.asarray(trace.tick_step) == k].max())

    assert worst(flat, "etadot", 1) > rate_tol
    assert max(worst(toed, "etadot", k) for k in range(3)) < rate_tol
    assert worst(flat, "eta", 1) > 2.0 * worst(toed, "eta", 1)
