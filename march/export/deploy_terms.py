"""The parts of ``deploy.json`` a G1 owner drives the robot from: joints, observations, limits.

:func:`joint_table` lists every policy joint with its Unitree motor index, default position,
action scale and the PD gains, torque limit and position limits read from the compiled scene by
name; :func:`observation_terms` describes each proprioception term (units, frame, source, clip,
training noise) with the range seen in training (from the student's observation normaliser,
:func:`training_range`); :func:`command_ranges`, :func:`latency_ranges` and
:func:`depth_intrinsics` give the trained command ranges, the training latencies and the depth
camera as a pinhole. Names follow one scheme everywhere (JSON, ONNX metadata, Unitree): the
G1's own joint names without the scene's ``robot/`` prefix (:data:`SCENE_PREFIX`).
"""

from __future__ import annotations

import math
from pathlib import PurePath
from typing import Any

SCENE_PREFIX = "robot/"
"""mjlab prefixes every name of the robot entity in the compiled scene (joints, actuators,
bodies, sites, sensors); ``deploy.json`` names them without it."""

G1_MOTOR_ORDER = (
    "left_hip_pitch_joint",
    "left_hip_roll_joint",
    "left_hip_yaw_joint",
    "left_knee_joint",
    "left_ankle_pitch_joint",
    "left_ankle_roll_joint",
    "right_hip_pitch_joint",
    "right_hip_roll_joint",
    "right_hip_yaw_joint",
    "right_knee_joint",
    "right_ankle_pitch_joint",
    "right_ankle_roll_joint",
    "waist_yaw_joint",
    "waist_roll_joint",
    "waist_pitch_joint",
    "left_shoulder_pitch_joint",
    "left_shoulder_roll_joint",
    "left_shoulder_yaw_joint",
    "left_elbow_joint",
    "left_wrist_roll_joint",
    "left_wrist_pitch_joint",
    "left_wrist_yaw_joint",
    "right_shoulder_pitch_joint",
    "right_shoulder_roll_joint",
    "right_shoulder_yaw_joint",
    "right_elbow_joint",
    "right_wrist_roll_joint",
    "right_wrist_pitch_joint",
    "right_wrist_yaw_joint",
)
"""Unitree G1 (29 DoF) motor index -> joint: unitree_sdk2's ``G1JointIndex`` (LowCmd_.motor_cmd
and LowState_.motor_state slots; ankles in the default pitch/roll mode)."""

TRAIN_RANGE_SIGMAS = 4.0
"""The range seen in training of an observation element: mean +- 4 sigma of the student's
observation normaliser (sigma = std + eps, what the network divides by). The checkpoint keeps the
running mean and std, not minima and maxima."""
OUT_OF_RANGE_MARGIN_SIGMAS = 1.0
"""How far past that range (in the same sigmas) an element is flagged: a network input beyond
5 in normalised units."""

UNITS = {
    "base_ang_vel": "rad/s",
    "projected_gravity": "1 (unit vector)",
    "joint_pos": "rad",
    "joint_vel": "rad/s",
    "actions": "1 (policy output; target = default_pos + action_scale * action)",
    "command": "m/s, m/s, rad/s",
}


def portable_path(path: str | None) -> str:
    """A checkpoint path without the training machine's directories: ``<run>/<stage>/<file>``."""
    if not path:
        return ""
    return PurePath(*PurePath(str(path)).parts[-3:]).as_posix()


def bare(name: str) -> str:
    return name.removeprefix(SCENE_PREFIX)


def joint_table(
    model: Any, robot_joints: list[str], default_pos: list[float], scale: list[float]
) -> list[dict[str, Any]]:
    """One object per policy joint (policy order): name, Unitree motor index, default position,
    action scale, and from the compiled scene by name: kp, kd, torque limit, position limits."""
    import mujoco

    by_joint = {
        int(model.actuator_trnid[a, 0]): a
        for a in range(model.nu)
        if model.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT
    }
    rows = []
    for name, q0, s in zip(robot_joints, default_pos, scale, strict=True):
        j = model.joint(name).id
        a = by_joint[j]
        kp = float(model.actuator_gainprm[a, 0])
        if abs(float(model.actuator_biasprm[a, 1]) + kp) > 1e-9 * max(kp, 1.0):
            raise ValueError(f"actuator {model.actuator(a).name} is not a position servo")
        lo, hi = (float(v) for v in model.actuator_forcerange[a])
        if not model.actuator_forcelimited[a] or lo != -hi:
            raise ValueError(f"actuator {model.actuator(a).name}: no symmetric force limit")
        rows.append(
            {
                "name": bare(name),
                "motor_index": G1_MOTOR_ORDER.index(bare(name)),
                "default_pos": float(q0),
                "action_scale": float(s),
                "kp": kp,
                "kd": -float(model.actuator_biasprm[a, 2]),
                "torque_limit": hi,
                "pos_limits": [float(v) for v in model.jnt_range[j]],
            }
        )
    return rows


