"""The robot loop end to end: in-process against the MuJoCo robot, then over DDS on loopback.

In-process (no DDS): :class:`Controller` drives :class:`SimRobot` in lockstep through the
start-up - the commands of every state by hand (zero torque: kp = kd = 0; ramp to the default
pose, which the robot on its band reaches; hold; the policy's targets; damping kd 1), each at
its motor slot (``motor_index``; a permuted table moves them), each with a valid CRC that the
robot checks (a corrupted one is dropped), and a LowState of another hardware variant damps.

Over DDS (two processes, domain 1, ``lo``): ``python -m march.robot selftest`` for a few
seconds (agreement with in-process sim2sim, exit 0), the same with ``guard=damp`` (the smoke
student's out-of-range proprioception damps it), a perturbed action caught by the comparison,
the watchdog (the robot process killed mid-policy) and Ctrl-C (SIGINT to the loop).
"""

from __future__ import annotations

import copy
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from robot_wire import until

ROOT = Path(__file__).resolve().parent.parent
pytestmark = pytest.mark.sim
FAST = {"zero_torque_s": 0.1, "ramp_s": 0.4, "hold_s": 0.1, "damping_s": 0.2}
DOMAIN = 20 + os.getpid() % 200
"""A DDS domain of this test session's own (another session's robots stay on theirs)."""


@pytest.fixture(scope="module")
def loaded(bundle):
    from march.sim2sim.deploy_bundle import Bundle

    return Bundle.load(bundle)


def _drive(b, steps: int, stop_at: float, variant_at: float = np.inf):
    from march.robot.policy_loop import Controller
    from march.robot.sim_robot import SimRobot
    from march.robot.states import Timing

    robot = SimRobot(b, band_s=100.0)
    ctl = Controller(b, Timing.from_spec(b.spec["deploy"], **FAST), guard_action="report")
    dt = float(b.spec["rates"]["control_dt_s"])
    out = []
    for k in range(steps):
        ls = robot.lowstate()
        if k * dt >= variant_at:
            ls.mode_machine = 4
        depth = (robot.sim.camera.planar(robot.model, robot.data), robot.tick)
        cmd = ctl.step(ls, 0.0, depth, k * dt, start=True, stop=k * dt >= stop_at)
        assert robot.apply(cmd)
        for _ in range(robot.decimation):
            robot.physics_step()
        out.append((ctl.machine.state, cmd, robot.bus.q(robot.data)))
    return robot, ctl, out


def _slots(cmd, field):
    return np.array([getattr(m, field) for m in cmd.motor_cmd])


def test_every_state_commands_what_it_should_at_the_right_slots(loaded):
    from march.robot import hg

    b = loaded
    robot, ctl, out = _drive(b, 60, stop_at=0.9)
    idx = ctl.motor_index
    default, kp = ctl.default, ctl.kp
    seen = [s for s, _, _ in out]
    assert seen[0] == "zero_torque" and "ramp" in seen and "hold" in seen and "policy" in seen
    assert seen[-1] in ("damping", "done") and "done" in seen
    for state, cmd, _q in out:
        assert hg.lowcmd_crc(cmd) == cmd.crc and cmd.mode_machine == 5 and cmd.mode_pr == 0
        mode = _slots(cmd, "mode")
        assert (mode[idx] == 1).all() and not mode[29:].any()
        k, d, target = _slots(cmd, "kp")[idx], _slots(cmd, "kd")[idx], _slots(cmd, "q")[idx]
        if state == "zero_torque":
            assert not k.any() and not d.any()
        elif state == "hold":
            np.testing.assert_allclose(target, default, atol=1e-6)
            np.testing.assert_allclose(k, kp, rtol=1e-6)
        elif state in ("damping", "done"):
            assert not k.any() and (d == ctl.timing.damping_kd).all()
    last_hold = [q for st, _, q in out if st == "hold"][-1]
    # the ramp brought it there (within the PD's sag under the robot's weight on its feet)
    assert np.abs(last_hold[idx] - default).max() < 0.2
    # the ramp: from the pose measured when it began to the default pose, linearly in time
    k0 = seen.index("ramp")
    n = seen.count("ramp")
    first = _slots(out[k0][1], "q")[idx]
    np.testing.assert_allclose(first, ctl.ramp_from, atol=1e-6)  # elapsed 0 at its first step
    np.testing.assert_allclose(ctl.ramp_from, out[k0 - 1][2][idx], atol=1e-6)  # measured q
    for j in range(n):
        a = min(j * float(b.spec["rates"]["control_dt_s"]) / FAST["ramp_s"], 1.0)
        want = ctl.ramp_from + a * (default - ctl.ramp_from)
        np.testing.assert_allclose(_slots(out[k0 + j][1], "q")[idx], want, atol=1e-5)
    policy = [(c, s) for (st, c, _), s in zip(out, ctl.log, strict=True) if st == "policy"]
    assert policy
    for cmd, step in policy:
        want = ctl.offset + ctl.scale * step.action
        np.testing.assert_allclose(_slots(cmd, "q")[idx], want, atol=1e-5)  # float32 message
    bad = copy.deepcopy(out[-1][1])
    bad.crc ^= 1
    assert not robot.apply(bad) and robot.dropped["crc"] == 1
    reasons = [w for _, _, b2, w in ctl.machine.transitions if b2 == "damping"]
    assert reasons == ["stop requested"]


