"""Test helper: a Hydra app whose job is an Optuna trial as ``march.train`` runs one, without the
simulation (seconds, not minutes), for the sweeper's own tests (tests/test_optuna_drivers.py).

    python tests/optuna_app.py -m --config-dir <dir> --config-name app [overrides]

The job calls :mod:`march.learn.tuning` where ``march.train.main`` does: ``begin`` before the run,
``report`` after every "evaluation" (``steps`` of them, ``step_s`` seconds apart, objective
``x * step``; the last one ``final``), then ``finish`` with the value ``x``, ``pruned`` or
``failed``, and ``end``. The trial whose number is in ``MARCH_CRASH_TRIALS`` (comma-separated)
raises at its first step; ``MARCH_APP_LOG`` names a file each job appends "start <n> <pid>" and
"end <n>" to.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import hydra
from omegaconf import DictConfig

from march.learn import tuning


def _log(line: str) -> None:
    if path := os.environ.get("MARCH_APP_LOG"):
        with Path(path).open("a") as f:
            f.write(line + "\n")


@hydra.main(config_path=None, config_name=None, version_base="1.3")
def app(cfg: DictConfig) -> float | None:
    number = os.environ.get(tuning.ENV_TRIAL, "-")
    _log(f"start {number} {os.getpid()}")
    crash = os.environ.get("MARCH_CRASH_TRIALS", "").split(",")
    try:
        tuning.begin()
        for step in range(1, int(cfg.steps) + 1):
            time.sleep(float(cfg.step_s))
            if number in crash:
                raise RuntimeError("injected crash")
            tuning.report(float(cfg.x) * step, step, final=step == int(cfg.steps))
        tuning.finish(float(cfg.x))
        return float(cfg.x)
    except BaseException as err:
        if tuning.is_pruned(err):
            tuning.pruned()
            return None
        tuning.failed(err)
        raise
    finally:
        tuning.end()
        _log(f"end {number}")


if __name__ == "__main__":
    app()
