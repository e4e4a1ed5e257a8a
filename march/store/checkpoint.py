"""Checkpoints: plain data, written atomically, carrying the config and layout they were trained with.

A checkpoint is a ``torch.save`` file of plain data only: tensors, numbers, strings, bytes, None,
and lists / tuples / dicts of them. It is read with ``torch.load(weights_only=True)``, whose
unpickler builds tensors and containers and calls no function the file names, so a crafted file
cannot run code on the machine that loads it. :func:`load_checkpoint` is the one place in march
that reads a checkpoint (``tests/test_checkpoint.py`` greps the package to keep it so).
"""

from __future__ import annotations

import contextlib
import dataclasses
import enum
import errno
import os
import pickle
import re
import tempfile
import warnings
from collections import OrderedDict
from collections.abc import Mapping
from pathlib import Path, PurePath
from typing import Any

import numpy as np
import torch

# The file-level checks live without torch (march.store.checkpoint_file); their names are
# read from here too, as before the split.
from march.store.checkpoint_file import (  # noqa: F401
    LATEST,
    MAX_CHECKPOINT_BYTES,
    CheckpointError,
    check_file,
    check_records,
    latest_checkpoint,
    open_plain_file,
)
from march.strict_json import dumps


def writes_files() -> bool:
    """Whether this process writes run files: a single process, or rank 0 of the process group
    (``march.learn.distributed`` joins it; after ``shutdown`` every process is alone again).
    Read from torch.distributed itself, so that this room sits below the training loops."""
    import torch.distributed as td

    return not (td.is_available() and td.is_initialized()) or td.get_rank() == 0


_CHECKED: dict[str, Any] = {}
"""Checkpoints this process read and checked, by absolute path, for the one read that uses them
(:func:`keep_checked`)."""


def _key(path: str | Path) -> str:
    return os.path.abspath(os.fspath(path))


def keep_checked(path: str | Path, payload: dict[str, Any]) -> None:
    """Keep ``payload``, read from ``path`` and checked (a resume's checkpoints, checked before
    any env is built), for the next :func:`load_checkpoint` of ``path`` in this process: the
    bytes that were checked are the bytes that are used, never a second read of a file that
    may have changed in between. A write of ``path`` (:func:`save_atomic`) forgets it."""
    _CHECKED[_key(path)] = payload


def save_atomic(payload: dict[str, Any], path: Path) -> None:
    """Write to a temporary file in the same directory, fsync, then rename over ``path``.

    A run killed mid-write leaves the previous checkpoint intact, never a truncated one. A write
    that fails (a full disk, a quota, an I/O error) removes its temporary file and raises
    :class:`CheckpointError`: one line, and the previous checkpoint is left as it was.
    In a run over N processes only rank 0 writes (march.learn.distributed).
    """
    _CHECKED.pop(_key(path), None)  # what was checked is no longer what the file holds
    if not writes_files():
        return
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as err:
        raise _write_error(path, err) from None
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(payload, f)
            f.flush()
            os.fsync(f.fileno())
        replace_durably(tmp, path)
    except BaseException as err:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        # torch.save reports a failed write as a RuntimeError wrapping the OS error.
        cause = err if isinstance(err, OSError) else err.__cause__ or err.__context__
        if isinstance(cause, OSError) or (
            isinstance(err, RuntimeError) and "write" in str(err).lower()
        ):
            raise _write_error(path, cause if isinstance(cause, OSError) else err) from None
        raise


def _write_error(path: Path, err: BaseException) -> CheckpointError:
    why = os.strerror(err.errno) if isinstance(err, OSError) and err.errno else str(err)
    why = why.strip().splitlines()[0] if why.strip() else type(err).__name__
    return CheckpointError(
        f"could not write checkpoint {path} ({why}); the checkpoints already in {path.parent} are "
        "intact: free space (or fix the file system), then continue with resume=<run dir>"
    )


