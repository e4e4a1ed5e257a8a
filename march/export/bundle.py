"""``python -m march.export student_ckpt=<file> [out=<folder> | out=<file>.onnx]``: a student as
an ONNX file plus the deployment bundle a robot-side loop needs.

    python -m march.export student_ckpt=outputs/<run>/student/latest.pt
    python -m march.export student_ckpt=outputs/<run>/student/latest.pt out=/tmp/g1_deploy
    python -m march.export student_ckpt=outputs/<run>/student/latest.pt out=/tmp/g1_student.onnx

The checkpoint decides the policy (:func:`march.learn.provenance.apply_checkpoint_config`): its
saved config's ``student`` section and its ``layout`` (proprio size, history length, image size,
action count) rebuild the :class:`~march.policies.student.StudentPolicy`, and its camera and
observation settings describe what deployment feeds; the command line does not change them.
:func:`march.export.onnx_graph.export_student_onnx` writes the fast deployment graph of the
deterministic ``act_inference`` (observation normalisers baked in;
:class:`~march.export.onnx_graph.DeployGraph`), checks
it against the policy with onnxruntime and times it on one CPU thread. ``out``: a file ending in
``.onnx``, or a folder that receives ``student.onnx``; default ``student.onnx`` next to the
checkpoint.

Beside ``<stem>.onnx`` it writes the deployment bundle (:func:`write_bundle`) that
``python -m march.sim2sim`` runs with MuJoCo and onnxruntime alone: ``<stem>.deploy.json``
(rates, robot joints and default pose, actions, proprioception order and history, command, depth
camera, terminations, metric definitions, each course's cells with their footholds, SHA-256 of
every file) and ``<stem>.hardware.mjb.gz`` / ``<stem>.stones.mjb.gz``: the evaluation env's
compiled MuJoCo model of each course (the G1 with its actuators, gains, effort limits, the depth
camera), DR and corruption off. A checkpoint whose layout is not the G1 env's (a test's toy
network) gets the ONNX file alone and a line saying why.

The file's ``metadata_props`` describe what deployment must feed (JSON where structured):

- ``proprio_hist`` (1, H, P): the last H proprioception vectors, oldest first; per step the terms
  ``base_ang_vel`` (3, rad/s, IMU), ``projected_gravity`` (3), ``joint_pos`` (A, rad, relative to
  the default pose), ``joint_vel`` (A, rad/s), ``actions`` (A, the previous output), ``command``
  (3) - the env's ``student`` observation group, raw (normalisation is inside the graph);
- ``command`` (1, 3): v_x [m/s], v_y [m/s], yaw rate [rad/s];
- ``depth`` (1, 1, 24, 32): chest-camera depth normalised to [0, 1]:
  (clip(d, min_range, max_range) - min_range) / (max_range - min_range), invalid / no return -> 1
  (``march.env.depth.normalize`` with the checkpoint's ``depth`` section);
- ``actions`` (1, A): joint position offsets as mjlab's G1 ``JointPositionAction``: target =
  default_joint_pos + action_scale * action, joints in ``action_joint_names`` order.

Plus ``variant``, ``teacher_ckpt``, ``iteration``, ``env_steps``, ``march_layout`` and
``deployment`` (the bundle's JSON file name, beside the ONNX).
A missing or wrong checkpoint is one line on stderr and exit status 2.
"""

from __future__ import annotations

import json
import re
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from march.config import MarchConfig
from march.config.cli import fail, run_tool
from march.env.build import PROPRIO_TERMS

USAGE = (
    "usage: python -m march.export student_ckpt=<file> [out=<folder> | out=<file>.onnx] "
    "[key=value ...]"
)
DEFAULT_NAME = "student.onnx"


