"""``python -m march.robot sim``: a MuJoCo G1 that speaks the robot's DDS topics.

Like Unitree's ``unitree_mujoco``: the bundle's compiled scene, stepped at the physics rate; it
subscribes to ``rt/lowcmd`` and applies the law of the G1's motor drivers per slot, torque =
kp (q_cmd - q) + kd (dq_cmd - dq) + tau, clipped to the motor's torque limit (the scene's
position actuators with the command's kp / kd; dq_cmd and tau folded into the target where
kp > 0), a motor with ``mode`` 0 limp; it publishes ``rt/lowstate`` every physics step (IMU at the
pelvis: quaternion w x y z, gyroscope, accelerometer, rpy; q / dq / tau_est per slot; ``tick`` =
physics steps; ``mode_machine`` / ``mode_pr`` of the bundle's G1; the CRC) and the depth image
in metres every control period. A LowCmd with a wrong CRC or another ``mode_machine`` is
dropped and counted (as the robot drops it).

``lockstep=true`` steps one control period per LowCmd received (no wall clock: the loop's
command of step k acts on the state it was computed from - zero added latency, for the
self-test); otherwise it runs in real time with the newest command. ``band=S``: for the first S
seconds of simulated time the pelvis is held at its spawn pose (position and orientation, zero
velocity after every physics step): the robot on a stand, its legs free, the stiff limit of
``unitree_mujoco``'s elastic band (a spring on the pelvis made the limp robot pitch over, and
a stiff one at 5 ms steps was unstable); then it lets go. ``log=<file.npz>``: the state (qpos, qvel) behind
every published tick and the command applied at each tick (q, kp, kd per slot: what reached
the motors), written on exit (SIGINT / SIGTERM). ``cmd_timeout=S`` (real time only): no valid
LowCmd for S seconds of wall time puts every motor in damping (kp 0, kd ``damping_kd``) until
the next valid one - the timeout an operator sets on a robot's motor side; 0 (the default)
keeps the last command, as a motor driver without a timeout does.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import mujoco
import numpy as np

from march.robot import dds, hg
from march.robot.signals import stop_on_signals
from march.sim2sim.deploy_bundle import Bundle
from march.sim2sim.runner import Sim2Sim


class SimRobot:
    """The scene, the motor law and the messages (no DDS: :func:`serve` adds it)."""

    def __init__(self, bundle: Bundle, course: str = "hardware", band_s: float = 0.0) -> None:
        self.sim = Sim2Sim(bundle, course)
        spec = bundle.spec
        self.spec, dep = spec, spec["deploy"]
        self.model, self.data = self.sim.model, self.sim.data
        self.bus = self.sim.bus
        self.sim.reset(bundle.cell(course, 0.0, 0), seed=-1)  # the start point, standing
        m = self.model
        self.limit = m.actuator_forcerange[self.bus.act, 1].copy()
        self.check_torque_limits()
        self.mode_machine, self.mode_pr = int(dep["mode_machine"]), int(dep["mode_pr"])
        self.decimation = self.sim.decimation
        self.tick = 0
        self.dropped = {"crc": 0, "mode_machine": 0}
        self.commands = 0
        self.band_s = band_s
        r = self.sim.root_q
        self.anchor = self.data.qpos[r : r + 7].copy()  # the pelvis pose on the stand
        self.limp()
        accel = [i for i in range(m.nsensor) if m.sensor(i).name.endswith("imu_lin_acc")]
        self.accel = int(m.sensor_adr[accel[0]]) if accel else None
        self.states: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.applied: dict[int, np.ndarray] = {}  # tick -> (3, slots): q, kp, kd as applied
        self.damping_kd = float(dep["shutdown"]["damping_kd"])
        self.timeouts = 0

    def check_torque_limits(self) -> None:
        """deploy.json's torque limits are the scene's force ranges (the motors the robot has):
        a bundle that says otherwise is refused, not simulated with the scene's."""
        from march.sim2sim.deploy_bundle import UsageError
        from march.sim2sim.motors import motor_table

        slots = motor_table(self.spec)
        for i, j in enumerate(self.spec["joints"]):
            scene = float(self.limit[int(slots[i])])
            lo, hi = self.model.actuator_forcerange[self.bus.act[int(slots[i])]]
            if abs(j["torque_limit"] - scene) > 1e-6 * scene or abs(lo + hi) > 1e-6 * scene:
                raise UsageError(
                    f"deploy.json joints[{i}].torque_limit = {j['torque_limit']:g} ({j['name']}): "
                    f"the scene's motor saturates at +-{scene:g} N m"
                )

    def limp(self) -> None:
        """Every motor off (kp = kd = 0) until a LowCmd says otherwise."""
        a = self.bus.act
        self.model.actuator_gainprm[a, 0] = 0.0
        self.model.actuator_biasprm[a, 1] = 0.0
        self.model.actuator_biasprm[a, 2] = 0.0

    def apply(self, cmd: hg.LowCmd_) -> bool:
        """The motor drivers take a LowCmd (False: dropped)."""
        if hg.lowcmd_crc(cmd) != int(cmd.crc):
            self.dropped["crc"] += 1
            return False
        if int(cmd.mode_machine) != self.mode_machine:
            self.dropped["mode_machine"] += 1
            return False
        m, d = self.model, self.data
        for s, a in enumerate(self.bus.act):
            mc = cmd.motor_cmd[s]
            on = int(mc.mode) != 0
            kp, kd = (float(mc.kp), float(mc.kd)) if on else (0.0, 0.0)
            m.actuator_gainprm[a, 0] = kp
            m.actuator_biasprm[a, 1] = -kp
            m.actuator_biasprm[a, 2] = -kd
            ff = float(mc.tau) + kd * float(mc.dq)
            d.ctrl[a] = float(mc.q) + (ff / kp if kp > 0 and on else 0.0)
        self.commands += 1
        self.applied[self.tick] = np.array(
            [[float(c.q), float(c.kp), float(c.kd)] for c in cmd.motor_cmd]
        ).T
        return True

    def damp(self) -> None:
        """The motors' own damping (the LowCmd timeout): kp 0, kd ``damping_kd``."""
        a = self.bus.act
        self.model.actuator_gainprm[a, 0] = 0.0
        self.model.actuator_biasprm[a, 1] = 0.0
        self.model.actuator_biasprm[a, 2] = -self.damping_kd
        self.data.ctrl[a] = 0.0
        self.timeouts += 1

    def physics_step(self) -> None:
        d = self.data
        mujoco.mj_step(self.model, d)
        if d.time < self.band_s:  # on the stand: the pelvis held where it was spawned
            r, v = self.sim.root_q, self.sim.root_v
            d.qpos[r : r + 7] = self.anchor
            d.qvel[v : v + 6] = 0.0
        self.tick += 1

    def lowstate(self) -> hg.LowState_:
        """The LowState of the current state (after ``mj_forward``)."""
        m, d = self.model, self.data
        mujoco.mj_forward(m, d)
        self.states[self.tick] = (d.qpos.copy(), d.qvel.copy())
        ls = hg.LowState_(mode_pr=self.mode_pr, mode_machine=self.mode_machine, tick=self.tick)
        quat = d.xquat[self.sim.root_body]
        imu = ls.imu_state
        imu.quaternion = [float(v) for v in quat]
        imu.gyroscope = [float(v) for v in d.sensordata[self.sim.gyro]]
        if self.accel is not None:
            imu.accelerometer = [float(v) for v in d.sensordata[self.accel : self.accel + 3]]
        rpy = np.zeros(3)
        w, x, y, z = quat
        rpy[0] = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
        rpy[1] = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
        rpy[2] = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
        imu.rpy = [float(v) for v in rpy]
        q, dq = self.bus.q(d), self.bus.dq(d)
        force = d.actuator_force[self.bus.act]
        for s in range(self.bus.num_motors):
            ms = ls.motor_state[s]
            ms.mode = 1
            ms.q, ms.dq, ms.tau_est = float(q[s]), float(dq[s]), float(force[s])
        ls.crc = hg.lowstate_crc(ls)
        return ls

    def depth(self) -> dds.DepthImage_:
        planar = self.sim.camera.planar(self.model, self.data)
        h, w = planar.shape[-2:]
        return dds.DepthImage_(self.tick, h, w, [float(v) for v in planar.reshape(-1)])

    def save(self, path: str) -> None:
        ticks = np.array(sorted(self.states), dtype=np.int64)
        qpos = np.stack([self.states[t][0] for t in ticks])
        qvel = np.stack([self.states[t][1] for t in ticks])
        tmp = Path(path).with_suffix(".tmp.npz")
        cmd_ticks = np.array(sorted(self.applied), dtype=np.int64)
        cmds = np.stack([self.applied[t] for t in cmd_ticks]) if len(cmd_ticks) else np.zeros(0)
        np.savez(tmp, ticks=ticks, qpos=qpos, qvel=qvel, cmd_ticks=cmd_ticks, cmds=cmds)
        tmp.replace(path)


