"""mjlab's Unitree G1 and the evaluation scene, for tools that need them without an env.

The export (:mod:`march.export`) writes the G1's joint order, action scales and default pose
into the ONNX metadata and compiles the evaluation env's MuJoCo model per course for the
deployment bundle; both come from here so that, as everywhere in march, only ``march.env``
imports mjlab.
"""

from __future__ import annotations

import re
from dataclasses import replace
from typing import Any

import mjlab  # noqa: F401  (before mujoco: mjlab sets MUJOCO_GL=egl, which mujoco reads once)
import mujoco
from mjlab.asset_zoo.robots.unitree_g1 import g1_constants as g1
from mjlab.scene import Scene

from march.config import MarchConfig
from march.env.build import build_env_cfg


def g1_joint_names() -> list[str]:
    """The G1's actuated joints in mjlab's order (= the action order)."""
    free = mujoco.mjtJoint.mjJNT_FREE
    spec = g1.get_spec()  # keep the spec alive while its joints are read
    return [str(j.name) for j in spec.joints if j.type != free]


def joint_value(table: Any, name: str, default: float | None) -> float | None:
    """A joint's entry in one of mjlab's name -> value tables: a float for all joints, or
    {regex: value} (the first full match), else ``default``."""
    if isinstance(table, (int, float)):
        return float(table)
    for pattern, value in (table or {}).items():
        if re.fullmatch(pattern, name):
            return float(value)
    return default


def g1_action_layout(num_actions: int) -> dict[str, list] | None:
    """Joint names (action order), action scales and default joint positions of mjlab's G1,
    or None when the checkpoint's action count is not the G1's."""
    names = g1_joint_names()
    if len(names) != num_actions:
        return None

    default_pos = dict(g1.get_g1_robot_cfg().init_state.joint_pos or {})
    return {
        "action_joint_names": names,
        "action_scale": [joint_value(g1.G1_ACTION_SCALE, n, None) for n in names],
        "default_joint_pos": [joint_value(default_pos, n, 0.0) for n in names],
    }


def course_scene(cfg: MarchConfig, course: str) -> tuple[Any, Any, Any]:
    """(MjModel, env cfg, mjlab Scene) of the evaluation env on ``course``, DR and corruption off.

    The model is compiled the way mjlab's ``Simulation`` compiles the env's scene
    (``scene.spec.compile()`` then the env's ``MujocoCfg.apply``), without the warp copy:
    the same G1 (actuators, gains, effort limits, armature, joint order), the same depth camera
    and the same course geoms as ``env.sim.mj_model`` (tests/test_sim2sim.py compares them).
    """
    ev = replace(cfg.eval, course=course, randomization=False, corruption=False)
    env_cfg = build_env_cfg(replace(cfg, eval=ev), "eval", num_envs=1)
    scene = Scene(env_cfg.scene, device="cpu")
    model = scene.spec.compile()
    env_cfg.sim.mujoco.apply(model)
    return model, env_cfg, scene


def g1_mjcf_spec() -> mujoco.MjSpec:
    """mjlab's G1 MJCF as it is (a fresh ``MjSpec``: the caller may add geoms to it before
    compiling, e.g. stones to film on), for the kinematic audit (:mod:`march.audit`)."""
    return g1.get_spec()


def g1_default_pose() -> tuple[dict[str, float], tuple[float, float, float]]:
    """The G1's default joint positions by joint name (mjlab's ``init_state``: the env's
    ``default_joint_pos``, which the upper-body CLF outputs are relative to) and its initial
    root position [m]."""
    init = g1.get_g1_robot_cfg().init_state
    table = dict(init.joint_pos or {})
    pose = {n: float(joint_value(table, n, 0.0) or 0.0) for n in g1_joint_names()}
    return pose, tuple(float(x) for x in init.pos)
