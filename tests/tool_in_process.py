"""A march tool's command line run inside the test process: ``python -m march.<tool> <args>``
as ``runpy`` runs it (its ``__main__`` block, Hydra included), its exit status, stdout and
stderr captured at the file descriptors (what a shell shows, a C library's writes included).

For the tests of what a tool *says* when it refuses (the line, its exit status, nothing run):
a subprocess paid ~2 s of CPU (python, torch) per refusal before saying it, on a 2-core
machine running the suite (issue 60). Tests of the process itself - what it imports, its
memory, signals, PATH, files Hydra writes in its working directory - keep a real process.
"""

from __future__ import annotations

import logging
import runpy
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def run_tool(
    capfd: pytest.CaptureFixture, module: str, *args: str, cwd: Path = ROOT
) -> subprocess.CompletedProcess:
    """``python -m <module> <args>`` from ``cwd`` (the repository root), in this process, as a
    :class:`subprocess.CompletedProcess` (returncode, stdout, stderr). What the run changed in
    the process is put back: the working directory, ``sys.argv``, the environment, the root
    logger's handlers (Hydra adds its job log's) and Hydra's global state; and what the
    process's exit does is done: a run directory lock the run holds is released (the lock's
    ``atexit`` handler), so that none is left behind, as none is by a process."""
    from hydra.core.global_hydra import GlobalHydra

    from march.store import run_lock

    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(cwd)
        mp.setattr(sys, "argv", [module, *args])
        mp.setenv("HYDRA_FULL_ERROR", "0")
        capfd.readouterr()  # what the test printed before is not the tool's
        try:
            runpy.run_module(module, run_name="__main__", alter_sys=True)
            code = 0
        except SystemExit as stop:
            code = stop.code if isinstance(stop.code, int) else (0 if stop.code is None else 1)
        finally:
            for h in root.handlers[:]:
                if h not in handlers:
                    root.removeHandler(h)
                    h.close()
            root.setLevel(level)
            GlobalHydra.instance().clear()
            run_lock.release_all()  # the process's atexit handler
        out = capfd.readouterr()
    return subprocess.CompletedProcess([module, *args], code, out.out, out.err)
