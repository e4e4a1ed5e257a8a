"""Test helper: ``march.train`` as a sweep command, with faults injected into chosen trials.

    MARCH_CRASH_TRIAL=1 MARCH_BAD_TRIAL=3 python tests/optuna_trial.py -m +sweep=optuna_clf ...

The trial whose Optuna trial number (``MARCH_OPTUNA_TRIAL``, set by the sweeper in the job's
environment) equals ``MARCH_CRASH_TRIAL`` raises in its teacher stage (a crashed run); the one
equal to ``MARCH_BAD_TRIAL`` has every evaluation's distance lowered by 100 m (a policy that walks
backwards: its intermediate rows fall below every other trial's, so the median pruner stops it).
Everything else is the real entry point, sweeper, launcher, runs and files.
"""

from __future__ import annotations

import os
import runpy

from march.evaluation import protocol
from march.learn.teacher import TeacherRunner


def _trial_is(var: str) -> bool:
    return os.environ.get("MARCH_OPTUNA_TRIAL") == os.environ.get(var, "none")


_learn = TeacherRunner.learn


def _learn_or_crash(self: TeacherRunner, *args, **kwargs):
    if _trial_is("MARCH_CRASH_TRIAL"):
        raise RuntimeError("injected crash")
    return _learn(self, *args, **kwargs)


_evaluate = protocol.evaluate


def _evaluate_badly(*args, **kwargs):
    row = _evaluate(*args, **kwargs)
    if _trial_is("MARCH_BAD_TRIAL"):
        row = {**row, "mean_distance_m": row["mean_distance_m"] - 100.0}
    return row


TeacherRunner.learn = _learn_or_crash  # type: ignore[method-assign]
protocol.evaluate = _evaluate_badly

if __name__ == "__main__":
    runpy.run_module("march.train", run_name="__main__", alter_sys=True)
