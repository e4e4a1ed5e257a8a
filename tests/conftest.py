"""Shared test set-up: one warp kernel cache for every test session (compiles once, ~40 s)."""

from __future__ import annotations

import os
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
os.environ.setdefault("WARP_CACHE_PATH", str(ROOT / ".warp_cache"))
os.environ.setdefault("WANDB_MODE", "offline")
os.environ.setdefault("MPLBACKEND", "Agg")
if os.environ.get("PYTEST_XDIST_WORKER"):
    # One worker per core: a second torch / OpenMP thread per worker (or per run a test starts)
    # only competes for the other worker's core, and OpenMP's fork/join waits on a busy core
    # made such steps several times slower. torch reads it when first imported (after this
    # file), and the runs a test starts inherit it.
    os.environ.setdefault("OMP_NUM_THREADS", "1")


import atexit  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402

import pytest  # noqa: E402
from filelock import FileLock  # noqa: E402

# The slowest files first, the many quick ones after them, so that with
# ``--dist loadfile`` the two workers start on the two longest chains and the quick files even
# out the end: longest processing time first. The first holds the session's smoke run and
# bundle; the second worker meanwhile runs three files that never step a simulator (CLI errors,
# config values, figures from synthetic runs, ~80 s): on a fresh clone the first run compiles
# warp's kernels (~30 s of one core), and a second simulation started beside it compiled the
# same kernels again (the cache has no lock). Then the sweeps, on a warm cache.
SLOW_FILES = (
    "test_sim2sim_agreement.py",
    "test_config.py",
    "test_config_values.py",
    "test_figures.py",
    "test_sweeps.py",
    "test_docs.py",  # every getting-started block: the docs site, a play, a modelfree smoke run
    "test_evaluate.py",
    "test_eval_repeat.py",
    "test_env_teacher.py",
    "test_pipeline.py",
    "test_distributed.py",
    "test_reliability.py",
    "test_resume_state.py",
    "test_distill.py",
    "test_extending.py",
    "test_syncs.py",
    "test_optuna_sweep.py",
)


# Programs the project does not install (neither `make install` nor pyproject's extras), with the
# make target that provides each, or None where no target does. The suite runs as on a fresh
# machine: they are hidden from the PATH of every test and every process a test starts, also
# where they are installed (CI's machine had Slurm from `make test-slurm`, and a test that
# needed srun passed there and failed on a newcomer's machine, issue 60). A test that needs one
# says so with ``@pytest.mark.needs_program("srun")``: it runs where the program is installed and
# skips elsewhere with one line naming the target. ffmpeg: march writes videos with
# imageio-ffmpeg's own binary (a pip package); chromium: scripts/capture_viewer.py, no test.
NOT_INSTALLED: dict[str, str | None] = {
    **dict.fromkeys(
        ("srun", "sbatch", "scontrol", "squeue", "salloc", "sinfo", "scancel", "sacct", "slurmd"),
        "make test-slurm",
    ),
    **dict.fromkeys(("ffmpeg", "ffprobe", "chromium", "chromium-browser", "google-chrome"), None),
}


def hidden_path(path: str, hide, shadow_root: Path) -> str:
    """``path`` (a PATH value) without the programs ``hide``: each directory that holds one is
    replaced by a directory under ``shadow_root`` of links to its other entries (the rest of
    /usr/bin stays reachable); directories that hold none are kept as they are (a venv's bin/
    is never replaced: python finds its venv from the path it was started by)."""
    out = []
    for i, entry in enumerate(path.split(os.pathsep)):
        folder = Path(entry) if entry else None
        if folder is None or not any((folder / name).exists() for name in hide):
            out.append(entry)
            continue
        shadow = shadow_root / f"{i}"
        shadow.mkdir(parents=True, exist_ok=True)
        for item in folder.iterdir():
            if item.name not in hide and not (shadow / item.name).exists():
                (shadow / item.name).symlink_to(item)
        out.append(str(shadow))
    return os.pathsep.join(out)