def training_range(payload: dict[str, Any], dims: list[tuple[str, int]]) -> dict[str, Any]:
    """Per proprioception term: the normaliser's mean and std and the range seen in training."""
    import torch

    sd = payload["student_state_dict"]
    eps = float(payload.get("config", {}).get("student", {}).get("normalizer_eps", 1e-2))
    out: dict[str, Any] = {}

    def stats(prefix: str) -> tuple[list[float], list[float]]:
        mean = torch.as_tensor(sd[f"{prefix}._mean"]).reshape(-1).double().tolist()
        std = torch.as_tensor(sd[f"{prefix}._std"]).reshape(-1).double().tolist()
        return mean, std

    def entry(mean: list[float], std: list[float]) -> dict[str, Any]:
        sig = [s + eps for s in std]
        k = TRAIN_RANGE_SIGMAS
        return {
            "mean": mean,
            "std": std,
            "lo": [m - k * s for m, s in zip(mean, sig, strict=True)],
            "hi": [m + k * s for m, s in zip(mean, sig, strict=True)],
        }

    mean, std = stats("proprio_normalizer")
    start = 0
    for name, dim in dims:
        out[name] = entry(mean[start : start + dim], std[start : start + dim])
        start += dim
    out["command_input"] = entry(*stats("command_normalizer"))
    out["rule"] = (
        f"range = mean +- {TRAIN_RANGE_SIGMAS:g} sigma, sigma = std + eps (eps {eps:g}, the "
        f"normaliser's); flagged when outside it by more than {OUT_OF_RANGE_MARGIN_SIGMAS:g} "
        "sigma, i.e. |x - mean| / sigma > "
        f"{TRAIN_RANGE_SIGMAS + OUT_OF_RANGE_MARGIN_SIGMAS:g} (the network's input in training "
        "sigmas)"
    )
    out["eps"] = eps
    out["margin_sigmas"] = OUT_OF_RANGE_MARGIN_SIGMAS
    return out


def observation_terms(
    dims: list[tuple[str, int]], env_cfg: Any, joint_names: list[str], imu_site: str, root: str
) -> list[dict[str, Any]]:
    """Each proprioception term: units, frame, source, clip, scale and training noise."""
    terms = env_cfg.observations["student"].terms
    joints = [bare(n) for n in joint_names]
    xyz = ["x", "y", "z"]
    describe = {
        "base_ang_vel": (
            f"IMU site {imu_site} (on the pelvis, not rotated against it: = {root} frame)",
            f"gyroscope at site {imu_site} (scene sensor imu_ang_vel); on the G1 "
            "LowState_.imu_state.gyroscope (the pelvis IMU)",
            xyz,
        ),
        "projected_gravity": (
            f"{root} (root body) frame",
            f"R^T (0, 0, -1), R the orientation of {root} in the world (the IMU at site "
            f"{imu_site}: LowState_.imu_state.quaternion, w x y z)",
            xyz,
        ),
        "joint_pos": (
            "joint space, relative to default_pos",
            "encoder position - default_pos (joints list order; LowState_.motor_state[i].q)",
            joints,
        ),
        "joint_vel": (
            "joint space",
            "encoder velocity (joints list order; LowState_.motor_state[i].dq)",
            joints,
        ),
        "actions": (
            "joint space (policy order)",
            "the previous policy output (0 at reset)",
            joints,
        ),
        "command": (
            "body (heading) frame, as training tracks it: v_x forward and v_y left along the "
            "root body's own x / y axes (mjlab's UniformVelocityCommand against "
            "root_link_lin_vel_b), yaw rate about the body's z (root_link_ang_vel_b)",
            "the velocity command of this step (the command section); on the robot the yaw "
            "rate comes from the heading controller on the IMU's yaw (heading_reference)",
            ["v_x", "v_y", "yaw_rate"],
        ),
    }
    out = []
    for name, dim in dims:
        cfg = terms[name]
        noise = getattr(cfg, "noise", None)
        frame, source, elements = describe[name]
        out.append(
            {
                "name": name,
                "dim": dim,
                "units": UNITS[name],
                "frame": frame,
                "source": source,
                "elements": elements,
                "clip": list(cfg.clip) if cfg.clip is not None else None,
                "scale": cfg.scale if cfg.scale is not None else 1.0,
                "training_noise_uniform": (
                    [float(noise.n_min), float(noise.n_max)] if noise is not None else None
                ),
            }
        )
    return out


