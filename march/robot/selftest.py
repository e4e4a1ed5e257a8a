"""``python -m march.robot selftest``: the DDS loop against in-process sim-to-sim, on loopback.

Starts the MuJoCo robot (``sim``, lockstep: one control period per LowCmd, so the loop adds no
latency) and the robot loop (``policy``, start=auto) as two processes on DDS domain 1 over the
loopback interface; the loop goes zero torque -> ramp -> hold -> policy for ``seconds`` ->
damping -> done while the robot hangs on its band until the policy starts. Then, in this
process, :class:`march.sim2sim.runner.Sim2Sim` shadows every policy step from the very states
the simulated robot published (its log: qpos, qvel per tick) - its own history and previous
action, depth by ray casting, the heading reference the loop took - and its ONNX action is
compared with the loop's. Prints the largest difference (against the tolerance of the
observation agreement test, ``ACTION_TOL``), missed deadlines, the p50 / p99 loop time and the
state machine's transitions; exit status 1 on disagreement or when nothing was compared.
Guard flags and missed deadlines are counted, not acted on, by default (``guard=report``,
``deadlines=report``): the smoke student trips the guard, and this machine's other processes
steal deadlines; both act (``=damp``) on a robot.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from march.sim2sim.deploy_bundle import Bundle, UsageError
from march.sim2sim.runner import Sim2Sim

ACTION_TOL = 5e-6
"""tests/test_sim2sim_agreement.py's ``action_out`` tolerance (float32 state in the messages
against float64 MuJoCo, as the env's float32 state there)."""
FAST_STARTUP = {"zero_torque_s": 0.5, "ramp_s": 1.0, "hold_s": 0.5, "damping_s": 0.5}
"""Start-up and shut-down times of the self-test (the bundle's are for a robot on a stand)."""


def shadow(bundle: Bundle, course: str, loop: dict[str, Any], states: dict) -> dict[str, Any]:
    """Max |loop action - sim2sim action| over the loop's policy steps, from the same states."""
    sim = Sim2Sim(bundle, course)
    cell = bundle.cell(course, 0.0, 0)
    ticks = {int(t): i for i, t in enumerate(states["ticks"])}
    steps = [s for s in loop["steps"] if s["action"] is not None]
    foreign = [s["lowstate_tick"] for s in steps if s["lowstate_tick"] not in ticks]
    if foreign:
        raise UsageError(
            f"the loop used LowState ticks the simulated robot never published ({foreign[:3]}): "
            "another robot or simulator publishes on this DDS domain; pick another domain="
        )
    if steps:
        sim.command_spec = dict(sim.command_spec, heading_target_rad=steps[0]["heading_ref"])
    sim.set_command(*loop["command"][:2])
    worst, prev, per_step, actions = 0.0, None, [], []

    def put(tick: int) -> None:
        i = ticks[tick]
        sim.data.qpos[:] = states["qpos"][i]
        sim.data.qvel[:] = states["qvel"][i]

    for k, s in enumerate(steps):
        put(s["lowstate_tick"])
        if k == 0:
            sim.start(cell)
        else:
            sim.last_action = prev
            sim.observe()
        if s["depth_tick"] != s["lowstate_tick"] and s["depth_tick"] in ticks:
            put(s["depth_tick"])
            import mujoco

            mujoco.mj_forward(sim.model, sim.data)
            image = sim.depth_image()
            put(s["lowstate_tick"])
            mujoco.mj_forward(sim.model, sim.data)
        else:
            image = sim.depth_image()
        feeds = {
            "proprio_hist": sim.history.array(),
            "command": sim.command.astype(np.float32)[None],
            "depth": image,
        }
        action, _ = sim.act(feeds)
        diff = float(np.abs(action - np.asarray(s["action"])).max())
        per_step.append(diff)
        worst = max(worst, diff)
        prev = action
        actions.append(np.asarray(action, dtype=np.float64).reshape(-1))
    out = {"compared": len(steps), "max_abs_diff": worst, "per_step": per_step}
    out.update(motor_commands(bundle, loop, states, actions))
    return out


