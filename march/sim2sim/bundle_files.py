"""A bundle's files checked without MuJoCo: a compiled scene read through the disk gate,
checked against its SHA-256 record and inflated within a bound (the simulator's
:class:`march.sim2sim.deploy_bundle.Bundle` and the robot's torch- and MuJoCo-free supervisor
both read scenes this way)."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

from march.sim2sim.bundle_schema import UsageError
from march.store.bounded_read import (
    MAX_INFLATION,
    MAX_SCENE_BYTES,
    FileRefused,
    gunzip_bounded,
    read_in_folder,
)


def scene_bytes(folder: Path, course: str, entry: dict[str, Any]) -> bytes:
    """The inflated MJB of ``course`` (its ``courses`` entry of deploy.json) in ``folder``: the
    gzipped file read through the gate, its SHA-256 against the record, inflated in pieces and
    bounded before it is held (a crafted small file cannot fill memory). One
    :class:`UsageError` line at the first fault."""
    path = folder / entry["scene"]
    try:
        packed = read_in_folder(folder, entry["scene"], f"{course} scene", MAX_SCENE_BYTES)
        if hashlib.sha256(packed).hexdigest() != entry["sha256"]:
            raise FileRefused(f"{path}: its SHA-256 differs from the bundle's record")
        limit = min(MAX_SCENE_BYTES, MAX_INFLATION * len(packed))
        return gunzip_bounded(packed, limit, f"{path}: the {course} scene")
    except FileRefused as err:
        raise UsageError(str(err).splitlines()[0]) from None
