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


import subprocess  # noqa: E402
import sys  # noqa: E402

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


def pytest_configure(config) -> None:
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
