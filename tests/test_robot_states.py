"""The robot loop's safety state machine over many generated fault timings (no DDS, no clock).

Each scenario is a 50 Hz tick sequence with random timings: when LowState starts, a gap in it
(stale: the watchdog, in zero torque too once a LowState has come), missed deadlines
(scattered or in a row) and skipped periods (each a missed deadline), a fault or guard flag (in
any state), a hardware variant change, a stop request (Ctrl-C), when start is pressed. An oracle written apart from
the machine (per-tick predicates over the whole schedule) gives the tick where damping must
begin and why; the machine must start damping exactly there, never pass a state out of order,
keep each start-up state for its time, damp for ``damping_s`` and end ``done``.
"""

from __future__ import annotations

import numpy as np
import pytest

from march.robot.states import (
    DAMPING,
    DONE,
    HOLD,
    POLICY,
    RAMP,
    ZERO_TORQUE,
    DeadlineBudget,
    SafetyMachine,
    Tick,
    Timing,
    command_for,
)

DT = 0.02
TIMING = Timing(
    zero_torque_s=0.3,
    ramp_s=0.5,
    hold_s=0.2,
    damping_s=0.4,
    damping_kd=8.0,
    watchdog_s=0.05,
    max_missed_in_window=5,
    window_steps=50,
    max_missed_in_a_row=3,
    wait_lowstate_s=1.0,
)
ORDER = [ZERO_TORQUE, RAMP, HOLD, POLICY, DAMPING, DONE]


def scenario(rng: np.random.Generator, n: int = 300) -> dict:
    t = np.arange(n) * DT
    ls_start = rng.uniform(0.0, 0.3)
    gap = sorted(rng.uniform(0.2, 6.0, 2)) if rng.random() < 0.4 else [np.inf, np.inf]
    gap[1] = gap[0] + rng.choice([0.03, 0.06, 0.2, 1.0]) if gap[0] < np.inf else np.inf
    arrivals = np.where((t >= ls_start) & ~((t >= gap[0]) & (t < gap[1])), t, np.nan)
    last = np.fmax.accumulate(np.nan_to_num(arrivals, nan=-np.inf))
    age = np.where(np.isfinite(last), t - last, np.nan)
    missed = rng.random(n) < rng.choice([0.0, 0.02, 0.08, 0.2])
    if rng.random() < 0.2:
        k = int(rng.integers(n - 5))
        missed[k : k + 3] = True
    skipped = np.zeros(n, dtype=int)
    if rng.random() < 0.2:
        skipped[int(rng.integers(n))] = int(rng.integers(1, 30))
    flag_at = rng.uniform(0.0, 6.0) if rng.random() < 0.3 else np.inf
    stop_at = rng.uniform(0.0, 6.0) if rng.random() < 0.5 else np.inf
    variant_bad_at = rng.uniform(0.0, 6.0) if rng.random() < 0.1 else np.inf
    start_at = rng.uniform(0.5, 3.0)
    return dict(
        t=t, age=age, missed=missed, skipped=skipped, flag_at=flag_at, stop_at=stop_at,
        variant_bad_at=variant_bad_at, start_at=start_at,
    )  # fmt: skip


def drive(s: dict, machine: SafetyMachine) -> list[str]:
    states = []
    for i, now in enumerate(s["t"]):
        age = None if np.isnan(s["age"][i]) else float(s["age"][i])
        flags = ("guard",) if now >= s["flag_at"] else ()
        tick = Tick(
            now=float(now),
            lowstate_age=age,
            missed_deadline=bool(s["missed"][i]),
            skipped=int(s["skipped"][i]),
            flags=flags,
            start=now >= s["start_at"],
            stop=now >= s["stop_at"],
            variant_ok=now < s["variant_bad_at"],
        )
        states.append(machine.tick(tick))
    return states


def oracle_first_damping(s: dict, states: list[str]) -> tuple[int | None, str | None]:
    """Where damping must begin, from the schedule and the states the machine reported before
    it (which state was active decides which checks apply)."""
    t, age, missed = s["t"], s["age"], s["missed"]
    window: list[bool] = []
    row = 0
    prev = ZERO_TORQUE
    for i, now in enumerate(t):
        if now >= s["stop_at"]:
            return i, "stop"
        if now >= s["variant_bad_at"]:
            return i, "variant"
        active = prev in (ZERO_TORQUE, RAMP, HOLD, POLICY)
        if active:
            waiting = prev == ZERO_TORQUE and np.isnan(age[i])  # no LowState yet
            if not waiting and (np.isnan(age[i]) or age[i] > TIMING.watchdog_s):
                return i, "watchdog"
            spent = False
            for m in [True] * int(s["skipped"][i]) + [bool(missed[i])]:
                window = (window + [m])[-TIMING.window_steps :]
                row = row + 1 if m else 0
                spent |= sum(window) > TIMING.max_missed_in_window
                spent |= row >= TIMING.max_missed_in_a_row
            if spent:
                return i, "deadline"
            if now >= s["flag_at"]:
                return i, "guard"
        if states[i] == DONE:
            return None, None
        prev = states[i]
    return None, None


REASON_WORDS = {
    "stop": "stop",
    "variant": "mode_machine",
    "watchdog": "watchdog",
    "deadline": "deadline",
    "guard": "guard",
}


