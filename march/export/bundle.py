"""``python -m march.export student_ckpt=<file> [out=<folder> | out=<file>.onnx]``: a student as
an ONNX file plus the deployment bundle a robot-side loop needs.

    python -m march.export student_ckpt=outputs/<run>/student/latest.pt
    python -m march.export student_ckpt=outputs/<run>/student/latest.pt out=/tmp/g1_deploy
    python -m march.export student_ckpt=outputs/<run>/student/latest.pt out=/tmp/g1_student.onnx

The checkpoint is read through the disk gate (:func:`march.store.gate.policy_from_checkpoint`:
no link, bounded size, its config and weights checked) and decides the policy: its
saved config's ``student`` section and its ``layout`` (proprio size, history length, image size,
action count) rebuild the :class:`~march.policies.student.StudentPolicy`, and its camera and
observation settings describe what deployment feeds; the command line does not change them.
:func:`march.export.onnx_graph.export_student_onnx` writes the fast deployment graph of the
deterministic ``act_inference`` (observation normalisers baked in;
:class:`~march.export.onnx_graph.DeployGraph`), checks
it against the policy with onnxruntime and times it on one CPU thread. ``out``: a file ending in
``.onnx``, or a folder that receives ``student.onnx``; default ``student.onnx`` next to the
checkpoint.

Beside ``<stem>.onnx`` it writes the deployment bundle (:func:`write_bundle`; its JSON from
:mod:`march.export.deploy_spec`) that ``python -m march.sim2sim`` runs with MuJoCo and onnxruntime
alone: ``<stem>.deploy.json`` (rates, robot joints and default pose, actions, proprioception order
and history, command, depth camera, terminations, metric definitions, each course's cells with their
footholds, SHA-256 of every file) and ``<stem>.hardware.mjb.gz`` / ``<stem>.stones.mjb.gz``: the
evaluation env's compiled MuJoCo model of each course (the G1 with its actuators, gains, effort
limits, the depth camera), DR and corruption off. A checkpoint whose layout is not the G1 env's (a
test's toy network) gets the ONNX file alone and a line saying why.

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
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from march.config import MarchConfig
from march.config.cli import fail, run_tool
from march.export.deploy_terms import portable_path

# march.env (and with it mjlab, ~9 s of imports) is imported where a bundle is built, not here:
# a bad command line or checkpoint gets its one line in a few seconds.

USAGE = (
    "usage: python -m march.export student_ckpt=<file> [out=<folder> | out=<file>.onnx] "
    "[key=value ...]"
)
DEFAULT_NAME = "student.onnx"


def _one_line(err: BaseException, limit: int = 400) -> str:
    text = " ".join(str(err).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def metadata(payload: dict[str, Any]) -> dict[str, str]:
    """The ONNX ``metadata_props`` for a student checkpoint (str -> str)."""
    from march.env.build import PROPRIO_TERMS
    from march.env.g1 import g1_action_layout
    from march.export.deploy_spec import proprio_term_dims

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
        "teacher_ckpt": portable_path(payload.get("teacher_ckpt")),
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
    :func:`march.store.provenance.apply_checkpoint_config`); None merges ``payload["config"]``'s.
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


def write_bundle(
    cfg: MarchConfig, payload: dict[str, Any], onnx_path: Path, extra: dict[str, Any]
) -> dict[str, Path] | str:
    """Write ``<stem>.deploy.json`` and ``<stem>.<course>.mjb.gz`` beside ``onnx_path``.

    Returns the files, or a one-line reason when the checkpoint's layout is not the G1 env's.
    """
    import gzip
    import tempfile

    import mujoco

    from march.env.g1 import course_scene, g1_joint_names
    from march.export.deploy_spec import course_cells, deployment_spec, layout_problem

    files = bundle_files(onnx_path)
    free = mujoco.mjtJoint.mjJNT_FREE
    # a cheap look before any scene is built
    problem = layout_problem(payload["layout"], cfg, len(g1_joint_names()))
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
            problem = layout_problem(payload["layout"], cfg, n_joints)
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
            "cells": course_cells(env_cfg, scene),
        }
    assert spec is not None
    attach_joint_table(onnx_path, spec["joints"])  # before its SHA-256 is taken
    spec["deploy"]["measured_latency_ms"] = float(extra["latency_ms_p95"])
    spec["onnx"] = {"file": onnx_path.name, "sha256": _sha256(onnx_path), **extra}
    spec["courses"] = courses
    from march.store.checkpoint import write_json_atomic
    from march.strict_json import strict

    write_json_atomic(strict(spec), files["json"])
    return files


def joint_table_metadata(joints: list[dict[str, Any]]) -> dict[str, str]:
    """The joint table as ONNX metadata: mjlab's keys and format (``joint_names``,
    ``joint_stiffness``, ``joint_damping``: comma-separated, policy order, as
    ``mjlab.rl.exporter_utils.get_base_metadata``), plus ``motor_index`` (the Unitree motor slot
    of each policy joint) and ``joint_table`` (every row of ``deploy.json`` ``joints``, JSON)."""

    def csv(values: list[Any]) -> str:
        return ",".join(f"{v:.9g}" if isinstance(v, float) else str(v) for v in values)

    return {
        "joint_names": ",".join(j["name"] for j in joints),
        "joint_stiffness": csv([float(j["kp"]) for j in joints]),
        "joint_damping": csv([float(j["kd"]) for j in joints]),
        "motor_index": csv([int(j["motor_index"]) for j in joints]),
        "joint_table": json.dumps(joints),
    }


def attach_joint_table(onnx_path: Path, joints: list[dict[str, Any]]) -> None:
    """Add :func:`joint_table_metadata` to the ONNX file's ``metadata_props`` (atomic)."""
    import os

    import onnx

    proto = onnx.load(str(onnx_path))
    props = {e.key: e.value for e in proto.metadata_props}
    props.update(joint_table_metadata(joints))
    onnx.helper.set_model_props(proto, props)
    tmp = onnx_path.with_name(onnx_path.name + ".tmp")
    onnx.save(proto, str(tmp))
    os.replace(tmp, onnx_path)


