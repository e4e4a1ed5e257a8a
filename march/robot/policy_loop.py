"""The robot-side loop: LowState (+ depth) -> observation by ``motor_index`` -> ONNX -> LowCmd.

:class:`Controller` is one control step without a clock or DDS: from a LowState and a depth
image it builds the observation exactly as :class:`march.sim2sim.runner.Sim2Sim` does (IMU
gyroscope, gravity from the IMU quaternion, joints read from motor slot ``motor_index[i]``,
previous raw action, the command with the heading controller on the IMU yaw), asks the safety
state machine (:mod:`march.robot.states`) which state this step is in, runs the policy in the
``policy`` state, checks the guards, and fills a LowCmd (kp / kd / targets per slot, the
hardware variant, the CRC). :func:`run` drives it on a fixed-rate clock (tick k starts at
t0 + k * period, whatever the work took; a command written after its period's end is a missed
deadline) over DDS, until the state machine is done.

The depth image comes through :class:`DepthSource` (``latest()`` -> metres, tick): the DDS
depth topic here; a camera driver (RealSense) can fill the same interface in-process.
"""

from __future__ import annotations

import math
import signal
import time
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from march.robot import hg
from march.robot.signals import ORDERLY_SIGNALS, say, stop_on_signals
from march.robot.states import (
    DAMPING,
    DONE,
    HOLD,
    POLICY,
    RAMP,
    MotorCommand,
    SafetyMachine,
    Tick,
    Timing,
)
from march.robot.states import command_for as state_command
from march.robot.wire_checks import (
    PROFILES,
    Limits,
    check_deploy_fields,
    command_fault,
    damping_lowcmd,
    depth_image,
    depth_invalid_flag,
    lowstate_fault,
)
from march.sim2sim.deploy_bundle import INPUTS, OUTPUT, Bundle, UsageError
from march.sim2sim.depth_camera import normalize_depth
from march.sim2sim.guard import RangeGuard
from march.sim2sim.motors import motor_table
from march.sim2sim.runner import History, policy_session


