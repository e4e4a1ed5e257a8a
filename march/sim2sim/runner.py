"""``python -m march.sim2sim onnx=<student.onnx>``: the exported student in plain MuJoCo.

    python -m march.sim2sim onnx=outputs/<run>/student/student.onnx
    python -m march.sim2sim onnx=<bundle>/student.onnx course=stones difficulty=0.5 seed=3
    python -m march.sim2sim onnx=<bundle>/student.onnx seconds=10 out=rollout.mp4

A sim-to-sim check of the deployment bundle that ``python -m march.export`` writes beside the
ONNX (``<stem>.deploy.json`` and one compiled scene per course, ``<stem>.<course>.mjb.gz``).
Nothing of the training stack runs here: MuJoCo's C library (CPU), onnxruntime and numpy only -
no torch, warp, mjlab, Hydra or march module that imports them (tests/test_sim2sim.py checks
``sys.modules``). The loop does what the robot's computer does, at the rates of training:

- every control step (50 Hz): proprioception (IMU gyro, projected gravity, joint positions
  relative to the default pose, joint velocities, the previous action, the command) pushed into a
  ``history_len`` history (oldest first, back-filled at reset), a 32x24 planar depth image from
  the training camera by MuJoCo's own ray casting (``mj_multiRay``, same pose, fovy, geom
  groups, clipping and normalisation; no corruption), one onnxruntime call on one CPU thread;
- between them (physics rate): the position targets ``offset + scale * action`` on the G1's
  MuJoCo position actuators (kp, kv and effort limits compiled into the scene), ``mj_step``.

Arguments (``key=value`` words, as every march tool; parsed here without Hydra):

- ``onnx``: the exported student (required); its bundle must lie beside it.
- ``course``: ``hardware`` (start platform, 4 stones, goal) or ``stones`` (the evaluation grid).
- ``difficulty``: stones only - the grid level whose difficulty is nearest (0..1).
- ``seed``: stones: which course of that level (seed mod columns); both: the spawn pose noise
  (the evaluation's reset ranges; seed < 0 spawns exactly at the start point).
- ``seconds``: episode length [s] (ends earlier on a fall).
- ``out``: optional video file (.mp4/.gif) from the scene's tracking camera; needs OpenGL
  offscreen (``MUJOCO_GL=egl``, the default here as in mjlab, or ``osmesa``) - refused with one
  line, before simulating, where there is none.
- ``threads``: onnxruntime intra-op threads (1, as on the robot).

Prints ONE JSON object: ``distance_m``, ``success``, ``fell``, ``abs_torque_nm``,
``abs_ang_jerk`` (march.evaluation.protocol's definitions, repeated in the bundle), ``steps``,
``ms_per_policy_call`` (median), ``ms_per_policy_call_p95``, ``ms_per_depth_image``, the course
cell and the arguments. Bad input is one line on stderr and exit status 2, before simulating.

Why reading the bundle is safe: ``deploy.json`` is parsed with ``json`` (data only, no code);
the scene is MuJoCo's binary model format, read by MuJoCo's own loader, which checks the file's
header, version and every size before use (a file of another MuJoCo version is refused); the
ONNX file is a protobuf graph of tensor operators that onnxruntime executes (no Python, no
pickle). The JSON records the SHA-256 of the ONNX file and the scenes, checked before use.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import onnxruntime as ort

from march.sim2sim.deploy_bundle import INPUTS, OUTPUT, Bundle, UsageError
from march.sim2sim.depth_camera import DepthCamera

USAGE = (
    "usage: python -m march.sim2sim onnx=<student.onnx> [course=hardware|stones] "
    "[difficulty=0.5] [seed=0] [seconds=20] [out=rollout.mp4] [threads=1]"
)


@dataclass
class Args:
    """The command line, typed."""

    onnx: str = ""
    course: str = "hardware"
    difficulty: float = 0.5
    seed: int = 0
    seconds: float = 20.0
    out: str = ""
    threads: int = 1


def parse_args(argv: Sequence[str]) -> Args:
    """``key=value`` words into :class:`Args` (Hydra-style, without Hydra)."""
    args = Args()
    types = {k: type(v) for k, v in vars(args).items()}
    for word in argv:
        key, eq, value = word.partition("=")
        if not eq:
            raise UsageError(f"expected key=value, got {word!r}. {USAGE}")
        key = key.lstrip("+")
        if key not in types:
            raise UsageError(f"unknown key {key!r}; keys: {', '.join(types)}. {USAGE}")
        try:
            setattr(args, key, types[key](value))
        except ValueError:
            raise UsageError(f"{key}={value}: not a {types[key].__name__}") from None
    if not args.onnx:
        raise UsageError(f"give onnx=<student.onnx> (written by python -m march.export). {USAGE}")
    if args.course not in ("hardware", "stones"):
        raise UsageError(f"course={args.course}: choose hardware or stones")
    if not 0.0 <= args.difficulty <= 1.0:
        raise UsageError(f"difficulty={args.difficulty}: must be in [0, 1]")
    if not args.seconds > 0.0:
        raise UsageError(f"seconds={args.seconds}: must be > 0")
    if args.threads < 1:
        raise UsageError(f"threads={args.threads}: must be >= 1")
    if args.out and Path(args.out).suffix.lower() not in (".mp4", ".gif"):
        raise UsageError(f"out={args.out}: the video must end in .mp4 or .gif")
    return args


# ---------------------------------------------------------------------------------------------
# Sensors: proprioception (the depth image: march.sim2sim.depth_camera).


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


# ---------------------------------------------------------------------------------------------
# The robot-side loop.


class Sim2Sim:
    """One G1 in a bundle's scene, driven by the exported student."""

    def __init__(self, bundle: Bundle, course: str, threads: int = 1) -> None:
        spec = bundle.spec
        self.spec = spec
        self.model = bundle.scene(course)
        self.data = mujoco.MjData(self.model)
        m = self.model
        robot, act, obs = spec["robot"], spec["action"], spec["observation"]
        rates = spec["rates"]
        if abs(m.opt.timestep - rates["physics_dt_s"]) > 1e-12:
            raise UsageError("the scene's timestep differs from the bundle's physics_dt_s")
        self.decimation = int(rates["decimation"])
        self.control_dt = float(rates["control_dt_s"])
        root = m.joint(robot["root_joint"])
        self.root_q = int(m.jnt_qposadr[root.id])
        self.root_v = int(m.jnt_dofadr[root.id])
        self.root_body = m.body(robot["root_body"]).id
        names = robot["joint_names"]
        self.qadr = np.array([m.jnt_qposadr[m.joint(n).id] for n in names])
        self.vadr = np.array([m.jnt_dofadr[m.joint(n).id] for n in names])
        self.default = np.asarray(robot["default_joint_pos"], dtype=np.float64)
        self.act_q = np.array([m.jnt_qposadr[m.joint(n).id] for n in act["joint_names"]])
        self.act_ids = np.array([m.actuator(n).id for n in act["actuator_names"]])
        for a, n in zip(self.act_ids, act["joint_names"], strict=True):
            if m.actuator_trnid[a, 0] != m.joint(n).id:
                raise UsageError(f"actuator {m.actuator(a).name} does not drive joint {n}")
        self.scale = np.asarray(act["scale"], dtype=np.float64)
        self.offset = np.asarray(act["offset"], dtype=np.float64)
        gyro = m.sensor(obs["base_ang_vel_sensor"])
        self.gyro = slice(int(m.sensor_adr[gyro.id]), int(m.sensor_adr[gyro.id]) + 3)
        self.feet = np.array([m.site(s).id for s in robot["foot_sites"]])
        self.terms = [(t["name"], int(t["dim"])) for t in obs["proprio_terms"]]
        self.command_spec = spec["command"]
        self.command = np.zeros(3)
        self.history = History(int(obs["history_len"]))
        self.camera = DepthCamera(m, spec["depth"])
        self.num_actions = len(self.act_ids)
        self.last_action = np.zeros(self.num_actions)
        self.session = policy_session(bundle.onnx_path, threads)

    # -- state -------------------------------------------------------------------------------

    def reset(self, cell: dict[str, Any], seed: int) -> None:
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
        self.start(cell)

    def start(self, cell: dict[str, Any]) -> None:
        """Begin an episode from the state in ``data`` (qpos, qvel set by the caller)."""
        self.cell = cell
        self.origin = np.asarray(cell["origin"], dtype=np.float64)
        self.last_action = np.zeros(self.num_actions)
        self.history = History(self.history.length)
        self.data.ctrl[self.act_ids] = self.offset + self.scale * self.last_action
        mujoco.mj_forward(self.model, self.data)
        self.update_command()
        self.history.push(self.proprio())

    def update_command(self) -> None:
        """The velocity command of this step (mjlab's UniformVelocityCommand in evaluation):
        fixed v_x, v_y; the yaw rate steers the root's heading back to the course heading."""
        c = self.command_spec
        self.command[0], self.command[1] = c["lin_vel_x"], c["lin_vel_y"]
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

    def proprio(self) -> np.ndarray:
        """One proprioception vector in the bundle's term order."""
        d = self.data
        values = {
            "base_ang_vel": d.sensordata[self.gyro],
            "projected_gravity": self.projected_gravity(),
            "joint_pos": d.qpos[self.qadr] - self.default,
            "joint_vel": d.qvel[self.vadr],
            "actions": self.last_action,
            "command": self.command,
        }
        parts = []
        for name, dim in self.terms:
            if name not in values or values[name].shape != (dim,):
                raise UsageError(f"proprioception term {name}({dim}) is not one this loop builds")
            parts.append(values[name])
        return np.concatenate(parts)

    def inputs(self) -> dict[str, np.ndarray]:
        """The ONNX feeds from the current state (the history already holds this step)."""
        return {
            "proprio_hist": self.history.array(),
            "command": self.command.astype(np.float32)[None],
            "depth": self.camera.image(self.model, self.data),
        }

    def act(self, feeds: dict[str, np.ndarray]) -> tuple[np.ndarray, float]:
        t0 = time.perf_counter()
        out = self.session.run([OUTPUT], feeds)[0]
        return out[0].astype(np.float64), (time.perf_counter() - t0) * 1e3

    def step(self, action: np.ndarray) -> None:
        """One control step: targets held for ``decimation`` physics steps, then mj_forward
        (derived quantities and sensors of the new state, as mjlab before its observations)."""
        m, d = self.model, self.data
        self.last_action = action
        target = self.offset + self.scale * action
        for _ in range(self.decimation):
            d.ctrl[self.act_ids] = target
            mujoco.mj_step(m, d)
        mujoco.mj_forward(m, d)
        self.update_command()
        self.history.push(self.proprio())

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