def command_ranges(env: dict[str, Any]) -> dict[str, Any]:
    """The velocity command ranges the student was trained on (the checkpoint's ``env``)."""
    return {
        "lin_vel_x": [float(v) for v in env["command_vx"]],
        "lin_vel_y": [float(v) for v in env["command_vy"]],
        "ang_vel_z": [float(v) for v in env["command_yaw_rate"]],
        "meaning": "m/s, m/s, rad/s in the robot's body (heading) frame, as training tracks "
        "it (root_link_lin_vel_b, root_link_ang_vel_b z); v_x drawn once per episode, v_y as "
        "drawn (0 when the range is [0, 0]), the yaw rate from the heading controller clipped to "
        "ang_vel_z; a command outside these ranges is refused (march.sim2sim.guard)",
    }


def latency_ranges(cfg_dict: dict[str, Any], physics_dt: float) -> dict[str, Any]:
    """The control and depth delays the student was trained with (its dr and depth sections)."""
    dr = cfg_dict.get("dr", {})
    on = dr.get("name", "paper") != "none"
    ms = [float(v) for v in dr.get("control_delay_ms", (0.0, 20.0))] if on else [0.0, 0.0]
    steps = [int(v) for v in cfg_dict.get("depth", {}).get("delay_steps", (0, 1))]
    return {
        "control_delay_ms": ms,
        "control_delay_resolution_ms": physics_dt * 1e3,
        "control_delay_draw": "once per episode: t ~ U(control_delay_ms), lag = round(t / "
        "physics_dt) physics steps; the position target reaches the motors lag physics steps "
        "late (mjlab's actuator delay buffer; the default-pose target before the first action)",
        "depth_delay_steps": steps,
        "depth_delay_draw": "every control step: lag ~ U{lo..hi} control steps (mjlab's "
        "observation DelayBuffer, hold_prob 0), clamped to the frames since the reset",
    }


def depth_intrinsics(width: int, height: int, fovy_deg: float) -> dict[str, Any]:
    """The training camera as a pinhole in pixels (MuJoCo: square pixels, centred)."""
    fy = 0.5 * height / math.tan(0.5 * math.radians(fovy_deg))
    fovx = 2.0 * math.degrees(math.atan(width / height * math.tan(0.5 * math.radians(fovy_deg))))
    return {
        "fx_px": fy,
        "fy_px": fy,
        "cx_px": 0.5 * width,
        "cy_px": 0.5 * height,
        "fovx_deg": fovx,
        "fovy_deg": fovy_deg,
        "convention": "pixel (row i, col j) centre at (j + 0.5, i + 0.5); u = fx X/Z + cx, "
        "v = fy Y/Z + cy in the optical frame (X right, Y down, Z forward)",
    }


REAL_DEPTH_RECIPE = [
    "1. Read the depth frame in metres (RealSense z16: value x depth_scale, 0.001 m by default); "
    "RealSense depth is already planar (distance along the optical axis), as the training's.",
    "2. Lay the 32x24 pixel grid (row i from the top, col j from the left; intrinsics above: "
    "fovy 55.2 deg, fovx ~69.8 deg, both inside a D435's depth field of view) over the real "
    "camera's through both intrinsics; each pixel is the mean of the valid (> 0) camera pixels "
    "whose centres fall in it, invalid when fewer than half are valid (the training renders one "
    "ray per pixel; a single RealSense pixel is noisier than their mean). python -m "
    "march.robot camera does this.",
    "3. Invalid (0, NaN) -> max_range_m; clip to [min_range_m, max_range_m]; "
    "(d - min_range_m) / (max_range_m - min_range_m) -> [0, 1].",
    "4. Feed as depth (1, 1, 24, 32) float32, row 0 at the top of the image.",
]