class DepthSource(Protocol):
    def latest(self) -> tuple[np.ndarray | None, int]:
        """The newest planar depth image in metres (H, W; 0 or NaN: no return) and its tick."""


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit quaternion (w, x, y, z)."""
    w, x, y, z = (float(v) for v in q / np.linalg.norm(q))
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def readings_of(ls: hg.LowState_) -> tuple[float, ...]:
    """What a LowState measured (joint q / dq, IMU quaternion and gyroscope): two LowStates
    with one tick and other readings come from two publishers."""
    motors = ls.motor_state
    return (
        *(m.q for m in motors),
        *(m.dq for m in motors),
        *ls.imu_state.quaternion,
        *ls.imu_state.gyroscope,
    )


def yaw_of(rot: np.ndarray) -> float:
    """Heading: atan2 of the body x axis in the horizontal plane (as the sim2sim runner)."""
    return math.atan2(rot[1, 0], rot[0, 0])


@dataclass
class StepLog:
    """What one control step did (for the self-test and the report)."""

    state: str
    lowstate_tick: int
    depth_tick: int
    action: np.ndarray | None
    heading_ref: float
    work_ms: float = 0.0
    missed: bool = False
    flags: tuple[str, ...] = ()


@dataclass
class Controller:
    """One control step of the robot loop (no clock, no DDS)."""

    bundle: Bundle
    timing: Timing
    command: tuple[float, float] = (math.nan, math.nan)
    guard_action: str = "damp"  # damp: a guard flag enters damping; report: only recorded
    deadline_action: str = "damp"  # damp: the deadline budget damps; report: only counted
    robot: str = "g1"  # a key of PROFILES: what the LowState publisher is
    log: list[StepLog] = field(default_factory=list)

    def __post_init__(self) -> None:
        spec = self.bundle.spec
        self.spec, dep = spec, spec["deploy"]
        self.motor_index = motor_table(spec)
        self.default = np.asarray(spec["robot"]["default_joint_pos"], dtype=np.float64)
        self.kp = np.array([j["kp"] for j in spec["joints"]])
        self.kd = np.array([j["kd"] for j in spec["joints"]])
        self.scale = np.asarray(spec["action"]["scale"], dtype=np.float64)
        self.offset = np.asarray(spec["action"]["offset"], dtype=np.float64)
        self.vel_limit = np.asarray(dep["joint_vel_limits"], dtype=np.float64)
        self.terms = [(t["name"], int(t["dim"])) for t in spec["observation"]["proprio_terms"]]
        self.history = History(int(spec["observation"]["history_len"]))
        self.guard = RangeGuard(spec)
        self.act_lo, self.act_hi = self._action_range()
        self.machine = SafetyMachine(self.timing)
        self.session = policy_session(
            self.bundle.onnx_bytes or self.bundle.onnx_path, 1, self.bundle.onnx_path
        )
        self._warm_up()
        c = spec["command"]
        vx = c["lin_vel_x"] if math.isnan(self.command[0]) else self.command[0]
        vy = c["lin_vel_y"] if math.isnan(self.command[1]) else self.command[1]
        self.cmd = np.array([vx, vy, 0.0])
        self.last_action = np.zeros(len(self.default))
        self.heading_ref = 0.0
        self.ramp_from = self.default.copy()
        self.depth = spec["depth"]
        self.mode_machine = int(dep["mode_machine"])
        self.profile = PROFILES[self.robot]
        self.mode_pr = int(dep["mode_pr"])
        self.limits = Limits.from_spec(spec, self.motor_index)
        self.damping = damping_lowcmd(self.limits, self.timing.damping_kd, self.mode_pr)
        self.last_tick, self.last_readings, self.tick_since = -1, None, 0.0
        check_deploy_fields(spec)

    def _warm_up(self, calls: int = 5) -> None:
        """onnxruntime's first calls allocate and plan: make them before the clock starts,
        not in the policy's first deadlines."""
        lay = self.spec["checkpoint"]["layout"]
        h, w = lay["image_hw"]
        feeds = {
            "proprio_hist": np.zeros((1, lay["history_len"], lay["proprio_dim"]), np.float32),
            "command": np.zeros((1, 3), np.float32),
            "depth": np.ones((1, 1, h, w), np.float32),
        }
        for _ in range(calls):
            self.session.run([OUTPUT], feeds)

    def _action_range(self) -> tuple[np.ndarray, np.ndarray]:
        rng = self.spec["observation"]["training_range"]
        r, eps, margin = rng["actions"], float(rng["eps"]), float(rng["margin_sigmas"])
        sig = np.asarray(r["std"]) + eps
        return np.asarray(r["lo"]) - margin * sig, np.asarray(r["hi"]) + margin * sig

    # -- observation ---------------------------------------------------------------------------

    def read(self, ls: hg.LowState_) -> dict[str, np.ndarray]:
        """Joint, IMU values of a LowState in the policy's joint order."""
        q = np.array([m.q for m in ls.motor_state], dtype=np.float64)
        dq = np.array([m.dq for m in ls.motor_state], dtype=np.float64)
        rot = quat_to_matrix(np.asarray(ls.imu_state.quaternion, dtype=np.float64))
        return {
            "q": q[self.motor_index],
            "dq": dq[self.motor_index],
            "gyro": np.asarray(ls.imu_state.gyroscope, dtype=np.float64),
            "rot": rot,
        }

    def update_command(self, rot: np.ndarray) -> None:
        c = self.spec["command"]
        if not c["heading_control"]:
            self.cmd[2] = c["ang_vel_z"]
            return
        err = (self.heading_ref - yaw_of(rot) + math.pi) % (2.0 * math.pi) - math.pi
        lo, hi = c["ang_vel_z_range"]
        self.cmd[2] = min(max(c["heading_stiffness"] * err, lo), hi)

    def proprio(self, x: dict[str, np.ndarray]) -> np.ndarray:
        values = {
            "base_ang_vel": x["gyro"],
            "projected_gravity": x["rot"].T @ np.array([0.0, 0.0, -1.0]),
            "joint_pos": x["q"] - self.default,
            "joint_vel": x["dq"],
            "actions": self.last_action.copy(),
            "command": self.cmd.copy(),
        }
        return np.concatenate([values[name] for name, _ in self.terms])

    def depth_input(self, image_m: np.ndarray | None) -> tuple[np.ndarray, list[str]]:
        d = self.depth
        h, w = int(d["height"]), int(d["width"])
        if image_m is None or np.shape(image_m) != (h, w):
            return np.ones((1, 1, h, w), np.float32), ["depth: no image of the camera's size"]
        img = np.asarray(image_m, dtype=np.float64)
        flags = []
        if not np.any(np.isfinite(img) & (img > 0)):
            flags.append("depth: image all NaN / zero")
        elif (mostly := depth_invalid_flag(img)) is not None:
            flags.append(mostly)
        img = np.where(np.isfinite(img), img, 0.0)
        norm = normalize_depth(img, float(d["min_range_m"]), float(d["max_range_m"]))
        return norm.astype(np.float32)[None, None], flags

    # -- one step --------------------------------------------------------------------------------

    def step(
        self,
        ls: hg.LowState_ | None,
        lowstate_age: float | None,
        depth: tuple[np.ndarray | None, int],
        now: float,
        missed: bool = False,
        start: bool = False,
        stop: bool = False,
        skipped: int = 0,
        ticks: list[tuple[int, Any]] | None = None,
    ) -> hg.LowCmd_:
        """This step's LowCmd from the newest LowState (``None`` before the first). Every
        reading is checked in every state (:func:`march.robot.wire_checks.lowstate_fault`): a fault
        damps at once, whatever ``guard`` says; the training-range guard acts per ``guard``.
        ``ticks``: (tick, :func:`readings_of`) of every LowState that arrived since the previous
        step, oldest first (the DDS loop's); ``None`` (an in-process caller): ``ls``'s own."""
        faults: list[str] = []
        x = None
        if ls is not None:
            fault = lowstate_fault(ls, self.limits, crc=self.profile.lowstate_crc)
            if fault is None:
                x = self.read(ls)
                if self.profile.tick_advances:
                    seen = ticks if ticks is not None else [(int(ls.tick), readings_of(ls))]
                    faults += self._tick_order(seen, now)
            else:
                faults.append(fault)
        want = self.mode_machine if self.profile.mode_machine is None else self.profile.mode_machine
        variant_ok = ls is None or int(ls.mode_machine) == want
        flags: list[str] = []
        prev = self.machine.state
        late = missed and self.deadline_action == "damp"
        skip = skipped if self.deadline_action == "damp" else 0
        tick = Tick(now, lowstate_age, late, skip, tuple(faults), start, stop, variant_ok)
        state = self.machine.tick(tick)
        elapsed = now - (self.machine.since or now)
        action, target = None, None
        if state == POLICY and x is not None:
            if prev != POLICY:  # the episode starts: history back-filled, previous action 0
                self.heading_ref = yaw_of(x["rot"])
                self.history = History(self.history.length)
                self.last_action = np.zeros_like(self.last_action)
            self.update_command(x["rot"])
            p = self.proprio(x)
            self.history.push(p)
            image, dflags = self.depth_input(depth[0])
            inputs = (self.history.array(), self.cmd.astype(np.float32)[None], image)
            feeds = dict(zip(INPUTS, inputs, strict=True))
            action = self.session.run([OUTPUT], feeds)[0][0].astype(np.float64)
            flags += [f.line() for f in self.guard.check(p)] + dflags
            bad = ~np.isfinite(action) | (action < self.act_lo) | (action > self.act_hi)
            if bad.any():
                flags.append(f"action out of range at {int(np.flatnonzero(bad)[0])}")
                action = np.where(np.isfinite(action), action, 0.0)
            self.last_action = action.copy()
            target = self.offset + self.scale * action
            if flags and self.guard_action == "damp":  # acted on now: this step damps
                state = self.machine.fault(now, "guard: " + "; ".join(flags[:3]))
                elapsed = 0.0
        if state == RAMP and prev != RAMP and x is not None:
            self.ramp_from = x["q"].copy()
        cmd = state_command(
            state,
            elapsed=elapsed,
            ramp_from=self.ramp_from,
            default=self.default,
            kp=self.kp,
            kd=self.kd,
            timing=self.timing,
            policy_target=target,
        )
        msg = self.lowcmd(cmd)
        unsafe = command_fault(msg, state, self.limits)
        if unsafe is not None:  # the last check before publish: never sent
            state = self.machine.fault(now, unsafe)
            msg = self.damping
        self.log.append(
            StepLog(
                state,
                int(ls.tick) if ls is not None else -1,
                int(depth[1]),
                action,  # computed this step (sent unless the step damped)
                self.heading_ref,
                flags=tuple(faults + flags),
            )
        )
        return msg

    def _tick_order(self, seen: list[tuple[int, Any]], now: float) -> list[str]:
        """The LowState's tick counts up, one publisher's. ``seen``: (tick, readings) of each
        LowState since the last step, oldest first. A tick that goes back, or comes again with
        other readings, is a second publisher on the topic or a replay: a fault at once. The
        same LowState re-sent (same tick, same readings: a lockstep robot feeding the watchdog)
        is no news, and a tick that stops advancing for ``watchdog_s`` is a stale robot however
        often it re-sends."""
        for tick, readings in seen:
            if self.last_tick >= 0 and tick < self.last_tick:
                return [
                    f"LowState: tick went back from {self.last_tick} to {tick} (a second "
                    "publisher or a replay on the LowState topic)"
                ]
            if tick == self.last_tick:
                if readings != self.last_readings:
                    return [
                        f"LowState: tick {tick} came twice with different readings (a second "
                        "publisher or a replay on the LowState topic)"
                    ]
                continue
            self.last_tick, self.last_readings, self.tick_since = tick, readings, now
        if self.last_tick >= 0 and now - self.tick_since > self.timing.watchdog_s:
            age = (now - self.tick_since) * 1e3
            return [f"watchdog: LowState tick frozen at {self.last_tick} ({age:.0f} ms)"]
        return []

    def damping_step(self, now: float) -> hg.LowCmd_:
        """A step once damping has begun: the damping command, nothing read."""
        self.machine.tick(Tick(now, 0.0, stop=True))
        self.log.append(StepLog(self.machine.state, -1, -1, None, self.heading_ref))
        return self.damping

    def lowcmd(self, cmd: MotorCommand) -> hg.LowCmd_:
        msg = hg.LowCmd_(mode_pr=self.mode_pr, mode_machine=self.mode_machine)
        enable = int(self.spec["deploy"]["motor_mode_enable"])
        for i, slot in enumerate(self.motor_index):
            m = msg.motor_cmd[int(slot)]
            m.mode = enable
            m.q, m.kp, m.kd = float(cmd.q[i]), float(cmd.kp[i]), float(cmd.kd[i])
        msg.crc = hg.lowcmd_crc(msg)
        return msg


