"""Test helpers for the robot's processes and wire: a line reader that cannot hang, and LowCmd
builders (a G1 command at the default pose with gains, a copy with one value changed).

Shared by tests/test_robot_*.py (one place for what each of them had written again)."""

from __future__ import annotations

import select
import subprocess
import time
from typing import Any


def until(proc: subprocess.Popen, text: str, timeout: float = 60.0) -> str:
    """Lines of ``proc``'s stdout up to the one holding ``text``; fails after ``timeout`` even
    when the process prints nothing (a select on its pipe, not a blocking read)."""
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


def hold_lowcmd(spec: dict[str, Any], kp: float = 40.0, kd: float = 2.0) -> Any:
    """A valid G1 LowCmd (deploy.json's mode_machine, every used slot enabled) holding the
    default pose with ``kp`` / ``kd``, its CRC set."""
    from march.robot import hg
    from march.sim2sim.motors import motor_table

    cmd = hg.LowCmd_(mode_machine=int(spec["deploy"]["mode_machine"]))
    for i, s in enumerate(motor_table(spec)):
        m = cmd.motor_cmd[int(s)]
        m.mode, m.q, m.kp, m.kd = 1, float(spec["robot"]["default_joint_pos"][i]), kp, kd
    cmd.crc = hg.lowcmd_crc(cmd)
    return cmd


def changed_lowcmd(cmd: Any, slot: int, **values: float) -> Any:
    """A copy of ``cmd`` with motor ``slot``'s fields set to ``values``, its CRC recomputed (a
    command only the loop's value checks can refuse)."""
    import copy

    from march.robot import hg

    out = copy.deepcopy(cmd)
    for key, value in values.items():
        setattr(out.motor_cmd[slot], key, value)
    out.crc = hg.lowcmd_crc(out)
    return out


def is_damping(cmd: Any, slots: Any, kd: float) -> bool:
    """kp 0 and kd ``kd`` at every used slot."""
    return all(cmd.motor_cmd[int(s)].kp == 0 and cmd.motor_cmd[int(s)].kd == kd for s in slots)