def _one_line(err: BaseException, limit: int = 400) -> str:
    text = " ".join(str(err).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def proprio_term_dims(proprio_dim: int, num_actions: int) -> list[tuple[str, int]] | None:
    """(name, size) per proprioception term, or None if ``proprio_dim`` is not 9 + 3A."""
    dims = dict.fromkeys(PROPRIO_TERMS, 3)
    for k in ("joint_pos", "joint_vel", "actions"):
        dims[k] = num_actions
    if sum(dims.values()) != proprio_dim:
        return None
    return [(k, dims[k]) for k in PROPRIO_TERMS]


def g1_action_layout(num_actions: int) -> dict[str, list] | None:
    """Joint names (action order), action scales and default joint positions of mjlab's G1,
    or None when the checkpoint's action count is not the G1's."""
    try:
        import mujoco
        from mjlab.asset_zoo.robots.unitree_g1 import g1_constants as g1
    except Exception:  # noqa: BLE001 - metadata is best effort without mjlab
        return None
    free = mujoco.mjtJoint.mjJNT_FREE
    spec = g1.get_spec()  # keep the spec alive while its joints are read
    names = [str(j.name) for j in spec.joints if j.type != free]
    if len(names) != num_actions:
        return None

    def resolve(table: dict[str, float], name: str, default: float | None) -> float | None:
        for pattern, value in table.items():
            if re.fullmatch(pattern, name):
                return float(value)
        return default

    default_pos = dict(g1.get_g1_robot_cfg().init_state.joint_pos or {})
    return {
        "action_joint_names": names,
        "action_scale": [resolve(g1.G1_ACTION_SCALE, n, None) for n in names],
        "default_joint_pos": [resolve(default_pos, n, 0.0) for n in names],
    }


def metadata(payload: dict[str, Any]) -> dict[str, str]:
    """The ONNX ``metadata_props`` for a student checkpoint (str -> str)."""
    lay = payload["layout"]
    cfg = payload.get("config", {})
    depth = cfg.get("depth", {})
    lo, hi = float(depth.get("min_range", 0.1)), float(depth.get("max_range", 3.0))
    h, p, a = int(lay["history_len"]), int(lay["proprio_dim"]), int(lay["num_actions"])
    ih, iw = (int(x) for x in lay["image_hw"])
    terms = proprio_term_dims(p, a)
    per_step = ", ".join(f"{n}({d})" for n, d in terms) if terms else ", ".join(PROPRIO_TERMS)
    observations = {
        "proprio_hist": {
            "shape": [1, h, p],
            "order": "oldest first",
            "terms": [{"name": n, "dim": d} for n, d in terms] if terms else list(PROPRIO_TERMS),
        },
        "command": {"shape": [1, 3], "terms": ["v_x [m/s]", "v_y [m/s]", "yaw_rate [rad/s]"]},
        "depth": {
            "shape": [1, 1, ih, iw],
            "range": [0.0, 1.0],
            "normalisation": f"(clip(d, {lo:g}, {hi:g}) - {lo:g}) / ({hi:g} - {lo:g}); "
            "invalid or no return -> 1",
            "min_range_m": lo,
            "max_range_m": hi,
        },
    }
    actions = {
        "shape": [1, a],
        "meaning": "joint position offsets: target = default_joint_pos + action_scale * action "
        "(mjlab G1 JointPositionAction)",
    }
    meta = {
        "variant": str(lay["variant"]),
        "teacher_ckpt": str(payload.get("teacher_ckpt") or ""),
        "iteration": str(payload.get("iteration", "")),
        "env_steps": str(payload.get("env_steps", "")),
        "march_layout": json.dumps(lay),
        "observations": json.dumps(observations),
        "actions": json.dumps(actions),
        "proprio_terms": ",".join(PROPRIO_TERMS),
        # Overrides export_student_onnx's defaults: the env feeds normalised depth, not metres.
        "input_depth": f"float32[batch,1,{ih},{iw}] normalised depth in [0,1] "
        f"(0 = {lo:g} m, 1 = {hi:g} m or no return)",
        "input_proprio_hist": f"float32[batch,{h},{p}] oldest first; per step {per_step}",
        "output_actions": f"float32[batch,{a}] joint position offsets "
        "(target = default_joint_pos + action_scale * action)",
    }
    g1 = g1_action_layout(a)
    if g1 is not None:
        meta.update({k: json.dumps(v) for k, v in g1.items()})
    return meta


def rebuild_student(payload: dict[str, Any], path: str, student_cfg: Any = None) -> Any:
    """The StudentPolicy the checkpoint describes (its own config and layout), weights loaded.

    ``student_cfg``: the ``student`` section already taken from the checkpoint (by
    :func:`march.learn.provenance.apply_checkpoint_config`); None merges ``payload["config"]``'s.
    """
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    from march.config import ConfigError, StudentCfg
    from march.learn.distill import build_student

    try:
        layout = payload["layout"]
        if student_cfg is None:
            student_cfg = OmegaConf.to_object(
                OmegaConf.merge(OmegaConf.structured(StudentCfg), payload["config"]["student"])
            )
        policy = build_student(MarchConfig(student=student_cfg), layout, "cpu")
        policy.load_state_dict(payload["student_state_dict"])
    except KeyError as err:
        fail(f"student_ckpt={path}: the checkpoint lacks {err}; write it with march.train")
    except (OmegaConfBaseException, ConfigError, TypeError, ValueError, RuntimeError) as err:
        fail(f"student_ckpt={path}: cannot rebuild the student from its config ({_one_line(err)})")
    policy.eval()
    return policy


# ---------------------------------------------------------------------------------------------
# The deployment bundle: what a robot-side loop (march.sim2sim) needs beside the ONNX.

BUNDLE_FORMAT = 1
"""Version of the ``<stem>.deploy.json`` layout; march.sim2sim refuses other versions."""
COURSES = ("hardware", "stones")
"""Courses written into a bundle, one compiled scene each (``<stem>.<course>.mjb.gz``)."""


def bundle_files(onnx_path: Path) -> dict[str, Path]:
    """Files of the bundle beside ``onnx_path``: ``json`` and one gzipped MJB per course."""
    stem = onnx_path.with_suffix("")
    files = {"json": Path(f"{stem}.deploy.json")}
    files.update({c: Path(f"{stem}.{c}.mjb.gz") for c in COURSES})
    return files


def _sha256(path: Path) -> str:
    import hashlib

    h = hashlib.sha256()
    with path.open("rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def course_scene(cfg: MarchConfig, course: str) -> tuple[Any, Any, Any]:
    """(MjModel, env cfg, mjlab Scene) of the evaluation env on ``course``, DR and corruption off.

    The model is compiled the way mjlab's ``Simulation`` compiles the env's scene
    (``scene.spec.compile()`` then the env's ``MujocoCfg.apply``), without the warp copy:
    the same G1 (actuators, gains, effort limits, armature, joint order), the same depth camera
    and the same course geoms as ``env.sim.mj_model`` (tests/test_sim2sim.py compares them).
    """
    from dataclasses import replace

    from mjlab.scene import Scene

    from march.env.build import build_env_cfg

    ev = replace(cfg.eval, course=course, randomization=False, corruption=False)
    env_cfg = build_env_cfg(replace(cfg, eval=ev), "eval", num_envs=1)
    scene = Scene(env_cfg.scene, device="cpu")
    model = scene.spec.compile()
    env_cfg.sim.mujoco.apply(model)
    return model, env_cfg, scene


def _resolve(table: Any, name: str, default: float | None) -> float | None:
    """mjlab's name -> value tables: a float for all, or {regex: value} (first full match)."""
    if isinstance(table, (int, float)):
        return float(table)
    for pattern, value in (table or {}).items():
        if re.fullmatch(pattern, name):
            return float(value)
    return default


def _courses(env_cfg: Any, scene: Any) -> list[list[dict[str, Any]]]:
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


def _layout_problem(layout: dict[str, Any], cfg: MarchConfig, num_joints: int) -> str | None:
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
    bare = [n.removeprefix("robot/") for n in robot_joints]
    ent = env_cfg.scene.entities["robot"]
    init = ent.init_state
    act_cfg = env_cfg.actions["joint_pos"]
    if getattr(act_cfg, "clip", None) is not None or not act_cfg.use_default_offset:
        raise ValueError("the action term clips or has no default offset: not supported here")
    default_pos = [_resolve(init.joint_pos, n, 0.0) for n in bare]
    scale = [_resolve(act_cfg.scale, n, 1.0) for n in bare]
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
    return {
        "format": BUNDLE_FORMAT,
        "mujoco_version": mujoco.__version__,
        "checkpoint": {
            "variant": str(lay["variant"]),
            "iteration": payload.get("iteration"),
            "env_steps": payload.get("env_steps"),
            "teacher_ckpt": str(payload.get("teacher_ckpt") or ""),
            "layout": lay,
        },
        "rates": {
            "physics_dt_s": float(model.opt.timestep),
            "decimation": int(env_cfg.decimation),
            "control_dt_s": float(model.opt.timestep) * int(env_cfg.decimation),
        },
        "robot": {
            "root_joint": root.name,
            "root_body": model.body(int(model.jnt_bodyid[root.id])).name,
            "joint_names": robot_joints,
            "default_joint_pos": default_pos,
            "init_root_pos": [float(v) for v in init.pos],
            "init_root_quat_wxyz": [float(v) for v in init.rot],
            "reset_pose_range": {k: [float(v) for v in r] for k, r in reset.items()},
            "foot_sites": [f"robot/{s}" for s in FOOT_SITES],
        },
        "action": {
            "joint_names": robot_joints,
            "actuator_names": actuators,
            "scale": scale,
            "offset": default_pos,
            "meaning": "actuator ctrl (position target, rad) = offset + scale * action; MuJoCo "
            "position actuators (kp, kv, force range in the scene) track it at the physics rate",
        },
        "observation": {
            "proprio_terms": [
                {"name": n, "dim": k} for n, k in proprio_term_dims(int(lay["proprio_dim"]), a)
            ],
            "history_len": int(lay["history_len"]),
            "history_order": "oldest first; at reset every slot holds the first observation",
            "base_ang_vel_sensor": "robot/imu_ang_vel",
            "projected_gravity": "R_root^T (0, 0, -1), R_root the root body's world rotation",
            "joint_pos": "qpos - default_joint_pos, joints in joint_names order",
            "joint_vel": "qvel, joints in joint_names order",
            "actions": "the previous raw policy output (0 at reset)",
            "command": "the command section's (v_x, v_y, yaw rate) of this step",
            "when": "after the control step's last physics step and mj_forward (as mjlab)",
        },
        "command": _command_spec(env_cfg),
        "depth": {
            "camera": d.name,
            "parent_body": model.body(int(model.cam_bodyid[cam.id])).name,
            "pos": [float(v) for v in model.cam_pos[cam.id]],
            "quat_wxyz": [float(v) for v in model.cam_quat[cam.id]],
            "fovy_deg": float(model.cam_fovy[cam.id]),
            "width": int(d.width),
            "height": int(d.height),
            "min_range_m": float(d.min_range),
            "max_range_m": float(d.max_range),
            "geom_groups": sorted(cam_groups),
            "pixel_ray": "pixel (row i, col j), row 0 at the top: camera-frame direction "
            "normalize(((2(j+0.5)/W - 1) t a, (1 - 2(i+0.5)/H) t, -1)), t = tan(fovy/2), a = W/H",
            "depth": "planar: hit distance x cos(angle to the optical axis); no hit -> invalid",
            "normalisation": "invalid (<= 0) -> max_range; clip to [min_range, max_range]; "
            "(d - min_range) / (max_range - min_range)",
        },
        "terminations": {
            "tilt_limit_rad": math.radians(cfg.reward.tilt_limit_deg),
            "min_base_height_m": float(cfg.reward.min_base_height_m),
            "max_foot_drop_m": float(cfg.reward.max_foot_drop_m),
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


def write_bundle(
    cfg: MarchConfig, payload: dict[str, Any], onnx_path: Path, extra: dict[str, Any]
) -> dict[str, Path] | str:
    """Write ``<stem>.deploy.json`` and ``<stem>.<course>.mjb.gz`` beside ``onnx_path``.

    Returns the files, or a one-line reason when the checkpoint's layout is not the G1 env's.
    """
    import gzip
    import tempfile

    import mujoco

    files = bundle_files(onnx_path)
    from mjlab.asset_zoo.robots.unitree_g1 import g1_constants as g1

    free = mujoco.mjtJoint.mjJNT_FREE
    g1_spec = g1.get_spec()  # a cheap look before any scene is built
    problem = _layout_problem(
        payload["layout"], cfg, sum(1 for j in g1_spec.joints if j.type != free)
    )
    if problem is not None:
        return problem
    spec: dict[str, Any] | None = None
    courses: dict[str, Any] = {}
    for course in COURSES:
        try:
            model, env_cfg, scene = course_scene(cfg, course)
        except ValueError as err:  # e.g. a terrain.size too short for the hardware course
            fail(f"cannot build the {course} course: {_one_line(err)}")
        if spec is None:
            n_joints = sum(1 for j in range(model.njnt) if model.jnt_type[j] != free)
            problem = _layout_problem(payload["layout"], cfg, n_joints)
            if problem is not None:
                return problem
            spec = deployment_spec(cfg, payload, model, env_cfg, scene)
        with tempfile.TemporaryDirectory() as tmp:
            raw = Path(tmp) / "scene.mjb"
            mujoco.mj_saveModel(model, str(raw), None)
            # ~2x smaller (meshes); march.sim2sim loads it from memory
            files[course].write_bytes(gzip.compress(raw.read_bytes(), compresslevel=1))
        courses[course] = {
            "scene": files[course].name,
            "sha256": _sha256(files[course]),
            "cells": _courses(env_cfg, scene),
        }
    assert spec is not None
    spec["onnx"] = {"file": onnx_path.name, "sha256": _sha256(onnx_path), **extra}
    spec["courses"] = courses
    from march.learn.checkpoint import write_json_atomic

    write_json_atomic(spec, files["json"])
    return files


def export(cfg: MarchConfig, overrides: Sequence[str] = ()) -> dict[str, Any]:
    from march.config import ConfigError
    from march.export.onnx_graph import export_student_onnx
    from march.learn.checkpoint import CheckpointError, load_checkpoint
    from march.learn.provenance import apply_checkpoint_config

    path = cfg.student_ckpt
    if not path:
        fail(f"give student_ckpt=<file> (outputs/<run>/student/latest.pt). {USAGE}")
    try:
        payload = load_checkpoint(path, "student", "cpu")
    except CheckpointError as err:
        fail(_one_line(err))
    try:  # the checkpoint decides the network, the camera and the observation layout
        cfg = apply_checkpoint_config(cfg, payload, overrides, path, "student")
    except ConfigError as err:
        fail(_one_line(err))
    if not cfg.out:
        out = Path(path).resolve().parent / DEFAULT_NAME
    elif cfg.out.lower().endswith(".onnx"):
        out = Path(cfg.out)
    else:
        out = Path(cfg.out) / DEFAULT_NAME  # a folder: the bundle goes inside
    if out.exists() and not out.is_file():
        fail(f"out={cfg.out}: {out} exists and is not a file")
    policy = rebuild_student(payload, path, cfg.student)
    meta = metadata(payload)
    meta["deployment"] = bundle_files(out)["json"].name
    result = export_student_onnx(policy, out, meta)
    print(
        f"student {policy.variant}, iteration {payload.get('iteration')}, "
        f"{result['num_params']} parameters, opset {result['opset']}"
    )
    print(f"parity: max |onnx - torch| = {result['max_abs_diff']:.3e}")
    print(
        f"latency: median {result['latency_ms_median']:.3f} ms, "
        f"p95 {result['latency_ms_p95']:.3f} ms (onnxruntime, batch 1, one thread)"
    )
    print(f"wrote {result['path']}")
    extra = {k: result[k] for k in ("max_abs_diff", "latency_ms_median", "opset")}
    bundle = write_bundle(cfg, payload, out, extra)
    if isinstance(bundle, str):
        print(f"no deployment bundle: the checkpoint's layout does not fit the G1 env ({bundle})")
    else:
        for f in bundle.values():
            print(f"wrote {f}")
        print(f"run it: python -m march.sim2sim onnx={out}")
    result["bundle"] = bundle
    return result


def main(argv: Sequence[str] | None = None) -> None:
    args = list(sys.argv[1:] if argv is None else argv)
    run_tool(lambda cfg: export(cfg, args), args, usage=USAGE)


if __name__ == "__main__":
    main(sys.argv[1:])
