"""The deployment spec of a bundle: what ``<stem>.deploy.json`` says beside the ONNX file.

:func:`deployment_spec` describes the evaluation env's G1 for a robot-side loop (rates, joints and
default pose, actions and their actuators, proprioception order and history, the velocity
command, the depth camera, terminations, metric definitions) from the env's compiled MuJoCo model
(:func:`march.env.g1.course_scene`); :func:`course_cells` turns a course grid into data (spawn
point, goal and boxes per cell). :func:`proprio_term_dims` gives the proprioception terms that the
ONNX metadata (:mod:`march.export.bundle`) repeats with mjlab's G1 action layout
(:func:`march.env.g1.g1_action_layout`).
"""

from __future__ import annotations

from typing import Any

from march.config import MarchConfig
from march.env.build import PROPRIO_TERMS
from march.env.g1 import joint_value
from march.export.deploy_terms import (
    REAL_DEPTH_RECIPE,
    SCENE_PREFIX,
    bare,
    command_ranges,
    depth_intrinsics,
    joint_table,
    latency_ranges,
    observation_terms,
    portable_path,
    robot_section,
    training_range,
)

BUNDLE_FORMAT = 3
"""Version of the ``<stem>.deploy.json`` layout; march.sim2sim refuses other versions."""


def proprio_term_dims(proprio_dim: int, num_actions: int) -> list[tuple[str, int]] | None:
    """(name, size) per proprioception term, or None if ``proprio_dim`` is not 9 + 3A."""
    dims = dict.fromkeys(PROPRIO_TERMS, 3)
    for k in ("joint_pos", "joint_vel", "actions"):
        dims[k] = num_actions
    if sum(dims.values()) != proprio_dim:
        return None
    return [(k, dims[k]) for k in PROPRIO_TERMS]


def course_cells(env_cfg: Any, scene: Any) -> list[list[dict[str, Any]]]:
    """The course grid of a scene as data: per cell its spawn point, goal and boxes (world)."""
    import numpy as np

    from march.env.stone_terrain import foothold_table

    table = foothold_table(env_cfg.scene.terrain.terrain_generator)
    origins = np.asarray(scene.terrain.terrain_origins.cpu(), dtype=np.float64)
    grid = []
    for r, row in enumerate(table.layouts):
        cells = []
        for c, lay in enumerate(row):
            corner = origins[r, c] - lay.origin  # mjlab shifts a sub-terrain by its cell corner
            centre = lay.center + corner
            boxes = [
                [*map(float, centre[k]), *map(float, lay.half_size[k]), int(lay.role[k])]
                for k in range(lay.num_boxes)
            ]
            cells.append(
                {
                    "row": r,
                    "col": c,
                    "difficulty": float(lay.difficulty),
                    "kind": lay.kind,
                    "origin": [float(v) for v in origins[r, c]],
                    "goal_distance": float(lay.goal_distance),
                    "course_length": float(lay.course_length),
                    "boxes": boxes,
                }
            )
        grid.append(cells)
    return grid


def layout_problem(layout: dict[str, Any], cfg: MarchConfig, num_joints: int) -> str | None:
    a, p = int(layout["num_actions"]), int(layout["proprio_dim"])
    if a != num_joints:
        return f"{a} actions, the G1 has {num_joints} joints"
    if proprio_term_dims(p, a) is None:
        return f"proprio_dim {p} is not 9 + 3 x {a}"
    hw = [int(x) for x in layout["image_hw"]]
    if hw != [cfg.depth.height, cfg.depth.width]:
        return f"image {hw} is not the camera's {[cfg.depth.height, cfg.depth.width]}"
    return None


def _command_spec(env_cfg: Any) -> dict[str, Any]:
    """The evaluation's velocity command: fixed v_x, v_y; the yaw rate either fixed or mjlab's
    heading controller (recomputed every control step from the root's heading)."""
    twist = env_cfg.commands["twist"]
    r = twist.ranges
    for name in ("lin_vel_x", "lin_vel_y"):
        lo, hi = getattr(r, name)
        if lo != hi:
            raise ValueError(f"the evaluation command's {name} is a range {lo, hi}, not one value")
    spec: dict[str, Any] = {
        "lin_vel_x": float(r.lin_vel_x[0]),
        "lin_vel_y": float(r.lin_vel_y[0]),
        "heading_control": bool(twist.heading_command and twist.rel_heading_envs >= 1.0),
    }
    if spec["heading_control"]:
        lo, hi = r.heading
        if lo != hi:
            raise ValueError(f"the evaluation's heading target is a range {lo, hi}, not one value")
        spec.update(
            heading_target_rad=float(lo),
            heading_stiffness=float(twist.heading_control_stiffness),
            ang_vel_z_range=[float(v) for v in r.ang_vel_z],
            meaning="yaw rate = clip(heading_stiffness * wrap_to_pi(heading_target - heading), "
            "ang_vel_z_range), heading = atan2 of the root's x axis in the world (x-y); "
            "recomputed every control step after mj_forward, before the observation",
        )
    else:
        lo, hi = r.ang_vel_z
        if lo != hi:
            raise ValueError(f"the evaluation command's ang_vel_z is a range {lo, hi}")
        spec["ang_vel_z"] = float(lo)
    return spec


