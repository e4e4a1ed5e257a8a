"""The robot loop's safety state machine and the motor commands of each state (numpy only).

States, in order: ``zero_torque`` (motors enabled, kp = kd = 0: the robot hangs on its stand)
-> ``ramp`` (kp / kd of the joints table, the target moving linearly from the measured pose to
the default pose over ``ramp_s``) -> ``hold`` (the default pose, until started) -> ``policy``
(the student's targets) -> ``damping`` (kp 0, kd ``damping_kd``, for ``damping_s``) -> ``done``.

:class:`SafetyMachine.tick` takes one control step's facts (:class:`Tick`: the time, whether a
fresh LowState has arrived and how old the latest is, whether the previous step met its
deadline, the guard flags raised this step, start and stop requests) and returns the state for
this step. Damping is entered from every active state (zero torque included) on: a stop request
(Ctrl-C, the end of the run), a stale LowState (older than ``watchdog_s``: the watchdog; in zero
torque once the first LowState has come), the deadline budget spent (:class:`DeadlineBudget`;
a skipped period counts as a missed deadline), any fault or guard flag of the step (a bad CRC,
a non-finite or out-of-limit reading, a malformed message, an exception), or a LowState of
another hardware variant. Damping always runs its full time; nothing leaves it but ``done``.
:attr:`SafetyMachine.fault_reason` is the cause when damping was not asked for. Every transition is recorded with its
time and reason. No DDS, no clock: the tests drive it with generated fault timings.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

ZERO_TORQUE, RAMP, HOLD, POLICY, DAMPING, DONE = (
    "zero_torque",
    "ramp",
    "hold",
    "policy",
    "damping",
    "done",
)
EPS = 1e-6
"""Seconds: a time limit counts as reached this close to it (ticks are sums of float periods)."""
ACTIVE = (ZERO_TORQUE, RAMP, HOLD, POLICY)
"""States before damping: the watchdog, the deadline budget and every fault apply."""
GAINS = (RAMP, HOLD, POLICY)
"""The only states whose commands may carry kp > 0."""
ORDERLY = ("stop requested",)
"""Damping reasons that are not faults (the loop exits 0 after them)."""


@dataclass
class Timing:
    """Start-up and shut-down timings and limits (``deploy.json`` ``deploy``)."""

    zero_torque_s: float
    ramp_s: float
    hold_s: float
    damping_s: float
    damping_kd: float
    watchdog_s: float
    max_missed_in_window: int
    window_steps: int
    max_missed_in_a_row: int
    wait_lowstate_s: float = 10.0
    """Zero torque longer than this without a LowState: done (nothing to control)."""

    @classmethod
    def from_spec(cls, deploy: dict[str, Any], **override: float) -> Timing:
        s, d = deploy["startup"], deploy["deadline"]
        values = {
            "zero_torque_s": s["zero_torque_s"],
            "ramp_s": s["ramp_s"],
            "hold_s": s["hold_s"],
            "damping_s": deploy["shutdown"]["damping_s"],
            "damping_kd": deploy["shutdown"]["damping_kd"],
            "watchdog_s": deploy["watchdog_s"],
            "max_missed_in_window": d["max_missed_in_window"],
            "window_steps": d["window_steps"],
            "max_missed_in_a_row": d["max_missed_in_a_row"],
        }
        values.update({k: v for k, v in override.items() if v is not None})
        return cls(**values)


class DeadlineBudget:
    """Missed deadlines: spent when more than ``max_in_window`` of the last ``window`` steps
    missed, or ``max_in_a_row`` in a row."""

    def __init__(self, max_in_window: int, window: int, max_in_a_row: int) -> None:
        self.max_in_window, self.max_in_a_row = max_in_window, max_in_a_row
        self.recent: deque[bool] = deque(maxlen=window)
        self.in_a_row = 0
        self.total = 0

    def record(self, missed: bool) -> bool:
        """Add one step; True when the budget is spent."""
        self.recent.append(bool(missed))
        self.in_a_row = self.in_a_row + 1 if missed else 0
        self.total += int(missed)
        return sum(self.recent) > self.max_in_window or self.in_a_row >= self.max_in_a_row


@dataclass
class Tick:
    """One control step's facts."""

    now: float
    lowstate_age: float | None  # seconds since the newest LowState; None: none yet
    missed_deadline: bool = False
    skipped: int = 0  # whole periods the clock skipped before this step: each a missed deadline
    flags: tuple[str, ...] = ()
    start: bool = False
    stop: bool = False
    variant_ok: bool = True


