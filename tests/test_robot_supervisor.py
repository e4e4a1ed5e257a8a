"""The supervisor outlives the policy: killed, the policy's place is taken by damping; invalid
commands get the policy killed and damped; the MuJoCo robot's own LowCmd timeout.

Processes on DDS (``lo``, a domain of this session's own): ``python -m march.robot sim`` in real
time (its log: every command applied, by physics tick), ``policy`` and ``supervisor``.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
pytestmark = pytest.mark.sim
DOMAIN = 20 + (os.getpid() + 57) % 200
FAST = {"zero_torque_s": 0.2, "ramp_s": 0.5, "hold_s": 0.2, "damping_s": 0.3}


def _start(*words: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "march.robot", *words],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def _until(proc: subprocess.Popen, text: str, timeout: float = 60.0) -> str:
    """Lines of ``proc`` up to the one holding ``text``; fails after ``timeout`` even when the
    process prints nothing (a select on its pipe, not a blocking read)."""
    import select

    seen, end = [], time.monotonic() + timeout
    while time.monotonic() < end:
        ready, _, _ = select.select([proc.stdout], [], [], max(0.0, end - time.monotonic()))
        if not ready:
            break
        line = proc.stdout.readline()
        if not line:
            break
        seen.append(line)
        if text in line:
            return "".join(seen)
    raise AssertionError(f"no {text!r} in: {''.join(seen)}")


def _stop(procs):
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
    outs = []
    for p in procs:
        try:
            out, _ = p.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            p.kill()
            out, _ = p.communicate()
        outs.append(out)
    return outs


def test_the_supervisor_imports_no_torch_nor_onnxruntime():
    code = (
        "import sys; import march.robot.robot_command, march.robot.supervisor, "
        "march.robot.camera; "
        "print(sorted(m for m in ('torch', 'onnxruntime', 'mjlab', 'warp') if m in sys.modules))"
    )
    res = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert res.stdout.strip() == "[]", res.stdout + res.stderr


def test_a_killed_policy_is_replaced_by_damping(bundle, tmp_path):
    common = [f"bundle={bundle.parent}", f"domain={DOMAIN}", "interface=lo"]
    log = tmp_path / "sim.npz"
    procs = []
    try:
        sim = _start("sim", *common, "band=100", f"log={log}")
        procs.append(sim)
        assert "[sim] publishing" in sim.stdout.readline()
        sup = _start("supervisor", *common)
        procs.append(sup)
        assert "[supervisor]" in sup.stdout.readline()
        fast = [f"{k}={v}" for k, v in FAST.items()]
        loop = _start("policy", *common, "start=auto", "guard=report", "deadlines=report", *fast)
        procs.append(loop)
        head = _until(loop, "hold -> policy")
        time.sleep(0.5)
        loop.kill()  # SIGKILL: no damping of its own
        loop.wait()
        took = _until(sup, "takeover", timeout=10)
        time.sleep(1.0)
        sim_out, sup_out, _ = _stop([sim, sup, loop])
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    print(head + took + sup_out + sim_out)
    assert "takeover: no LowCmd for" in took
    data = np.load(log)
    ticks, cmds = data["ticks"], data["cmds"]
    cmd_ticks = data["cmd_ticks"]
    from march.sim2sim.deploy_bundle import Bundle
    from march.sim2sim.motors import motor_table

    spec = Bundle.load(bundle).spec
    slots = motor_table(spec)
    kp = cmds[:, 1][:, slots]
    kd = cmds[:, 2][:, slots]
    gains = np.flatnonzero(kp.any(axis=1))
    assert len(gains) > 20  # ramp, hold and policy reached the robot
    last_policy = gains[-1]
    after = np.arange(last_policy + 1, len(cmd_ticks))
    assert len(after) > 20, "the supervisor's damping did not reach the robot"
    assert not kp[after].any() and np.allclose(kd[after], 8.0)  # only damping after the kill
    dt = float(spec["rates"]["physics_dt_s"])
    gap = (cmd_ticks[after[0]] - cmd_ticks[last_policy]) * dt
    timeout = 2 * float(spec["deploy"]["watchdog_s"])
    print(f"last policy command -> first supervisor damping: {gap * 1e3:.0f} ms of robot time")
    assert gap < timeout + 0.2
    assert ticks[-1] > cmd_ticks[after[-1]] - 1


def test_invalid_commands_get_the_policy_killed_and_damped(bundle):
    from march.robot import dds, hg
    from march.sim2sim.deploy_bundle import Bundle
    from march.sim2sim.motors import motor_table

    spec = Bundle.load(bundle).spec
    slots = motor_table(spec)
    dummy = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    domain = DOMAIN + 1
    sup = _start(
        "supervisor", f"bundle={bundle.parent}", f"domain={domain}", "interface=lo",
        f"policy_pid={dummy.pid}",
    )  # fmt: skip
    try:
        assert "[supervisor]" in sup.stdout.readline()
        dp = dds.participant(domain, "lo")
        w = dds.writer(dp, "rt/lowcmd", hg.LowCmd_)
        r = dds.Latest(dp, "rt/lowcmd", hg.LowCmd_, qos=dds.best_effort(64))
        good = hg.LowCmd_(mode_machine=int(spec["deploy"]["mode_machine"]))
        for i, s in enumerate(slots):
            m = good.motor_cmd[int(s)]
            m.mode, m.q, m.kp, m.kd = 1, float(spec["robot"]["default_joint_pos"][i]), 40.0, 2.0
        good.crc = hg.lowcmd_crc(good)
        for _ in range(25):
            w.write(good)
            time.sleep(0.02)
        bad = hg.LowCmd_(mode_machine=good.mode_machine, motor_cmd=good.motor_cmd)
        bad.motor_cmd[int(slots[3])].q = float("nan")
        bad.crc = hg.lowcmd_crc(bad)
        w.write(bad)
        took = _until(sup, "takeover", timeout=10)
        assert dummy.wait(timeout=10) == -signal.SIGKILL
        seen = []
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            seen += [m for m in r.reader.take(N=64) if isinstance(m, hg.LowCmd_)]
            time.sleep(0.01)
        damping = [
            m for m in seen
            if all(m.motor_cmd[int(s)].kp == 0 and m.motor_cmd[int(s)].kd == 8.0 for s in slots)
        ]  # fmt: skip
        assert len(damping) >= 20, len(damping)  # ~50 Hz for a second
        assert "invalid LowCmd (command: slot" in took and "not finite" in took, took
        assert f"killed the policy (pid {dummy.pid})" in took
    finally:
        _stop([sup])
        if dummy.poll() is None:
            dummy.kill()


def test_the_simulated_robot_damps_after_its_lowcmd_timeout(bundle):
    from march.robot import dds, hg
    from march.sim2sim.deploy_bundle import Bundle
    from march.sim2sim.motors import motor_table

    spec = Bundle.load(bundle).spec
    slots = motor_table(spec)
    domain = DOMAIN + 2
    sim = _start(
        "sim", f"bundle={bundle.parent}", f"domain={domain}", "interface=lo", "band=100",
        "cmd_timeout=0.1",
    )  # fmt: skip
    try:
        assert "[sim] publishing" in sim.stdout.readline()
        dp = dds.participant(domain, "lo")
        w = dds.writer(dp, "rt/lowcmd", hg.LowCmd_)
        cmd = hg.LowCmd_(mode_machine=int(spec["deploy"]["mode_machine"]))
        for i, s in enumerate(slots):
            m = cmd.motor_cmd[int(s)]
            m.mode, m.q, m.kp, m.kd = 1, float(spec["robot"]["default_joint_pos"][i]), 40.0, 2.0
        cmd.crc = hg.lowcmd_crc(cmd)
        for _ in range(20):
            w.write(cmd)
            time.sleep(0.02)
        line = _until(sim, "no valid LowCmd", timeout=10)
        (out,) = _stop([sim])
    finally:
        if sim.poll() is None:
            sim.kill()
            sim.wait()
    assert "no valid LowCmd for 0.1 s: motors damping" in line
    assert "timeouts 1" in out, out