# ---------------------------------------------------------------------------------------------
# The loop over DDS on a fixed-rate clock.


class InputFault(RuntimeError):
    """A message the loop cannot use (its text is the one line that names it)."""


DEPTH_STALE_S = 0.25
"""Seconds: in the policy state, a depth image older than this (7 frames of a 30 Hz camera) is a
stale input - the camera stopped - and damps; before the policy the image is not used."""


class DdsDepth:
    """The depth topic as a :class:`DepthSource`; a malformed message is an :class:`InputFault`
    (in every state: a camera that sends garbage before the policy starts is not trusted), and
    so is, in the policy state, an image older than :data:`DEPTH_STALE_S`."""

    def __init__(self, box: Any, height: int, width: int) -> None:
        self.box, self.height, self.width = box, height, width
        self.in_policy = False  # set by the loop each step

    def latest(self) -> tuple[np.ndarray | None, int]:
        msg, arrived = self.box.take()
        if msg is None:
            return None, -1
        age = time.perf_counter() - arrived
        if self.in_policy and age > DEPTH_STALE_S:
            raise InputFault(f"depth: stale image ({age * 1e3:.0f} ms old, tick {int(msg.tick)})")
        img, problem = depth_image(msg, self.height, self.width)
        if problem is not None:
            raise InputFault(problem)
        return img, int(msg.tick)