def fsync_dir(directory: Path) -> None:
    """Make a rename or a new file in ``directory`` durable (its entry survives a power loss)."""
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    except OSError as err:
        if err.errno not in (errno.EINVAL, errno.ENOTSUP, errno.EBADF):
            raise  # a file system without directory fsync is fine; an I/O error is not
    finally:
        os.close(fd)


def replace_durably(tmp: str | Path, path: Path) -> None:
    """``os.replace(tmp, path)`` (``tmp`` already fsynced), then fsync of the directory."""
    os.replace(tmp, path)
    fsync_dir(path.parent)


def write_text_durably(path: Path, text: str) -> None:
    """``path`` replaced by ``text`` in one rename, data and directory fsynced."""
    tmp = path.with_name(path.name + ".tmp")
    with tmp.open("w", newline="") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    replace_durably(tmp, path)


def write_json_atomic(obj: Any, path: Path) -> None:
    """A strict JSON file (:mod:`march.strict_json`: NaN and infinities as null) replaced in one
    rename (fsynced): readers never see half of it (rank 0 only)."""
    if not writes_files():
        return
    write_text_durably(path, dumps(obj, indent=2, default=float))  # strict: NaN -> null


def save_checkpoint(payload: dict[str, Any], directory: Path, iteration: int) -> Path:
    """``model_<it>.pt`` plus ``latest.pt`` (both atomic); the payload must be plain data."""
    bad = non_plain(payload)
    if bad is not None:
        # A programming error, not a user one: refuse to write a file that load_checkpoint refuses.
        raise TypeError(f"checkpoint payload holds {bad}; convert it with to_plain() before saving")
    path = directory / f"model_{iteration:06d}.pt"
    # latest.pt first (docs/decisions.md, Reliability): it is then always the newest complete one. A kill during its write
    # leaves the previous one (no iteration of this save was checkpointed yet); a kill during
    # model_<it>.pt's leaves that copy to be written on resume (ensure_model_file).
    save_atomic(payload, directory / LATEST)
    save_atomic(payload, path)
    return path


def ensure_model_file(payload: dict[str, Any], directory: Path) -> Path:
    """``model_<it>.pt`` of a checkpoint read from ``latest.pt`` (a resume), written if a kill
    cut its write short, so that every save point keeps its own file."""
    path = directory / f"model_{int(payload['iteration']):06d}.pt"
    if not path.is_file():
        save_atomic(payload, path)
    return path


#: Leaf types a checkpoint may hold, matched exactly (a subclass, e.g. an IntEnum, is a class
#: the weights-only unpickler would have to build). ``nn.Parameter`` is a tensor it knows.
PLAIN_LEAVES = (torch.Tensor, torch.nn.Parameter, str, bytes, int, float, bool, type(None))
#: Containers: ``state_dict()`` returns an OrderedDict; ``torch.Size`` is a tuple.
PLAIN_MAPS = (dict, OrderedDict)
PLAIN_SEQS = (list, tuple, torch.Size)

#: Top-level payload keys holding a torch RNG state (``torch.get_rng_state()``,
#: ``torch.Generator.get_state()``): a 1-D uint8 CPU tensor for CPU and CUDA generators alike.
TORCH_RNG_KEYS = ("rng", "generator")
#: Entries loaded onto the CPU whatever the device: RNG states (``Generator.set_state`` takes a
#: CPU tensor) and the env state the runners copy onto the env device themselves.
CPU_KEYS = (*TORCH_RNG_KEYS, "streams", "curriculum", "episode")


def non_plain(obj: Any, where: str = "payload") -> str | None:
    """Where ``obj`` holds something other than plain data (e.g. "a Path at payload['x']"), or None."""
    if type(obj) in PLAIN_MAPS:
        for k, v in obj.items():
            if type(k) not in (str, int):  # str keys; int keys in optimizer states
                return f"a {type(k).__name__} key at {where}"
            found = non_plain(v, f"{where}[{k!r}]")
            if found:
                return found
        return None
    if type(obj) in PLAIN_SEQS:
        for i, v in enumerate(obj):
            found = non_plain(v, f"{where}[{i}]")
            if found:
                return found
        return None
    return None if type(obj) in PLAIN_LEAVES else f"a {type(obj).__name__} at {where}"


