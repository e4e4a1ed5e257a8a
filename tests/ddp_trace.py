"""Test helper: ``march.train`` under torchrun with every update's result dumped per rank.

    MARCH_TRACE_DIR=<dir> torchrun --standalone --nproc_per_node=2 tests/ddp_trace.py <overrides>

After each PPO update and each distillation update, every rank saves (into MARCH_TRACE_DIR)
``<stage>_<n>_rank<r>.pt``: the networks' state dicts (normaliser buffers included), the
learning rate, the rollout that update learned from and whether that rank writes run files; at
each teacher checkpoint and after a teacher resume, the rank's own state (levels, clocks,
commands, streams: ``teacher_save_<it>_rank<r>.pt``, ``teacher_restored_<it>_rank<r>.pt``).
``MARCH_TRACE_TAG`` prefixes every file name (a resumed launch's files apart).
Nothing else changes: the real entry point, envs, runners and files.

Imported as a plug-in (``extra_modules=[tests.ddp_trace]``, with the repository on PYTHONPATH)
it traces the same way inside a job that a launcher starts (``make test-slurm``'s Slurm jobs):
the rank is the process group's, read when a file is written.
"""

from __future__ import annotations

import os
import runpy
from pathlib import Path

import torch
from rsl_rl.algorithms import PPO

from march.learn import distributed
from march.learn.distill import DistillRunner
from march.learn.teacher import TeacherRunner
from march.learn.train_state import collect_state

OUT = Path(os.environ["MARCH_TRACE_DIR"])
TAG = os.environ.get("MARCH_TRACE_TAG", "")  # a prefix: a resumed launch's files apart
_count = {"teacher": 0, "student": 0}


def _rank() -> int:
    """This process's rank (known once the process group is up, whoever launched it)."""
    return distributed.current().rank


def _dump(stage: str, state: dict[str, torch.Tensor], rollout: dict[str, torch.Tensor]) -> None:
    _count[stage] += 1
    payload = {
        "kind": "trace",  # read back through march's weights-only load_checkpoint
        "state": state,
        "rollout": rollout,
        "writes_files": distributed.writes_files(),
    }
    torch.save(payload, OUT / f"{TAG}{stage}_{_count[stage]}_rank{_rank()}.pt")


_ppo_update = PPO.update


def _traced_ppo_update(self: PPO) -> dict[str, float]:
    rollout = {"actions": self.storage.actions.clone(), "rewards": self.storage.rewards.clone()}
    losses = _ppo_update(self)
    state = {f"actor.{k}": v.clone() for k, v in self.actor.state_dict().items()}
    state |= {f"critic.{k}": v.clone() for k, v in self.critic.state_dict().items()}
    state["learning_rate"] = torch.tensor(self.learning_rate, dtype=torch.float64)
    _dump("teacher", state, rollout)
    return losses


_distill_update = DistillRunner._update


def _traced_distill_update(self: DistillRunner, steps: list) -> dict[str, float]:
    rollout = {"proprio": torch.stack([s[0] for s in steps]), "teacher_mean": steps[0][3]}
    info = _distill_update(self, steps)
    _dump("student", {k: v.clone() for k, v in self.student.state_dict().items()}, rollout)
    return info


_teacher_save = TeacherRunner.save
_teacher_resume = TeacherRunner.try_resume


def _rank_state(self: TeacherRunner) -> dict:
    """This rank's own part of a checkpoint as its env and process hold it now."""
    return collect_state(self.env.unwrapped, self.device)


def _traced_save(self: TeacherRunner):
    torch.save(_rank_state(self), OUT / f"{TAG}teacher_save_{self.iteration}_rank{_rank()}.pt")
    return _teacher_save(self)


def _traced_resume(self: TeacherRunner) -> bool:
    resumed = _teacher_resume(self)
    if resumed:
        name = f"{TAG}teacher_restored_{self.iteration}_rank{_rank()}.pt"
        torch.save(_rank_state(self), OUT / name)
    return resumed


OUT.mkdir(parents=True, exist_ok=True)
TeacherRunner.save = _traced_save  # type: ignore[method-assign]
TeacherRunner.try_resume = _traced_resume  # type: ignore[method-assign]
PPO.update = _traced_ppo_update  # type: ignore[method-assign]
DistillRunner._update = _traced_distill_update  # type: ignore[method-assign]

if __name__ == "__main__":
    # As `python -m march.train` (Hydra finds conf/ from the module run as __main__).
    runpy.run_module("march.train", run_name="__main__", alter_sys=True)