def test_a_permuted_motor_table_moves_the_commands(loaded):
    from march.robot.policy_loop import Controller
    from march.robot.states import HOLD, Timing
    from march.sim2sim.deploy_bundle import Bundle

    spec = copy.deepcopy(loaded.spec)
    a, b = spec["joints"][3]["motor_index"], spec["joints"][9]["motor_index"]
    spec["joints"][3]["motor_index"], spec["joints"][9]["motor_index"] = b, a
    ctl = Controller(Bundle(loaded.onnx_path, spec), Timing.from_spec(spec["deploy"]))
    from march.robot.states import MotorCommand

    cmd = ctl.lowcmd(MotorCommand(ctl.default, ctl.kp, ctl.kd))
    assert HOLD and cmd.motor_cmd[b].q == pytest.approx(ctl.default[3], abs=1e-6)
    assert cmd.motor_cmd[a].q == pytest.approx(ctl.default[9], abs=1e-6)


def test_a_lowstate_of_another_variant_damps(loaded):
    _, ctl, out = _drive(loaded, 40, stop_at=np.inf, variant_at=0.5)
    reasons = [w for _, _, b, w in ctl.machine.transitions if b == "damping"]
    assert len(reasons) == 1 and "mode_machine" in reasons[0]


# ---------------------------------------------------------------------------------------------
# Over DDS on loopback.


def _robot(*words: str, **kw) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "march.robot", *words],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=240,
        **kw,
    )


# The self-tests run the policy loop against the simulated robot in real time (50 Hz, a 2 s
# LowState watchdog): on 2 cores under the default suite's two xdist workers the loop can miss
# 100 deadlines in a row and its watchdog damps first (seen in a random-order run). They run in
# `make robot-check`, one process at a time, with the fault matrix.
REAL_TIME = pytest.mark.slow