def to_plain(obj: Any) -> Any:
    """``obj`` with numpy arrays/scalars, paths, enums, dataclasses and generators made plain data.

    For re-saving an older checkpoint from a trusted source (README, "Checkpoints are plain
    data"); anything else that is not plain raises TypeError naming its type.
    """
    if isinstance(obj, torch.Generator):
        return obj.get_state()
    if isinstance(obj, np.ndarray):
        return torch.from_numpy(np.ascontiguousarray(obj))
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, PurePath):
        return str(obj)
    if isinstance(obj, enum.Enum):
        return to_plain(obj.value)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return to_plain(dataclasses.asdict(obj))
    if isinstance(obj, Mapping):
        return {to_plain(k): to_plain(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [to_plain(v) for v in obj]
    if isinstance(obj, tuple):
        return tuple(to_plain(v) for v in obj)
    if obj is None or type(obj) in PLAIN_LEAVES:
        return obj
    if isinstance(obj, torch.Tensor):  # a tensor subclass: keep the data, drop the class
        return obj.detach().as_subclass(torch.Tensor)
    for base in (bool, int, float, str, bytes):  # e.g. a str subclass
        if isinstance(obj, base):
            return base(obj)
    raise TypeError(f"{type(obj).__module__}.{type(obj).__qualname__} is not plain data")


def _why_refused(err: BaseException) -> tuple[bool, str]:
    """(names code, one-line reason) from torch's multi-paragraph weights-only error."""
    text = str(err)
    named = re.search(r"GLOBAL ([\w.]+)", text)
    if named:
        return True, f"loading it would call {named.group(1)}"
    detail = re.search(r"WeightsUnpickler error:\s*([^\n]+)", text)
    return False, (detail.group(1).strip() if detail else "not a torch.save file")


def _place(obj: Any, device: str, key: Any = None) -> Any:
    """Tensors onto ``device``, except optimizer step counts, which stay on the CPU.

    torch.optim keeps a non-capturable optimizer's ``step`` on the CPU (it moves it itself when
    the optimizer is capturable or fused); on a GPU it would cost a host sync per parameter.
    """
    if isinstance(obj, torch.Tensor):
        return obj if key == "step" else obj.to(device)
    if isinstance(obj, dict):
        placed = type(obj)((k, _place(v, device, k)) for k, v in obj.items())
        if hasattr(obj, "_metadata"):  # a state_dict's module versions, read by load_state_dict
            placed._metadata = obj._metadata
        return placed
    if isinstance(obj, list):
        return [_place(v, device) for v in obj]
    if isinstance(obj, tuple) and not isinstance(obj, torch.Size):
        return tuple(_place(v, device) for v in obj)
    return obj


def _read_plain(path: str | Path, label: str, wanted: str) -> Any:
    """The one unpickling read of march: plain data only (``weights_only=True``), bounded in
    size, no link; a file that names any Python callable is refused in one line."""
    p = Path(path)
    f = open_plain_file(
        p,
        label,
        MAX_CHECKPOINT_BYTES,
        wanted,
    )
    check_records(f, label)
    try:
        # Read onto the CPU whatever device wrote it (a GPU run's file loads on a CPU-only
        # machine); tensors are moved afterwards, RNG states never. torch warns about unusual
        # pickle protocols on stderr: the outcome is reported as one line instead.
        with warnings.catch_warnings(), f:
            warnings.simplefilter("ignore")
            payload = torch.load(f, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as err:
        names_code, why = _why_refused(err)
        if names_code:
            raise CheckpointError(
                f"{label}: refused: {why}, and a march checkpoint is plain data "
                "(tensors, numbers, strings, lists, dicts); nothing in the file was run. Re-save "
                "it from a trusted environment (README: Checkpoints are plain data) or retrain"
            ) from None
        raise CheckpointError(f"{label}: not a readable checkpoint ({why})") from None
    except Exception as err:  # noqa: BLE001 - any unreadable file is the same user error
        # torch's messages run to several sentences; the first names the fault.
        text = str(err).strip()
        why = text.splitlines()[0].split(". ")[0].rstrip(".") if text else type(err).__name__
        raise CheckpointError(
            f"{label}: not a readable checkpoint (truncated or corrupt: {why})"
        ) from None
    return payload


def load_plain_file(path: str | Path, label: str) -> Any:
    """A plain-data torch file that is not a checkpoint (e.g. a test's trace of a rank's state)
    through the same read as a checkpoint: weights only, bounded, no link; CheckpointError."""
    payload = _read_plain(path, label, "a plain-data file written by march")
    bad = non_plain(payload)
    if bad is not None:
        raise CheckpointError(f"{label}: holds {bad}, which is not plain data")
    return payload


def load_checkpoint(
    path: str | Path, kind: str, device: str = "cpu", source: str | None = None
) -> dict[str, Any]:
    """Load a march checkpoint of ``kind`` (teacher | student) or raise CheckpointError.

    ``source``: how errors name the file (default ``<kind>_ckpt=<path>``, the option that passed
    it; a resume passes ``resume=<run dir>: <path>``).

    Only plain data is read (``weights_only=True``): a file that names any Python callable is
    refused with one line, and nothing in it runs. Model and optimizer tensors come back on
    ``device``; torch RNG states (``rng``, ``generator``) always come back as CPU uint8 tensors,
    the only form ``torch.set_rng_state`` and ``Generator.set_state`` accept, so a checkpoint
    written on one device resumes on any other (CPU, ``cuda``, ``cuda:1``, ``meta``); so do
    the ``streams``, ``curriculum`` and ``episode`` entries (:mod:`march.learn.train_state`).
    A checkpoint this process checked and kept (:func:`keep_checked`) is taken from memory.
    """
    label = source or f"{kind}_ckpt={path}"
    payload = _CHECKED.pop(_key(path), None)  # read and checked already (keep_checked)
    if payload is None:
        payload = _read_plain(
            path, label, f"a checkpoint written by march.train (outputs/<run>/{kind}/latest.pt)"
        )
    if not isinstance(payload, dict) or payload.get("kind") != kind:
        found = payload.get("kind") if isinstance(payload, dict) else type(payload).__name__
        raise CheckpointError(f"{label}: this is a {found!r} checkpoint, not a {kind}")
    # weights_only also rebuilds types other libraries allow-listed (tensordict's TensorDict):
    # harmless to load, but not what a march checkpoint holds.
    bad = non_plain(payload)
    if bad is not None:
        raise CheckpointError(
            f"{label}: holds {bad}, which is not plain data; re-save it from a "
            "trusted environment (README: Checkpoints are plain data) or retrain"
        )
    for key in TORCH_RNG_KEYS:
        state = payload.get(key)
        if key in payload and not (
            isinstance(state, torch.Tensor) and state.dtype == torch.uint8 and state.dim() == 1
        ):
            raise CheckpointError(f"{label}: '{key}' is not a torch RNG state (a 1-D uint8 tensor)")
    return {
        k: v.to("cpu").contiguous()
        if k in TORCH_RNG_KEYS
        else v
        if k in CPU_KEYS
        else _place(v, device, k)
        for k, v in payload.items()
    }


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


def state_differences(a: Any, b: Any, where: str = "state") -> list[str]:
    """Where two nested checkpoint entries (dicts, tensors, plain values) differ: each path, or
    a path with both key lists where the keys differ; tensors are compared exactly (shape,
    dtype, values). [] when they are the same (a resumed rank's state against the saved one)."""
    if isinstance(a, dict) and isinstance(b, dict):
        if a.keys() != b.keys():
            return [f"{where}: keys {sorted(a)} vs {sorted(b)}"]
        return [d for k in a for d in state_differences(a[k], b[k], f"{where}.{k}")]
    if isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor):
        ok = a.shape == b.shape and a.dtype == b.dtype and torch.equal(a, b)
        return [] if ok else [where]
    return [] if a == b else [where]
