"""``python -m march.robot <job> bundle=<dir> [key=value ...]``: the jobs and their arguments.

    python -m march.robot policy bundle=<dir> [domain=0 interface=eth0 start=enter]
    python -m march.robot sim bundle=<dir> [domain=1 interface=lo band=5 lockstep=false]
    python -m march.robot selftest bundle=<dir> [seconds=5]

``bundle``: the folder ``python -m march.export`` wrote (one ``*.deploy.json``), or its ONNX
file. ``policy``: the robot loop (:mod:`march.robot.policy_loop`); ``start=enter`` waits in hold
for a line on stdin, ``start=auto`` starts after ``hold_s``; ``seconds``: how long the policy
runs before damping (default: until Ctrl-C); ``vx`` / ``vy`` the command [m/s, body frame];
``guard=damp`` (default: a guard flag enters damping) or ``report`` (flags only recorded; ``lo``
only); ``deadlines=damp`` (default: the missed-deadline budget damps) or ``report`` (counted
only; ``lo`` only: the self-test's default, where other processes share the CPU); ``zero_torque_s`` / ``ramp_s`` / ``hold_s`` / ``damping_s`` override the bundle's
timings; ``log=<file.json>`` writes every step; ``lockstep=true`` (``lo`` only: the
self-test) waits for the lockstep robot's answer before each step. A fault (any exception, a
malformed message, a bad CRC, an impossible reading, a stale LowState, the deadline budget, a
guard flag) damps for ``damping_s`` and exits 1 with one line naming it. ``robot=unitree_mujoco``
(``lo`` only): Unitree's MuJoCo bridge publishes the LowState (mode_machine 0, no CRC, tick 0;
the command re-sent at 200 Hz). ``sim``: the MuJoCo robot
(:mod:`march.robot.sim_robot`). ``selftest``: both on loopback (:mod:`march.robot.selftest`). ``supervisor``
(:mod:`march.robot.supervisor`): damps when the policy's LowCmds stop (``timeout_s``) or go
invalid (``policy_pid=``: kill that process first). ``camera`` (:mod:`march.robot.camera`):
publishes the depth topic from a RealSense (``source=realsense``) or a recording
(``source=file file=<.bag or .npz>``; a replay starts once a reader of the topic is matched,
``wait_for_reader_s``, default 5), preprocessed as in training. ``sim cmd_timeout=S``: the
simulated motors damp after S s without a valid LowCmd. ``policy supervisor=required`` (the
default): the policy does not start before the supervisor's heartbeat has come and damps when
it stops or says the supervisor took over; ``supervisor=none`` only on ``lo``.
Bad input is one line on stderr and exit status 2, before anything starts.
"""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from march.sim2sim.bundle_schema import UsageError

LOCKSTEP_WAIT_S = 2.0
"""``lockstep=true`` (loopback only): how long a step waits for the lockstep robot's answer
to the previous command before the watchdog judges the LowState's age."""

JOBS = ("policy", "sim", "selftest", "supervisor", "camera")
USAGE = (
    "usage: python -m march.robot policy|sim|selftest|supervisor|camera bundle=<dir> [domain=N] [interface=lo] "
    "[seconds=S] [start=enter|auto] [guard=damp|report] [band=S] [lockstep=true] [log=<file>]"
)
KEYS: dict[str, Any] = {
    "bundle": str,
    "domain": int,
    "interface": str,
    "seconds": float,
    "wait_for_reader_s": float,
    "start": str,
    "guard": str,
    "deadlines": str,
    "vx": float,
    "vy": float,
    "course": str,
    "band": float,
    "lockstep": str,
    "log": str,
    "keep": str,
    "zero_torque_s": float,
    "ramp_s": float,
    "hold_s": float,
    "damping_s": float,
    "max_seconds": float,
    "cmd_timeout": float,
    "timeout_s": float,
    "policy_pid": int,
    "robot": str,
    "resend_hz": float,
    "source": str,
    "file": str,
    "fps": float,
    "supervisor": str,
}
ALLOWED = {
    "policy": {"bundle", "domain", "interface", "seconds", "start", "guard", "deadlines", "vx", "vy", "log",
               "zero_torque_s", "ramp_s", "hold_s", "damping_s", "max_seconds", "lockstep", "robot", "resend_hz",
               "supervisor"},
    "sim": {"bundle", "domain", "interface", "seconds", "course", "band", "lockstep", "log",
            "cmd_timeout"},
    "selftest": {"bundle", "domain", "interface", "seconds", "guard", "deadlines", "course", "keep"},
    "supervisor": {"bundle", "domain", "interface", "seconds", "timeout_s", "policy_pid"},
    "camera": {"bundle", "domain", "interface", "seconds", "source", "file", "fps", "wait_for_reader_s"},
}  # fmt: skip


