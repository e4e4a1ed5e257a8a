"""Run directories as a finished run leaves them (its config.yaml), resuming one, and the
``python -m march.train`` command line, for the resume tests (tests/test_reliability.py,
tests/test_resume_state.py)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from omegaconf import OmegaConf

from march.config.cli import load
from march.store.resume_rules import resume_config

ROOT = Path(__file__).resolve().parent.parent


def saved_run(tmp_path: Path, *overrides: str) -> Path:
    """``tmp_path/run`` holding the config.yaml of a smoke run with ``overrides``."""
    run = tmp_path / "run"
    run.mkdir()
    cfg = load(["compute=smoke", *overrides])
    OmegaConf.save(OmegaConf.structured(cfg), run / "config.yaml")
    return run


def resume(run: Path, *overrides: str):
    """``resume_config`` as ``python -m march.train resume=<run> <overrides>`` calls it."""
    ovs = [*overrides, f"resume={run}"]
    return resume_config(run, load(["compute=auto", *ovs]), ovs)


def train_cli(*args: str, timeout: int = 300) -> subprocess.CompletedProcess:
    """``python -m march.train <args>`` from the repository root, output captured."""
    env = dict(os.environ, HYDRA_FULL_ERROR="0")
    return subprocess.run(
        [sys.executable, "-m", "march.train", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
    )