TARGET_TOL = 2e-5
"""Rad: a target's float32 rounding on the wire (|q| < 3: 2e-7) plus the largest action scale
(0.55) x ACTION_TOL."""
GAIN_RTOL = 1e-6
"""kp / kd go on the wire as float32."""


def motor_commands(
    bundle: Bundle, loop: dict[str, Any], states: dict, actions: list[np.ndarray]
) -> dict[str, Any]:
    """What reached the simulated robot's motors (its log of applied LowCmds, by slot) against
    what sim-to-sim says each policy step must send: target = offset + scale x (its action), the
    joints table's kp / kd; and damping (kp 0, kd damping_kd) after the policy. A loop that
    logs one action but sends another (a clipped one, say) fails here."""
    from march.sim2sim.motors import motor_table

    spec = bundle.spec
    if "cmd_ticks" not in states or not len(states["cmd_ticks"]):
        return {"commands_compared": 0, "target_diff": np.inf, "gain_diff": np.inf}
    at = {int(t): i for i, t in enumerate(states["cmd_ticks"])}
    cmds = states["cmds"]
    slots = motor_table(spec)
    offset = np.asarray(spec["action"]["offset"], dtype=np.float64)
    scale = np.asarray(spec["action"]["scale"], dtype=np.float64)
    kp = np.array([j["kp"] for j in spec["joints"]])
    kd = np.array([j["kd"] for j in spec["joints"]])
    damp_kd = float(spec["deploy"]["shutdown"]["damping_kd"])
    policy_steps = [s for s in loop["steps"] if s["action"] is not None]
    n, t_diff, g_diff = 0, 0.0, 0.0
    for s, a in zip(policy_steps, actions, strict=False):
        i = at.get(int(s["lowstate_tick"]))
        if i is None or s["state"] != "policy":
            continue  # the step damped, or its command was not the one applied at that tick
        q, p, d = cmds[i][0][slots], cmds[i][1][slots], cmds[i][2][slots]
        t_diff = max(t_diff, float(np.abs(q - (offset + scale * a)).max()))
        g_diff = max(
            g_diff, float(np.abs(p - kp).max() / kp.max()), float(np.abs(d - kd).max() / kd.max())
        )
        n += 1
    last = at[max(at)]  # the last command applied: the loop's damping
    if (
        np.abs(cmds[last][1][slots]).max() > 0
        or np.abs(cmds[last][2][slots] - damp_kd).max() > 1e-6
    ):
        g_diff = max(g_diff, 1.0)
    return {"commands_compared": n, "target_diff": t_diff, "gain_diff": g_diff}


def _python() -> list[str]:
    return [sys.executable, "-m", "march.robot"]


