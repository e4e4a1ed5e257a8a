"""march's Hydra sweeper on a maintained Optuna (>= 4): ``hydra/sweeper=march_optuna``.

Hydra's own ``hydra-optuna-sweeper`` (1.3.0, the latest) pins ``optuna<3``: no journal storage,
and a study that lives in memory. This one keeps the study in a journal file under the sweep
directory, so the same command resumes it; see docs/scaling.md ("Tuning").
"""

from hydra_plugins.march_optuna_sweeper.config import MarchOptunaSweeperConf

__all__ = ["MarchOptunaSweeperConf"]
