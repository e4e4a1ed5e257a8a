"""Hydra's submitit Slurm launcher with ``srun_args`` (``hydra/launcher=march_submitit_slurm``).

``hydra-submitit-launcher`` 1.2 (the latest) hands every option of its config to sbatch's header
or to submitit, but has no field for the arguments of the ``srun`` line that starts the tasks.
Options that only srun reads (``--kill-on-bad-exit``: sbatch refuses the whole job on it) belong
there; ``conf/hydra/launcher/march_slurm_ddp.yaml`` uses it. See docs/scaling.md ("Slurm").
"""

from hydra_plugins.march_slurm_launcher.config import MarchSlurmQueueConf

__all__ = ["MarchSlurmQueueConf"]
