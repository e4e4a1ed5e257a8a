"""The smoke run's student in mjlab's evaluation env on the hardware course, DR and corruption
off: the training side of the sim-to-sim comparisons (tests/test_sim2sim.py,
tests/test_deploy_spec.py)."""

from __future__ import annotations

from pathlib import Path
from typing import Any


def hardware_eval_cfg(smoke_run: Path) -> tuple[Any, Any]:
    """(run config as the checkpoint defines it, mjlab env config of 1 env): evaluation env on
    the hardware course, no DR, no depth corruption, no proprioception noise."""
    from march.config.cli import load
    from march.env.build import build_env_cfg
    from march.store.checkpoint import load_checkpoint
    from march.store.provenance import apply_checkpoint_config

    ckpt = str(smoke_run / "student" / "latest.pt")
    overrides = ["eval.randomization=false", "eval.corruption=false", "eval.course=hardware"]
    cfg = apply_checkpoint_config(
        load(overrides), load_checkpoint(ckpt, "student"), overrides, ckpt, "student"
    )
    env_cfg = build_env_cfg(cfg, "eval", num_envs=1)
    # eval.corruption covers the depth image; the proprioception noise is switched off here
    env_cfg.observations["student"].enable_corruption = False
    return cfg, env_cfg