G1_MODE_MACHINE = 5
"""``LowState_.mode_machine`` of a 29-DoF G1 (unitree_sdk2's G1 notes: 4 = 23-DoF, 5 = 29-DoF,
6 = 27-DoF, waist locked); ``march.robot`` refuses a LowState of another variant."""
G1_MODE_PR = 0
"""``LowCmd_.mode_pr``: 0 = PR (ankle and waist commanded as pitch / roll joints, the joints of
this policy), 1 = AB (the parallel linkage's motors A / B)."""
JOINT_VEL_LIMITS = (
    ("wrist_pitch", 22.0),
    ("wrist_yaw", 22.0),
    ("hip_roll", 20.0),
    ("knee", 20.0),
    ("hip_pitch", 32.0),
    ("hip_yaw", 32.0),
    ("waist_yaw", 32.0),
    ("", 37.0),
)
"""Joint velocity limit [rad/s] by name (first match): mjlab's G1 ``ElectricActuator``
``velocity_limit`` per motor (4010: 22, 7520-22: 20, 7520-14: 32, 5020 and the 2x5020 ankle /
waist linkages: 37)."""


def joint_vel_limit(name: str) -> float:
    return next(v for key, v in JOINT_VEL_LIMITS if key in name)


def robot_section(joint_names: list[str], control_dt: float) -> dict[str, Any]:
    """What ``march.robot`` needs beyond the policy: the message variant, start-up and shut-down
    timings and gains, velocity limits, watchdog, deadline budget, the heading reference."""
    return {
        "msg_type": "hg",
        "lowcmd_topic": "rt/lowcmd",
        "lowstate_topic": "rt/lowstate",
        "num_motor_slots": 35,
        "mode_machine": G1_MODE_MACHINE,
        "mode_pr": G1_MODE_PR,
        "motor_mode_enable": 1,
        "lowstate_hz": 500.0,
        "startup": {
            "zero_torque_s": 1.0,
            "ramp_s": 3.0,
            "ramp_gains": "the joints table's kp / kd (the policy's own)",
            "hold": "at the default pose with the joints' kp / kd until started (Enter, or "
            "start=auto after hold_s)",
            "hold_s": 1.0,
        },
        "shutdown": {
            # kd 1: Unitree's G1 low-level example's kd; stable in Unitree's MuJoCo bridge at 50
            # and 200 Hz, where kd 4 and 8 oscillate or diverge (docs/deploying.md, issue 58)
            "damping_kd": 1.0,
            "damping_s": 3.0,
            "meaning": "kp 0, kd damping_kd, q/dq/tau 0 on every used slot, sent for damping_s "
            "(then the loop exits; kd 1 as Unitree's G1 low-level example)",
        },
        "joint_vel_limits": [joint_vel_limit(n) for n in joint_names],
        "joint_vel_limits_meaning": "rad/s per policy joint (mjlab's G1 motor velocity limits); "
        "a measured |dq| above it is a guard flag",
        "watchdog_s": 0.05,
        "watchdog_meaning": "no new LowState (tick) for this long: damping",
        "deadline": {
            "period_s": control_dt,
            "max_missed_in_window": 5,
            "window_steps": 50,
            "max_missed_in_a_row": 3,
            "meaning": "a step misses its deadline when its command goes out after the end of "
            "its period; more than max_missed_in_window misses in the last window_steps steps, "
            "or max_missed_in_a_row in a row: damping",
        },
        "guards": "damping on: a proprioception element outside training (observation."
        "training_range, past its margin) or not finite, a |dq| above joint_vel_limits, a "
        "depth image that is all NaN / all zero (or mostly invalid), an action not finite or "
        "outside the actions' training range, a LowState with another mode_machine or a bad "
        "CRC",
        "heading_reference": "imu_yaw",
        "heading_meaning": "the heading controller's heading is the yaw of "
        "LowState_.imu_state.quaternion (w x y z), its target the IMU yaw when the policy "
        "starts (heading_target_rad is the simulation's world angle, not used on the robot)",
        "measured_latency_ms": None,
        "measured_latency_meaning": "p95 of one onnxruntime policy call on the export machine "
        "(one thread); python -m march.sim2sim delays=measured uses it as the control delay",
    }
