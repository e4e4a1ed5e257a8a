"""march's damping command holds in Unitree's own MuJoCo bridge (unitree_mujoco's
``simulate_python``, run headless by :mod:`march.robot.unitree_mujoco_run`): the bundle's damping
LowCmd (kp 0, kd ``damping_kd`` on every joint, :func:`march.robot.wire_checks.damping_lowcmd`)
published at 50 Hz (the control rate) and at 200 Hz (the bridge's rate, as ``robot=unitree_mujoco``
re-sends), the G1 on Unitree's elastic band: the bridge neither diverges nor oscillates.

The bridge computes each LowCmd's torque once, when it arrives, and holds it until the next:
an explicit damping whose kd must stay small against the joints' inertia (armature 0.01 kg m^2)
and the hold time. Measured here (docs/deploying.md): kd 8 diverges (50 Hz) or cycles at 60 rad/s
(200 Hz), kd 4 cycles at 37-80 rad/s; kd 2 and 1 settle under 0.2 rad/s. Needs clones of
unitree_mujoco and unitree_sdk2_python (``UNITREE_MUJOCO=``, ``UNITREE_SDK2=``) and pygame (the
bridge imports it); without them it is skipped with one line. ``make robot-check`` runs it.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from robot_wire import until

ROOT = Path(__file__).resolve().parent.parent
pytestmark = pytest.mark.sim
DOMAIN = 20 + (os.getpid() + 151) % 200
"""A DDS domain of this session's own (cyclonedds takes 0-232)."""
MUJOCO = os.environ.get("UNITREE_MUJOCO", "")
SDK2 = os.environ.get("UNITREE_SDK2", "")


def _missing() -> str | None:
    if not (MUJOCO and (Path(MUJOCO) / "simulate_python").is_dir()):
        return "UNITREE_MUJOCO=<unitree_mujoco clone> not given"
    if not (SDK2 and (Path(SDK2) / "unitree_sdk2py").is_dir()):
        return "UNITREE_SDK2=<unitree_sdk2_python clone> not given"
    try:
        import pygame  # noqa: F401
    except ImportError:
        return "pygame not installed"
    return None


def run_damping(spec: dict, rate_hz: float, domain: int, kd: float, seconds: float = 5.0):
    """The bridge for ``seconds`` on march's damping command at ``rate_hz``: (exit, output)."""
    from march.robot import dds, hg
    from march.robot.wire_checks import Limits, damping_lowcmd
    from march.sim2sim.motors import motor_table

    env = dict(os.environ, PYTHONPATH=os.pathsep.join([SDK2, os.environ.get("PYTHONPATH", "")]))
    bridge = subprocess.Popen(
        [sys.executable, "-m", "march.robot.unitree_mujoco_run", f"unitree_mujoco={MUJOCO}",
         f"domain={domain}", f"seconds={seconds}", "band_s=100"],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    try:
        until(bridge, "[unitree_mujoco] scene", timeout=120)
        limits = Limits.from_spec(spec, motor_table(spec))
        cmd = damping_lowcmd(limits, kd, int(spec["deploy"]["mode_pr"]))
        w = dds.writer(dds.participant(domain, "lo"), "rt/lowcmd", hg.LowCmd_)
        t0, k = time.perf_counter(), 0
        deadline = t0 + seconds + 30  # the bridge ends itself after `seconds`; a bound, no check
        while bridge.poll() is None and time.perf_counter() < deadline:
            w.write(cmd)
            k += 1
            wait = t0 + k / rate_hz - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
        out, _ = bridge.communicate(timeout=60)
    finally:
        if bridge.poll() is None:
            bridge.kill()
            bridge.wait()
    return bridge.returncode, out


@pytest.mark.slow  # real time, ~10 s per rate: make robot-check
@pytest.mark.parametrize("rate_hz", [50.0, 200.0])
def test_unitree_bridge_holds_march_damping(bundle, rate_hz):
    missing = _missing()
    if missing:
        pytest.skip(f"{missing}: make unitree-sim UNITREE_MUJOCO=... UNITREE_SDK2=... needs them")
    from march.sim2sim.deploy_bundle import Bundle

    spec = Bundle.load(bundle).spec
    kd = float(spec["deploy"]["shutdown"]["damping_kd"])
    rc, out = run_damping(spec, rate_hz, DOMAIN + (rate_hz > 100), kd)
    print(out)
    last = [ln for ln in out.splitlines() if "done:" in ln]
    assert last and "done: stood" in last[-1] and rc == 0, out[-2000:]
