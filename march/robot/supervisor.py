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
  that process (SIGKILL): a live publisher of bad commands cannot be outvoted on a topic;
- it is itself stopped (SIGINT, SIGTERM, SIGHUP: a closed terminal) while the policy runs: its
  heartbeat says it is leaving (the policy damps on it), its own damping joins once the policy's
  commands have turned gainless (or after ``timeout_s``), for ``damping_s``, before it exits.

It publishes a heartbeat (:class:`march.robot.dds.Heartbeat_`, every control period, with
``took_over``): the policy loop (``supervisor=required``, its default) does not start the policy
before one has come, and damps when it stops or says the supervisor took over.

The bundle is read through the disk gate (:mod:`march.store.bounded_read`: no link, sizes bounded
before reading, strict JSON - a key given twice is refused - the ONNX file's and each scene's
SHA-256 and each scene's inflated size) and the schema, and refused in one line as
``march.robot policy`` would refuse it.

What it cannot do (docs/deploying.md): stop a robot whose network link or DDS is down (its
commands do not arrive either), outvote a live policy it may not kill, or act faster than
``timeout_s``; the robot's own damping mode (the remote's emergency stop, Unitree's motion
switcher) covers those.
"""

from __future__ import annotations

import hashlib
import math
import os
import signal
import time
from pathlib import Path
from typing import Any

from march.robot import dds, hg
from march.robot.signals import say, stop_on_signals
from march.robot.wire_checks import Limits, command_fault, damping_lowcmd
from march.sim2sim.bundle_files import scene_bytes
from march.sim2sim.bundle_schema import SchemaError, UsageError, check_spec
from march.sim2sim.motors import MotorTableError, motor_table
from march.store.bounded_read import (
    MAX_ONNX_BYTES,
    MAX_SPEC_BYTES,
    FileRefused,
    parse_json_strict,
    read_in_folder,
)


def _deploy_json(path: str) -> tuple[Path, str]:
    """(folder, file name) of the bundle's deploy.json: ``bundle=<dir>`` or ``<file>.onnx``."""
    p = Path(path)
    if p.is_dir():
        found = sorted(p.glob("*.deploy.json"))
        if len(found) != 1:
            raise UsageError(f"bundle={path}: {len(found)} *.deploy.json files, expected one")
        p = found[0]
    elif p.suffix == ".onnx":
        p = p.with_suffix(".deploy.json")
    return p.parent, p.name


def read_spec(path: str, files: bool = True) -> dict[str, Any]:
    """deploy.json of a bundle folder (or beside an ONNX file) through the disk gate and the
    schema, without MuJoCo; with ``files``, the ONNX file and every scene too (their SHA-256,
    each scene's inflated size bounded): one :class:`UsageError` line at the first fault."""
    folder, name = _deploy_json(path)
    label = str(folder / name)
    try:
        spec = parse_json_strict(read_in_folder(folder, name, "deploy.json", MAX_SPEC_BYTES), label)
        if not isinstance(spec, dict):
            raise UsageError(f"{label}: not a JSON object")
        check_spec(spec)
        motor_table(spec)
        if files:
            _check_files(folder, spec)
    except (FileRefused, MotorTableError) as err:
        raise UsageError(str(err).splitlines()[0]) from None
    except SchemaError as err:
        raise UsageError(f"{label}: {err}") from None
    return spec


def _check_files(folder: Path, spec: dict[str, Any]) -> None:
    """The files the bundle names, as :class:`march.sim2sim.deploy_bundle.Bundle` checks them:
    the ONNX file's SHA-256, each scene's SHA-256 and its inflated size (bounded while it
    inflates: a gzip bomb is refused at the bound, never held whole)."""
    data = read_in_folder(folder, spec["onnx"]["file"], "ONNX file", MAX_ONNX_BYTES)
    if hashlib.sha256(data).hexdigest() != spec["onnx"]["sha256"]:
        raise FileRefused(f"{folder / spec['onnx']['file']}: its SHA-256 differs from the record")
    del data
    for course, entry in spec["courses"].items():
        scene_bytes(folder, course, entry)


