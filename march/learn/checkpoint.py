"""Checkpoints: written atomically, carrying the config and layout they were trained with."""

from __future__ import annotations

import json
import os
import re
import tempfile
from pathlib import Path
from typing import Any

import torch

LATEST = "latest.pt"


class CheckpointError(RuntimeError):
    """A checkpoint that is missing or does not fit the current config; says how to fix it."""


def save_atomic(payload: dict[str, Any], path: Path) -> None:
    """Write to a temporary file in the same directory, fsync, then rename over ``path``.

    A run killed mid-write leaves the previous checkpoint intact, never a truncated one.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(payload, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_json_atomic(obj: Any, path: Path) -> None:
    """A JSON file replaced in one rename: readers never see half of it."""
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(obj, indent=2, default=float))
    os.replace(tmp, path)


def save_checkpoint(payload: dict[str, Any], directory: Path, iteration: int) -> Path:
    """``model_<it>.pt`` plus ``latest.pt`` (both atomic)."""
    path = directory / f"model_{iteration:06d}.pt"
    save_atomic(payload, path)
    save_atomic(payload, directory / LATEST)
    return path


def latest_checkpoint(directory: Path) -> Path | None:
    """The newest checkpoint in ``directory`` (``latest.pt`` if present), or None."""
    if (directory / LATEST).is_file():
        return directory / LATEST
    found = sorted(
        p for p in directory.glob("model_*.pt") if re.fullmatch(r"model_\d+\.pt", p.name)
    )
    return found[-1] if found else None


def load_checkpoint(path: str | Path, kind: str, device: str = "cpu") -> dict[str, Any]:
    """Load a march checkpoint of ``kind`` (teacher | student) or raise CheckpointError."""
    p = Path(path)
    if not p.is_file():
        raise CheckpointError(
            f"{kind}_ckpt={path}: no such file; pass a checkpoint written by march.train "
            f"(outputs/<run>/{kind}/latest.pt)"
        )
    try:
        payload = torch.load(p, map_location=device, weights_only=False)
    except Exception as err:  # noqa: BLE001 - any unreadable file is the same user error
        raise CheckpointError(f"{kind}_ckpt={path}: not a readable checkpoint ({err})") from err
    if not isinstance(payload, dict) or payload.get("kind") != kind:
        found = payload.get("kind") if isinstance(payload, dict) else type(payload).__name__
        raise CheckpointError(f"{kind}_ckpt={path}: this is a {found!r} checkpoint, not a {kind}")
    return payload


def check_layout(
    saved: dict[str, Any], current: dict[str, Any], what: str, path: str | Path
) -> None:
    """The observation/action layout a checkpoint was trained with must equal the current one."""
    diffs = [
        f"{k}: checkpoint {saved.get(k)!r} vs config {current.get(k)!r}"
        for k in sorted(set(saved) | set(current))
        if saved.get(k) != current.get(k)
    ]
    if diffs:
        raise CheckpointError(
            f"{what} checkpoint {path} does not fit this config ({'; '.join(diffs)}); "
            "use the config it was trained with (its 'config' entry) or train a new one"
        )