def policy_session(path: Path, threads: int = 1) -> ort.InferenceSession:
    """onnxruntime on the CPU with ``threads`` threads, every graph optimisation on."""
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    try:
        sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    except Exception as err:  # noqa: BLE001 - any unloadable graph is the same user error
        raise UsageError(f"onnx={path}: onnxruntime cannot load it ({err})") from None
    names = [i.name for i in sess.get_inputs()]
    if names != list(INPUTS):
        raise UsageError(f"onnx={path}: inputs {names}, expected {list(INPUTS)}")
    return sess


class Video:
    """Offscreen frames from the scene's tracking camera (needs an OpenGL context)."""

    def __init__(self, model: mujoco.MjModel, path: str, fps: float) -> None:
        try:
            with warnings.catch_warnings():  # GLFW's own warnings say the same, twice
                warnings.simplefilter("ignore")
                self.renderer = mujoco.Renderer(model, 240, 320)  # sides divisible by 16
        except Exception as err:  # noqa: BLE001 - no GL backend: refuse in one line
            backend = os.environ.get("MUJOCO_GL", "default")
            raise UsageError(
                f"out={path}: no OpenGL context for offscreen video here with MUJOCO_GL={backend} "
                f"({type(err).__name__}); on Debian/Ubuntu install libegl1 libgl1-mesa-dri (EGL), "
                "or libosmesa6 and set MUJOCO_GL=osmesa; or drop out="
            ) from None
        cams = [model.camera(i).name for i in range(model.ncam)]
        self.camera = "robot/tracking" if "robot/tracking" in cams else -1
        self.path, self.fps, self.frames = path, fps, []

    def grab(self, data: mujoco.MjData) -> None:
        self.renderer.update_scene(data, camera=self.camera)
        self.frames.append(self.renderer.render().copy())

    def write(self) -> None:
        import imageio.v2 as imageio  # lazy: only for a video

        Path(self.path).parent.mkdir(parents=True, exist_ok=True)
        imageio.mimsave(self.path, self.frames, fps=self.fps)


