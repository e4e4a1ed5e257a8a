"""The deployment bundle as the robot-side loop reads it: ``<stem>.deploy.json`` beside the ONNX.

:meth:`Bundle.load` checks, before anything is simulated: the JSON (format version, MuJoCo
version, the schema of :mod:`march.sim2sim.bundle_schema`: every key, every type; sizes that
must agree), the files it names (plain names inside the bundle's folder - no directories, no
``..``, no absolute paths - read without following a symbolic link, sizes bounded before they
are read: :mod:`march.store.bounded_read`), the ONNX file's SHA-256;
:meth:`Bundle.scene` loads a course's compiled scene (gzipped MJB, SHA-256 checked) and
:meth:`Bundle.cell` picks a course cell. :data:`INPUTS` and :data:`OUTPUT` name the ONNX graph's
feeds and result. Every fault is a :class:`UsageError`: one line for the user, never a
``KeyError`` / ``IndexError`` / ``EOFError`` traceback. MuJoCo, json and hashlib only.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import mujoco

from march.sim2sim.bundle_files import scene_bytes
from march.sim2sim.bundle_schema import SchemaError, UsageError, check_spec
from march.sim2sim.motors import MotorTableError, motor_table
from march.store.bounded_read import (
    MAX_ONNX_BYTES,
    MAX_SPEC_BYTES,
    FileRefused,
    parse_json_strict,
    read_in_folder,
)

BUNDLE_FORMAT = 3
"""The ``deploy.json`` layout this loop reads (march.export.deploy_spec.BUNDLE_FORMAT)."""
INPUTS = ("proprio_hist", "command", "depth")
OUTPUT = "actions"


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def read_in_bundle(folder: Path, name: Any, what: str, limit: int = MAX_ONNX_BYTES) -> bytes:
    """The bytes of the file ``name`` in ``folder`` through the disk gate
    (:func:`march.store.bounded_read.read_in_folder`: a plain name inside the folder, no link,
    a regular file of at most ``limit`` bytes)."""
    try:
        return read_in_folder(folder, name, what, limit)
    except FileRefused as err:
        raise UsageError(str(err)) from None


def _agree(spec: dict[str, Any]) -> None:
    """Sizes that must agree between sections (after the schema)."""
    lay = spec["checkpoint"]["layout"]
    a = lay["num_actions"]
    sizes = {
        "joints": len(spec["joints"]),
        "robot.joint_names": len(spec["robot"]["joint_names"]),
        "robot.default_joint_pos": len(spec["robot"]["default_joint_pos"]),
        "action.joint_names": len(spec["action"]["joint_names"]),
        "action.actuator_names": len(spec["action"]["actuator_names"]),
        "action.scale": len(spec["action"]["scale"]),
        "action.offset": len(spec["action"]["offset"]),
        "deploy.joint_vel_limits": len(spec["deploy"]["joint_vel_limits"]),
    }
    for key, n in sizes.items():
        if n != a:
            raise UsageError(f"deploy.json: {key} has {n} entries, the policy {a} actions")
    obs = spec["observation"]
    dims = [t["dim"] for t in obs["proprio_terms"]]
    if sum(dims) != lay["proprio_dim"] or [t["dim"] for t in obs["terms"]] != dims:
        raise UsageError("deploy.json: observation term sizes do not add up to proprio_dim")
    for t in obs["terms"]:
        r = obs["training_range"].get(t["name"])
        if r is None or {len(v) for v in r.values()} != {t["dim"]}:
            raise UsageError(f"deploy.json: training_range.{t['name']} is not {t['dim']} long")
        if len(t["elements"]) != t["dim"]:
            raise UsageError(f"deploy.json: observation term {t['name']} names not {t['dim']}")
    if obs["history_len"] != lay["history_len"] or obs["history_len"] < 1:
        raise UsageError("deploy.json: observation.history_len is not the layout's")
    try:
        motor_table(spec)
    except MotorTableError as err:
        raise UsageError(f"deploy.json joints: {err}") from None
    d = spec["depth"]
    if [d["height"], d["width"]] != lay["image_hw"]:
        raise UsageError("deploy.json: depth height / width are not the layout's image_hw")
    rates = spec["rates"]
    if not (rates["physics_dt_s"] > 0 and rates["decimation"] >= 1):
        raise UsageError("deploy.json: rates.physics_dt_s must be > 0 and decimation >= 1")
    if abs(rates["control_dt_s"] - rates["physics_dt_s"] * rates["decimation"]) > 1e-9:
        raise UsageError("deploy.json: rates.control_dt_s is not physics_dt_s x decimation")


@dataclass
class Bundle:
    """``<stem>.deploy.json`` beside an ONNX file, checked."""

    onnx_path: Path
    spec: dict[str, Any]
    onnx_bytes: bytes = field(default=b"", repr=False)
    """The ONNX graph as read and checked against the bundle's SHA-256: what the policy loads
    (never the file by its path again)."""

    @classmethod
    def load(cls, onnx_path: str | Path) -> Bundle:
        onnx_path = Path(onnx_path)
        if not onnx_path.exists() and not onnx_path.is_symlink():
            raise UsageError(f"onnx={onnx_path}: no such file (python -m march.export writes it)")
        folder = onnx_path.parent
        name = onnx_path.with_suffix(".deploy.json").name
        if not (folder / name).exists() and not (folder / name).is_symlink():
            raise UsageError(
                f"onnx={onnx_path}: no deployment bundle beside it ({name}); export it "
                "with python -m march.export student_ckpt=<file> out=<folder>"
            )
        raw = read_in_bundle(folder, name, "deploy.json", MAX_SPEC_BYTES)
        path = folder / name
        try:
            spec = parse_json_strict(raw, str(path))
        except FileRefused as err:
            raise UsageError(str(err)) from None
        if not isinstance(spec, dict) or spec.get("format") != BUNDLE_FORMAT:
            found = spec.get("format") if isinstance(spec, dict) else None
            raise UsageError(f"{path}: bundle format {found!r}, this loop reads {BUNDLE_FORMAT}")
        if spec.get("mujoco_version") != mujoco.__version__:
            raise UsageError(
                f"{path}: 'mujoco_version' {spec.get('mujoco_version')!r}: the scenes were "
                f"compiled with MuJoCo {spec.get('mujoco_version')}, "
                f"this is MuJoCo {mujoco.__version__} (MJB files are version-bound)"
            )
        try:
            check_spec(spec)
        except SchemaError as err:
            raise UsageError(f"{path}: {err}") from None
        _agree(spec)
        if spec["onnx"]["file"] != onnx_path.name:
            raise UsageError(
                f"{path}: describes {spec['onnx']['file']!r}, not {onnx_path.name!r} (renamed?)"
            )
        data = read_in_bundle(folder, spec["onnx"]["file"], "ONNX file")
        if _sha256(data) != spec["onnx"]["sha256"]:
            raise UsageError(f"onnx={onnx_path}: its SHA-256 differs from the bundle's record")
        return cls(onnx_path, spec, data)

    def scene(self, course: str) -> mujoco.MjModel:
        """The compiled scene of ``course`` (gzipped MJB, loaded from memory)."""
        courses = self.spec["courses"]
        if course not in courses:
            raise UsageError(f"course={course}: the bundle has {', '.join(courses)}")
        raw = scene_bytes(self.onnx_path.parent, course, courses[course])
        path = self.onnx_path.parent / courses[course]["scene"]
        try:
            return mujoco.MjModel.from_binary_path("scene.mjb", {"scene.mjb": raw})
        except (OSError, EOFError, ValueError) as err:
            raise UsageError(f"{path}: not a MuJoCo {mujoco.__version__} scene ({err})") from None

    def cell(self, course: str, difficulty: float, seed: int) -> dict[str, Any]:
        """The course cell: hardware's only one; stones: nearest level, column seed mod C."""
        if course not in self.spec["courses"]:
            raise UsageError(f"course={course}: the bundle has {', '.join(self.spec['courses'])}")
        grid = self.spec["courses"][course]["cells"]  # non-empty rows (the schema)
        if course == "hardware":
            return grid[0][0]
        row = min(range(len(grid)), key=lambda r: abs(grid[r][0]["difficulty"] - difficulty))
        return grid[row][seed % len(grid[row])]
