"""The supervisor outlives the policy: killed, the policy's place is taken by damping within
``timeout_s`` + one control period; invalid commands get the policy killed and damped; the
supervisor gone (SIGKILL) or closed (SIGHUP) damps the policy too; the MuJoCo robot's own LowCmd
timeout. The supervisor starts without torch, onnxruntime or MuJoCo and reads the bundle through
the disk gate (a key given twice, a gzip-bomb scene, a joint range wider than the G1's: one line).

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
from robot_wire import changed_lowcmd, hold_lowcmd, is_damping, until

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


def test_the_supervisor_imports_no_torch_nor_onnxruntime_nor_mujoco(bundle):
    """Imported, and with a bundle read and its supervisor built (the scenes' checks included)."""
    code = (
        "import sys; import march.robot.robot_command, march.robot.camera; "
        "from march.robot.supervisor import Supervisor, read_spec; "
        f"Supervisor(read_spec({str(bundle.parent)!r}), 0.1); "
        "print(sorted(m for m in ('torch', 'onnxruntime', 'mujoco', 'mjlab', 'warp') "
        "if m in sys.modules))"
    )
    res = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert res.stdout.strip() == "[]", res.stdout + res.stderr


def _start_three(bundle, domain: int, log, procs: list) -> tuple:
    """Start sim (logging to ``log``), supervisor and policy on ``domain``, each appended to
    ``procs`` as it starts (the caller stops them); returns (sim, supervisor, policy, the
    policy's output up to its policy state)."""
    common = [f"bundle={bundle.parent}", f"domain={domain}", "interface=lo"]
    sim = _start("sim", *common, "band=100", f"log={log}")
    procs.append(sim)
    assert "[sim] publishing" in sim.stdout.readline()
    sup = _start("supervisor", *common)
    procs.append(sup)
    assert "[supervisor]" in sup.stdout.readline()
    fast = [f"{k}={v}" for k, v in FAST.items()]
    loop = _start("policy", *common, "start=auto", "guard=report", "deadlines=report", *fast)
    procs.append(loop)
    return sim, sup, loop, until(loop, "hold -> policy")


def test_a_killed_policy_is_replaced_by_damping(bundle, tmp_path):
    log = tmp_path / "sim.npz"
    procs = []
    try:
        sim, sup, loop, head = _start_three(bundle, DOMAIN, log, procs)
        time.sleep(0.5)
        loop.kill()  # SIGKILL: no damping of its own
        loop.wait()
        took = until(sup, "takeover", timeout=10)
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
    damp_kd = float(spec["deploy"]["shutdown"]["damping_kd"])
    assert not kp[after].any() and np.allclose(kd[after], damp_kd)  # only damping after the kill
    dt = float(spec["rates"]["physics_dt_s"])
    gap = (cmd_ticks[after[0]] - cmd_ticks[last_policy]) * dt
    timeout = 2 * float(spec["deploy"]["watchdog_s"])
    period = float(spec["deploy"]["deadline"]["period_s"])
    print(f"last policy command -> first supervisor damping: {gap * 1e3:.0f} ms of robot time")
    # What it promises (docs/deploying.md): the takeover after timeout_s without a LowCmd, its
    # first damping within one control period of that (it polls every millisecond)
    assert timeout - period <= gap <= timeout + period, gap
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
        good = hold_lowcmd(spec)
        for _ in range(25):
            w.write(good)
            time.sleep(0.02)
        w.write(changed_lowcmd(good, int(slots[3]), q=float("nan")))
        took = until(sup, "takeover", timeout=10)
        assert dummy.wait(timeout=10) == -signal.SIGKILL
        seen = []
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            seen += [m for m in r.reader.take(N=64) if isinstance(m, hg.LowCmd_)]
            time.sleep(0.01)
        kd = float(spec["deploy"]["shutdown"]["damping_kd"])
        damping = [m for m in seen if is_damping(m, slots, kd)]
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

    spec = Bundle.load(bundle).spec
    domain = DOMAIN + 2
    sim = _start(
        "sim", f"bundle={bundle.parent}", f"domain={domain}", "interface=lo", "band=100",
        "cmd_timeout=0.1",
    )  # fmt: skip
    try:
        assert "[sim] publishing" in sim.stdout.readline()
        dp = dds.participant(domain, "lo")
        w = dds.writer(dp, "rt/lowcmd", hg.LowCmd_)
        cmd = hold_lowcmd(spec)
        for _ in range(20):
            w.write(cmd)
            time.sleep(0.02)
        line = until(sim, "no valid LowCmd", timeout=10)
        (out,) = _stop([sim])
    finally:
        if sim.poll() is None:
            sim.kill()
            sim.wait()
    assert "no valid LowCmd for 0.1 s: motors damping" in line
    assert "timeouts 1" in out, out


def _three(bundle, tmp_path, domain: int, fault: str) -> dict:
    """sim, supervisor and policy (supervisor=required, its default); ``fault`` planted 0.5 s
    into the policy state: ``sup_kill`` (SIGKILL to the supervisor), ``sup_hup`` (SIGHUP to the
    supervisor), ``loop_hup`` (SIGHUP to the loop). Returns the outputs, exit codes and the
    robot's log of applied commands."""
    log = tmp_path / f"sim_{fault}.npz"
    procs = []
    try:
        sim, sup, loop, head = _start_three(bundle, domain, log, procs)
        time.sleep(0.5)
        target = {"sup_kill": sup, "sup_hup": sup, "loop_hup": loop}[fault]
        target.send_signal(signal.SIGKILL if fault == "sup_kill" else signal.SIGHUP)
        loop_out, _ = loop.communicate(timeout=60)
        time.sleep(0.5)  # the supervisor's takeover after the loop's end, when it lives
        sim_out, sup_out = _stop([sim, sup])
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    data = np.load(log)
    return {
        "loop": head + loop_out,
        "loop_rc": loop.returncode,
        "sup": sup_out,
        "sup_rc": sup.returncode,
        "sim": sim_out,
        "cmds": data["cmds"],
    }


def _gains_after_damping(bundle, cmds) -> tuple[int, int]:
    """(commands with kp > 0 after the robot's first damping command, damping commands)."""
    from march.sim2sim.deploy_bundle import Bundle
    from march.sim2sim.motors import motor_table

    spec = Bundle.load(bundle).spec
    slots = motor_table(spec)
    kp, kd = cmds[:, 1][:, slots], cmds[:, 2][:, slots]
    kd_damp = float(spec["deploy"]["shutdown"]["damping_kd"])
    damp = np.flatnonzero(~kp.any(axis=1) & np.isclose(kd, kd_damp).all(axis=1))
    gains = np.flatnonzero(kp.any(axis=1))
    assert len(gains) > 20  # ramp, hold and policy reached the robot
    if not len(damp):
        return 0, 0
    return int((gains > damp[0]).sum()), len(damp)


@pytest.mark.parametrize("fault", ["sup_kill", "sup_hup", "loop_hup"])
def test_a_supervisor_gone_or_a_closed_terminal_damps(bundle, tmp_path, fault):
    """The supervisor SIGKILLed: the policy damps ("supervisor gone") and exits 1. SIGHUP to the
    supervisor (its terminal closed): it damps for damping_s, its heartbeat says so, the policy
    damps too. SIGHUP to the loop: the loop damps (exit 1, SIGHUP named), then the supervisor
    takes over. In each: no command with kp > 0 reaches the robot after its first damping one."""
    domain = DOMAIN + 3 + ["sup_kill", "sup_hup", "loop_hup"].index(fault)
    r = _three(bundle, tmp_path, domain, fault)
    print(r["loop"] + r["sup"] + r["sim"])
    want = {
        "sup_kill": "policy -> damping  (supervisor gone: no heartbeat for",
        "sup_hup": "policy -> damping  (supervisor: it took over or is stopping",
        "loop_hup": "policy -> damping  (SIGHUP: the terminal closed",
    }[fault]
    assert want in r["loop"] and "damping -> done" in r["loop"], r["loop"]
    assert r["loop_rc"] == 1
    if fault == "sup_hup":
        assert "takeover: SIGHUP while the policy ran; damping" in r["sup"], r["sup"]
        assert r["sup_rc"] == 0  # it handled the signal: damped, then left
    if fault == "loop_hup":
        assert "takeover: no LowCmd for" in r["sup"], r["sup"]
    gained, damped = _gains_after_damping(bundle, r["cmds"])
    assert damped > 10 and gained == 0, (gained, damped)


def test_the_policy_waits_in_hold_for_the_supervisor(bundle):
    """supervisor=required (the default) and none running: the policy never starts."""
    common = [f"bundle={bundle.parent}", f"domain={DOMAIN + 7}", "interface=lo"]
    sim = _start("sim", *common, "band=100")
    loop = None
    try:
        assert "[sim] publishing" in sim.stdout.readline()
        fast = [f"{k}={v}" for k, v in FAST.items()]
        loop = _start("policy", *common, "start=auto", "guard=report", "deadlines=report", *fast)
        head = until(loop, "waiting for the supervisor's heartbeat")
        time.sleep(1.0)
        (out,) = _stop([loop])
        _stop([sim])
    finally:
        for p in (sim, loop):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait()
    assert "ramp -> hold" in head and "hold -> policy" not in head + out, head + out
    assert "hold -> damping  (stop requested)" in out, out


# ---------------------------------------------------------------------------------------------
# The bundle through the gate: one line, exit 2, quickly and in little memory.


def _copy_bundle(bundle: Path, dest: Path) -> Path:
    import shutil

    shutil.copytree(bundle.parent, dest)
    return dest


def _refused(*words: str) -> tuple[subprocess.CompletedProcess, float, float]:
    """``python -m march.robot <words>``: the result, its wall seconds and peak resident MB."""
    code = (
        "import resource, subprocess, sys, time; t = time.perf_counter(); "
        "r = subprocess.run([sys.executable, '-m', 'march.robot', *sys.argv[1:]], "
        "capture_output=True, text=True, timeout=60); "
        "print(r.returncode, time.perf_counter() - t, "
        "resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024); "
        "sys.stderr.write(r.stderr)"
    )
    res = subprocess.run(
        [sys.executable, "-c", code, *words], cwd=ROOT, capture_output=True, text=True, timeout=90
    )
    assert len(res.stdout.split()) == 3, res.stdout + res.stderr[-2000:]
    rc, wall, mb = res.stdout.split()
    res.returncode = int(rc)
    return res, float(wall), float(mb)


def test_a_bad_bundle_is_one_line_from_the_supervisor(bundle, tmp_path):
    """A key given twice in deploy.json, a hardware scene that is a gzip bomb (its SHA-256
    recorded, so that only the inflation can refuse it), a default pose outside the G1's joint
    range with the bundle's own pos_limits widened to allow it: each one line, exit 2, within
    10 s and 200 MB resident, from the supervisor (and the camera's reader, the same)."""
    import gzip
    import hashlib
    import json

    dup = _copy_bundle(bundle, tmp_path / "dup")
    spec_path = dup / "student.deploy.json"
    text = spec_path.read_text()
    doubled = text.replace('"format": 3,', '"format": 3, "format": 3,', 1)
    assert doubled != text
    spec_path.write_text(doubled)
    assert json.loads(doubled)["format"] == 3  # loose JSON takes it
    bomb = _copy_bundle(bundle, tmp_path / "bomb")
    spec = json.loads((bomb / "student.deploy.json").read_text())
    scene = bomb / spec["courses"]["hardware"]["scene"]
    with gzip.open(scene, "wb", compresslevel=1) as f:
        zeros = bytes(1 << 24)
        for _ in range(64):  # 1 GiB of zeros, ~1 MB packed
            f.write(zeros)
    spec["courses"]["hardware"]["sha256"] = hashlib.sha256(scene.read_bytes()).hexdigest()
    (bomb / "student.deploy.json").write_text(json.dumps(spec))
    wide = _copy_bundle(bundle, tmp_path / "wide")
    spec = json.loads((wide / "student.deploy.json").read_text())
    spec["joints"][0]["pos_limits"] = [-20.0, 20.0]
    spec["joints"][0]["default_pos"] = 10.0
    spec["robot"]["default_joint_pos"][0] = 10.0
    spec["action"]["offset"][0] = 10.0
    (wide / "student.deploy.json").write_text(json.dumps(spec))
    cases = {
        dup: "the key 'format' is given twice",
        bomb: "inflates to more than",
        wide: "wider than the G1's joint range",
    }
    for folder, words in cases.items():
        res, wall, mb = _refused("supervisor", f"bundle={folder}", "domain=9", "interface=lo")
        lines = res.stderr.strip().splitlines()
        print(folder.name, res.returncode, f"{wall:.1f} s", f"{mb:.0f} MB", lines)
        assert res.returncode == 2 and len(lines) == 1 and words in lines[0], res.stderr
        assert lines[0].startswith("error: ") and wall < 10 and mb < 200
    from march.sim2sim.deploy_bundle import Bundle, UsageError

    with pytest.raises(UsageError, match="wider than the G1's joint range"):
        Bundle.load(wide / "student.onnx")
