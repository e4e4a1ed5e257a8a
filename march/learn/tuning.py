"""A run as one trial of march's Optuna sweeper (``hydra/sweeper=march_optuna``): report each
evaluation row's objective to the study and stop early when its pruner says so.

The sweeper (``hydra_plugins/march_optuna_sweeper``) sets ``MARCH_OPTUNA_TRIAL_ID``,
``MARCH_OPTUNA_STORAGE`` and ``MARCH_OPTUNA_STUDY`` in the job's environment
(``hydra.job.env_set``); outside a trial every function here does nothing, and Optuna is not
imported. The pruner is the sweep's own (``hydra.sweeper.pruner`` of the job's Hydra config).
In a run over N ranks rank 0 reports and decides, and every rank follows its decision.
"""

from __future__ import annotations

import math
import os
from typing import Any

from march.learn import distributed

ENV_TRIAL_ID = "MARCH_OPTUNA_TRIAL_ID"
ENV_STORAGE = "MARCH_OPTUNA_STORAGE"
ENV_STUDY = "MARCH_OPTUNA_STUDY"

_trial: dict[str, Any] = {}


def in_trial() -> bool:
    return ENV_TRIAL_ID in os.environ


def _open() -> Any:
    """This job's ``optuna.Trial`` (opened once)."""
    key = (os.environ[ENV_STORAGE], os.environ[ENV_STUDY], os.environ[ENV_TRIAL_ID])
    if _trial.get("key") != key:  # a local launcher runs every trial in one process
        import optuna
        from hydra.core.hydra_config import HydraConfig
        from hydra.utils import instantiate

        from hydra_plugins.march_optuna_sweeper.sweeper import open_storage

        pruner_cfg = HydraConfig.get().sweeper.get("pruner") if HydraConfig.initialized() else None
        pruner = instantiate(pruner_cfg) if pruner_cfg else optuna.pruners.NopPruner()
        study = optuna.load_study(
            study_name=os.environ[ENV_STUDY],
            storage=open_storage(os.environ[ENV_STORAGE]),
            pruner=pruner,
        )
        _trial.update(key=key, trial=optuna.trial.Trial(study, int(os.environ[ENV_TRIAL_ID])))
    return _trial["trial"]


def report(value: float, step: int) -> None:
    """Report an evaluation's objective at ``step``; raise ``optuna.TrialPruned`` (on every rank)
    when the study's pruner stops this trial. A non-finite value is not reported (Optuna
    records it as the trial's failure when the run returns it)."""
    if not in_trial():
        return
    prune = False
    if distributed.writes_files():
        trial = _open()
        if math.isfinite(value):
            trial.report(float(value), int(step))
        prune = trial.should_prune()
    if distributed.agree(prune):
        import optuna

        raise optuna.TrialPruned(f"pruned at step {step} (objective {value:.6g})")


def is_pruned(err: BaseException) -> bool:
    return type(err).__name__ == "TrialPruned" and in_trial()