def parse(argv: Sequence[str]) -> tuple[str, dict[str, Any]]:
    if not argv or argv[0] not in JOBS:
        raise UsageError(f"first word: one of {', '.join(JOBS)}. {USAGE}")
    job, args = argv[0], {}
    for word in argv[1:]:
        key, eq, value = word.partition("=")
        if not eq:
            raise UsageError(f"expected key=value, got {word!r}. {USAGE}")
        if key not in ALLOWED[job]:
            raise UsageError(f"{job}: unknown key {key!r}; keys: {', '.join(sorted(ALLOWED[job]))}")
        if key in args:
            raise UsageError(f"{key} given twice")
        try:
            typed = KEYS[key](value)
        except ValueError:
            raise UsageError(f"{key}={value}: not a {KEYS[key].__name__}") from None
        if isinstance(typed, float) and math.isnan(typed):
            raise UsageError(f"{key}={value}: not a number")
        args[key] = typed
    if "bundle" not in args:
        raise UsageError(f"give bundle=<dir> (written by python -m march.export). {USAGE}")
    checks = {
        "domain": lambda v: 0 <= v <= 232,
        "seconds": lambda v: v > 0,
        "wait_for_reader_s": lambda v: 0 <= v <= 600,
        "start": lambda v: v in ("enter", "auto"),
        "guard": lambda v: v in ("damp", "report"),
        "deadlines": lambda v: v in ("damp", "report"),
        "lockstep": lambda v: v in ("true", "false"),
        "band": lambda v: 0 <= v < math.inf,
        "cmd_timeout": lambda v: 0 <= v < 600,
        "timeout_s": lambda v: 0.005 <= v <= 10,
        "policy_pid": lambda v: v > 0,
        "robot": lambda v: v in ("g1", "unitree_mujoco"),
        "resend_hz": lambda v: 0 <= v <= 1000,
        "source": lambda v: v in ("realsense", "file"),
        "fps": lambda v: 1 <= v <= 90,
        "course": lambda v: v in ("hardware", "stones"),
        "supervisor": lambda v: v in ("required", "none"),
        "vx": math.isfinite,
        "vy": math.isfinite,
        **{k: (lambda v: 0 <= v < 600) for k in ("zero_torque_s", "ramp_s", "hold_s", "damping_s")},
    }
    for key, ok in checks.items():
        if key in args and not ok(args[key]):
            raise UsageError(f"{key}={args[key]}: not allowed ({USAGE})")
    loose_values = (
        ("guard", "report"), ("deadlines", "report"), ("lockstep", "true"),
        ("robot", "unitree_mujoco"), ("supervisor", "none"),
    )  # fmt: skip
    if job == "policy" and "resend_hz" in args and args.get("interface", "eth0") != "lo":
        raise UsageError("resend_hz= only on the loopback interface (a simulated robot)")
    for key, loose in loose_values:
        if job == "policy" and args.get(key) == loose and args.get("interface", "eth0") != "lo":
            raise UsageError(f"{key}={loose} only on the loopback interface (a simulated robot)")
    return job, args