def deployment_spec(
    cfg: MarchConfig, payload: dict[str, Any], model: Any, env_cfg: Any, scene: Any
) -> dict[str, Any]:
    """Everything except the courses and file names: robot, rates, observation, depth, action."""
    import math

    import mujoco

    from march.env.terminations import FOOT_SITES

    free = mujoco.mjtJoint.mjJNT_FREE
    joints = [model.joint(j).name for j in range(model.njnt)]
    root = next(model.joint(j) for j in range(model.njnt) if model.jnt_type[j] == free)
    robot_joints = [n for j, n in enumerate(joints) if model.jnt_type[j] != free]
    bare_names = [bare(n) for n in robot_joints]
    ent = env_cfg.scene.entities["robot"]
    init = ent.init_state
    act_cfg = env_cfg.actions["joint_pos"]
    if getattr(act_cfg, "clip", None) is not None or not act_cfg.use_default_offset:
        raise ValueError("the action term clips or has no default offset: not supported here")
    default_pos = [joint_value(init.joint_pos, n, 0.0) for n in bare_names]
    scale = [joint_value(act_cfg.scale, n, 1.0) for n in bare_names]
    actuator_of = {}
    for a in range(model.nu):
        if model.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT:
            actuator_of[int(model.actuator_trnid[a, 0])] = model.actuator(a).name
    actuators = [actuator_of[model.joint(n).id] for n in robot_joints]
    lay = payload["layout"]
    d = cfg.depth
    cam_groups = set(d.geom_groups)
    for s in env_cfg.scene.sensors or ():  # mjlab renders the union with raycast sensors' groups
        groups = getattr(s, "include_geom_groups", None)
        if s.name != d.name and hasattr(s, "include_geom_groups"):
            cam_groups |= set(groups if groups is not None else range(6))
    cam = model.camera(d.name)
    reset = env_cfg.events["reset_base"].params["pose_range"]
    a = int(lay["num_actions"])
    dims = proprio_term_dims(int(lay["proprio_dim"]), a)
    trained = payload.get("config", {})
    imu_site = "imu_in_pelvis"
    root_body = model.body(int(model.jnt_bodyid[root.id])).name
    physics_dt = float(model.opt.timestep)
    return {
        "format": BUNDLE_FORMAT,
        "mujoco_version": mujoco.__version__,
        "names": "the G1's own names (Unitree's, as in the ONNX metadata) everywhere in this "
        f"file; in the compiled scenes the robot's joints, actuators, bodies, sites and sensors "
        f"carry scene_prefix ({SCENE_PREFIX!r}); the depth camera is a scene name",
        "scene_prefix": SCENE_PREFIX,
        "checkpoint": {
            "variant": str(lay["variant"]),
            "iteration": payload.get("iteration"),
            "env_steps": payload.get("env_steps"),
            "teacher_ckpt": portable_path(payload.get("teacher_ckpt")),
            "layout": lay,
        },
        "rates": {
            "physics_dt_s": physics_dt,
            "physics_hz": 1.0 / physics_dt,
            "decimation": int(env_cfg.decimation),
            "control_dt_s": physics_dt * int(env_cfg.decimation),
            "control_hz": 1.0 / (physics_dt * int(env_cfg.decimation)),
        },
        "joints": joint_table(model, robot_joints, default_pos, scale),
        "joints_meaning": "policy order (the order of joint_pos, joint_vel, actions); "
        "motor_index: unitree_sdk2 G1JointIndex (LowCmd_.motor_cmd slot); target = default_pos "
        "+ action_scale * action [rad]; torque = kp (target - q) - kd dq, clipped to "
        "+-torque_limit [N m]; pos_limits [rad] (the scene's joint range)",
        "robot": {
            "root_joint": bare(root.name),
            "root_body": bare(root_body),
            "joint_names": bare_names,
            "default_joint_pos": default_pos,
            "init_root_pos": [float(v) for v in init.pos],
            "init_root_quat_wxyz": [float(v) for v in init.rot],
            "reset_pose_range": {k: [float(v) for v in r] for k, r in reset.items()},
            "foot_sites": list(FOOT_SITES),
            "imu_site": imu_site,
        },
        "action": {
            "joint_names": bare_names,
            "actuator_names": [bare(n) for n in actuators],
            "scale": scale,
            "offset": default_pos,
            "clip": None,
            "meaning": "actuator ctrl (position target, rad) = offset + scale * action; MuJoCo "
            "position actuators (kp, kv, force range in the scene) track it at the physics rate",
        },
        "observation": {
            "proprio_terms": [{"name": n, "dim": k} for n, k in dims],
            "terms": observation_terms(dims, env_cfg, robot_joints, imu_site, bare(root_body)),
            "training_range": training_range(payload, dims),
            "history_len": int(lay["history_len"]),
            "history_order": "oldest first; at reset every slot holds the first observation",
            "base_ang_vel_sensor": "imu_ang_vel",
            "projected_gravity": "R_root^T (0, 0, -1), R_root the root body's world rotation",
            "joint_pos": "qpos - default_joint_pos, joints in joint_names order",
            "joint_vel": "qvel, joints in joint_names order",
            "actions": "the previous raw policy output (0 at reset)",
            "command": "the command section's (v_x, v_y, yaw rate) of this step",
            "when": "after the control step's last physics step and mj_forward (as mjlab)",
        },
        "deploy": robot_section(bare_names, physics_dt * int(env_cfg.decimation)),
        "command": _command_spec(env_cfg),
        "command_ranges": command_ranges(trained.get("env") or asdict_env(cfg)),
        "latency": latency_ranges(trained or {"dr": asdict_section(cfg.dr)}, physics_dt),
        "depth": {
            "camera": d.name,
            "parent_body": bare(model.body(int(model.cam_bodyid[cam.id])).name),
            "pos": [float(v) for v in model.cam_pos[cam.id]],
            "quat_wxyz": [float(v) for v in model.cam_quat[cam.id]],
            "pose_meaning": "camera frame in the parent body's frame (MuJoCo camera: looks "
            f"along -z, +y up): the mount at {list(d.pos)} m in torso_link, pitched "
            f"{d.pitch_deg:g} deg down from the torso's +x",
            "fovy_deg": float(model.cam_fovy[cam.id]),
            "width": int(d.width),
            "height": int(d.height),
            "intrinsics": depth_intrinsics(int(d.width), int(d.height), float(d.fovy)),
            "units": "input: normalised depth in [0, 1] (0 = min_range_m, 1 = max_range_m or no "
            "return); metres before the normalisation",
            "min_range_m": float(d.min_range),
            "max_range_m": float(d.max_range),
            "geom_groups": sorted(cam_groups),
            "pixel_ray": "pixel (row i, col j), row 0 at the top: camera-frame direction "
            "normalize(((2(j+0.5)/W - 1) t a, (1 - 2(i+0.5)/H) t, -1)), t = tan(fovy/2), a = W/H",
            "depth": "planar: hit distance x cos(angle to the optical axis); no hit -> invalid",
            "normalisation": "invalid (<= 0) -> max_range; clip to [min_range, max_range]; "
            "(d - min_range) / (max_range - min_range)",
            "from_a_real_camera": REAL_DEPTH_RECIPE,
        },
        "terminations": {
            "tilt_limit_rad": math.radians(cfg.termination.tilt_limit_deg),
            "min_base_height_m": float(cfg.termination.min_base_height_m),
            "max_foot_drop_m": float(cfg.termination.max_foot_drop_m),
            "meaning": "fall: acos(-g_b,z) > tilt_limit; root z - origin z < min_base_height; "
            "a foot site below origin z - max_foot_drop",
        },
        "metrics": {
            "distance_m": "root x - origin x at the last control step, clipped to "
            "[0, course_length]",
            "success": "distance >= goal_distance and no fall",
            "abs_torque_nm": "mean over control steps and actuators of |actuator_force|",
            "abs_ang_jerk": "mean over control steps (from the third) and axes of "
            "|(w_t - 2 w_t-1 + w_t-2)| / dt^2, w the root angular velocity in the body frame",
        },
    }


def asdict_env(cfg: MarchConfig) -> dict[str, Any]:
    """The command ranges of ``cfg.env`` as the checkpoint's saved config spells them."""
    return {k: list(getattr(cfg.env, k)) for k in ("command_vx", "command_vy", "command_yaw_rate")}


def asdict_section(section: Any) -> dict[str, Any]:
    from dataclasses import asdict

    return asdict(section)
