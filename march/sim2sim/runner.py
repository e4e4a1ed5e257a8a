"""The robot-side control loop of ``python -m march.sim2sim`` (the command line:
:mod:`march.sim2sim.command_line`).

Nothing of the training stack runs here: MuJoCo's C library (CPU), onnxruntime and numpy only -
no torch, warp, mjlab, Hydra or march module that imports them (tests/test_sim2sim.py checks
``sys.modules``). :class:`Sim2Sim` does what the robot's computer does, at the rates of training:

- every control step (50 Hz): proprioception (IMU gyro, projected gravity, joint positions
  relative to the default pose, joint velocities, the previous action, the command) pushed into a
  ``history_len`` history (oldest first, back-filled at reset), a 32x24 planar depth image from
  the training camera by MuJoCo's own ray casting (``mj_multiRay``, same pose, fovy, geom
  groups, clipping and normalisation; no corruption), one onnxruntime call on one CPU thread;
- between them (physics rate): the position targets ``offset + scale * action`` on the G1's
  MuJoCo position actuators (kp, kv and effort limits compiled into the scene), ``mj_step``.

Latency as in training (:class:`Delays`): the position target reaches the actuators
``control_lag`` physics steps late (mjlab's actuator delay buffer: the default-pose target before
the first action), and the depth image is ``depth_lag`` control steps old (drawn every step from a
range, clamped to the frames since the reset, as mjlab's observation delay buffer).
:func:`rollout` runs one episode and reports, per step, the observation elements outside the
range seen in training (:class:`march.sim2sim.guard.RangeGuard`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import onnxruntime as ort

from march.sim2sim.deploy_bundle import INPUTS, OUTPUT, Bundle, UsageError
from march.sim2sim.depth_camera import DepthCamera
from march.sim2sim.guard import RangeGuard
from march.sim2sim.motors import MotorBus, MotorTableError, motor_table


@dataclass
class History:
    """The last ``length`` proprioception vectors, oldest first; back-filled on the first push."""

    length: int
    frames: list[np.ndarray] = field(default_factory=list)

    def push(self, x: np.ndarray) -> None:
        if not self.frames:
            self.frames = [x.copy() for _ in range(self.length)]
        else:
            self.frames = self.frames[1:] + [x.copy()]

    def array(self) -> np.ndarray:
        return np.stack(self.frames)[None].astype(np.float32)


@dataclass
class Delays:
    """One episode's latencies: the command lag [physics steps] and the depth lag range
    [control steps] (lo == hi: a fixed lag; lo < hi: drawn every control step from ``rng``)."""

    control_lag: int = 0
    depth_lag: tuple[int, int] = (0, 0)
    rng: np.random.Generator = field(default_factory=lambda: np.random.default_rng(0))

    @classmethod
    def draw_train(cls, latency: dict[str, Any], physics_dt: float, seed: int) -> Delays:
        """As training draws them (``deploy.json`` ``latency``): t ~ U(control_delay_ms),
        lag = round(t / physics_dt); the depth lag every step from depth_delay_steps."""
        rng = np.random.default_rng(seed)
        lo, hi = latency["control_delay_ms"]
        lag = int(round(float(rng.uniform(lo, hi)) / (physics_dt * 1e3)))
        d_lo, d_hi = (int(v) for v in latency["depth_delay_steps"])
        return cls(lag, (d_lo, d_hi), rng)

    @classmethod
    def measured(cls, spec: dict[str, Any], seed: int = 0) -> Delays:
        """The bundle's measured policy latency as the control delay, rounded up to the physics
        step (the target cannot reach the motors before the policy has answered)."""
        ms = spec["deploy"]["measured_latency_ms"] or 0.0
        lag = int(math.ceil(float(ms) / (spec["rates"]["physics_dt_s"] * 1e3) - 1e-9))
        return cls(lag, (0, 0), np.random.default_rng(seed))

    def draw_depth_lag(self) -> int:
        lo, hi = self.depth_lag
        return lo if lo == hi else int(self.rng.integers(lo, hi + 1))

    def describe(self, physics_dt: float) -> dict[str, Any]:
        return {
            "control_delay_ms": self.control_lag * physics_dt * 1e3,
            "control_lag_physics_steps": self.control_lag,
            "depth_delay_steps": list(self.depth_lag),
        }


class Sim2Sim:
    """One G1 in a bundle's scene, driven by the exported student."""

    def __init__(self, bundle: Bundle, course: str, threads: int = 1) -> None:
        try:
            self._bind(bundle, course)
        except (KeyError, IndexError) as err:  # a name the bundle gives that its scene lacks
            raise UsageError(
                f"the bundle's {course} scene does not fit its deploy.json: {err}"
            ) from None
        # The bytes Bundle.load checked against the bundle's SHA-256, not the file read again.
        self.session = policy_session(
            bundle.onnx_bytes or bundle.onnx_path, threads, bundle.onnx_path
        )

    def _bind(self, bundle: Bundle, course: str) -> None:
        """Find everything deploy.json names in the scene."""
        spec = bundle.spec
        self.spec = spec
        self.model = bundle.scene(course)
        self.data = mujoco.MjData(self.model)
        m = self.model
        robot, act, obs = spec["robot"], spec["action"], spec["observation"]
        pre = spec["scene_prefix"]  # the bundle names robot parts without the scene's prefix
        rates = spec["rates"]
        if abs(m.opt.timestep - rates["physics_dt_s"]) > 1e-12:
            raise UsageError("the scene's timestep differs from the bundle's physics_dt_s")
        self.physics_dt = float(m.opt.timestep)
        self.decimation = int(rates["decimation"])
        self.control_dt = float(rates["control_dt_s"])
        root = m.joint(pre + robot["root_joint"])
        self.root_q = int(m.jnt_qposadr[root.id])
        self.root_v = int(m.jnt_dofadr[root.id])
        self.root_body = m.body(pre + robot["root_body"]).id
        # The simulated robot's wiring (slot -> joint, actuator) and the bundle's motor table
        # (policy joint -> slot): joints are reached through motor slots, never by name.
        self.bus = MotorBus(m, pre)
        try:
            self.motor_index = motor_table(spec)
        except MotorTableError as err:
            raise UsageError(f"deploy.json joints: {err}") from None
        if (self.motor_index >= self.bus.num_motors).any():
            raise UsageError("deploy.json joints: a motor_index names a slot this G1 leaves unused")
        if act["joint_names"] != robot["joint_names"]:
            raise UsageError("deploy.json: action.joint_names is not robot.joint_names")
        self.qadr = self.bus.qadr[self.motor_index]  # policy order
        self.vadr = self.bus.vadr[self.motor_index]
        self.act_ids = self.bus.act[self.motor_index]
        self.default = np.asarray(robot["default_joint_pos"], dtype=np.float64)
        self.scale = np.asarray(act["scale"], dtype=np.float64)
        self.offset = np.asarray(act["offset"], dtype=np.float64)
        gyro = m.sensor(pre + obs["base_ang_vel_sensor"])
        self.gyro = slice(int(m.sensor_adr[gyro.id]), int(m.sensor_adr[gyro.id]) + 3)
        self.feet = np.array([m.site(pre + s).id for s in robot["foot_sites"]])
        self.terms = [(t["name"], int(t["dim"])) for t in obs["proprio_terms"]]
        self.command_spec = spec["command"]
        self.command = np.zeros(3)
        self.command[:2] = self.command_spec["lin_vel_x"], self.command_spec["lin_vel_y"]
        self.history = History(int(obs["history_len"]))
        self.camera = DepthCamera(m, spec["depth"])
        self.num_actions = len(self.act_ids)
        self.last_action = np.zeros(self.num_actions)
        self.delays = Delays()
        self.targets: list[np.ndarray] = []
        self.depth_frames: list[np.ndarray] = []
        self.guard = RangeGuard(spec)

    # -- state -------------------------------------------------------------------------------

    def set_command(self, vx: float, vy: float) -> None:
        """The forward and lateral command of the episode (the yaw rate stays the heading
        controller's); the caller checks the trained ranges (march.sim2sim.guard)."""
        self.command[0], self.command[1] = vx, vy

    def reset(self, cell: dict[str, Any], seed: int, delays: Delays | None = None) -> None:
        """Spawn as the evaluation env does: init pose at the cell's start point, with the
        reset's pose noise drawn from ``seed`` (none for seed < 0); joints at default, at rest."""
        m, d = self.model, self.data
        robot = self.spec["robot"]
        mujoco.mj_resetData(m, d)
        noise = dict.fromkeys(("x", "y", "z", "roll", "pitch", "yaw"), 0.0)
        if seed >= 0:
            rng = np.random.default_rng(seed)
            for k, (lo, hi) in robot["reset_pose_range"].items():
                noise[k] = float(rng.uniform(lo, hi))
        pos = np.asarray(cell["origin"]) + np.asarray(robot["init_root_pos"])
        pos += [noise["x"], noise["y"], noise["z"]]
        turn = np.zeros(4)
        mujoco.mju_euler2Quat(turn, np.array([noise["roll"], noise["pitch"], noise["yaw"]]), "XYZ")
        quat = np.zeros(4)
        mujoco.mju_mulQuat(quat, np.asarray(robot["init_root_quat_wxyz"], dtype=np.float64), turn)
        d.qpos[self.root_q : self.root_q + 3] = pos
        d.qpos[self.root_q + 3 : self.root_q + 7] = quat
        d.qpos[self.qadr] = self.default
        d.qvel[:] = 0.0
        self.start(cell, delays)

    def start(self, cell: dict[str, Any], delays: Delays | None = None) -> None:
        """Begin an episode from the state in ``data`` (qpos, qvel set by the caller)."""
        self.cell = cell
        self.origin = np.asarray(cell["origin"], dtype=np.float64)
        self.delays = delays if delays is not None else Delays()
        self.last_action = np.zeros(self.num_actions)
        self.history = History(self.history.length)
        self.depth_frames = []
        rest = self.joint_targets(self.last_action)  # the default-pose target
        self.targets = [rest.copy() for _ in range(self.delays.control_lag + 1)]
        self.data.ctrl[self.act_ids] = rest
        self.observe()

    def observe(self) -> None:
        """Derived quantities and sensors of the current state (``mj_forward``), this step's
        command and proprioception (as mjlab after its physics steps)."""
        mujoco.mj_forward(self.model, self.data)
        self.update_command()
        self.history.push(self.proprio())

    def update_command(self) -> None:
        """The velocity command of this step (mjlab's UniformVelocityCommand in evaluation):
        fixed v_x, v_y; the yaw rate steers the root's heading back to the course heading."""
        c = self.command_spec
        if not c["heading_control"]:
            self.command[2] = c["ang_vel_z"]
            return
        x_axis = self.data.xmat[self.root_body].reshape(3, 3)[:, 0]
        heading = math.atan2(x_axis[1], x_axis[0])
        err = (c["heading_target_rad"] - heading + math.pi) % (2.0 * math.pi) - math.pi
        lo, hi = c["ang_vel_z_range"]
        self.command[2] = min(max(c["heading_stiffness"] * err, lo), hi)

    def projected_gravity(self) -> np.ndarray:
        return self.data.xmat[self.root_body].reshape(3, 3).T @ np.array([0.0, 0.0, -1.0])

    def term_values(self) -> dict[str, np.ndarray]:
        """Each proprioception term of the current state, raw units (the bundle's definitions)."""
        d = self.data
        return {
            "base_ang_vel": d.sensordata[self.gyro].copy(),
            "projected_gravity": self.projected_gravity(),
            "joint_pos": d.qpos[self.qadr] - self.default,
            "joint_vel": d.qvel[self.vadr].copy(),
            "actions": self.last_action.copy(),
            "command": self.command.copy(),
        }

    def proprio(self) -> np.ndarray:
        """One proprioception vector in the bundle's term order."""
        values = self.term_values()
        parts = []
        for name, dim in self.terms:
            if name not in values or values[name].shape != (dim,):
                raise UsageError(f"proprioception term {name}({dim}) is not one this loop builds")
            parts.append(values[name])
        return np.concatenate(parts)

    def depth_image(self) -> np.ndarray:
        """(1, 1, H, W) normalised depth of the current kinematics (no delay)."""
        return self.camera.image(self.model, self.data)

    def inputs(self) -> dict[str, np.ndarray]:
        """The ONNX feeds from the current state (the history already holds this step); the
        depth image through the episode's depth delay."""
        frame = self.depth_image()
        keep = self.delays.depth_lag[1] + 1
        if not self.depth_frames:  # back-filled at reset: earlier frames read as the first
            self.depth_frames = [frame] * keep
        else:
            self.depth_frames = self.depth_frames[1:] + [frame]
        lag = self.delays.draw_depth_lag()
        return {
            "proprio_hist": self.history.array(),
            "command": self.command.astype(np.float32)[None],
            "depth": self.depth_frames[-1 - lag],
        }

    def act(self, feeds: dict[str, np.ndarray]) -> tuple[np.ndarray, float]:
        t0 = time.perf_counter()
        out = self.session.run([OUTPUT], feeds)[0]
        return out[0].astype(np.float64), (time.perf_counter() - t0) * 1e3

    def joint_targets(self, action: np.ndarray) -> np.ndarray:
        """Position targets [rad] of an action, policy order (mjlab's JointPositionAction:
        default pose + scale * action, no clip)."""
        return self.offset + self.scale * action

    def stored_action(self, action: np.ndarray) -> np.ndarray:
        """What the next observation reports as the previous action: the raw policy output,
        unclipped (mjlab's ``last_action`` reads the action manager's raw action)."""
        return action.copy()

    def step(self, action: np.ndarray) -> None:
        """One control step: the raw action kept as the next observation's previous action,
        its targets held for ``decimation`` physics steps (each through the command delay,
        written to motor slot ``motor_index[i]``), then the observation of the new state."""
        m, d = self.model, self.data
        action = np.asarray(action, dtype=np.float64)
        self.last_action = self.stored_action(action)
        target = self.joint_targets(action)
        for _ in range(self.decimation):
            self.targets = self.targets[1:] + [target]
            d.ctrl[self.act_ids] = self.targets[0]  # control_lag physics steps old
            mujoco.mj_step(m, d)
        self.observe()

    # -- course ------------------------------------------------------------------------------

    def progress(self) -> float:
        along = self.data.qpos[self.root_q] - self.origin[0]
        return float(min(max(along, 0.0), self.cell["course_length"]))

    def fell(self) -> bool:
        t = self.spec["terminations"]
        tilt = math.acos(float(np.clip(-self.projected_gravity()[2], -1.0, 1.0)))
        low = self.data.qpos[self.root_q + 2] - self.origin[2] < t["min_base_height_m"]
        feet = self.data.site_xpos[self.feet, 2] < self.origin[2] - t["max_foot_drop_m"]
        return bool(tilt > t["tilt_limit_rad"] or low or feet.any())


