"""One run over N processes (torchrun, srun): data-parallel teacher PPO and distillation.

``torchrun --nproc_per_node=N -m march.train ...`` starts N ranks of one run. Every rank builds
its own env of ``compute.num_envs`` envs (per rank: the run steps N x num_envs envs) on the same
courses (the terrain seed is shared) with its own seed stream (:func:`rank_seed`; rank 0 keeps the
run's seed, so a one-process run is unchanged). The policy is the same on every rank:

- initial parameters are broadcast from rank 0 (rsl-rl's ``broadcast_parameters`` for PPO,
  :func:`broadcast_module` for the student);
- PPO runs rsl-rl's ``multi_gpu`` path (gradients all-reduced, KL reduced, learning rate
  broadcast from rank 0): rsl-rl's runner hard-codes nccl and ``cuda:<local_rank>``, its
  algorithm's collective calls work with any backend, so march initialises the process group
  itself (nccl on CUDA, gloo on CPU) and hands PPO the ``multi_gpu`` dict;
- distillation averages its gradients the same way (:func:`average_gradients`);
- every observation normaliser learns the moments of all ranks' batches once per iteration
  (:mod:`march.learn.rank_normalizers`: per-rank moments kept on the device
  during the rollout, then one all-gather for all normalisers, combined in rank order, so
  every rank computes the same bits; rsl-rl leaves them per rank);
- episode statistics, losses, fault counts and evaluation rollouts are reduced over the ranks;
- rank 0 alone writes files (:func:`writes_files` gates march's writers) and prints.

With one process (no ``WORLD_SIZE`` or ``WORLD_SIZE=1``) every function here is the identity.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # torch where a function needs it: march.train's refusals run without it
    import torch


@dataclass(frozen=True)
class Dist:
    """This process's place in the run."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0
    backend: str = ""

    @property
    def main(self) -> bool:
        return self.rank == 0

    @property
    def active(self) -> bool:
        return self.world > 1


_DIST = Dist()


def current() -> Dist:
    return _DIST


def writes_files() -> bool:
    """Whether this process writes run files (rank 0, or a single process)."""
    return _DIST.rank == 0