def fault_line(err: BaseException) -> str:
    """The one line naming an exception that ended the loop's normal steps."""
    if isinstance(err, InputFault):
        return str(err)
    text = str(err).splitlines()[0] if str(err) else ""
    if type(err).__module__.startswith("cyclonedds"):
        return f"DDS: {type(err).__name__}: {text}"[:300]
    return f"exception: {type(err).__name__}: {text}"[:300]


LOWSTATE_DEPTH = 2
"""LowStates the loop's reader keeps between two steps (the newest ones)."""
SUPERVISOR_TIMEOUT_S = 0.25
"""Seconds: with ``supervisor=required``, no heartbeat for this long once one has come is a
supervisor gone (12 of its 20 ms heartbeats missed: a crash, a kill, a lost terminal; not the
scheduling jitter of a loaded computer)."""


class CommandOut:
    """``rt/lowcmd`` with a way back: a write that raises (the DDS participant lost, a library
    fault) leaves the loop damping, and each damping command is tried on a fresh participant
    and writer when the old one fails (:meth:`damp`)."""

    def __init__(self, domain: int, interface: str, topic: str) -> None:
        self.domain, self.interface, self.topic = domain, interface, topic
        self.participant, self.writer = self._open()
        self.reopened = 0
        self.damping_sent = 0
        self.damping_lost = 0

    def _open(self) -> tuple[Any, Any]:
        from march.robot import dds

        dp = dds.participant(self.domain, self.interface)
        return dp, dds.writer(dp, self.topic, hg.LowCmd_)

    def write(self, cmd: hg.LowCmd_) -> None:
        self.writer.write(cmd)

    def damp(self, cmd: hg.LowCmd_) -> bool:
        """Send the damping command, on a new participant if the old one fails; False when
        neither could send it (counted: the exit line says so)."""
        for fresh in (False, True):
            try:
                if fresh:
                    self.participant, self.writer = self._open()
                    self.reopened += 1
                self.writer.write(cmd)
                self.damping_sent += 1
                return True
            except Exception:  # noqa: BLE001 - the next try, or the count
                continue
        self.damping_lost += 1
        return False


