"""Unitree's own MuJoCo bridge (``unitree_mujoco``'s ``simulate_python``), headless, for
``make unitree-sim``: the robot loop against the simulator Unitree ships, not march's.

    python -m march.robot.unitree_mujoco_run unitree_mujoco=<clone> [domain=1] [seconds=20]
        [band_s=4]

Nothing of unitree_mujoco is copied here: its ``simulate_python/unitree_sdk2py_bridge.py`` is
imported from the clone given (it needs ``unitree_sdk2py`` - unitree_sdk2_python's source on
``PYTHONPATH`` - and ``pygame`` importable), with a ``config`` module of this file's making
(``ROBOT`` g1, no joystick, the domain, ``lo``). What ``unitree_mujoco.py`` does, minus its
viewer window: the G1 29-DoF scene, the bridge (LowState at the physics rate; each LowCmd's PD
torque computed once when it arrives and held until the next), ``mj_step`` in real time every
5 ms, Unitree's ``ElasticBand`` on the torso for the first ``band_s`` seconds (its rest length
set so that the band carries the robot's weight at the spawn height). Each second it prints
the pelvis height and the largest joint speed; the last line says whether the robot fell
(pelvis below 0.45 m after the band), diverged (a joint faster than 100 rad/s, or a non-finite
state) or oscillated (the largest joint speed over 10 rad/s on average through the last second:
a limit cycle, as the bridge's held torque makes of a damping kd too large for its joints), and the exit status
is 1 for a divergence or an oscillation (``make unitree-sim`` fails then), 0 otherwise.
"""

from __future__ import annotations

import math
import sys
import time
import types
from pathlib import Path

FALL_HEIGHT_M = 0.45
DIVERGED_RAD_S = 100.0
OSCILLATING_RAD_S = 10.0
"""The largest joint speed, averaged over the last whole second, above which the robot is
oscillating (measured: the bridge on damping alone settles under 0.2 rad/s at kd 1 and 2 and
cycles at 12-80 rad/s peaks at kd 4 and 8)."""


def _config(scene: Path, domain: int) -> types.ModuleType:
    config = types.ModuleType("config")
    config.ROBOT, config.ROBOT_SCENE = "g1", str(scene)
    config.DOMAIN_ID, config.INTERFACE = domain, "lo"
    config.USE_JOYSTICK, config.JOYSTICK_TYPE, config.JOYSTICK_DEVICE = 0, "xbox", 0
    config.PRINT_SCENE_INFORMATION, config.ENABLE_ELASTIC_BAND = False, True
    config.SIMULATE_DT, config.VIEWER_DT = 0.005, 0.02
    return config


def main(argv: list[str]) -> int:
    args = dict(word.split("=", 1) for word in argv)
    root = Path(args["unitree_mujoco"])
    scene = root / "unitree_robots" / "g1" / "scene_29dof.xml"
    bridge_py = root / "simulate_python" / "unitree_sdk2py_bridge.py"
    if not scene.is_file() or not bridge_py.is_file():
        print(f"error: unitree_mujoco={root}: no {scene.name} or {bridge_py.name}", file=sys.stderr)
        return 2
    domain, seconds = int(args.get("domain", 1)), float(args.get("seconds", 20))
    band_s = float(args.get("band_s", 4))
    sys.modules["config"] = _config(scene, domain)
    sys.path.insert(0, str(bridge_py.parent))
    import mujoco
    import numpy as np
    from unitree_sdk2py.core.channel import ChannelFactoryInitialize
    from unitree_sdk2py_bridge import ElasticBand, UnitreeSdk2Bridge

    model = mujoco.MjModel.from_xml_path(str(scene))
    data = mujoco.MjData(model)
    model.opt.timestep = 0.005
    mujoco.mj_forward(model, data)
    ChannelFactoryInitialize(domain, "lo")
    bridge = UnitreeSdk2Bridge(model, data)
    band = ElasticBand()
    torso = model.body("torso_link").id
    weight = float(model.body_subtreemass[1]) * 9.81
    band.length = float(np.linalg.norm(band.point - data.qpos[:3])) - weight / band.stiffness
    first = [model.actuator(i).name for i in range(3)]
    print(
        f"[unitree_mujoco] {scene.name}: {model.nu} motors ({', '.join(first)}, ...), "
        f"domain {domain}, lo; band for {band_s:g} s",
        flush=True,
    )
    t0, k, worst, lowest, verdict = time.perf_counter(), 0, 0.0, math.inf, "stood"
    steps_per_s = round(1.0 / model.opt.timestep)
    second_sum, last_second = 0.0, math.nan  # the mean max |dq| of the last whole second
    while time.perf_counter() - t0 < seconds:
        if data.time < band_s:
            data.xfrc_applied[torso, :3] = band.Advance(data.qpos[:3], data.qvel[:3])
        else:
            data.xfrc_applied[torso, :3] = 0.0
        mujoco.mj_step(model, data)
        k += 1
        speed = float(np.abs(data.qvel[6:]).max())
        z = float(data.qpos[2])
        if not (math.isfinite(speed) and math.isfinite(z)) or speed > DIVERGED_RAD_S:
            verdict = f"diverged at {data.time:.2f} s (max joint speed {speed:.3g} rad/s)"
            break
        worst, lowest = max(worst, speed), min(lowest, z) if data.time >= band_s else lowest
        second_sum += speed
        if k % steps_per_s == 0:
            last_second, second_sum = second_sum / steps_per_s, 0.0
        if k % 200 == 0:
            print(f"[unitree_mujoco] t {data.time:6.2f} s  pelvis z {z:.3f} m  max |dq| "
                  f"{speed:.2f} rad/s", flush=True)  # fmt: skip
        wait = t0 + k * model.opt.timestep - time.perf_counter()
        if wait > 0:
            time.sleep(wait)
    if verdict == "stood" and last_second > OSCILLATING_RAD_S:
        verdict = (
            f"oscillated (max joint speed {last_second:.1f} rad/s on average over the last "
            f"second, over {OSCILLATING_RAD_S:g})"
        )
    if verdict == "stood" and lowest < FALL_HEIGHT_M:
        verdict = f"fell (pelvis down to {lowest:.2f} m after the band)"
    del bridge
    print(
        f"[unitree_mujoco] done: {verdict}; max |dq| {worst:.2f} rad/s, {last_second:.2f} on average in the "
        "last second",
        flush=True,
    )
    return 1 if verdict.startswith(("diverged", "oscillated")) else 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
