"""``python -m march.robot supervisor``: a small process that outlives the policy and damps.

It watches ``rt/lowcmd`` and ``rt/lowstate`` (numpy, cyclonedds and :mod:`march.robot.wire_checks`
only: no torch, no onnxruntime, no MuJoCo, so that it starts in a fraction of a second and a
policy that dies of memory or a library fault does not take it along). It takes over - publishes
the damping command (kp 0, kd ``damping_kd`` on every used slot, its CRC) on ``rt/lowcmd`` at the
control rate until it is stopped - when, after the policy's first command:

- no LowCmd has come for ``timeout_s`` (default: 2 x ``watchdog_s``): the policy died, hung,
  or was stopped;
- a LowCmd fails the loop's own last check (:func:`march.robot.wire_checks.command_fault`, with kp
  allowed: a non-finite value, kp / kd outside the motor's range, another ``mode_machine``, a
  used slot disabled or an unused one enabled, a bad CRC); with ``policy_pid=`` it first kills
  that process (SIGKILL): a live publisher of bad commands cannot be outvoted on a topic.

What it cannot do (docs/deploying.md): stop a robot whose network link or DDS is down (its
commands do not arrive either), outvote a live policy it may not kill, or act faster than
``timeout_s``; the robot's own damping mode (the remote's emergency stop, Unitree's motion
switcher) covers those.
"""

from __future__ import annotations

import json
import math
import os
import signal
import time
from pathlib import Path
from typing import Any

from march.robot import dds, hg
from march.robot.signals import stop_on_signals
from march.robot.wire_checks import Limits, command_fault, damping_lowcmd
from march.sim2sim.bundle_schema import SchemaError, check_spec
from march.sim2sim.deploy_bundle import UsageError

MAX_SPEC_BYTES = 16 * 2**20


def read_spec(path: str) -> dict[str, Any]:
    """deploy.json of a bundle folder (or beside an ONNX file), schema-checked, without MuJoCo."""
    p = Path(path)
    if p.is_dir():
        found = sorted(p.glob("*.deploy.json"))
        if len(found) != 1:
            raise UsageError(f"bundle={path}: {len(found)} *.deploy.json files, expected one")
        p = found[0]
    elif p.suffix == ".onnx":
        p = p.with_suffix(".deploy.json")
    if p.is_symlink() or not p.is_file():
        raise UsageError(f"bundle={path}: no deploy.json (a regular file) at {p}")
    if p.stat().st_size > MAX_SPEC_BYTES:
        raise UsageError(f"{p}: {p.stat().st_size} bytes, too large for a deploy.json")
    try:
        spec = json.loads(p.read_text())
        check_spec(spec)
    except (ValueError, UnicodeDecodeError, RecursionError) as err:
        raise UsageError(f"{p}: {err}".splitlines()[0]) from None
    except SchemaError as err:
        raise UsageError(f"{p}: {err}") from None
    return spec


class Supervisor:
    """The watch and the takeover (no clock of its own: :func:`serve` drives it)."""

    def __init__(self, spec: dict[str, Any], timeout_s: float, policy_pid: int = 0) -> None:
        from march.sim2sim.motors import motor_table

        self.limits = Limits.from_spec(spec, motor_table(spec))
        dep = spec["deploy"]
        self.damping = damping_lowcmd(
            self.limits, float(dep["shutdown"]["damping_kd"]), int(dep["mode_pr"])
        )
        self.timeout_s, self.policy_pid = timeout_s, policy_pid
        self.last_cmd: float | None = None
        self.last_state: float | None = None
        self.seen = 0
        self.took_over: tuple[float, str] | None = None

    def command(self, cmd: Any, now: float) -> None:
        if self.took_over is not None:
            return  # its own damping comes back on the topic: no longer judged
        self.seen += 1
        self.last_cmd = now
        why = command_fault(cmd, "policy", self.limits) if isinstance(cmd, hg.LowCmd_) else None
        if why is not None:
            self.take_over(now, f"invalid LowCmd ({why})")

    def check_time(self, now: float) -> None:
        if self.took_over is None and self.last_cmd is not None:
            if now - self.last_cmd > self.timeout_s:
                gap = (now - self.last_cmd) * 1e3
                self.take_over(now, f"no LowCmd for {gap:.0f} ms")

    def take_over(self, now: float, why: str) -> None:
        if self.policy_pid > 0:
            try:
                os.kill(self.policy_pid, signal.SIGKILL)
                why += f"; killed the policy (pid {self.policy_pid})"
            except ProcessLookupError:
                pass
        self.took_over = (now, why)


def serve(
    spec: dict[str, Any],
    domain: int,
    interface: str,
    timeout_s: float,
    seconds: float = math.inf,
    policy_pid: int = 0,
) -> Supervisor:
    dp = dds.participant(domain, interface)
    dep = spec["deploy"]
    sup = Supervisor(spec, timeout_s, policy_pid)
    cmds = dds.Latest(dp, dep["lowcmd_topic"], hg.LowCmd_, qos=dds.best_effort(64))
    states = dds.Latest(dp, dep["lowstate_topic"], hg.LowState_)
    out = dds.writer(dp, dep["lowcmd_topic"], hg.LowCmd_)
    stop, _ = stop_on_signals()
    period = float(dep["deadline"]["period_s"])
    t0 = time.perf_counter()
    print(
        f"[supervisor] domain {domain}, interface {interface}: watching {dep['lowcmd_topic']} "
        f"(takeover after {timeout_s * 1e3:.0f} ms without a valid LowCmd)",
        flush=True,
    )
    next_send, sent = t0, 0
    while not stop["flag"] and time.perf_counter() - t0 < seconds:
        now = time.perf_counter()
        for msg in cmds.reader.take(N=64):
            sup.command(msg, now)
        if states.poll():
            sup.last_state = now
        sup.check_time(now)
        if sup.took_over is not None:
            if sent == 0:
                t, why = sup.took_over
                print(f"[supervisor] {t - t0:7.3f} s  takeover: {why}; damping", flush=True)
            if now >= next_send:
                out.write(sup.damping)
                sent += 1
                next_send = max(next_send + period, now)
        time.sleep(1e-3)
    sup.sent = sent
    return sup


def main(args: dict[str, Any]) -> int:
    spec = read_spec(args["bundle"])
    timeout = args.get("timeout_s", 2.0 * float(spec["deploy"]["watchdog_s"]))
    sup = serve(
        spec,
        args.get("domain", 0),
        args.get("interface", "eth0"),
        timeout,
        args.get("seconds", math.inf),
        args.get("policy_pid", 0),
    )
    state = "took over" if sup.took_over else "did not take over"
    print(f"[supervisor] done: {sup.seen} LowCmds watched, {state}, {sup.sent} damping sent")
    return 0