def _wait_until(t: float, out: CommandOut, cmd: Any, resend_hz: float, fresh_until: float) -> None:
    """Sleep until ``t``; with ``resend_hz``, re-publish ``cmd`` (already checked) meanwhile, but
    never after ``fresh_until`` (its LowState would then be older than the watchdog allows)."""
    while True:
        wait = t - time.perf_counter()
        if wait <= 0:
            return
        if resend_hz <= 0 or cmd is None:
            time.sleep(wait)
            return
        time.sleep(min(wait, 1.0 / resend_hz))
        now = time.perf_counter()
        if now < t - 0.2 / resend_hz and now < fresh_until:
            out.write(cmd)


def _newer(box: Any, tick: int, timeout: float) -> None:
    """Lockstep: poll until a LowState newer than ``tick`` arrives (or ``timeout``)."""
    end = time.perf_counter() + timeout
    while True:
        box.poll()
        if box.sample is not None and int(box.sample.tick) > tick:
            return
        if time.perf_counter() >= end:
            return
        time.sleep(2e-4)


def _supervisor_check(box: Any, now: float, timeout: float) -> bool:
    """With ``supervisor=required``: True once a live heartbeat has come (the policy may start);
    an :class:`InputFault` when the supervisor took over or its heartbeat stopped."""
    beat, at = box.take()
    if beat is None:
        return False
    if int(beat.took_over):
        raise InputFault(
            f"supervisor: it took over or is stopping (pid {int(beat.pid)}); damping (start a "
            "new supervisor for the next run)"
        )
    if now - at > timeout:
        raise InputFault(f"supervisor gone: no heartbeat for {(now - at) * 1e3:.0f} ms")
    return True