@pytest.mark.parametrize("seed", range(8))
def test_damping_begins_exactly_where_a_fault_does(seed):
    rng = np.random.default_rng(seed)
    kinds = set()
    for _ in range(150):
        s = scenario(rng)
        m = SafetyMachine(TIMING)
        states = drive(s, m)
        first, kind = oracle_first_damping(s, states)
        got = next((i for i, st in enumerate(states) if st == DAMPING), None)
        assert got == first, (kind, first, got, m.transitions)
        if kind is not None:
            kinds.add(kind)
            why = next(w for _, _, b, w in m.transitions if b == DAMPING)
            assert REASON_WORDS[kind] in why, (kind, why)
        check_order_and_times(states, s["t"], m, s["start_at"])
    assert kinds >= {"stop", "watchdog", "deadline", "guard"}


def check_order_and_times(states: list[str], t: np.ndarray, m: SafetyMachine, start_at):
    seq = [m.transitions[0][1]] + [b for _, _, b, _ in m.transitions] if m.transitions else []
    idx = [ORDER.index(x) for x in seq]
    assert idx == sorted(idx), seq  # never back, never out of order
    if DAMPING in seq:
        assert seq[-2:] == [DAMPING, DONE] or seq[-1] == DAMPING
    skipped = {(a, b) for _, a, b, _ in m.transitions if ORDER.index(b) - ORDER.index(a) > 1}
    assert skipped <= {(a, DAMPING) for a in ORDER[:4]} | {(ZERO_TORQUE, DONE)}
    entered = {b: time for time, _, b, _ in m.transitions}
    left = {a: time for time, a, _, _ in m.transitions}
    for state, need in ((ZERO_TORQUE, TIMING.zero_torque_s), (RAMP, TIMING.ramp_s)):
        if state in left and (state == ZERO_TORQUE or state in entered):
            began = entered.get(state, 0.0)
            if next(b for _, a, b, _ in m.transitions if a == state) != DAMPING:
                assert left[state] - began >= need - 1e-6
    if POLICY in entered:
        assert (
            entered[POLICY] >= start_at and entered[POLICY] - entered[HOLD] >= TIMING.hold_s - 1e-6
        )
    if DONE in entered and DAMPING in entered:
        assert entered[DONE] - entered[DAMPING] >= TIMING.damping_s - 1e-6
    after = states[states.index(DAMPING) :] if DAMPING in states else []
    assert all(st in (DAMPING, DONE) for st in after)


def test_a_clean_run_reaches_the_policy_and_stays():
    s = scenario(np.random.default_rng(0))
    s.update(
        age=np.zeros_like(s["t"]), missed=np.zeros_like(s["missed"]), flag_at=np.inf,
        skipped=np.zeros_like(s["skipped"]),
        stop_at=np.inf, variant_bad_at=np.inf, start_at=0.0,
    )  # fmt: skip
    m = SafetyMachine(TIMING)
    states = drive(s, m)
    assert [b for _, _, b, _ in m.transitions] == [RAMP, HOLD, POLICY]
    t = {b: time for time, _, b, _ in m.transitions}
    assert t[RAMP] == pytest.approx(0.3) and t[HOLD] == pytest.approx(0.8)
    assert t[POLICY] == pytest.approx(1.0) and states[-1] == POLICY


def test_deadline_budget_by_hand():
    b = DeadlineBudget(max_in_window=2, window=5, max_in_a_row=3)
    assert [b.record(x) for x in (1, 0, 1, 0, 0, 1)] == [False] * 6  # 2 in any 5
    b = DeadlineBudget(2, 5, 3)
    assert [b.record(x) for x in (1, 0, 1, 1)] == [False, False, False, True]  # 3 in 5
    b = DeadlineBudget(10, 50, 3)
    assert [b.record(x) for x in (1, 1, 0, 1, 1, 1)] == [False] * 5 + [True]  # 3 in a row


def test_commands_of_each_state_by_hand():
    d = np.array([0.1, -0.3, 0.6])
    q0 = np.array([0.5, 0.0, 0.0])
    kp, kd = np.array([40.0, 99.0, 14.0]), np.array([2.5, 6.3, 0.9])
    args = dict(ramp_from=q0, default=d, kp=kp, kd=kd, timing=TIMING)
    z = command_for(ZERO_TORQUE, elapsed=0.1, **args)
    assert not z.kp.any() and not z.kd.any()
    r = command_for(RAMP, elapsed=0.25, **args)  # halfway through 0.5 s
    np.testing.assert_allclose(r.q, [0.3, -0.15, 0.3])
    np.testing.assert_allclose(command_for(RAMP, elapsed=9.0, **args).q, d)
    h = command_for(HOLD, elapsed=1.0, **args)
    np.testing.assert_allclose(h.q, d) and np.testing.assert_allclose(h.kp, kp)
    p = command_for(POLICY, elapsed=0.0, policy_target=d + 0.2, **args)
    np.testing.assert_allclose(p.q, d + 0.2)
    dmp = command_for(DAMPING, elapsed=0.0, **args)
    assert not dmp.kp.any() and (dmp.kd == 8.0).all()