def policy_session(
    graph: Path | bytes, threads: int = 1, path: Path | None = None
) -> ort.InferenceSession:
    """onnxruntime on the CPU with ``threads`` threads, every graph optimisation on. ``graph``:
    the ONNX model's bytes (as read and checked: :attr:`Bundle.onnx_bytes`) or a file;
    ``path``: how messages name it (default ``graph``)."""
    path = path if path is not None else graph if isinstance(graph, Path) else Path("<bytes>")
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    try:
        model = graph if isinstance(graph, bytes) else str(graph)
        sess = ort.InferenceSession(model, opts, providers=["CPUExecutionProvider"])
    except Exception as err:  # noqa: BLE001 - any unloadable graph is the same user error
        raise UsageError(f"onnx={path}: onnxruntime cannot load it ({err})") from None
    names = [i.name for i in sess.get_inputs()]
    if names != list(INPUTS):
        raise UsageError(f"onnx={path}: inputs {names}, expected {list(INPUTS)}")
    return sess


def rollout(
    sim: Sim2Sim,
    seconds: float,
    frame: Callable[[mujoco.MjData], None] | None = None,
    max_steps: int | None = None,
    report: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Run one episode from the current state; the metrics of
    march.evaluation.protocol.rollout_metrics, and the observation elements outside training.

    As there, the step that ends the episode (fall or time-out) adds no torque or jerk, and the
    distance is the progress before that step. ``frame`` gets the state after every step (a
    video); ``report`` one line per flagged element and step.
    """
    horizon = math.ceil(seconds / sim.control_dt - 1e-9)
    if max_steps is not None:
        horizon = min(horizon, max_steps)
    cell = sim.cell
    torque = jerk = 0.0
    live_steps = jerk_steps = 0
    w1 = w2 = None
    policy_ms, depth_ms = [], []
    fell = False
    flagged_steps, by_term, first = 0, {}, []
    before = sim.progress()
    for t in range(1, horizon + 1):
        flags = sim.guard.check(sim.history.frames[-1])  # what the policy sees this step
        if flags:
            flagged_steps += 1
            for f in flags:
                by_term[f.term] = by_term.get(f.term, 0) + 1
                line = f.line(t - 1)
                if len(first) < 5:
                    first.append(line)
                if report is not None:
                    report(line)
        before = sim.progress()
        t0 = time.perf_counter()
        feeds = sim.inputs()
        depth_ms.append((time.perf_counter() - t0) * 1e3)
        action, ms = sim.act(feeds)
        policy_ms.append(ms)
        sim.step(action)
        if frame is not None:
            frame(sim.data)
        fell = sim.fell()
        if fell or t >= horizon:
            break
        live_steps += 1
        torque += float(np.abs(sim.data.actuator_force[sim.act_ids]).mean())
        w = sim.data.qvel[sim.root_v + 3 : sim.root_v + 6].copy()
        if w2 is not None and live_steps >= 3:
            jerk += float((np.abs(w - 2.0 * w1 + w2) / sim.control_dt**2).mean())
            jerk_steps += 1
        w2, w1 = w1, w
    return {
        "distance_m": before,
        "success": bool(before >= cell["goal_distance"] and not fell),
        "fell": fell,
        "abs_torque_nm": torque / max(live_steps, 1),
        "abs_ang_jerk": jerk / max(jerk_steps, 1),
        "steps": len(policy_ms),
        "seconds_simulated": len(policy_ms) * sim.control_dt,
        "ms_per_policy_call": float(np.median(policy_ms)),
        "ms_per_policy_call_p95": float(np.percentile(policy_ms, 95)),
        "ms_per_depth_image": float(np.median(depth_ms)),
        "out_of_range": {
            "steps_flagged": flagged_steps,
            "elements_by_term": by_term,
            "first": first,
        },
    }