def run_selftest(
    bundle_arg: str,
    seconds: float,
    domain: int = 1,
    interface: str = "lo",
    guard: str = "report",
    course: str = "hardware",
    keep: str = "",
    deadlines: str = "report",
) -> int:
    from march.robot.policy_loop import load_bundle

    bundle = load_bundle(bundle_arg)
    onnx = str(bundle.onnx_path)
    folder = Path(keep) if keep else Path(tempfile.mkdtemp(prefix="march_selftest_"))
    folder.mkdir(parents=True, exist_ok=True)
    sim_log, loop_log = folder / "sim.npz", folder / "loop.json"
    band = FAST_STARTUP["zero_torque_s"] + FAST_STARTUP["ramp_s"] + FAST_STARTUP["hold_s"]
    common = [f"bundle={onnx}", f"domain={domain}", f"interface={interface}"]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    sim = subprocess.Popen(
        [*_python(), "sim", *common, f"course={course}", "lockstep=true", f"band={band}",
         f"log={sim_log}"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
    )  # fmt: skip
    try:
        line = sim.stdout.readline() if sim.stdout else ""
        if "[sim] publishing" not in line:
            raise UsageError(f"the simulated robot did not start: {line.strip()}")
        fast = [f"{k}={v}" for k, v in FAST_STARTUP.items()]
        t0 = time.perf_counter()
        loop = subprocess.run(
            [*_python(), "policy", *common, "start=auto", f"seconds={seconds}",
             f"guard={guard}", f"deadlines={deadlines}", f"log={loop_log}", "lockstep=true",
             "supervisor=none", *fast],
            capture_output=True,
            text=True,
            env=env,
            timeout=seconds + 120,
        )  # fmt: skip
        wall = time.perf_counter() - t0
    except subprocess.TimeoutExpired:
        raise UsageError(f"the robot loop did not finish within {seconds + 120:g} s") from None
    finally:
        sim.send_signal(signal.SIGINT)
        try:
            out, _ = sim.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            sim.kill()
            out, _ = sim.communicate()
    fault = loop.stderr.strip().splitlines()[-1] if loop.stderr.strip() else ""
    guarded = guard == "damp" and "fault: guard:" in fault  # the guard acted, as asked
    if (loop.returncode != 0 and not (loop.returncode == 1 and guarded)) or not loop_log.is_file():
        print(loop.stdout[-2000:] + loop.stderr[-2000:], file=sys.stderr)
        raise UsageError(f"the robot loop failed (exit {loop.returncode}): {fault}")
    if not sim_log.is_file():
        raise UsageError(f"the simulated robot wrote no log: {out[-500:]}")
    log = json.loads(loop_log.read_text())
    states = dict(np.load(sim_log))
    result = shadow(bundle, course, log, states)
    return report(result, log, out, wall, seconds, domain, interface)


def report(
    result: dict[str, Any],
    log: dict[str, Any],
    sim_out: str,
    wall: float,
    seconds: float,
    domain: int,
    interface: str,
) -> int:
    steps = log["steps"]
    work = np.array([s["work_ms"] for s in steps])
    missed = sum(s["missed"] for s in steps)
    ok = result["compared"] > 0 and result["max_abs_diff"] <= ACTION_TOL
    sent_ok = (
        result.get("commands_compared", 0) > 0
        and result["target_diff"] <= TARGET_TOL
        and result["gain_diff"] <= GAIN_RTOL
    )
    ok = ok and sent_ok
    period_ms = log["period_s"] * 1e3
    print(
        f"selftest: robot loop and MuJoCo robot as two processes on DDS domain {domain}, "
        f"interface {interface} (lockstep); policy {seconds:g} s; {wall:.1f} s wall"
    )
    verdict = "OK" if ok else "DISAGREE" if result["compared"] else "NOTHING COMPARED"
    print(
        f"agreement: {result['compared']} policy steps compared with in-process sim2sim from "
        f"the same states: max |action difference| = {result['max_abs_diff']:.2e} "
        f"(tolerance {ACTION_TOL:.0e}) -> {verdict}"
    )
    if "commands_compared" in result:
        print(
            f"motors: {result['commands_compared']} applied commands against sim2sim: max "
            f"|target difference| = {result['target_diff']:.2e} rad (tolerance {TARGET_TOL:.0e}), "
            f"max relative kp / kd difference = {result['gain_diff']:.2e} (tolerance "
            f"{GAIN_RTOL:.0e}), damping at the end -> {'OK' if sent_ok else 'DISAGREE'}"
        )
    print(
        f"missed deadlines: {missed} of {len(steps)} control steps (period {period_ms:g} ms; "
        f"deadlines={log.get('deadlines', 'damp')})"
    )
    print(
        f"loop time (LowState in -> LowCmd out): p50 {np.percentile(work, 50):.2f} ms, "
        f"p99 {np.percentile(work, 99):.2f} ms, max {work.max():.2f} ms"
    )
    flagged = sum(1 for s in steps if s["flags"])
    print(f"guard flags: {flagged} steps flagged (guard={log['guard']})")
    print("transitions:")
    for t, a, b, why in log["transitions"]:
        print(f"  {t:7.3f} s  {a} -> {b}  ({why})")
    tail = [ln for ln in sim_out.splitlines() if ln.startswith("[sim]")]
    if tail:
        print(tail[-1])
    return 0 if ok else 1