@dataclass
class SafetyMachine:
    """Zero torque -> ramp -> hold -> policy -> damping -> done."""

    timing: Timing
    state: str = ZERO_TORQUE
    since: float | None = None
    transitions: list[tuple[float, str, str, str]] = field(default_factory=list)

    def __post_init__(self) -> None:
        t = self.timing
        self.budget = DeadlineBudget(t.max_missed_in_window, t.window_steps, t.max_missed_in_a_row)

    def _go(self, now: float, state: str, why: str) -> None:
        self.transitions.append((now, self.state, state, why))
        self.state, self.since = state, now

    def _damp_reason(self, k: Tick) -> str | None:
        if k.stop:
            return "stop requested"
        if not k.variant_ok:
            return "LowState of another hardware variant (mode_machine)"
        if self.state not in ACTIVE:
            return None
        waiting = self.state == ZERO_TORQUE and k.lowstate_age is None  # none yet: may wait
        if not waiting and (k.lowstate_age is None or k.lowstate_age > self.timing.watchdog_s):
            age = "none" if k.lowstate_age is None else f"{k.lowstate_age * 1e3:.0f} ms"
            return f"watchdog: LowState stale ({age})"
        spent = any([self.budget.record(True) for _ in range(k.skipped)])
        spent = self.budget.record(k.missed_deadline) or spent
        if spent:
            skipped = f", {k.skipped} periods skipped" if k.skipped else ""
            return f"deadline budget spent ({self.budget.total} missed{skipped})"
        if k.flags:
            return "; ".join(k.flags[:3])
        return None

    @property
    def fault_reason(self) -> str | None:
        """Why the loop damped or ended when nobody asked it to (None: an orderly end)."""
        for _, _, b, why in self.transitions:
            if b == DAMPING or (b == DONE and why == "no LowState"):
                return None if why in ORDERLY else why
        return None

    def fault(self, now: float, why: str) -> str:
        """Damping now, from any state before it (a guard raised inside a step)."""
        if self.state not in (DAMPING, DONE):
            self._go(now, DAMPING, why)
        return self.state

    def tick(self, k: Tick) -> str:
        """The state for this step, after the transitions its facts call for."""
        t = self.timing
        if self.since is None:
            self.since = k.now
        elapsed = k.now - self.since + EPS
        if self.state in (DAMPING, DONE):
            if self.state == DAMPING and elapsed >= t.damping_s:
                self._go(k.now, DONE, "damping time over")
            return self.state
        why = self._damp_reason(k)
        if why is not None:
            self._go(k.now, DAMPING, why)
            return self.state
        if self.state == ZERO_TORQUE:
            fresh = k.lowstate_age is not None and k.lowstate_age <= t.watchdog_s
            if fresh and elapsed >= t.zero_torque_s:
                self._go(k.now, RAMP, "LowState live, zero torque time over")
            elif not fresh and elapsed >= t.wait_lowstate_s:
                self._go(k.now, DONE, "no LowState")
        elif self.state == RAMP and elapsed >= t.ramp_s:
            self._go(k.now, HOLD, "at the default pose")
        elif self.state == HOLD and k.start and elapsed >= t.hold_s:
            self._go(k.now, POLICY, "started")
        return self.state


@dataclass
class MotorCommand:
    """Per policy joint: position target, kp, kd (dq and tau are always 0)."""

    q: np.ndarray
    kp: np.ndarray
    kd: np.ndarray
    enable: bool = True


def command_for(
    state: str,
    *,
    elapsed: float,
    ramp_from: np.ndarray,
    default: np.ndarray,
    kp: np.ndarray,
    kd: np.ndarray,
    timing: Timing,
    policy_target: np.ndarray | None = None,
) -> MotorCommand:
    """The motor command of ``state``, ``elapsed`` seconds into it (policy joint order)."""
    zeros = np.zeros_like(default)
    if state == ZERO_TORQUE:
        return MotorCommand(zeros, zeros, zeros)
    if state == RAMP:
        a = min(max(elapsed / timing.ramp_s, 0.0), 1.0) if timing.ramp_s > 0 else 1.0
        return MotorCommand(ramp_from + a * (default - ramp_from), kp, kd)
    if state == HOLD:
        return MotorCommand(default.copy(), kp, kd)
    if state == POLICY:
        assert policy_target is not None
        return MotorCommand(policy_target, kp, kd)
    if state == DAMPING:
        return MotorCommand(zeros, zeros, np.full_like(default, timing.damping_kd))
    return MotorCommand(zeros, zeros, np.full_like(default, timing.damping_kd))  # done: damp