class Supervisor:
    """The watch and the takeover (no clock of its own: :func:`serve` drives it)."""

    def __init__(self, spec: dict[str, Any], timeout_s: float, policy_pid: int = 0) -> None:
        self.limits = Limits.from_spec(spec, motor_table(spec))
        dep = spec["deploy"]
        self.damping = damping_lowcmd(
            self.limits, float(dep["shutdown"]["damping_kd"]), int(dep["mode_pr"])
        )
        self.damping_s = float(dep["shutdown"]["damping_s"])
        self.timeout_s, self.policy_pid = timeout_s, policy_pid
        self.last_cmd: float | None = None
        self.last_state: float | None = None
        self.seen = 0
        self.took_over: tuple[float, str] | None = None
        self.policy_gainless = False  # the newest LowCmd has kp 0 on every joint (damping)

    def command(self, cmd: Any, now: float) -> None:
        if self.took_over is not None:
            return  # its own damping comes back on the topic: no longer judged
        self.seen += 1
        self.last_cmd = now
        if isinstance(cmd, hg.LowCmd_):
            self.policy_gainless = all(cmd.motor_cmd[int(s)].kp == 0 for s in self.limits.slots)
        why = command_fault(cmd, "policy", self.limits) if isinstance(cmd, hg.LowCmd_) else None
        if why is not None:
            self.take_over(now, f"invalid LowCmd ({why})")

    def check_time(self, now: float) -> None:
        if self.took_over is None and self.last_cmd is not None:
            if now - self.last_cmd > self.timeout_s:
                gap = (now - self.last_cmd) * 1e3
                self.take_over(now, f"no LowCmd for {gap:.0f} ms")

    def policy_live(self, now: float) -> bool:
        """A policy has sent a LowCmd within ``timeout_s`` and the supervisor has not taken over."""
        return (
            self.took_over is None
            and self.last_cmd is not None
            and now - self.last_cmd <= self.timeout_s
        )

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
    beat_out = dds.writer(dp, dds.SUPERVISOR_TOPIC, dds.Heartbeat_)
    stop, _ = stop_on_signals()
    period = float(dep["deadline"]["period_s"])
    t0 = time.perf_counter()
    say(
        f"[supervisor] domain {domain}, interface {interface}: watching {dep['lowcmd_topic']} "
        f"(takeover after {timeout_s * 1e3:.0f} ms without a valid LowCmd)"
    )
    next_send, next_beat, sent, seq, leave_at = t0, t0, 0, 0, math.inf
    handing: float | None = None
    while time.perf_counter() - t0 < seconds and time.perf_counter() < leave_at:
        now = time.perf_counter()
        for msg in cmds.reader.take(N=64):
            sup.command(msg, now)
        if states.poll():
            sup.last_state = now
        sup.check_time(now)
        if stop["flag"] and leave_at == math.inf and handing is None:
            # Stopped (a closed terminal included) while a policy runs: damp before leaving.
            # The heartbeat says so first, and the supervisor's own damping joins once the
            # policy's commands have turned to damping (or timeout_s passed): two publishers,
            # and no policy command with gains lands after the first damping one.
            if sup.policy_live(now):
                handing, next_beat = now, now
            else:
                leave_at = now
        if handing is not None and sup.took_over is None:
            if sup.policy_gainless or now - handing > sup.timeout_s:
                sup.take_over(now, f"{stop['signal']} while the policy ran")
                leave_at = now + sup.damping_s
        if sup.took_over is not None:
            if sent == 0:
                t, why = sup.took_over
                say(f"[supervisor] {t - t0:7.3f} s  takeover: {why}; damping")
            if now >= next_send:
                out.write(sup.damping)
                sent += 1
                next_send = max(next_send + period, now)
        if now >= next_beat:
            seq += 1
            leaving = sup.took_over is not None or handing is not None
            beat_out.write(dds.Heartbeat_(os.getpid(), seq % 2**32, int(leaving)))
            next_beat = max(next_beat + period, now)
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
    say(f"[supervisor] done: {sup.seen} LowCmds watched, {state}, {sup.sent} damping sent")
    return 0
