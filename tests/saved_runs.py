"""Run directories as a finished run leaves them (its config.yaml), and resuming one, for the
resume tests (tests/test_reliability.py, tests/test_resume_state.py)."""

from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf

from march.config.cli import load
from march.config.resume import resume_config


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