def rollout(
    sim: Sim2Sim, seconds: float, video: Video | None = None, max_steps: int | None = None
) -> dict[str, Any]:
    """Run one episode from the current state; the metrics of
    march.evaluation.protocol.rollout_metrics.

    As there, the step that ends the episode (fall or time-out) adds no torque or jerk, and the
    distance is the progress before that step.
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
    before = sim.progress()
    for t in range(1, horizon + 1):
        before = sim.progress()
        t0 = time.perf_counter()
        feeds = sim.inputs()
        depth_ms.append((time.perf_counter() - t0) * 1e3)
        action, ms = sim.act(feeds)
        policy_ms.append(ms)
        sim.step(action)
        if video is not None:
            video.grab(sim.data)
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
    }


def run(args: Args) -> dict[str, Any]:
    """Load, check, simulate; the JSON row (also printed by :func:`main`)."""
    bundle = Bundle.load(args.onnx)
    sim = Sim2Sim(bundle, args.course, args.threads)
    cell = bundle.cell(args.course, args.difficulty, args.seed)
    video = Video(sim.model, args.out, 1.0 / sim.control_dt) if args.out else None
    sim.reset(cell, args.seed)
    t0 = time.perf_counter()
    row = rollout(sim, args.seconds, video)
    wall = time.perf_counter() - t0
    if video is not None:
        video.write()
    return {
        "course": args.course,
        "cell": [cell["row"], cell["col"]],
        "difficulty": cell["difficulty"],
        "goal_distance_m": cell["goal_distance"],
        "seed": args.seed,
        **row,
        "realtime_factor": row["seconds_simulated"] / wall if wall > 0 else None,
        "video": args.out or None,
        "onnx": str(args.onnx),
    }


def main(argv: Sequence[str] | None = None) -> None:
    try:
        args = parse_args(list(sys.argv[1:] if argv is None else argv))
        row = run(args)
    except UsageError as err:
        print(f"error: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    print(json.dumps(row))
