"""``hydra/launcher=march_submitit_slurm``: ``submitit_slurm`` plus the ``srun`` line's arguments."""

from __future__ import annotations

from dataclasses import dataclass, field

from hydra.core.config_store import ConfigStore
from hydra_plugins.hydra_submitit_launcher.config import SlurmQueueConf


@dataclass
class MarchSlurmQueueConf(SlurmQueueConf):
    srun_args: list[str] = field(default_factory=list)
    """Arguments of the ``srun`` that starts the job's tasks (submitit's ``srun_args``), for
    srun-only options such as ``--kill-on-bad-exit=1`` (in ``additional_parameters`` they would go
    into the ``#SBATCH`` header, where sbatch refuses them)."""


ConfigStore.instance().store(
    group="hydra/launcher",
    name="march_submitit_slurm",
    node=MarchSlurmQueueConf,
    provider="march",
)
