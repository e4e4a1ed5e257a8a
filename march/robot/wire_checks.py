"""What the robot loop reads and what it sends, checked: one line naming the first fault.

:class:`Limits` holds, per policy joint, the ranges a reading and a command must respect, from
the bundle and the G1's physical table (:mod:`march.sim2sim.bundle_schema`): joint position
limits (with :data:`~march.sim2sim.bundle_schema.POS_LIMIT_MARGIN_RAD`), motor velocity limits,
kp / kd bounds. Built at start-up, it re-checks the bundle's motor-facing values itself
(:func:`~march.sim2sim.bundle_schema.check_motor_ranges`): the loop refuses a bundle that
reached it by another road than :class:`march.sim2sim.deploy_bundle.Bundle`.

- :func:`lowstate_fault`: a LowState the loop must not act on (bad CRC, a non-finite or
  impossible IMU value, a joint reading not finite or past its limit, |dq| past the motor's).
- :func:`depth_fault`: a depth message whose size is not the camera's, or not finite in a way
  no camera produces (inf / negative), and an image that is mostly invalid pixels.
- :func:`check_deploy_fields`: deploy.json's wire facts (message type, slots, heading
  reference, period, LowState rate) held to what the loop implements; :data:`PROFILES`: what the
  loop expects of its LowState publisher (a G1, or Unitree's MuJoCo bridge).
- :func:`command_fault`: the last check before a LowCmd is published (finite targets, kp / kd
  within bounds, kp > 0 only in ramp / hold / policy, dq and tau 0, unused slots off, CRC).

Numpy and :mod:`march.robot.hg` only: the supervisor process uses it without onnxruntime.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from march.robot import hg
from march.sim2sim.bundle_schema import (
    POS_LIMIT_MARGIN_RAD,
    SchemaError,
    check_motor_ranges,
    gain_bounds,
)

MAX_INVALID_DEPTH = 0.5
"""An image with more than this fraction of invalid pixels (no return: 0 or NaN) is flagged
(the training's depth corruption drops far fewer; a covered or blinded camera returns few)."""
GAIN_STATES = ("ramp", "hold", "policy")


class BundleRefused(ValueError):
    """The bundle's motor-facing values are outside the G1's ranges (one line)."""


@dataclass
class Limits:
    """Per policy joint (policy order) and per motor slot."""

    names: list[str]
    slots: np.ndarray  # motor slot of each policy joint
    pos_lo: np.ndarray
    pos_hi: np.ndarray
    vel: np.ndarray
    kp_max: np.ndarray
    kd_max: np.ndarray
    mode_machine: int
    enable: int

    @classmethod
    def from_spec(cls, spec: dict[str, Any], slots: np.ndarray) -> Limits:
        try:
            check_motor_ranges(spec)
        except (SchemaError, KeyError, TypeError, StopIteration) as err:
            raise BundleRefused(f"the robot loop refuses the bundle: {err}") from None
        joints = spec["joints"]
        names = [j["name"] for j in joints]
        bounds = np.array([gain_bounds(n)[:2] for n in names])
        lim = np.array([j["pos_limits"] for j in joints], dtype=np.float64)
        return cls(
            names,
            np.asarray(slots, dtype=np.int64),
            lim[:, 0] - POS_LIMIT_MARGIN_RAD,
            lim[:, 1] + POS_LIMIT_MARGIN_RAD,
            np.asarray(spec["deploy"]["joint_vel_limits"], dtype=np.float64),
            bounds[:, 0],
            bounds[:, 1],
            int(spec["deploy"]["mode_machine"]),
            int(spec["deploy"]["motor_mode_enable"]),
        )


def _first(bad: np.ndarray) -> int:
    return int(np.flatnonzero(bad)[0])


def lowstate_fault(ls: Any, lim: Limits, crc: bool = True) -> str | None:
    """Why the loop must not act on ``ls`` (None: it may). ``crc=False`` only for a simulator
    that sends none (:data:`march.robot.policy_loop.PROFILES`)."""
    if not isinstance(ls, hg.LowState_):
        return f"LowState: not a LowState ({type(ls).__name__})"
    if len(ls.motor_state) != hg.NUM_MOTORS:
        return f"LowState: {len(ls.motor_state)} motor states, expected {hg.NUM_MOTORS}"
    if crc and hg.lowstate_crc(ls) != int(ls.crc):
        return f"LowState: CRC mismatch (tick {int(ls.tick)})"
    imu = ls.imu_state
    quat = np.asarray(imu.quaternion, dtype=np.float64)
    imu_values = np.concatenate([quat, np.asarray(imu.gyroscope, dtype=np.float64)])
    if not np.isfinite(imu_values).all():
        return "LowState: IMU reading not finite"
    if not 0.9 < float(np.linalg.norm(quat)) < 1.1:
        return f"LowState: IMU quaternion of norm {float(np.linalg.norm(quat)):.3g}"
    q = np.array([ls.motor_state[s].q for s in lim.slots], dtype=np.float64)
    dq = np.array([ls.motor_state[s].dq for s in lim.slots], dtype=np.float64)
    for what, v in (("q", q), ("dq", dq)):
        if not np.isfinite(v).all():
            i = _first(~np.isfinite(v))
            return f"LowState: {what} of {lim.names[i]} not finite ({v[i]})"
    out = (q < lim.pos_lo) | (q > lim.pos_hi)
    if out.any():
        i = _first(out)
        return (
            f"LowState: {lim.names[i]} at {q[i]:.3f} rad, past its limit "
            f"[{lim.pos_lo[i] + POS_LIMIT_MARGIN_RAD:.3f}, {lim.pos_hi[i] - POS_LIMIT_MARGIN_RAD:.3f}]"
        )
    fast = np.abs(dq) > lim.vel
    if fast.any():
        i = _first(fast)
        return f"LowState: |dq| of {lim.names[i]} {abs(dq[i]):.1f} rad/s over {lim.vel[i]:g}"
    return None


def depth_image(msg: Any, height: int, width: int) -> tuple[np.ndarray | None, str | None]:
    """A depth message as an (H, W) image in metres, or why it is malformed."""
    try:
        h, w, n = int(msg.height), int(msg.width), len(msg.depth_m)
    except (AttributeError, TypeError) as err:
        return None, f"depth: malformed message ({err})"
    if (h, w) != (height, width) or n != h * w:
        return None, (
            f"depth: malformed message ({h}x{w} with {n} values; the camera's is {height}x{width})"
        )
    img = np.asarray(msg.depth_m, dtype=np.float64).reshape(h, w)
    if np.isinf(img).any() or (img < 0).any():
        return None, "depth: malformed message (inf or negative depth)"
    return img, None


def depth_invalid_flag(img: np.ndarray, max_invalid: float = MAX_INVALID_DEPTH) -> str | None:
    """The "mostly invalid" guard: no return (0) or NaN on more than ``max_invalid``."""
    bad = ~(np.isfinite(img) & (img > 0))
    frac = float(bad.mean())
    if frac > max_invalid:
        return f"depth: {frac:.0%} of the image invalid (over {max_invalid:.0%})"
    return None


def command_fault(cmd: hg.LowCmd_, state: str, lim: Limits) -> str | None:
    """The last check before publishing ``cmd`` in ``state`` (None: it may go out)."""
    used = set(int(s) for s in lim.slots)
    if int(cmd.mode_machine) != lim.mode_machine:
        return f"command: mode_machine {int(cmd.mode_machine)}"
    for s, m in enumerate(cmd.motor_cmd):
        values = (m.q, m.dq, m.tau, m.kp, m.kd)
        if not all(math.isfinite(v) for v in values):
            return f"command: slot {s} not finite (q {m.q}, kp {m.kp}, kd {m.kd})"
        if m.dq != 0.0 or m.tau != 0.0:
            return f"command: slot {s} carries dq / tau"
        if s not in used:
            if m.mode != 0 or m.kp != 0.0 or m.kd != 0.0:
                return f"command: unused slot {s} enabled"
    for i, s in enumerate(lim.slots):
        m = cmd.motor_cmd[int(s)]
        if not 0.0 <= m.kp <= lim.kp_max[i] or not 0.0 <= m.kd <= lim.kd_max[i]:
            return f"command: {lim.names[i]} kp {m.kp:g} / kd {m.kd:g} outside the motor's range"
        if m.kp > 0.0 and state not in GAIN_STATES:
            return f"command: kp {m.kp:g} at {lim.names[i]} in state {state}"
        if int(m.mode) != lim.enable:
            return f"command: {lim.names[i]} mode {int(m.mode)}"
    if hg.lowcmd_crc(cmd) != int(cmd.crc):
        return "command: CRC mismatch"
    return None


def damping_lowcmd(lim: Limits, kd: float, mode_pr: int) -> hg.LowCmd_:
    """The damping command (kp 0, kd ``kd``, q / dq / tau 0 on every used slot), with its CRC:
    built from nothing but the limits, so that it can be sent whatever else has failed."""
    msg = hg.LowCmd_(mode_pr=mode_pr, mode_machine=lim.mode_machine)
    for s in lim.slots:
        m = msg.motor_cmd[int(s)]
        m.mode, m.kd = lim.enable, float(kd)
    msg.crc = hg.lowcmd_crc(msg)
    return msg


@dataclass(frozen=True)
class RobotProfile:
    """What the loop expects of its LowState publisher (``robot=`` on the command line)."""

    mode_machine: int | None  # the LowState's mode_machine; None: deploy.json's
    lowstate_crc: bool  # the LowState carries Unitree's CRC
    tick_advances: bool  # the LowState tick counts up (a frozen tick is a stale robot)
    resend_hz: float  # re-publish the current LowCmd this often between steps (0: never)


PROFILES = {
    "g1": RobotProfile(None, True, True, 0.0),
    "unitree_mujoco": RobotProfile(0, False, False, 200.0),
}
"""``g1``: a G1 (and march.robot sim). ``unitree_mujoco``: Unitree's MuJoCo bridge
(simulate_python), loopback only: its LowState has mode_machine 0, no CRC and tick 0, and it
computes the PD torque once per LowCmd and holds it until the next, so the loop re-sends each
command at the bridge's 200 Hz physics rate (docs/deploying.md)."""


DEPLOY_FIELDS = {
    ("msg_type",): "hg",
    ("heading_reference",): "imu_yaw",
    ("num_motor_slots",): hg.NUM_MOTORS,
}


def check_deploy_fields(spec: dict[str, Any]) -> None:
    """deploy.json's facts about the wire that this loop implements, read and held to it."""
    dep = spec["deploy"]
    for (key,), want in DEPLOY_FIELDS.items():
        if dep[key] != want:
            raise BundleRefused(
                f"deploy.json deploy.{key} = {dep[key]!r}: this loop speaks {want!r}"
            )
    if abs(float(dep["deadline"]["period_s"]) - float(spec["rates"]["control_dt_s"])) > 1e-9:
        raise BundleRefused("deploy.json deploy.deadline.period_s differs from rates.control_dt_s")
    if float(dep["watchdog_s"]) * float(dep["lowstate_hz"]) < 2.0:
        raise BundleRefused(
            f"deploy.json deploy.watchdog_s {dep['watchdog_s']} s is under two LowState periods "
            f"at lowstate_hz {dep['lowstate_hz']}"
        )