@REAL_TIME
def test_selftest_agrees_with_sim2sim(bundle, tmp_path):
    res = _robot(
        "selftest", f"bundle={bundle.parent}", "seconds=2", f"keep={tmp_path}", f"domain={DOMAIN}"
    )
    print(res.stdout)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "-> OK" in res.stdout and "missed deadlines:" in res.stdout
    assert "hold -> policy" in res.stdout and "damping -> done" in res.stdout
    line = next(ln for ln in res.stdout.splitlines() if ln.startswith("agreement"))
    # ~100 policy steps; fewer where a loaded machine spends the deadline budget (damping)
    assert int(line.split()[1]) >= 10
    # the comparison itself: one action changed by 1e-4 in the loop's log is a disagreement
    from march.robot.selftest import report, shadow
    from march.sim2sim.deploy_bundle import Bundle

    log = json.loads((tmp_path / "loop.json").read_text())
    states = dict(np.load(tmp_path / "sim.npz"))
    b = Bundle.load(bundle)
    honest = shadow(b, "hardware", log, states)
    assert honest["max_abs_diff"] <= 5e-6
    k = next(i for i, s in enumerate(log["steps"]) if s["state"] == "policy") + 20
    log["steps"][k]["action"][7] += 1e-4
    bad = shadow(b, "hardware", log, states)
    assert bad["max_abs_diff"] >= 1e-4 - 1e-6
    assert report(bad, log, "", 1.0, 2.0, 1, "lo") == 1
    # what reached the motors: the honest run's targets and gains agree with sim2sim's ...
    assert honest["commands_compared"] >= 10
    assert honest["target_diff"] <= 2e-5 and honest["gain_diff"] <= 1e-6
    # ... and a loop that logs its action but sends it clipped fails. This student's actions
    # stay inside +-0.46, where a +-1 clip changes nothing (no comparison can see it), so the
    # clip is at half the largest |action| it produced
    from march.robot.selftest import motor_commands
    from march.sim2sim.motors import motor_table

    acts = np.array([s["action"] for s in log["steps"] if s["action"] is not None])
    limit = 0.5 * np.abs(acts).max()
    spec, slots = b.spec, motor_table(b.spec)
    off, sc = np.asarray(spec["action"]["offset"]), np.asarray(spec["action"]["scale"])
    at = {int(t): i for i, t in enumerate(states["cmd_ticks"])}
    clipped = dict(states, cmds=states["cmds"].copy())
    for s in log["steps"]:
        if s["action"] is not None and s["state"] == "policy" and s["lowstate_tick"] in at:
            a = np.clip(np.asarray(s["action"]), -limit, limit)
            clipped["cmds"][at[s["lowstate_tick"]]][0][slots] = off + sc * a
    actions = [np.asarray(s["action"]) for s in log["steps"] if s["action"] is not None]
    seen = motor_commands(b, log, clipped, actions)
    assert seen["target_diff"] > 1e-3, seen
    assert report({**honest, **seen}, log, "", 1.0, 2.0, 1, "lo") == 1
    # and kp sent twice the table's at one joint of one policy step
    raised = dict(states, cmds=states["cmds"].copy())
    k = at[next(s["lowstate_tick"] for s in log["steps"] if s["state"] == "policy")]
    raised["cmds"][k][1][slots[0]] *= 2.0
    assert motor_commands(b, log, raised, actions)["gain_diff"] > 0.3


@REAL_TIME
def test_selftest_with_the_guard_on_damps_the_smoke_student(bundle):
    res = _robot(
        "selftest", f"bundle={bundle.parent}", "seconds=2", "guard=damp", f"domain={DOMAIN + 1}"
    )
    assert "policy -> damping  (guard:" in res.stdout, res.stdout + res.stderr
    assert res.returncode == 0 and "-> OK" in res.stdout


def _start(*words: str, stderr=subprocess.STDOUT) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "march.robot", *words],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=stderr,
        text=True,
    )


def test_watchdog_and_ctrl_c_over_dds(bundle):
    fast = [f"{k}={v}" for k, v in FAST.items()]
    common = [f"bundle={bundle.parent}", f"domain={DOMAIN + 2}", "interface=lo"]
    procs: list[subprocess.Popen] = []

    def start(*words: str) -> subprocess.Popen:
        procs.append(_start(*words))
        return procs[-1]

    try:
        # the watchdog: the robot dies while the policy runs
        sim = start("sim", *common, "band=100", "lockstep=true")
        assert "[sim] publishing" in sim.stdout.readline()
        loop = _start("policy", *common, "start=auto", "guard=report", "deadlines=report", *fast,
                      "supervisor=none", stderr=subprocess.PIPE)  # fmt: skip
        procs.append(loop)
        head = until(loop, "hold -> policy")
        time.sleep(0.3)
        sim.kill()
        sim.wait()
        out, err = loop.communicate(timeout=60)
        out = head + out
        assert loop.returncode == 1, out  # a fault: damping, then exit 1 naming it
        assert "policy -> damping  (watchdog: LowState" in out, out  # stale, or its tick frozen
        assert "error: the robot loop damped on a fault: watchdog" in err
        assert "damping -> done" in out
        # Ctrl-C
        sim = start("sim", *common, "band=100", "lockstep=true")
        assert "[sim] publishing" in sim.stdout.readline()
        loop = start(
            "policy", *common, "start=auto", "guard=report", "deadlines=report", "supervisor=none",
            *fast,
        )  # fmt: skip
        head = until(loop, "hold -> policy")
        time.sleep(0.3)
        loop.send_signal(signal.SIGINT)
        out, _ = loop.communicate(timeout=60)
        out = head + out
        assert loop.returncode == 0, out
        assert "policy -> damping  (stop requested)" in out and "damping -> done" in out, out
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()


