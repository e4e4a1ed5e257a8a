"""The deployment bundle as the robot-side loop reads it: ``<stem>.deploy.json`` beside the ONNX.

:class:`Bundle` loads and checks the JSON (format version, MuJoCo version, the ONNX file's
SHA-256), loads a course's compiled scene (gzipped MJB, SHA-256 checked) and picks a course cell;
:data:`INPUTS` and :data:`OUTPUT` name the ONNX graph's feeds and result. Bad input raises
:class:`UsageError`, one line for the user. MuJoCo, json and hashlib only (no training stack).
"""

from __future__ import annotations

import gzip
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mujoco

BUNDLE_FORMAT = 2
"""The ``deploy.json`` layout this loop reads (march.export.deploy_spec.BUNDLE_FORMAT)."""
INPUTS = ("proprio_hist", "command", "depth")
OUTPUT = "actions"


class UsageError(ValueError):
    """Bad arguments or an unusable bundle: one line for the user."""


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


@dataclass
class Bundle:
    """``<stem>.deploy.json`` beside an ONNX file, checked."""

    onnx_path: Path
    spec: dict[str, Any]

    @classmethod
    def load(cls, onnx_path: str | Path) -> Bundle:
        onnx_path = Path(onnx_path)
        if not onnx_path.is_file():
            raise UsageError(f"onnx={onnx_path}: no such file (python -m march.export writes it)")
        path = onnx_path.with_suffix(".deploy.json")
        if not path.is_file():
            raise UsageError(
                f"onnx={onnx_path}: no deployment bundle beside it ({path.name}); export it "
                "with python -m march.export student_ckpt=<file> out=<folder>"
            )
        try:
            spec = json.loads(path.read_text())
        except (OSError, ValueError) as err:
            raise UsageError(f"{path}: not readable JSON ({err})") from None
        if not isinstance(spec, dict) or spec.get("format") != BUNDLE_FORMAT:
            found = spec.get("format") if isinstance(spec, dict) else None
            raise UsageError(f"{path}: bundle format {found!r}, this loop reads {BUNDLE_FORMAT}")
        if spec.get("mujoco_version") != mujoco.__version__:
            raise UsageError(
                f"{path}: the scenes were compiled with MuJoCo {spec.get('mujoco_version')}, "
                f"this is MuJoCo {mujoco.__version__} (MJB files are version-bound)"
            )
        want = spec["onnx"]["sha256"]
        if _sha256(onnx_path.read_bytes()) != want:
            raise UsageError(f"onnx={onnx_path}: its SHA-256 differs from the bundle's record")
        return cls(onnx_path, spec)

    def scene(self, course: str) -> mujoco.MjModel:
        """The compiled scene of ``course`` (gzipped MJB, loaded from memory)."""
        entry = self.spec["courses"][course]
        path = self.onnx_path.parent / entry["scene"]
        if not path.is_file():
            raise UsageError(f"{path}: the bundle's {course} scene is missing")
        packed = path.read_bytes()
        if _sha256(packed) != entry["sha256"]:
            raise UsageError(f"{path}: its SHA-256 differs from the bundle's record")
        return mujoco.MjModel.from_binary_path("scene.mjb", {"scene.mjb": gzip.decompress(packed)})

    def cell(self, course: str, difficulty: float, seed: int) -> dict[str, Any]:
        """The course cell: hardware's only one; stones: nearest level, column seed mod C."""
        grid = self.spec["courses"][course]["cells"]
        if course == "hardware":
            return grid[0][0]
        row = min(range(len(grid)), key=lambda r: abs(grid[r][0]["difficulty"] - difficulty))
        return grid[row][seed % len(grid[row])]
