"""Shared test set-up: one warp kernel cache for every test session (compiles once, ~40 s)."""

from __future__ import annotations

import os
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
os.environ.setdefault("WARP_CACHE_PATH", str(ROOT / ".warp_cache"))
os.environ.setdefault("WANDB_MODE", "offline")
os.environ.setdefault("MPLBACKEND", "Agg")


import subprocess  # noqa: E402
import sys  # noqa: E402

import pytest  # noqa: E402


@pytest.fixture(scope="session")
def smoke_run(tmp_path_factory) -> Path:
    """`python -m march.train compute=smoke` exactly as a user runs it (once per session)."""
    run_dir = tmp_path_factory.mktemp("smoke")
    out = subprocess.run(
        [sys.executable, "-m", "march.train", "compute=smoke", f"hydra.run.dir={run_dir}"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    (run_dir / "stdout.txt").write_text(out.stdout)
    return run_dir


@pytest.fixture(scope="session")
def bundle(smoke_run, tmp_path_factory) -> Path:
    """The smoke student exported as a deployment bundle (``python -m march.export``)."""
    out = tmp_path_factory.mktemp("bundle")
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
    return out / "student.onnx"
