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
- every observation normaliser is updated with the moments of all ranks' batches
  (:func:`sync_normalizers`: one all-gather of (count, mean, var) per update, combined in rank
  order, so every rank computes the same bits; rsl-rl leaves them per rank);
- episode statistics, losses, fault counts and evaluation rollouts are reduced over the ranks;
- rank 0 alone writes files (:func:`writes_files` gates march's writers) and prints.

With one process (no ``WORLD_SIZE`` or ``WORLD_SIZE=1``) every function here is the identity.
"""

from __future__ import annotations

import dataclasses
import os
import types
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
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


def init(device: str) -> Dist:
    """Join the process group described by the environment (no-op for one process).

    nccl with ``cuda:<local_rank>`` when ``device`` is CUDA, gloo on CPU. Returns the rank's place.
    """
    global _DIST
    rank, world, local = env_world()
    if world <= 1:
        _DIST = Dist()
        return _DIST
    import torch.distributed as td

    backend = "nccl" if device.startswith("cuda") else "gloo"
    if not td.is_initialized():
        if backend == "nccl":
            torch.cuda.set_device(local)
        td.init_process_group(backend=backend, rank=rank, world_size=world)
    _DIST = Dist(rank=rank, world=world, local_rank=local, backend=backend)
    return _DIST


def shutdown() -> None:
    global _DIST
    if _DIST.active:
        import torch.distributed as td

        if td.is_initialized():
            td.destroy_process_group()
    _DIST = Dist()


def rank_device(device: str, d: Dist | None = None) -> str:
    """A CUDA run puts rank r on ``cuda:<local_rank>``; CPU stays CPU."""
    d = d or _DIST
    if d.active and device.startswith("cuda"):
        return f"cuda:{d.local_rank}"
    return device


def rank_config(cfg: Any, d: Dist | None = None) -> Any:
    """The rank's copy of the run config: its own seed and device, everything else shared."""
    d = d or _DIST
    if not d.active:
        return cfg
    compute = dataclasses.replace(cfg.compute, device=rank_device(cfg.compute.device, d))
    return dataclasses.replace(cfg, seed=rank_seed(cfg.seed, d.rank), compute=compute)


def _device() -> torch.device:
    """The device collectives run on (nccl needs CUDA tensors)."""
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

    y = x.to(_device()).clone()
    td.all_reduce(y, op=td.ReduceOp.SUM)
    return y.to(x.device)


def mean_over_ranks(values: Mapping[str, float]) -> dict[str, float]:
    """Each value averaged over the ranks (a NaN on any rank makes it NaN everywhere, so every
    rank takes the same undo decision in :class:`march.learn.faults.UpdateGuard`)."""
    if not _DIST.active or not values:
        return dict(values)
    keys = list(values)
    x = torch.tensor([float(values[k]) for k in keys], dtype=torch.float64)
    x = _all_reduce_sum(x) / _DIST.world
    return dict(zip(keys, x.tolist(), strict=True))


def sum_over_ranks(value: int) -> int:
    if not _DIST.active:
        return int(value)
    return int(_all_reduce_sum(torch.tensor([int(value)], dtype=torch.int64)).item())


def pop_episode_stats(stats: Any) -> dict[str, float]:
    """``EpisodeStats.pop`` over all ranks: the mean over every rank's last ``window`` finished
    episodes (each rank weighted by its episode count)."""
    if not _DIST.active:
        return stats.pop()
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
    import torch.distributed as td

    flat = torch.cat([p.grad.reshape(-1) for p in params]).to(_device())
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


def _combined_update(norm: Any, x: torch.Tensor) -> None:
    """rsl-rl's ``EmpiricalNormalization.update`` with the batch of all ranks: the ranks'
    (count, mean, var) are gathered and combined in rank order (same bits on every rank)."""
    if not norm.training:
        return
    if norm.until is not None and norm.count >= norm.until:
        return
    import torch.distributed as td

    x = x.reshape(-1, x.shape[-1]) if x.dim() > 2 else x
    dim = x.shape[-1]
    local = torch.empty(1 + 2 * dim, dtype=torch.float64, device=_device())
    local[0] = x.shape[0]
    local[1 : 1 + dim] = x.double().mean(0).to(local.device)
    local[1 + dim :] = x.double().var(0, unbiased=False).to(local.device)
    parts = [torch.empty_like(local) for _ in range(_DIST.world)]
    td.all_gather(parts, local)
    stacked = torch.stack(parts).to(x.device)  # (world, 1 + 2 dim), rank order
    counts = stacked[:, :1]
    n = counts.sum()
    mean_x = (counts * stacked[:, 1 : 1 + dim]).sum(0) / n
    var_x = (counts * (stacked[:, 1 + dim :] + (stacked[:, 1 : 1 + dim] - mean_x) ** 2)).sum(0) / n
    dtype = norm._mean.dtype
    mean_x, var_x = mean_x.to(dtype).unsqueeze(0), var_x.to(dtype).unsqueeze(0)
    count_x = int(n.item())
    norm.count += count_x
    rate = count_x / norm.count
    delta_mean = mean_x - norm._mean
    norm._mean += rate * delta_mean
    norm._var += rate * (var_x - norm._var + delta_mean * (mean_x - norm._mean))
    norm._std = torch.sqrt(norm._var)


def sync_normalizers(*modules: torch.nn.Module) -> int:
    """Make every rsl-rl ``EmpiricalNormalization`` inside ``modules`` learn from all ranks'
    batches (see :func:`_combined_update`); returns how many were found. No-op for one process."""
    if not _DIST.active:
        return 0
    from rsl_rl.modules.normalization import EmpiricalNormalization

    found = 0
    for module in modules:
        for sub in module.modules():
            if isinstance(sub, EmpiricalNormalization):
                sub.update = types.MethodType(_combined_update, sub)  # type: ignore[method-assign]
                found += 1
    return found


def with_rank_states(payload: dict[str, Any], generator: torch.Generator | None = None) -> dict:
    """``payload`` plus every rank's random states (``rank_rng``: torch's global state and the
    runner's generator per rank), so that a resume of an N-rank run restores each rank's own
    stream. A collective: every rank calls it; one process returns ``payload`` unchanged."""
    if not _DIST.active:
        return payload
    mine = {"rng": torch.get_rng_state()}
    if generator is not None:
        mine["generator"] = generator.get_state().cpu()
    states = gather_objects(mine)
    return {**payload, "rank_rng": states, "world_size": _DIST.world}


def restore_rank_states(
    payload: dict[str, Any], generator: torch.Generator | None = None
) -> str | None:
    """After a resume has loaded rank 0's states (``rng``, ``generator``): rank r takes its own
    from ``rank_rng``. A rank the checkpoint has no states for (a resume with more ranks than it
    was written by) seeds a fresh stream from its rank seed and the iteration; returns a note."""
    d = _DIST
    states = payload.get("rank_rng")
    if states is not None and d.rank < len(states):
        torch.set_rng_state(states[d.rank]["rng"])
        if generator is not None and "generator" in states[d.rank]:
            generator.set_state(states[d.rank]["generator"])
        return None
    if d.rank == 0:
        return None
    seed = rank_seed(int(payload["config"]["seed"]) + int(payload["iteration"]), d.rank)
    torch.manual_seed(seed)
    if generator is not None:
        generator.manual_seed(seed)
    written = int(payload.get("world_size", 1))
    return f"rank {d.rank}: checkpoint written by {written} rank(s); fresh random stream {seed}"


def eval_share(num_rollouts: int, d: Dist | None = None) -> tuple[int, int]:
    """(first rollout index, count) of this rank's slice of an evaluation's rollouts: rank r runs
    indices [r n / N, (r + 1) n / N), so the ranks together run the one-process index set."""
    d = d or _DIST
    lo = d.rank * num_rollouts // d.world
    hi = (d.rank + 1) * num_rollouts // d.world
    return lo, hi - lo


def gather_rollouts(per: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Every rank's per-rollout metrics concatenated in rank order (= rollout index order)."""
    if not _DIST.active:
        return per
    parts = gather_objects({k: v.cpu() for k, v in per.items()})
    keys = next((list(p) for p in parts if p), [])  # a rank with no share has no keys
    return {k: torch.cat([p[k] for p in parts if p]) for k in keys}