def run(
    ctl: Controller,
    domain: int,
    interface: str,
    start: str = "enter",
    policy_seconds: float = math.inf,
    max_seconds: float = math.inf,
    depth: DepthSource | None = None,
    lockstep_s: float = 0.0,
    supervisor_s: float = 0.0,
) -> list[StepLog]:
    """Drive ``ctl`` at the control rate until done. ``start``: ``enter`` (a line on stdin
    starts the policy from hold; stdin closed is a fault) or ``auto``; the policy runs
    ``policy_seconds`` then stops (damping); SIGINT / SIGTERM stop it too, SIGHUP (the terminal
    gone) damps as a fault. Any exception in a step (a malformed message, a bug, a DDS write
    that fails) is a fault: damping from that step on, for its full time, sent by a path that
    reads nothing (on a fresh DDS participant if the old one fails: :class:`CommandOut`). Just
    before each write, a command whose LowState is older than ``watchdog_s`` (the process
    stalled or was stopped between reading and writing) is replaced by damping: no command is
    published from a stale LowState. ``lockstep_s`` > 0 (the self-test against a lockstep robot
    only): each step first waits up to that long for the LowState that answers the previous
    command. ``supervisor_s`` > 0 (``supervisor=required``): the policy does not start before
    the supervisor's heartbeat has come, and damps when it stops for ``supervisor_s`` or says
    the supervisor took over."""
    from march.robot import dds

    dp = dds.participant(domain, interface)
    dep = ctl.spec["deploy"]
    # The newest two LowStates of each poll, their ticks checked in order (a duplicate or a
    # second publisher shows between them); not more: each costs ~1 ms to deserialize here.
    state_box = dds.Latest(
        dp, dep["lowstate_topic"], hg.LowState_, qos=dds.best_effort(LOWSTATE_DEPTH)
    )
    out = CommandOut(domain, interface, dep["lowcmd_topic"])
    ctl.out = out
    beats = dds.Latest(dp, dds.SUPERVISOR_TOPIC, dds.Heartbeat_) if supervisor_s > 0 else None
    hw = (int(ctl.depth["height"]), int(ctl.depth["width"]))
    source = depth or DdsDepth(dds.Latest(dp, dds.DEPTH_TOPIC, dds.DepthImage_), *hw)
    stop, old = stop_on_signals()
    enter = _stdin_lines() if start == "enter" else None
    period = float(dep["deadline"]["period_s"])
    watchdog = ctl.timing.watchdog_s
    t0 = time.perf_counter()
    k, missed, skipped, policy_t0, shown, used_tick = 0, False, 0, None, 0, -1
    last_cmd, fresh_until, waiting_said = None, 0.0, False
    ctl.skipped_total = 0
    try:
        while ctl.machine.state != DONE:
            tick_start = t0 + k * period
            _wait_until(tick_start, out, last_cmd, ctl.profile.resend_hz, fresh_until)
            now = time.perf_counter()
            if now - tick_start > period:  # stopped or starved before this step began
                extra = int((now - tick_start) // period)
                k, skipped, ctl.skipped_total = (
                    k + extra,
                    skipped + extra,
                    ctl.skipped_total + extra,
                )
                tick_start += extra * period
            arrived = None
            try:
                if ctl.machine.state == DAMPING:
                    cmd = ctl.damping_step(now - t0)
                else:
                    if stop["flag"] and stop["signal"] not in ORDERLY_SIGNALS:
                        raise InputFault(
                            f"{stop['signal']}: the terminal closed or the session dropped"
                        )
                    if lockstep_s > 0:
                        _newer(state_box, used_tick, lockstep_s)
                        now = time.perf_counter()
                    ls, arrived = state_box.take()
                    ticks = [(int(s.tick), readings_of(s)) for s in state_box.drain()]
                    used_tick = int(ls.tick) if ls is not None else used_tick
                    age = None if arrived is None else now - arrived
                    want_start = start == "auto" or (enter is not None and enter())
                    if beats is not None and not _supervisor_check(beats, now, supervisor_s):
                        if want_start and ctl.machine.state == HOLD and not waiting_said:
                            say("[policy] hold: waiting for the supervisor's heartbeat")
                            waiting_said = True
                        want_start = False
                    over = policy_t0 is not None and now - policy_t0 >= policy_seconds
                    quit_now = stop["flag"] or over or now - t0 >= max_seconds
                    if isinstance(source, DdsDepth):
                        source.in_policy = ctl.machine.state == POLICY
                    image = source.latest()
                    cmd = ctl.step(
                        ls, age, image, now - t0, missed, want_start, quit_now, skipped, ticks
                    )
                # The last look before the write: a command from a LowState older than the
                # watchdog (a stall, SIGSTOP, a hung call since it was read) never goes out.
                if arrived is not None and cmd is not ctl.damping:
                    at = time.perf_counter()
                    late = at - arrived
                    if late > watchdog:  # damping's time counts from now, not the step's start
                        ctl.machine.fault(
                            at - t0,
                            f"watchdog: LowState {late * 1e3:.0f} ms old at the write (a stall "
                            "or a robot gone since it was read; its command not sent)",
                        )
                        cmd = ctl.damping
                out.write(cmd)
            except Exception as err:  # noqa: BLE001 - every fault ends in damping
                ctl.machine.fault(time.perf_counter() - t0, fault_line(err))
                cmd = ctl.damping
                out.damp(cmd)
            last_cmd = cmd
            fresh_until = (arrived if arrived is not None else 0.0) + watchdog
            if cmd is ctl.damping:
                fresh_until = math.inf  # damping reads nothing: always fit to re-send
            done = time.perf_counter()
            if ctl.machine.state == POLICY and policy_t0 is None:
                policy_t0 = now
            missed = done > tick_start + period  # the command went out after its period
            if ctl.log:
                ctl.log[-1].work_ms, ctl.log[-1].missed = (done - now) * 1e3, missed
            for t, a, b, why in ctl.machine.transitions[shown:]:  # as they happen
                say(f"[policy] {t:7.3f} s  {a} -> {b}  ({why})")
            shown = len(ctl.machine.transitions)
            k += 1
            behind = time.perf_counter() - (t0 + k * period)
            skipped = int(behind // period) if behind > period else 0
            k += skipped  # whole periods with no command: each a missed deadline
            ctl.skipped_total += skipped
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    return ctl.log


def _stdin_lines():
    """A non-blocking 'has a line arrived on stdin' check; stdin at its end (the terminal
    closed, or none given) is an :class:`InputFault`, never a start."""
    import select
    import sys

    def ready() -> bool:
        r, _, _ = select.select([sys.stdin], [], [], 0)
        if r:
            if not sys.stdin.readline():
                raise InputFault("stdin closed: start=enter has no terminal to read Enter from")
            return True
        return False

    return ready


def load_bundle(path: str) -> Bundle:
    """``bundle=<dir>`` (holding one ``*.deploy.json``) or ``bundle=<file>.onnx``."""
    from pathlib import Path

    p = Path(path)
    if p.is_dir():
        found = sorted(p.glob("*.deploy.json"))
        if len(found) != 1:
            raise UsageError(f"bundle={path}: {len(found)} *.deploy.json files, expected one")
        p = found[0].with_name(found[0].name.removesuffix(".deploy.json") + ".onnx")
    return Bundle.load(p)
