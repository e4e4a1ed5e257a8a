"""A run's ``status.json``: written in one rename, read so that it tells the truth.

The writer (``march.train``) records ``running`` with its pid and host when it starts, then
``done`` / ``failed`` / ``preempted`` / ``pruned``. A run killed with SIGKILL (the OOM killer,
``kill -9``, a node's crash) writes nothing more, so its file keeps saying ``running``.
:func:`read_status` is what every reader uses (``march.inspect run``, the figures'
``analysis/rundirs.py``, ``march.train resume=``): a ``running`` status whose pid is gone on this
host reads as ``killed``; one from another host is reported as it is, with the host named (this
host cannot see that process).
"""

from __future__ import annotations

import json
import os
import socket
import time
from pathlib import Path
from typing import Any

from march.store.bounded_read import FileRefused, open_regular

STATUS_NAME = "status.json"
MAX_STATUS_BYTES = 1 << 20
"""A status file is a few hundred bytes (an error message at most a few KB)."""


def write_status(run_dir: Path, state: str, **extra: Any) -> None:
    """``<run>/status.json`` replaced by ``{"state": state, "time": now, **extra}`` (rank 0)."""
    from march.store.checkpoint import write_json_atomic  # torch: not for the readers

    write_json_atomic({"state": state, "time": time.time(), **extra}, Path(run_dir) / STATUS_NAME)


def pid_alive(pid: int) -> bool:
    """Whether a process with this pid exists on this host (signal 0: nothing is sent)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process: it exists
        return True
    except (OverflowError, ValueError, OSError):
        return False
    return True


def read_status(run_dir: Path) -> dict[str, Any] | None:
    """The run's status as a dict with at least ``state`` (None without a status file).

    An unreadable file reads as ``{"state": "unreadable", "error": <why>}``. A ``running``
    status whose ``host`` is this host and whose ``pid`` is no longer alive reads as
    ``killed``, with ``"recorded": "running"`` and a ``note`` saying why.
    """
    path = Path(run_dir) / STATUS_NAME
    if not os.path.lexists(path):
        return None
    try:
        with open_regular(path, str(path), MAX_STATUS_BYTES, "a run's status.json") as f:
            status = json.loads(f.read().decode())
    except (FileRefused, ValueError, UnicodeDecodeError, RecursionError) as err:
        return {"state": "unreadable", "error": str(err).splitlines()[0] if str(err) else ""}
    if not isinstance(status, dict) or not isinstance(status.get("state"), str):
        return {"state": "unreadable", "error": f"{path}: no 'state' entry"}
    pid, host = status.get("pid"), status.get("host")
    if status["state"] == "running" and type(pid) is int and host == socket.gethostname():
        if not pid_alive(pid):
            status = {
                **status,
                "state": "killed",
                "recorded": "running",
                "note": f"status.json says running, but its pid {pid} is gone on this host "
                f"({host}): the run was killed; continue it with resume={run_dir}",
            }
    return status
