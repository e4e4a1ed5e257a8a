"""``python -m march.export student_ckpt=<file> [out=student.onnx]``: a student as one ONNX file.

    python -m march.export student_ckpt=outputs/<run>/student/latest.pt
    python -m march.export student_ckpt=outputs/<run>/student/latest.pt out=/tmp/g1_student.onnx

The checkpoint alone decides the network: its saved config's ``student`` section and its
``layout`` (proprio size, history length, image size, action count) rebuild the
:class:`~march.policies.student.StudentPolicy` - no env is built, and the command-line config does
not change the architecture. :func:`march.onnx_export.export_student_onnx` writes the graph of the
deterministic ``act_inference`` (observation normalisers baked in), checks it against torch with
onnxruntime and times it on one CPU thread. Default ``out``: ``student.onnx`` next to the
checkpoint. Prints the parity (max |onnx - torch|), the latency (median / p95 ms, batch 1, one
thread) and the file written.

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

Plus ``variant``, ``teacher_ckpt``, ``iteration``, ``env_steps`` and ``march_layout``.
A missing or wrong checkpoint is one line on stderr and exit status 2.
"""

from __future__ import annotations

import json
import re
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from march.cli import fail, run_tool
from march.config import MarchConfig
from march.env.build import PROPRIO_TERMS

USAGE = "usage: python -m march.export student_ckpt=<file> [out=student.onnx] [key=value ...]"
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


def rebuild_student(payload: dict[str, Any], path: str) -> Any:
    """The StudentPolicy the checkpoint describes (its own config and layout), weights loaded."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    from march.config import ConfigError, StudentCfg
    from march.learn.distill import build_student

    try:
        section = payload["config"]["student"]
        layout = payload["layout"]
        student_cfg = OmegaConf.to_object(
            OmegaConf.merge(OmegaConf.structured(StudentCfg), section)
        )
        policy = build_student(MarchConfig(student=student_cfg), layout, "cpu")
        policy.load_state_dict(payload["student_state_dict"])
    except KeyError as err:
        fail(f"student_ckpt={path}: the checkpoint lacks {err}; write it with march.train")
    except (OmegaConfBaseException, ConfigError, TypeError, ValueError, RuntimeError) as err:
        fail(f"student_ckpt={path}: cannot rebuild the student from its config ({_one_line(err)})")
    policy.eval()
    return policy


def export(cfg: MarchConfig) -> dict[str, Any]:
    from march.learn.checkpoint import CheckpointError, load_checkpoint
    from march.onnx_export import export_student_onnx

    path = cfg.student_ckpt
    if not path:
        fail(f"give student_ckpt=<file> (outputs/<run>/student/latest.pt). {USAGE}")
    try:
        payload = load_checkpoint(path, "student", "cpu")
    except CheckpointError as err:
        fail(_one_line(err))
    out = Path(cfg.out) if cfg.out else Path(path).resolve().parent / DEFAULT_NAME
    if out.suffix.lower() != ".onnx":
        fail(f"out={out}: the file must end in .onnx")
    policy = rebuild_student(payload, path)
    result = export_student_onnx(policy, out, metadata(payload))
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
    return result


def main(argv: Sequence[str] | None = None) -> None:
    run_tool(export, argv, usage=USAGE)


if __name__ == "__main__":
    main(sys.argv[1:])