def output_path(out_arg: str, ckpt: str) -> Path:
    """Where the ONNX file goes, checked before any work: ``out`` a ``.onnx`` file (replaced if
    it is one), a folder (created), or none (beside the checkpoint). Refused in one line: an
    existing non-folder given as the folder, a folder or a link where the files go, a parent
    that is a file or cannot be written."""
    import os

    if not out_arg:  # beside the checkpoint as named: its folder in the run, not a link's target
        folder = Path(os.path.abspath(ckpt)).parent
        if folder.resolve() != folder:
            fail(
                f"student_ckpt={ckpt}: its folder {folder} is reached through a symbolic link (it "
                f"is {folder.resolve()}); march writes no file through a link: give out=<folder>"
            )
        out = folder / DEFAULT_NAME
    elif out_arg.lower().endswith(".onnx"):
        out = Path(out_arg)
    else:
        folder = Path(out_arg)
        if folder.exists() and not folder.is_dir():
            fail(f"out={out_arg}: exists and is not a folder (give a folder or a .onnx file)")
        out = folder / DEFAULT_NAME  # a folder: the bundle goes inside
    for f in (out, *bundle_files(out).values()):
        if f.is_symlink():
            fail(f"out={out_arg}: {f} is a symbolic link; not written through")
        if f.exists() and not f.is_file():
            fail(f"out={out_arg}: {f} exists and is not a file")
    parent = out.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        fail(f"out={out_arg}: {parent} is not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        fail(f"out={out_arg}: {parent} is not writable")
    return out


def export(cfg: MarchConfig, overrides: Sequence[str] = ()) -> dict[str, Any]:
    from march.config import ConfigError
    from march.store.checkpoint import CheckpointError
    from march.store.gate import policy_from_checkpoint

    path = cfg.student_ckpt
    if not path:
        fail(f"give student_ckpt=<file> (outputs/<run>/student/latest.pt). {USAGE}")
    out = output_path(cfg.out, path)  # refused before any work
    try:  # the disk gate; then the checkpoint decides the network, camera and layout
        payload, cfg, _ = policy_from_checkpoint(cfg, "student", path, overrides)
    except (CheckpointError, ConfigError) as err:
        fail(_one_line(err))
    from march.export.onnx_graph import export_student_onnx  # torch, rsl-rl, onnx: after the checks

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
    extra = {k: result[k] for k in ("max_abs_diff", "latency_ms_median", "latency_ms_p95", "opset")}
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
    from march.store.checkpoint_file import check_checkpoint_files

    # student_ckpt= judged (link, size, zip records) before the term check loads the simulator
    run_tool(lambda cfg: export(cfg, args), args, usage=USAGE, before_terms=check_checkpoint_files)


if __name__ == "__main__":
    main(sys.argv[1:])