def serve(
    robot: SimRobot,
    domain: int,
    interface: str,
    lockstep: bool,
    seconds: float = math.inf,
    log: str = "",
    cmd_timeout: float = 0.0,
) -> dict[str, int]:
    """Run ``robot`` on DDS until SIGINT / SIGTERM or ``seconds`` of wall time."""
    dp = dds.participant(domain, interface)
    dep = robot.spec["deploy"]
    state_w = dds.writer(dp, dep["lowstate_topic"], hg.LowState_)
    depth_w = dds.writer(dp, dds.DEPTH_TOPIC, dds.DepthImage_)
    cmd_box = dds.Latest(dp, dep["lowcmd_topic"], hg.LowCmd_)
    stop, _ = stop_on_signals()
    dt = robot.model.opt.timestep
    t0 = time.perf_counter()
    seen = 0

    def publish(with_depth: bool) -> None:
        state_w.write(robot.lowstate())
        if with_depth:
            depth_w.write(robot.depth())

    publish(True)
    print(f"[sim] publishing on domain {domain}, interface {interface}", flush=True)
    k = 0
    last_ok, timed_out = time.perf_counter(), False
    while not stop["flag"] and time.perf_counter() - t0 < seconds:
        if lockstep:
            if not cmd_box.wait(0.01):
                state_w.write(robot.lowstate())  # keep the loop's watchdog fed while idle
                continue
            cmd = cmd_box.sample
            seen = cmd_box.count
            robot.apply(cmd)
            for _ in range(robot.decimation):
                robot.physics_step()
            publish(True)
        else:
            cmd, _ = cmd_box.take()
            if cmd is not None and cmd_box.count != seen:
                seen = cmd_box.count
                if robot.apply(cmd):
                    last_ok, timed_out = time.perf_counter(), False
            if cmd_timeout > 0 and not timed_out and time.perf_counter() - last_ok > cmd_timeout:
                robot.damp()
                timed_out = True
                print(f"[sim] no valid LowCmd for {cmd_timeout:g} s: motors damping", flush=True)
            robot.physics_step()
            k += 1
            publish(k % robot.decimation == 0)
            wait = t0 + k * dt - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
    if log:
        robot.save(log)
    drops = {f"dropped_{k}": v for k, v in robot.dropped.items()}
    return {"commands": robot.commands, **drops, "timeouts": robot.timeouts}