FULL_PATH = os.environ.setdefault("MARCH_TESTS_FULL_PATH", os.environ.get("PATH", ""))
"""The PATH as the suite found it (a ``needs_program`` test runs with it); pytest-xdist's
workers inherit it from the controller, whose PATH they inherit already hidden."""
if any(shutil.which(name) for name in NOT_INSTALLED):
    _shadow = Path(tempfile.mkdtemp(prefix="march-path-"))
    atexit.register(shutil.rmtree, _shadow, ignore_errors=True)
    os.environ["PATH"] = hidden_path(FULL_PATH, NOT_INSTALLED, _shadow)


@pytest.fixture(autouse=True)
def _needs_program(request, monkeypatch):
    """``@pytest.mark.needs_program(name, ...)``: the real PATH where every ``name`` is installed,
    else a skip naming the make target that installs it."""
    for mark in request.node.iter_markers("needs_program"):
        for name in mark.args:
            if name not in NOT_INSTALLED or NOT_INSTALLED[name] is None:
                pytest.fail(f"needs_program({name!r}): no make target installs it (conftest.py)")
            if shutil.which(name, path=FULL_PATH) is None:
                pytest.skip(f"needs {name}: `{NOT_INSTALLED[name]}` installs it")
        monkeypatch.setenv("PATH", FULL_PATH)


def pytest_configure(config) -> None:
    config.addinivalue_line(
        "markers", "needs_program(*names): a program the project does not install (conftest.py)"
    )
    # pytest-xdist orders files by their number of tests unless told not to; keep ours.
    if hasattr(config.option, "loadscopereorder"):
        config.option.loadscopereorder = False


def pytest_collection_modifyitems(config, items) -> None:
    rank = {name: i for i, name in enumerate(SLOW_FILES)}
    # A stable sort: each file's tests stay together and in their order (module fixtures).
    items.sort(key=lambda item: rank.get(item.path.name, len(SLOW_FILES)))


def shared_dir(tmp_path_factory, name: str, build) -> Path:
    """A directory ``build(path)`` fills once per test session, also when pytest-xdist runs the
    session in several worker processes: the first worker builds it under a file lock in the
    session's common temp dir, the others wait and reuse it (a failed build fails them all)."""
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    if worker is None:
        path = tmp_path_factory.mktemp(name)
        build(path)
        return path
    root = tmp_path_factory.getbasetemp().parent  # shared by the session's workers
    path, done, failed = root / name, root / f"{name}.done", root / f"{name}.failed"
    with FileLock(str(root / f"{name}.lock")):
        if failed.is_file():
            pytest.fail(f"shared fixture {name} failed in another worker: {failed.read_text()}")
        if not done.is_file():
            path.mkdir(exist_ok=True)
            try:
                build(path)
            except BaseException as err:
                failed.write_text(str(err)[-3000:])
                raise
            done.write_text(worker)
    return path


def _smoke(run_dir: Path) -> None:
    out = subprocess.run(
        [sys.executable, "-m", "march.train", "compute=smoke", f"hydra.run.dir={run_dir}"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    (run_dir / "stdout.txt").write_text(out.stdout)


@pytest.fixture(scope="session")
def smoke_run(tmp_path_factory) -> Path:
    """`python -m march.train compute=smoke` exactly as a user runs it (once per session)."""
    return shared_dir(tmp_path_factory, "smoke", _smoke)


@pytest.fixture(scope="session")
def bundle(smoke_run, tmp_path_factory) -> Path:
    """The smoke student exported as a deployment bundle (``python -m march.export``)."""

    def export(out: Path) -> None:
        _export(smoke_run, out)

    return shared_dir(tmp_path_factory, "bundle", export) / "student.onnx"


def _export(smoke_run: Path, out: Path) -> None:
    ckpt = smoke_run / "student" / "latest.pt"
    res = subprocess.run(
        [sys.executable, "-m", "march.export", f"student_ckpt={ckpt}", f"out={out}"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    assert "run it: python -m march.sim2sim" in res.stdout
