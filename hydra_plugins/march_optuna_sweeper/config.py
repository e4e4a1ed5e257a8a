"""The sweeper's options (``hydra.sweeper.*``), registered as ``hydra/sweeper=march_optuna``."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from hydra.core.config_store import ConfigStore


@dataclass
class MarchOptunaSweeperConf:
    _target_: str = "hydra_plugins.march_optuna_sweeper.sweeper.MarchOptunaSweeper"
    _recursive_: bool = False
    """The sweeper builds its sampler and pruner itself (a resumed study reseeds its sampler)."""
    direction: str = "maximize"
    """maximize or minimize the job's return value (march.train: the final ``objective``)."""
    study_name: str = "march"
    storage: str | None = None
    """Where the study lives. None: the journal file ``<hydra.sweep.dir>/<study_name>.journal``
    (re-running the same command with the same ``hydra.sweep.dir`` resumes the study); a file
    path (a journal file); or an Optuna RDB URL (``sqlite:///...``, ``postgresql://...``)."""
    n_trials: int = 20
    """The study's total: trials already in the storage count (a finished study runs none)."""
    n_jobs: int = 1
    """Trials launched together (one launcher batch: parallel under Slurm)."""
    max_failures: int = 2
    """Failed trials (a crash, a non-finite value) of this sweep it goes on after; one more stops
    it. Failures of earlier sweeps of the study stay recorded and do not count again."""
    heartbeat_s: float = 30.0
    """How often [s] a trial's job marks itself alive (``<sweep dir>/<trial>/.optuna_heartbeat``).
    A sweep that finds a RUNNING trial waits for it while its job is alive, and gives it up once
    the job's process is gone (same host) or its mark is 4 intervals old."""
    sampler: Any = field(  # a resumed study: seed + the number of trials already recorded
        default_factory=lambda: {"_target_": "optuna.samplers.TPESampler", "seed": 0}
    )
    pruner: Any = field(
        default_factory=lambda: {
            "_target_": "optuna.pruners.MedianPruner",
            "n_startup_trials": 2,
            "n_warmup_steps": 0,
        }
    )
    """Asked at every evaluation row of a trial (march.learn.tuning); null: no pruning."""
    params: dict[str, str] = field(default_factory=dict)
    """The search space in Hydra's sweep syntax: ``interval(a, b)`` (float), ``tag(int, interval(a, b))``,
    ``tag(log, interval(a, b))``, ``range(a, b[, step])``, ``choice(x, y, ...)``;
    a plain value is fixed for every trial."""


ConfigStore.instance().store(
    group="hydra/sweeper", name="march_optuna", node=MarchOptunaSweeperConf, provider="march"
)