def _export_slurm_env() -> None:
    """Inside a Slurm job step of several tasks (``srun``, or submitit's
    ``hydra/launcher=march_slurm_ddp``) and not under torchrun: torch's env:// variables from
    Slurm's, as submitit's TorchDistributedEnvironment sets them (the job's first node is the
    master, the port drawn from the job id, RANK = SLURM_PROCID, LOCAL_RANK = SLURM_LOCALID)."""
    if "WORLD_SIZE" in os.environ or int(os.environ.get("SLURM_NTASKS", "1")) <= 1:
        return
    if "SLURM_PROCID" not in os.environ or "SLURM_JOB_ID" not in os.environ:
        return
    import random

    from submitit.slurm.slurm import SlurmJobEnvironment

    job = SlurmJobEnvironment()  # reads SLURM_* (also outside a submitit job: plain srun)
    port = os.environ.get("MASTER_PORT") or str(random.Random(job.job_id).randint(20000, 60000))
    os.environ.update(
        {
            "MASTER_ADDR": os.environ.get("MASTER_ADDR") or job.hostnames[0],
            "MASTER_PORT": port,
            "RANK": str(job.global_rank),
            "WORLD_SIZE": str(job.num_tasks),
            "LOCAL_RANK": str(job.local_rank),
            "LOCAL_WORLD_SIZE": str(job.num_tasks // max(job.num_nodes, 1)),
        }
    )


def env_world() -> tuple[int, int, int]:
    """(rank, world size, local rank) from torchrun's or Slurm's environment."""
    _export_slurm_env()
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local = int(os.environ.get("LOCAL_RANK", str(rank)))
    return rank, world, local


def rank_seed(seed: int, rank: int) -> int:
    """Rank ``rank``'s seed in a run seeded ``seed``: the seed itself on rank 0, otherwise a
    number drawn from numpy's SeedSequence of (seed, rank) in 0..2^31-1 (warp takes an int32), so
    no rank of one run repeats a rank of a run seeded seed + k."""
    if rank == 0:
        return int(seed)
    return int(np.random.SeedSequence([int(seed), int(rank)]).generate_state(1)[0] % 2**31)


DEFAULT_TIMEOUT_S = 300.0
"""The process group's timeout (``compute.dist_timeout_s``): a collective that waits longer for a
rank (dead, hung, or stopped by the scheduler) raises instead of holding every device; torch's
own defaults are 10 min (nccl) and 30 min (gloo)."""


def visible_device(local_rank: int, count: int | None = None) -> str:
    """The CUDA device of a rank from what its process can see: one visible GPU (a cluster that
    binds one GPU per task, ``CUDA_VISIBLE_DEVICES`` set per task) is ``cuda:0`` whatever the
    local rank; several are indexed by the local rank. One line when the rank has none."""
    import torch

    count = torch.cuda.device_count() if count is None else count
    if count == 1:
        return "cuda:0"
    if local_rank >= count:
        from march.errors import ConfigError

        raise ConfigError(
            f"local rank {local_rank} sees {count} CUDA device(s): start at most {count} "
            "processes per node (torchrun --nproc_per_node, Slurm --ntasks-per-node) or bind "
            "one GPU per task"
        )
    return f"cuda:{local_rank}"


def init(device: str, timeout_s: float = DEFAULT_TIMEOUT_S) -> Dist:
    """Join the process group described by the environment (no-op for one process).

    nccl on the rank's visible CUDA device (:func:`visible_device`) when ``device`` is CUDA, gloo
    on CPU; every collective gives up after ``timeout_s`` (:func:`lost_rank` words the error).
    Returns the rank's place.
    """
    global _DIST
    rank, world, local = env_world()
    if world <= 1:
        _DIST = Dist()
        return _DIST
    import datetime

    import torch
    import torch.distributed as td

    backend = "nccl" if device.startswith("cuda") else "gloo"
    if not td.is_initialized():
        if backend == "nccl":
            torch.cuda.set_device(torch.device(visible_device(local)))
        td.init_process_group(
            backend=backend,
            rank=rank,
            world_size=world,
            timeout=datetime.timedelta(seconds=float(timeout_s)),
        )
    _DIST = Dist(rank=rank, world=world, local_rank=local, backend=backend)
    return _DIST


def lost_rank(err: BaseException) -> str | None:
    """One line for an error that means another rank of the run is gone or hung (a collective
    that failed or timed out), or None for any other error."""
    import torch.distributed as td

    text = str(err).strip()
    dist_error = isinstance(err, getattr(td, "DistError", ()))
    words = ("gloo", "nccl", "connection closed", "connection reset", "timed out")
    if not _DIST.active or not (dist_error or any(w in text.lower() for w in words)):
        return None
    first = text.splitlines()[0] if text else type(err).__name__
    first = first.split("] ", 1)[-1][:160]  # gloo's messages start with a source location
    return (
        f"rank {_DIST.rank}: another rank of this {_DIST.world}-rank run stopped or stopped "
        f"answering ({type(err).__name__}: {first})"
    )


_ON_LEAVE: list[Callable[[], None]] = []
"""What runs when this process leaves its process group (:func:`on_leave`)."""


def on_leave(forget: Callable[[], None]) -> None:
    """Run ``forget`` when this process leaves its process group (:func:`abort`,
    :func:`shutdown`): a module that holds state of the group registers how to drop it
    (:mod:`march.learn.rank_normalizers` forgets the normalisers it took over). Registering
    the same callable twice runs it once. This module imports none of its users."""
    if forget not in _ON_LEAVE:
        _ON_LEAVE.append(forget)


def _leave_group() -> None:
    for forget in _ON_LEAVE:
        forget()


def abort() -> None:
    """Leave the process group after a lost rank without waiting for the others."""
    global _DIST
    _leave_group()
    _DIST = Dist()


def rank_log(run_dir: Any) -> Any:
    """Ranks > 0 print into ``<run>/ranks/rank<r>.log`` (stdout and stderr, line-buffered; a
    traceback lands there too); rank 0 keeps the console and Hydra's ``train.log``. Returns the
    file's path (None on rank 0 or for one process)."""
    import sys
    from pathlib import Path

    if not _DIST.active or _DIST.main:
        return None
    path = Path(run_dir) / "ranks" / f"rank{_DIST.rank}.log"
    path.parent.mkdir(parents=True, exist_ok=True)
    f = path.open("a", buffering=1)
    sys.stdout = sys.stderr = f
    return path


def shutdown() -> None:
    global _DIST
    _leave_group()
    if _DIST.active:
        import torch.distributed as td

        if td.is_initialized():
            td.destroy_process_group()
    _DIST = Dist()


def rank_device(device: str, d: Dist | None = None, count: int | None = None) -> str:
    """A CUDA run puts rank r on its visible device (:func:`visible_device`); CPU stays CPU."""
    d = d or _DIST
    if d.active and device.startswith("cuda"):
        return visible_device(d.local_rank, count)
    return device


def rank_config(cfg: Any, d: Dist | None = None, count: int | None = None) -> Any:
    """The rank's copy of the run config: its own seed and device, everything else shared."""
    d = d or _DIST
    if not d.active:
        return cfg
    device = rank_device(cfg.compute.device, d, count)
    compute = dataclasses.replace(cfg.compute, device=device)
    return dataclasses.replace(cfg, seed=rank_seed(cfg.seed, d.rank), compute=compute)


def collective_device() -> torch.device:
    """The device collectives run on (nccl needs CUDA tensors)."""
    import torch

    if _DIST.backend == "nccl":
        return torch.device("cuda", torch.cuda.current_device())
    return torch.device("cpu")


def agree(value: Any) -> Any:
    """Rank 0's ``value`` on every rank (a path, a decision read from a file only rank 0 owns)."""
    if not _DIST.active:
        return value
    import torch.distributed as td

    box = [value]
    td.broadcast_object_list(box, src=0)
    return box[0]


def barrier() -> None:
    if _DIST.active:
        import torch.distributed as td

        td.barrier()


def gather_objects(obj: Any) -> list[Any]:
    """Every rank's ``obj`` in rank order, on every rank."""
    if not _DIST.active:
        return [obj]
    import torch.distributed as td

    out: list[Any] = [None] * _DIST.world
    td.all_gather_object(out, obj)
    return out


def _all_reduce_sum(x: torch.Tensor) -> torch.Tensor:
    import torch.distributed as td

    y = x.to(collective_device()).clone()
    td.all_reduce(y, op=td.ReduceOp.SUM)
    return y.to(x.device)


def mean_over_ranks(values: Mapping[str, float]) -> dict[str, float]:
    """Each value averaged over the ranks (a NaN on any rank makes it NaN everywhere, so every
    rank takes the same undo decision in :class:`march.learn.faults.UpdateGuard`)."""
    if not _DIST.active or not values:
        return dict(values)
    import torch

    keys = list(values)
    x = torch.tensor([float(values[k]) for k in keys], dtype=torch.float64)
    x = _all_reduce_sum(x) / _DIST.world
    return dict(zip(keys, x.tolist(), strict=True))


def sum_over_ranks(value: int) -> int:
    if not _DIST.active:
        return int(value)
    import torch

    return int(_all_reduce_sum(torch.tensor([int(value)], dtype=torch.int64)).item())


def pop_episode_stats(stats: Any) -> dict[str, float]:
    """``EpisodeStats.pop`` over all ranks: the mean over every rank's last ``window`` finished
    episodes (each rank weighted by its episode count)."""
    if not _DIST.active:
        return stats.pop()
    import torch

    count = int(stats.total.clamp(max=stats.window))
    local = torch.zeros(4, dtype=torch.float64)
    if count:
        local[:3] = stats.buffer[:count].double().sum(0).cpu()
        local[3] = count
    total = _all_reduce_sum(local)
    n = float(total[3])
    if n == 0:
        nan = float("nan")
        return {"mean_reward": nan, "mean_episode_length": nan, "mean_distance_m": nan}
    ret, length, dist = (total[:3] / n).tolist()
    return {"mean_reward": ret, "mean_episode_length": length, "mean_distance_m": dist}


def broadcast_module(module: torch.nn.Module) -> None:
    """Rank 0's parameters and buffers (normalisers included) on every rank."""
    if not _DIST.active:
        return
    state = agree({k: v.detach().cpu() for k, v in module.state_dict().items()})
    module.load_state_dict(state)


def average_gradients(parameters: Iterable[torch.nn.Parameter]) -> None:
    """All-reduce the gradients to their mean over the ranks (one flat buffer; rsl-rl's
    ``reduce_parameters`` for modules it does not own)."""
    if not _DIST.active:
        return
    params = [p for p in parameters if p.grad is not None]
    if not params:
        return
    import torch
    import torch.distributed as td

    flat = torch.cat([p.grad.reshape(-1) for p in params]).to(collective_device())
    td.all_reduce(flat, op=td.ReduceOp.SUM)
    flat /= _DIST.world
    offset = 0
    for p in params:
        n = p.numel()
        p.grad.copy_(flat[offset : offset + n].view_as(p.grad).to(p.grad.device))
        offset += n


def ppo_multi_gpu() -> dict[str, int] | None:
    """rsl-rl's ``multi_gpu`` runner entry for this process (None for one process)."""
    if not _DIST.active:
        return None
    return {"global_rank": _DIST.rank, "local_rank": _DIST.local_rank, "world_size": _DIST.world}


RANK_KEYS = ("curriculum", "episode", "streams", "rng", "generator")
"""Checkpoint entries that belong to one rank: its envs' levels, clocks and commands and every
random stream it draws from. The top-level entries are rank 0's (a one-process reader's view);
``rank_states[r]`` holds rank r's."""


def with_rank_states(payload: dict[str, Any]) -> dict:
    """``payload`` plus ``rank_states``: every rank's :data:`RANK_KEYS` entries, gathered on
    rank 0 (the rank that writes; the other ranks' payloads are not written), and
    ``world_size``. A collective: every rank calls it; one process returns ``payload``."""
    if not _DIST.active:
        return payload
    import torch.distributed as td

    mine = {k: payload[k] for k in RANK_KEYS if k in payload}
    out: list[Any] | None = [None] * _DIST.world if _DIST.main else None
    td.gather_object(mine, out, dst=0)
    return {**payload, "rank_states": out or [], "world_size": _DIST.world}


def written_by(payload: Mapping[str, Any]) -> int:
    """The number of ranks that wrote a checkpoint (1: a one-process run)."""
    return int(payload.get("world_size", 1))


def world_mismatch(payload: Mapping[str, Any], world: int | None = None) -> str | None:
    """Why this run cannot resume ``payload``, or None. A run resumes only on the number of
    ranks that wrote it (docs/scaling.md): rank r's envs, levels and streams are rank r's, and
    N ranks' state does not split or merge into M ranks' without changing what the run learns."""
    world = _DIST.world if world is None else world
    written = written_by(payload)
    if written == world:
        return None
    return (
        f"written by {written} rank(s), this run has {world}: resume it with {written} "
        f"process(es) (torchrun --nproc_per_node / Slurm tasks x nodes = {written})"
    )


def own_rank_state(payload: dict[str, Any], d: Dist | None = None) -> dict[str, Any]:
    """``payload`` with this rank's entries of ``rank_states`` in place of rank 0's (the ranks
    must match: :func:`world_mismatch`). A multi-rank checkpoint written before ``rank_states``
    (``rank_rng``: torch streams only) gives rank r its torch streams and rank 0's others."""
    d = d or _DIST
    states = payload.get("rank_states")
    if isinstance(states, list) and d.rank < len(states) and isinstance(states[d.rank], dict):
        return {**payload, **states[d.rank]}
    legacy = payload.get("rank_rng")
    if isinstance(legacy, list) and d.rank < len(legacy) and d.rank > 0:
        mine = dict(legacy[d.rank])
        out = {**payload, **mine}
        if isinstance(payload.get("streams"), dict):
            out["streams"] = {**payload["streams"], "torch": mine["rng"]}
            if "generator" in mine and "distill" in payload["streams"]:
                out["streams"]["distill"] = mine["generator"]
        return out
    return payload