def test_torque_limits_saturate_where_deploy_json_says(loaded):
    """Every motor driven 10 rad past its target with the joints' kp saturates at exactly
    deploy.json's torque_limit (the scene's force range); a bundle whose torque limits say
    otherwise (x2, as slipped through the sim-to-sim tests) is refused in one line."""
    from march.robot import hg
    from march.robot.sim_robot import SimRobot
    from march.sim2sim.deploy_bundle import Bundle, UsageError
    from march.sim2sim.motors import motor_table

    spec = loaded.spec
    slots = motor_table(spec)
    limit = np.array([j["torque_limit"] for j in spec["joints"]])
    for sign in (1.0, -1.0):
        robot = SimRobot(loaded, band_s=100.0)
        q = robot.bus.q(robot.data)
        cmd = hg.LowCmd_(mode_machine=robot.mode_machine)
        for i, s in enumerate(slots):
            m = cmd.motor_cmd[int(s)]
            m.mode, m.kp, m.kd = 1, spec["joints"][i]["kp"], 0.0
            m.q = float(q[int(s)] + sign * 10.0)
        cmd.crc = hg.lowcmd_crc(cmd)
        assert robot.apply(cmd)
        robot.physics_step()
        ls = robot.lowstate()
        tau = np.array([ls.motor_state[int(s)].tau_est for s in slots])
        np.testing.assert_allclose(tau, sign * limit, rtol=1e-6)  # saturated, each its own
    for scale in (2.0, 0.5):
        bad = copy.deepcopy(spec)
        bad["joints"][7]["torque_limit"] *= scale
        with pytest.raises(UsageError, match=r"joints\[7\]\.torque_limit"):
            SimRobot(Bundle(loaded.onnx_path, bad), band_s=100.0)


def test_deploy_json_wire_fields_are_read_and_held(loaded):
    from march.robot.wire_checks import BundleRefused, check_deploy_fields

    check_deploy_fields(loaded.spec)
    cases = {
        ("msg_type",): ("go", "msg_type"),
        ("heading_reference",): ("world", "heading_reference"),
        ("num_motor_slots",): (29, "num_motor_slots"),
        ("deadline", "period_s"): (0.01, "period_s"),
        ("watchdog_s",): (0.003, "watchdog_s"),
        ("lowstate_hz",): (30.0, "lowstate_hz"),
    }
    for path, (value, word) in cases.items():
        bad = copy.deepcopy(loaded.spec)
        node = bad["deploy"]
        for p in path[:-1]:
            node = node[p]
        node[path[-1]] = value
        with pytest.raises(BundleRefused, match=word):
            check_deploy_fields(bad)