def policy(args: dict[str, Any]) -> int:
    from march.robot.policy_loop import SUPERVISOR_TIMEOUT_S, Controller, load_bundle, run
    from march.robot.signals import say
    from march.robot.states import Timing
    from march.robot.wire_checks import BundleRefused
    from march.sim2sim.guard import CommandRefused, check_command

    bundle = load_bundle(args["bundle"])
    spec = bundle.spec
    over = {k: args.get(k) for k in ("zero_torque_s", "ramp_s", "hold_s", "damping_s")}
    timing = Timing.from_spec(spec["deploy"], **over)
    vx = args.get("vx", spec["command"]["lin_vel_x"])
    vy = args.get("vy", spec["command"]["lin_vel_y"])
    try:
        check_command(spec, (vx, vy, 0.0))
    except CommandRefused as err:
        raise UsageError(str(err)) from None
    try:
        ctl = Controller(
            bundle,
            timing,
            (vx, vy),
            args.get("guard", "damp"),
            args.get("deadlines", "damp"),
            robot=args.get("robot", "g1"),
        )
        if "resend_hz" in args:  # the profile's rate, overridden (loopback only)
            from dataclasses import replace

            ctl.profile = replace(ctl.profile, resend_hz=args["resend_hz"])
    except BundleRefused as err:
        raise UsageError(str(err)) from None
    domain, iface = args.get("domain", 0), args.get("interface", "eth0")
    say(f"[policy] domain {domain}, interface {iface}; zero torque until LowState")
    sup_s = SUPERVISOR_TIMEOUT_S if args.get("supervisor", "required") == "required" else 0.0
    log = run(
        ctl,
        domain,
        iface,
        args.get("start", "enter"),
        args.get("seconds", math.inf),
        args.get("max_seconds", math.inf),
        lockstep_s=LOCKSTEP_WAIT_S if args.get("lockstep") == "true" else 0.0,
        supervisor_s=sup_s,
    )
    missed = sum(s.missed for s in log) + ctl.skipped_total
    say(
        f"[policy] {len(log)} steps, {missed} missed deadlines "
        f"({ctl.skipped_total} periods skipped)"
    )
    if args.get("log"):
        out = {
            "period_s": float(spec["rates"]["control_dt_s"]),
            "command": [float(vx), float(vy)],
            "guard": ctl.guard_action,
            "deadlines": ctl.deadline_action,
            "transitions": ctl.machine.transitions,
            "steps": [
                {
                    "state": s.state,
                    "lowstate_tick": s.lowstate_tick,
                    "depth_tick": s.depth_tick,
                    "action": None if s.action is None else [float(v) for v in s.action],
                    "heading_ref": s.heading_ref,
                    "work_ms": s.work_ms,
                    "missed": s.missed,
                    "flags": list(s.flags),
                }
                for s in log
            ],
        }
        tmp = Path(args["log"]).with_suffix(".tmp")
        tmp.write_text(json.dumps(out))
        tmp.replace(args["log"])
    why = ctl.machine.fault_reason
    lost = ctl.out.damping_lost
    if lost:  # the robot may still hold the last command that reached it
        sent = ctl.out.damping_sent
        why = (
            f"{why}; {lost} damping commands could not be sent ({sent} were, on a new DDS "
            "participant): damp the robot with its remote"
        )
    if why is not None:
        say(f"error: the robot loop damped on a fault: {why}", err=True)
        return 1
    return 0


def sim(args: dict[str, Any]) -> int:
    from march.robot.policy_loop import load_bundle
    from march.robot.sim_robot import SimRobot, serve

    bundle = load_bundle(args["bundle"])
    robot = SimRobot(bundle, args.get("course", "hardware"), args.get("band", 0.0))
    stats = serve(
        robot,
        args.get("domain", 1),
        args.get("interface", "lo"),
        args.get("lockstep", "false") == "true",
        args.get("seconds", math.inf),
        args.get("log", ""),
        args.get("cmd_timeout", 0.0),
    )
    print("[sim] done: " + ", ".join(f"{k} {v}" for k, v in stats.items()), flush=True)
    return 0


def selftest(args: dict[str, Any]) -> int:
    from march.robot.selftest import run_selftest

    return run_selftest(
        args["bundle"],
        args.get("seconds", 5.0),
        args.get("domain", 1),
        args.get("interface", "lo"),
        args.get("guard", "report"),
        args.get("course", "hardware"),
        args.get("keep", ""),
        args.get("deadlines", "report"),
    )


def supervisor(args: dict[str, Any]) -> int:
    from march.robot.supervisor import main as run_supervisor

    return run_supervisor(args)


def camera(args: dict[str, Any]) -> int:
    from march.robot.camera import main as run_camera

    return run_camera(args)


def main(argv: Sequence[str] | None = None) -> None:
    words = list(sys.argv[1:] if argv is None else argv)
    try:
        job, args = parse(words)
        rc = {
            "policy": policy,
            "sim": sim,
            "selftest": selftest,
            "supervisor": supervisor,
            "camera": camera,
        }[job](args)
    except UsageError as err:
        print(f"error: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    raise SystemExit(rc)
