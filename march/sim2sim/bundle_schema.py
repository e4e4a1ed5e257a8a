"""The schema of ``<stem>.deploy.json``: every key required, every value typed (json only).

:func:`check_spec` walks a parsed bundle against :data:`SCHEMA` and raises :class:`SchemaError`
with one line naming the first key that is missing, unknown or of the wrong type (``joints[3]
.kp: expected a number, got 'abc'``), so that nothing later in the loop meets a ``KeyError``,
``IndexError`` or a string where a number belongs. Types: ``int``, ``num`` (int or float,
finite), ``str``, ``bool``, ``None``; ``[t]`` a list of t, ``[t, n]`` of exactly n; a dict a
fixed set of keys; :class:`Opt` a value that may also be null; :class:`Map` a dict of any keys.
Cross-checks that need two keys (sizes that must agree, paths that must stay in the bundle) are
in :mod:`march.sim2sim.deploy_bundle`.

:func:`check_motor_ranges` (run by :func:`check_spec`, and again by the robot loop on the values
it will send) holds everything that reaches a motor to the G1's physical ranges
(:data:`G1_MOTORS`): kp, kd >= 0 and at most the motor's :data:`KP_MAX_ERROR_RAD` /
:data:`KD_MAX_S` bounds, a torque limit > 0 and within the motor's rating, the default pose
inside the joint's limits, 0 < |action scale| <= :data:`MAX_ACTION_SCALE_RAD`, the damping kd
within every motor's kd bound.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any


class UsageError(ValueError):
    """Bad arguments or an unusable bundle: one line for the user (also
    ``march.sim2sim.deploy_bundle.UsageError``; here, where no MuJoCo is imported, so that the
    robot's supervisor and camera raise and catch it without MuJoCo)."""


class SchemaError(ValueError):
    """A deploy.json that does not match the schema: one line."""


@dataclass(frozen=True)
class Opt:
    """``kind`` or null."""

    kind: Any


@dataclass(frozen=True)
class Map:
    """A dict whose values are ``kind``; its keys any of ``keys`` (None: any key), none
    required."""

    kind: Any
    keys: tuple[str, ...] | None = None


NUM, INT, STR, BOOL = "num", "int", "str", "bool"
PAIR = [NUM, 2]
RANGE = {"mean": [NUM], "std": [NUM], "lo": [NUM], "hi": [NUM]}
JOINT = {
    "name": STR,
    "motor_index": INT,
    "default_pos": NUM,
    "action_scale": NUM,
    "kp": NUM,
    "kd": NUM,
    "torque_limit": NUM,
    "pos_limits": PAIR,
}
TERM = {
    "name": STR,
    "dim": INT,
    "units": STR,
    "frame": STR,
    "source": STR,
    "elements": [STR],
    "clip": Opt(PAIR),
    "scale": NUM,
    "training_noise_uniform": Opt(PAIR),
}
CELL = {
    "row": INT,
    "col": INT,
    "difficulty": NUM,
    "kind": STR,
    "origin": [NUM, 3],
    "goal_distance": NUM,
    "course_length": NUM,
    "boxes": [[NUM, 6]],
}
COURSE = {"scene": STR, "sha256": STR, "cells": [[CELL]]}
SCHEMA: dict[str, Any] = {
    "format": INT,
    "mujoco_version": STR,
    "names": STR,
    "scene_prefix": STR,
    "checkpoint": {
        "variant": STR,
        "iteration": Opt(INT),
        "env_steps": Opt(INT),
        "teacher_ckpt": STR,
        "layout": {
            "variant": STR,
            "proprio_dim": INT,
            "history_len": INT,
            "image_hw": [INT, 2],
            "num_actions": INT,
        },
    },
    "rates": {
        "physics_dt_s": NUM,
        "physics_hz": NUM,
        "decimation": INT,
        "control_dt_s": NUM,
        "control_hz": NUM,
    },
    "joints": [JOINT],
    "joints_meaning": STR,
    "robot": {
        "root_joint": STR,
        "root_body": STR,
        "joint_names": [STR],
        "default_joint_pos": [NUM],
        "init_root_pos": [NUM, 3],
        "init_root_quat_wxyz": [NUM, 4],
        # the axes the evaluation's reset draws (a subset of six)
        "reset_pose_range": Map(PAIR, ("x", "y", "z", "roll", "pitch", "yaw")),
        "foot_sites": [STR],
        "imu_site": STR,
    },
    "action": {
        "joint_names": [STR],
        "actuator_names": [STR],
        "scale": [NUM],
        "offset": [NUM],
        "clip": None,
        "meaning": STR,
    },
    "observation": {
        "proprio_terms": [{"name": STR, "dim": INT}],
        "terms": [TERM],
        "training_range": {
            **dict.fromkeys(
                (
                    "base_ang_vel",
                    "projected_gravity",
                    "joint_pos",
                    "joint_vel",
                    "actions",
                    "command",
                    "command_input",
                ),
                RANGE,
            ),
            "rule": STR,
            "eps": NUM,
            "margin_sigmas": NUM,
        },
        "history_len": INT,
        "history_order": STR,
        "base_ang_vel_sensor": STR,
        "projected_gravity": STR,
        "joint_pos": STR,
        "joint_vel": STR,
        "actions": STR,
        "command": STR,
        "when": STR,
    },
    "deploy": {
        "msg_type": STR,
        "lowcmd_topic": STR,
        "lowstate_topic": STR,
        "num_motor_slots": INT,
        "mode_machine": INT,
        "mode_pr": INT,
        "motor_mode_enable": INT,
        "lowstate_hz": NUM,
        "startup": {
            "zero_torque_s": NUM,
            "ramp_s": NUM,
            "ramp_gains": STR,
            "hold": STR,
            "hold_s": NUM,
        },
        "shutdown": {"damping_kd": NUM, "damping_s": NUM, "meaning": STR},
        "joint_vel_limits": [NUM],
        "joint_vel_limits_meaning": STR,
        "watchdog_s": NUM,
        "watchdog_meaning": STR,
        "deadline": {
            "period_s": NUM,
            "max_missed_in_window": INT,
            "window_steps": INT,
            "max_missed_in_a_row": INT,
            "meaning": STR,
        },
        "guards": STR,
        "heading_reference": STR,
        "heading_meaning": STR,
        "measured_latency_ms": Opt(NUM),
        "measured_latency_meaning": STR,
    },
    "command": Map(Any),  # two shapes (heading control or a fixed yaw rate): checked below
    "command_ranges": {"lin_vel_x": PAIR, "lin_vel_y": PAIR, "ang_vel_z": PAIR, "meaning": STR},
    "latency": {
        "control_delay_ms": PAIR,
        "control_delay_resolution_ms": NUM,
        "control_delay_draw": STR,
        "depth_delay_steps": [INT, 2],
        "depth_delay_draw": STR,
    },
    "depth": {
        "camera": STR,
        "parent_body": STR,
        "pos": [NUM, 3],
        "quat_wxyz": [NUM, 4],
        "pose_meaning": STR,
        "fovy_deg": NUM,
        "width": INT,
        "height": INT,
        "intrinsics": {
            "fx_px": NUM,
            "fy_px": NUM,
            "cx_px": NUM,
            "cy_px": NUM,
            "fovx_deg": NUM,
            "fovy_deg": NUM,
            "convention": STR,
        },
        "units": STR,
        "min_range_m": NUM,
        "max_range_m": NUM,
        "geom_groups": [INT],
        "pixel_ray": STR,
        "depth": STR,
        "normalisation": STR,
        "from_a_real_camera": [STR],
    },
    "terminations": {
        "tilt_limit_rad": NUM,
        "min_base_height_m": NUM,
        "max_foot_drop_m": NUM,
        "meaning": STR,
    },
    "metrics": dict.fromkeys(("distance_m", "success", "abs_torque_nm", "abs_ang_jerk"), STR),
    "onnx": {
        "file": STR,
        "sha256": STR,
        "max_abs_diff": NUM,
        "latency_ms_median": NUM,
        "latency_ms_p95": NUM,
        "opset": INT,
    },
    "courses": {"hardware": COURSE, "stones": COURSE},
}
HEADING = {
    "lin_vel_x": NUM,
    "lin_vel_y": NUM,
    "heading_control": BOOL,
    "heading_target_rad": NUM,
    "heading_stiffness": NUM,
    "ang_vel_z_range": PAIR,
    "meaning": STR,
}
FIXED_YAW = {"lin_vel_x": NUM, "lin_vel_y": NUM, "heading_control": BOOL, "ang_vel_z": NUM}


def _kind(kind: Any) -> str:
    if isinstance(kind, dict) or isinstance(kind, Map):
        return "an object"
    if isinstance(kind, list):
        return "a list"
    return {NUM: "a number", INT: "an integer", STR: "a string", BOOL: "true / false"}.get(
        kind, "null"
    )


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def check(value: Any, kind: Any, where: str) -> None:
    """Raise :class:`SchemaError` at the first place ``value`` does not match ``kind``."""
    if kind is Any:
        return
    if isinstance(kind, Opt):
        if value is not None:
            check(value, kind.kind, where)
        return
    ok = True
    if kind is None:
        ok = value is None
    elif kind == NUM:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        if ok and not math.isfinite(value):
            raise SchemaError(f"{where}: {value!r} is not a finite number")
    elif kind == INT:
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif kind == STR:
        ok = isinstance(value, str)
    elif kind == BOOL:
        ok = isinstance(value, bool)
    elif isinstance(kind, Map):
        ok = isinstance(value, dict)
        if ok:
            for k, v in value.items():
                if kind.keys is not None and k not in kind.keys:
                    raise SchemaError(f"{where}: unknown key {k!r}")
                check(v, kind.kind, f"{where}.{k}")
    elif isinstance(kind, dict):
        ok = isinstance(value, dict)
        if ok:
            missing = [k for k in kind if k not in value]
            if missing:
                raise SchemaError(f"{where}: missing key {missing[0]!r}")
            extra = [k for k in value if k not in kind]
            if extra:
                raise SchemaError(f"{where}: unknown key {extra[0]!r}")
            for k, sub in kind.items():
                check(value[k], sub, f"{where}.{k}")
    elif isinstance(kind, list):
        ok = isinstance(value, list)
        if ok:
            if len(kind) == 2 and len(value) != kind[1]:
                raise SchemaError(f"{where}: {len(value)} entries, expected {kind[1]}")
            if len(kind) == 1 and not value:
                raise SchemaError(f"{where}: an empty list")
            for i, v in enumerate(value):
                check(v, kind[0], f"{where}[{i}]")
    if not ok:
        raise SchemaError(f"{where}: expected {_kind(kind)}, got {_short(value)}")


G1_MOTORS: tuple[tuple[str, str, float], ...] = (
    ("wrist_pitch", "4010", 5.0),
    ("wrist_yaw", "4010", 5.0),
    ("hip_roll", "7520-22", 139.0),
    ("knee", "7520-22", 139.0),
    ("hip_pitch", "7520-14", 88.0),
    ("hip_yaw", "7520-14", 88.0),
    ("waist_yaw", "7520-14", 88.0),
    ("ankle", "2x5020", 50.0),
    ("waist", "2x5020", 50.0),
    ("", "5020", 25.0),
)
"""(joint-name part, motor, rated peak torque [N m]), first match: Unitree's G1 motors as mjlab's
G1 model rates them (4010 5, 7520-22 139, 7520-14 88, the ankle / waist 2x5020 linkages 50, 5020
25)."""
KP_MAX_ERROR_RAD = 0.1
"""kp at most rating / 0.1 rad [N m / rad]: the rated torque at 0.1 rad of error (7520-22: 1390,
5020: 250, 4010: 50; Unitree's own G1 examples use 40-150)."""
KD_MAX_S = 0.2
"""kd at most max(10, rating x 0.2 s) [N m s / rad] (7520-22: 27.8, 5020 and 4010: 10, so
Unitree's damping kd 8 fits every motor)."""
MAX_ACTION_SCALE_RAD = 1.0
"""|action scale| at most 1 rad per unit of action (mjlab's G1: 0.07-0.44)."""
POS_LIMIT_MARGIN_RAD = 0.1
"""A measured joint position this far past its limit is a sensor or model fault (the robot
loop's reading check; the default pose must be inside the limits themselves)."""


G1_JOINT_RANGES: dict[str, tuple[float, float]] = {
    "left_hip_pitch_joint": (-2.5307, 2.8798),
    "left_hip_roll_joint": (-0.5236, 2.9671),
    "left_hip_yaw_joint": (-2.7576, 2.7576),
    "left_knee_joint": (-0.087267, 2.8798),
    "left_ankle_pitch_joint": (-0.87267, 0.5236),
    "left_ankle_roll_joint": (-0.2618, 0.2618),
    "right_hip_pitch_joint": (-2.5307, 2.8798),
    "right_hip_roll_joint": (-2.9671, 0.5236),
    "right_hip_yaw_joint": (-2.7576, 2.7576),
    "right_knee_joint": (-0.087267, 2.8798),
    "right_ankle_pitch_joint": (-0.87267, 0.5236),
    "right_ankle_roll_joint": (-0.2618, 0.2618),
    "waist_yaw_joint": (-2.618, 2.618),
    "waist_roll_joint": (-0.52, 0.52),
    "waist_pitch_joint": (-0.52, 0.52),
    "left_shoulder_pitch_joint": (-3.0892, 2.6704),
    "left_shoulder_roll_joint": (-1.5882, 2.2515),
    "left_shoulder_yaw_joint": (-2.618, 2.618),
    "left_elbow_joint": (-1.0472, 2.0944),
    "left_wrist_roll_joint": (-1.97222, 1.97222),
    "left_wrist_pitch_joint": (-1.61443, 1.61443),
    "left_wrist_yaw_joint": (-1.61443, 1.61443),
    "right_shoulder_pitch_joint": (-3.0892, 2.6704),
    "right_shoulder_roll_joint": (-2.2515, 1.5882),
    "right_shoulder_yaw_joint": (-2.618, 2.618),
    "right_elbow_joint": (-1.0472, 2.0944),
    "right_wrist_roll_joint": (-1.97222, 1.97222),
    "right_wrist_pitch_joint": (-1.61443, 1.61443),
    "right_wrist_yaw_joint": (-1.61443, 1.61443),
}
"""The G1's (29 DoF) joint ranges [rad], march's own table: mjlab's G1 model, equal to Unitree's
``g1_29dof.xml`` (unitree_mujoco). A bundle's ``pos_limits`` must lie inside them and its default
pose inside both: a bundle cannot widen the range it is checked against (issue 59)."""
JOINT_RANGE_TOL_RAD = 1e-4
"""Rounding a bundle may carry against the table's values."""


def motor_of(joint: str) -> tuple[str, float]:
    """The G1 motor driving ``joint`` and its rated torque [N m]."""
    return next((motor, torque) for part, motor, torque in G1_MOTORS if part in joint)


def gain_bounds(joint: str) -> tuple[float, float, float]:
    """(kp max [N m/rad], kd max [N m s/rad], rated torque [N m]) of ``joint``'s motor."""
    _, torque = motor_of(joint)
    return torque / KP_MAX_ERROR_RAD, max(10.0, torque * KD_MAX_S), torque


def check_motor_ranges(spec: Any) -> None:
    """Everything that reaches a motor within the G1's physical ranges; one line at the first
    value out of range (``joints[3].kp = -500 (left_knee_joint, 7520-22): outside [0, 1390]``)."""
    for i, j in enumerate(spec["joints"]):
        name = j["name"]
        motor, _ = motor_of(name)
        kp_max, kd_max, rated = gain_bounds(name)
        where = f"deploy.json.joints[{i}]"
        for key, lo, hi in (("kp", 0.0, kp_max), ("kd", 0.0, kd_max)):
            if not lo <= j[key] <= hi:
                raise SchemaError(
                    f"{where}.{key} = {j[key]:g} ({name}, {motor}): outside [{lo:g}, {hi:g}]"
                )
        if not 0.0 < j["torque_limit"] <= rated * (1 + 1e-6):
            raise SchemaError(
                f"{where}.torque_limit = {j['torque_limit']:g} ({name}, {motor}): outside "
                f"(0, {rated:g}] N m, the motor's rating"
            )
        lo, hi = j["pos_limits"]
        if not lo < hi:
            raise SchemaError(f"{where}.pos_limits = {[lo, hi]}: empty")
        if name not in G1_JOINT_RANGES:
            raise SchemaError(f"{where}.name = {name!r}: not a joint of the G1 (29 DoF)")
        g_lo, g_hi = G1_JOINT_RANGES[name]
        if lo < g_lo - JOINT_RANGE_TOL_RAD or hi > g_hi + JOINT_RANGE_TOL_RAD:
            raise SchemaError(
                f"{where}.pos_limits = {[lo, hi]} ({name}): wider than the G1's joint range "
                f"{[g_lo, g_hi]}"
            )
        for key, value in (("default_pos", j["default_pos"]),):
            if not lo <= value <= hi:
                raise SchemaError(f"{where}.{key} = {value:g} ({name}): outside {[lo, hi]}")
        if not 0.0 < abs(j["action_scale"]) <= MAX_ACTION_SCALE_RAD:
            raise SchemaError(
                f"{where}.action_scale = {j['action_scale']:g} ({name}): outside "
                f"(0, {MAX_ACTION_SCALE_RAD:g}] rad"
            )
    names = [j["name"] for j in spec["joints"]]
    for key, values in (
        ("robot.default_joint_pos", spec["robot"]["default_joint_pos"]),
        ("action.scale", spec["action"]["scale"]),
    ):
        table = [j["default_pos" if "pos" in key else "action_scale"] for j in spec["joints"]]
        if len(values) != len(table) or any(
            abs(a - b) > 1e-9 for a, b in zip(values, table, strict=False)
        ):
            raise SchemaError(f"deploy.json.{key}: differs from the joints table")
    kd = spec["deploy"]["shutdown"]["damping_kd"]
    worst = min(names, key=lambda n: gain_bounds(n)[1])
    if not 0.0 <= kd <= gain_bounds(worst)[1]:
        raise SchemaError(
            f"deploy.json.deploy.shutdown.damping_kd = {kd:g}: outside [0, "
            f"{gain_bounds(worst)[1]:g}] ({worst}'s motor)"
        )


def check_spec(spec: Any) -> None:
    """``spec`` (a parsed deploy.json) against :data:`SCHEMA`; one line at the first fault."""
    check(spec, SCHEMA, "deploy.json")
    cmd = spec["command"]
    if "heading_control" not in cmd:
        raise SchemaError("deploy.json.command: missing key 'heading_control'")
    check(cmd["heading_control"], BOOL, "deploy.json.command.heading_control")
    check(cmd, HEADING if cmd["heading_control"] else FIXED_YAW, "deploy.json.command")
    check_motor_ranges(spec)