def test_the_unitree_mujoco_profile_is_explicit_and_loopback_only(loaded):
    """Unitree's MuJoCo bridge publishes LowState with mode_machine 0, crc 0 and tick 0: the
    G1 profile damps on it at once; robot=unitree_mujoco accepts exactly that (and still every
    reading check); the profile is refused off lo."""
    from march.robot import hg
    from march.robot.policy_loop import Controller
    from march.robot.robot_command import parse
    from march.robot.states import Timing
    from march.sim2sim.deploy_bundle import UsageError
    from march.sim2sim.motors import motor_table

    slots = motor_table(loaded.spec)
    bridge = hg.LowState_(mode_machine=0, tick=0)  # what the bridge sends: no crc
    for i, s in enumerate(slots):
        bridge.motor_state[int(s)].q = float(loaded.spec["robot"]["default_joint_pos"][i])
    timing = Timing.from_spec(loaded.spec["deploy"], **FAST)
    g1 = Controller(loaded, timing)
    g1.step(bridge, 0.0, (None, -1), 0.0)
    assert g1.machine.state == "damping" and "mode_machine" in g1.machine.fault_reason
    g1 = Controller(loaded, timing)
    variant5 = copy.deepcopy(bridge)
    variant5.mode_machine = 5  # the right variant, no crc
    g1.step(variant5, 0.0, (None, -1), 0.0)
    assert g1.machine.state == "damping" and "CRC" in g1.machine.fault_reason
    um = Controller(loaded, timing, robot="unitree_mujoco")
    for k in range(30):  # zero torque -> ramp -> hold on a frozen tick 0: no fault
        um.step(bridge, 0.0, (None, -1), k * 0.02)
    assert um.machine.state == "hold", um.machine.transitions
    nan = copy.deepcopy(bridge)
    nan.motor_state[int(slots[2])].dq = float("nan")
    um.step(nan, 0.0, (None, -1), 0.62)
    assert um.machine.state == "damping" and "not finite" in um.machine.fault_reason
    with pytest.raises(UsageError, match="loopback"):
        parse(["policy", "bundle=x", "robot=unitree_mujoco", "interface=eth0"])
    with pytest.raises(UsageError, match="loopback"):
        parse(["policy", "bundle=x", "resend_hz=200", "interface=eth0"])


def test_lowstate_ticks_must_count_up(loaded):
    """The LowState tick, one publisher's, counts up: back (a replay, a second publisher), or the
    same tick again with other readings (two publishers) damp at once with the cause named; the
    same LowState re-sent is no news, and a tick that stops advancing (re-sent or not) damps
    after watchdog_s; ticks that count up never do. In-process, the loop's own step."""
    from march.robot import hg
    from march.robot.policy_loop import Controller
    from march.robot.sim_robot import SimRobot
    from march.robot.states import Timing

    timing = Timing.from_spec(loaded.spec["deploy"], **FAST)
    ls = SimRobot(loaded, band_s=100.0).lowstate()
    a, b = "readings a", "readings b"
    cases = {
        "up": ([[(5, a)], [(6, a)], [(7, b), (8, a)], [(9, b)]], None),
        "resent": ([[(5, a)], [(6, a)], [(6, a)], [(7, a)]], None),
        "twice": ([[(5, a)], [(6, a)], [(6, b)]], "tick 6 came twice with different readings"),
        "within": ([[(5, a)], [(6, a), (6, b)]], "tick 6 came twice with different readings"),
        "back": ([[(5, a)], [(6, a)], [(7, a)], [(3, a)]], "went back from 7 to 3"),
        "back_within": ([[(5, a)], [(9, a), (8, a)]], "went back from 9 to 8"),
    }
    for name, (steps, want) in cases.items():
        ctl = Controller(loaded, timing, guard_action="report")
        for k, ticks in enumerate(steps):
            ls.tick = ticks[-1][0]
            ls.crc = hg.lowstate_crc(ls)
            ctl.step(ls, 0.0, (None, -1), k * 0.002, ticks=ticks)
        reason = ctl.machine.fault_reason
        if want is None:
            assert reason is None and ctl.machine.state == "zero_torque", (name, reason)
        else:
            assert ctl.machine.state == "damping" and want in reason, (name, reason)
    # frozen: re-sent (or nothing new) for longer than the watchdog
    for resent in ([(5, a)], []):
        ctl = Controller(loaded, timing, guard_action="report")
        ls.tick = 5
        ls.crc = hg.lowstate_crc(ls)
        ctl.step(ls, 0.0, (None, -1), 0.0, ticks=[(5, a)])
        ctl.step(ls, 0.0, (None, -1), timing.watchdog_s * 0.9, ticks=resent)
        assert ctl.machine.state == "zero_torque"
        ctl.step(ls, 0.0, (None, -1), timing.watchdog_s * 1.1, ticks=resent)
        assert ctl.machine.state == "damping" and "tick frozen at 5" in ctl.machine.fault_reason
