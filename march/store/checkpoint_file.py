"""A checkpoint file judged before torch reads a record, without torch: no link, a regular file
within :data:`MAX_CHECKPOINT_BYTES`, its zip directory's records stored as ``torch.save`` stores
them (an inflated size told by the directory, never found by inflating).

Every tool's refusal of a crafted checkpoint (a zip bomb, a link, a file too large) runs here
before torch is imported (~250 MB resident for the import alone), so it holds the issue's
200 MB bound; :mod:`march.store.checkpoint` reads the records afterwards.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from march.errors import ConfigError

LATEST = "latest.pt"

MAX_CHECKPOINT_BYTES = 4 << 30
"""Larger files are refused before they are read (a full-size student checkpoint is ~50 MB,
with its optimizer state; the smoke run's are 15 MB)."""


class CheckpointError(RuntimeError):
    """A checkpoint that is missing or does not fit the current config; says how to fix it."""


def open_plain_file(path: Path, label: str, limit: int, wanted: str) -> Any:
    """:func:`march.store.bounded_read.open_regular` (no link, a regular file within ``limit``
    bytes) with its refusal as a :class:`CheckpointError`."""
    from march.store.bounded_read import FileRefused, open_regular

    try:
        return open_regular(path, label, limit, wanted)
    except FileRefused as err:
        raise CheckpointError(str(err)) from None


def latest_checkpoint(directory: Path) -> Path | None:
    """The newest checkpoint in ``directory`` (``latest.pt`` if present), or None."""
    import re

    if (directory / LATEST).is_file():
        return directory / LATEST
    found = sorted(
        p for p in directory.glob("model_*.pt") if re.fullmatch(r"model_\d+\.pt", p.name)
    )
    return found[-1] if found else None


def check_records(f: Any, label: str) -> None:
    """The zip archive a ``torch.save`` file is, judged by its central directory before torch
    inflates any record: every record stored as torch writes it (uncompressed: its inflated
    size is its packed size) and all of them within the file's own size. A record deflated
    from gigabytes of zeros (a 17 MB file that torch would inflate to 1.5 GB before any check
    of ours) is refused here, having read only the directory. ``f``: the open file, left at
    its start. A file that is no zip archive is left to torch (its legacy format, or its own
    refusal of a file that is no checkpoint)."""
    import zipfile

    size = os.fstat(f.fileno()).st_size
    try:
        if not zipfile.is_zipfile(f):
            return  # torch's legacy format (records as they are in the file) or no checkpoint
        with zipfile.ZipFile(f) as archive:
            records = archive.infolist()
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as err:
        why = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise CheckpointError(
            f"{label}: not a readable checkpoint (truncated or corrupt: {why})"
        ) from None
    finally:
        f.seek(0)
    inflated = 0
    for record in records:
        if record.compress_type != zipfile.ZIP_STORED or record.file_size != record.compress_size:
            raise CheckpointError(
                f"{label}: its record {record.filename!r} is compressed ({record.compress_size} "
                f"bytes that inflate to {record.file_size}); torch.save stores every record as "
                "it is, so it is no checkpoint march wrote; not read"
            )
        inflated += record.file_size
    if inflated > size:
        raise CheckpointError(
            f"{label}: its records add up to {inflated} bytes, more than the file's {size}; "
            "not a checkpoint march wrote; not read"
        )


def check_file(path: str | Path, label: str) -> None:
    """The checks on ``path`` that read no record (no link, a regular file within
    :data:`MAX_CHECKPOINT_BYTES`, its zip directory: :func:`check_records`): a run's files are
    all put through these before any of them is unpickled and checked in full."""
    with open_plain_file(Path(path), label, MAX_CHECKPOINT_BYTES, "a march checkpoint") as f:
        check_records(f, label)


def check_checkpoint_files(cfg: Any) -> None:
    """The checkpoint files a config names (``teacher_ckpt=``, ``student_ckpt=``), as far as
    they can be judged without unpickling (:func:`check_file`: no link, bounded, zip records as
    torch writes them), one :class:`ConfigError` line: a tool passes it to
    ``run_tool(before_terms=...)``, so a zip bomb is refused before torch or the simulator
    loads. A missing file is left to the tool, whose message says what to pass."""
    for kind in ("teacher", "student"):
        path = getattr(cfg, f"{kind}_ckpt", None)
        if path and os.path.lexists(path):
            try:
                check_file(path, f"{kind}_ckpt={path}")
            except CheckpointError as err:
                raise ConfigError(str(err)) from None
