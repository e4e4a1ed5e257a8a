"""The schema of ``<stem>.deploy.json``: every key required, every value typed (json only).

:func:`check_spec` walks a parsed bundle against :data:`SCHEMA` and raises :class:`SchemaError`
with one line naming the first key that is missing, unknown or of the wrong type (``joints[3]
.kp: expected a number, got 'abc'``), so that nothing later in the loop meets a ``KeyError``,
``IndexError`` or a string where a number belongs. Types: ``int``, ``num`` (int or float,
finite), ``str``, ``bool``, ``None``; ``[t]`` a list of t, ``[t, n]`` of exactly n; a dict a
fixed set of keys; :class:`Opt` a value that may also be null; :class:`Map` a dict of any keys.
Cross-checks that need two keys (sizes that must agree, paths that must stay in the bundle) are
in :mod:`march.sim2sim.deploy_bundle`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any


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


def check_spec(spec: Any) -> None:
    """``spec`` (a parsed deploy.json) against :data:`SCHEMA`; one line at the first fault."""
    check(spec, SCHEMA, "deploy.json")
    cmd = spec["command"]
    if "heading_control" not in cmd:
        raise SchemaError("deploy.json.command: missing key 'heading_control'")
    check(cmd["heading_control"], BOOL, "deploy.json.command.heading_control")
    check(cmd, HEADING if cmd["heading_control"] else FIXED_YAW, "deploy.json.command")
