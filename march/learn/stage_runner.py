"""The training loop both stages share: the teacher's PPO and the student's distillation.

rsl-rl's split: a runner owns the loop, an algorithm owns the update. :class:`StageRunner` is the
runner part, written once:

- **resume** from the stage's atomic checkpoint (``<run>/<stage>/latest.pt``): torn writes
  removed, the layout checked, this rank's levels, episode clocks and random streams put back,
  the rows past the checkpoint dropped from ``metrics.csv`` and ``eval.csv``;
- **checkpoints** every ``save_interval`` iterations and at the stage's end (every rank's random
  states gathered, rank 0 writes);
- **evaluation rows** every ``eval_interval`` iterations, before that iteration's checkpoint (a
  run killed in between redoes both), and for the teacher once more at the stage's end;
- **the metrics row**: episode statistics, curriculum level, the per-term ``reward/<term>`` and
  ``termination/<term>`` columns (one device read per iteration, mean over ranks), the
  algorithm's own columns (``loss/<part>`` of distillation), fault counts; the same values go to
  the logger (:class:`march.learn.metrics.MetricsLog`) and a progress line with the ETA;
- **faults and preemption**: non-finite envs reset (:class:`EnvFaults`, used by the rollouts),
  non-finite updates undone (:class:`UpdateGuard`), SIGTERM / USR2 stop after a checkpointed
  iteration (:mod:`march.learn.preemption`).

A stage supplies what differs (:class:`march.learn.teacher.TeacherRunner`,
:class:`march.learn.distill.DistillRunner`): how it collects a rollout and updates from it, what
its checkpoint holds beyond the common entries, the policy it evaluates, and its own row columns.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import torch

from march.config import MarchConfig
from march.env.course import CourseRuler
from march.env.term_meter import pop_terms
from march.learn import distributed, preemption
from march.learn.faults import EnvFaults, UpdateGuard
from march.learn.metrics import MetricsLog, Progress, has_row, truncate_rows
from march.learn.train_state import collect_state, mean_terrain_level, rank_payload, restore_state
from march.store.checkpoint import (
    check_layout,
    ensure_model_file,
    latest_checkpoint,
    load_checkpoint,
    save_checkpoint,
)

if TYPE_CHECKING:
    from mjlab.envs import ManagerBasedRlEnv

EvaluateFn = Callable[[Any, int, int], dict[str, Any]]
"""(policy, iteration, env steps) -> the eval.csv row it appended."""


class EpisodeStats:
    """Return, length [control steps] and course progress of finished episodes.

    The progress the runners pass each step is :meth:`CourseRuler.foothold_progress` (the point
    both feet have reached, read before the step): an episode's distance is where its feet
    were at its last step, so a fall is not paid as progress (docs/evaluation.md).

    Reported as means over the last ``window`` finished episodes (rsl-rl's convention), so an
    iteration in which no episode ended still has a value once any episode has ended. The
    per-step bookkeeping never synchronises with the device (no ``nonzero()`` / ``len()`` of
    data-dependent size): finished episodes go into a ring buffer of ``window`` rows in env order
    (slot = episodes so far + rank among this step's, mod window); when more than ``window`` end
    in one step only the last ``window`` are kept, the others are written to a spare row.
    """

    def __init__(self, num_envs: int, device: str, window: int = 100) -> None:
        self.ret = torch.zeros(num_envs, device=device)
        self.len = torch.zeros(num_envs, device=device)
        self.window = window
        self.buffer = torch.zeros(window + 1, 3, device=device)  # (return, length, distance)
        self.total = torch.zeros((), dtype=torch.long, device=device)  # episodes ended so far

    def step(self, reward: torch.Tensor, done: torch.Tensor, progress: torch.Tensor) -> None:
        self.ret += reward
        self.len += 1
        d = done.long()
        rank = torch.cumsum(d, 0) - d  # order of each finished episode within this step
        n = d.sum()
        keep = done & (rank >= n - self.window)
        slot = torch.where(keep, (self.total + rank) % self.window, self.window)
        ended = torch.stack([self.ret, self.len, progress.to(self.ret.dtype)], dim=-1)
        self.buffer.index_copy_(0, slot, ended)
        self.total += n
        self.ret.masked_fill_(done, 0.0)
        self.len.masked_fill_(done, 0.0)

    def pop(self) -> dict[str, float]:
        count = int(self.total.clamp(max=self.window))  # once per iteration: a sync is fine
        if count == 0:
            nan = float("nan")
            return {"mean_reward": nan, "mean_episode_length": nan, "mean_distance_m": nan}
        ret, length, dist = self.buffer[:count].mean(0).tolist()
        return {"mean_reward": ret, "mean_episode_length": length, "mean_distance_m": dist}


class StageRunner:
    """One training stage's loop; checkpoints in ``<run>/<stage>/``; resumes by itself.

    A subclass sets :attr:`stage` (``teacher`` / ``student``: the checkpoint kind, its folder and
    the ``stage`` of its metrics and eval rows) and :attr:`group` (its config block, whose
    ``num_steps_per_env``, ``save_interval``, ``eval_interval`` and ``max_nonfinite_updates`` the
    loop reads), builds its algorithm after ``super().__init__`` and sets :attr:`layout`, and
    implements the hooks under "what a stage supplies".
    """

    stage: ClassVar[str]
    group: ClassVar[str]
    progress_columns: ClassVar[dict[str, str]] = {}
    """The console line's fields: label -> metrics column."""
    evaluates_last: ClassVar[bool] = False
    """Evaluate the stage's last iteration here (the teacher; the student's is the pipeline's
    eval stage, summary.json)."""

    def __init__(
        self,
        env: ManagerBasedRlEnv,
        cfg: MarchConfig,
        run_dir: Path,
        log: MetricsLog,
        evaluate_fn: EvaluateFn | None = None,
    ) -> None:
        self.cfg, self.run_dir, self.log = cfg, run_dir, log
        self.unwrapped = env  # the mjlab env: its state goes into the checkpoint
        self.evaluate_fn = evaluate_fn
        self.device = cfg.compute.device
        self.ruler = CourseRuler(env)
        self.ckpt_dir = run_dir / self.stage
        self.iteration = 0  # iterations completed
        self.env_steps = 0
        self.wall_s = 0.0
        self.world = distributed.current().world
        self.layout: dict[str, Any] = {}
        self.generators: dict[str, torch.Generator] = {}  # checkpointed besides the global ones
        self.faults = EnvFaults(env)
        self.guard = UpdateGuard(
            self.group,
            self.stage_cfg.max_nonfinite_updates,
            self.snapshot,
            self.restore,
            self.parameters,
        )

    @property
    def stage_cfg(self) -> Any:
        return getattr(self.cfg, self.group)

    # ------------------------------------------------------------------ what a stage supplies

    def algorithm_state(self) -> dict[str, Any]:
        """The checkpoint entries of the stage's algorithm (networks, optimizer, ...)."""
        raise NotImplementedError

    def load_algorithm_state(self, payload: dict[str, Any]) -> None:
        """Put back :meth:`algorithm_state`'s entries of a resumed checkpoint."""
        raise NotImplementedError

    def snapshot(self) -> Any:
        """What :meth:`restore` puts back when an update is undone (:class:`UpdateGuard`)."""
        raise NotImplementedError

    def restore(self, saved: Any) -> None:
        raise NotImplementedError

    def parameters(self) -> Any:
        """The trained parameters (checked for NaN / inf after each update)."""
        raise NotImplementedError

    def resumed(self, payload: dict[str, Any]) -> None:
        """After a resume put the env's state back (its reset observations are current)."""

    def start(self) -> None:
        """Before the first iteration of :meth:`learn`."""

    def collect(self, stats: EpisodeStats) -> Any:
        """One iteration's rollout (``stats`` sees every step); returns what :meth:`update` takes."""
        raise NotImplementedError

    def update(self, batch: Any) -> dict[str, float]:
        """The algorithm's update from a rollout; its losses, mean over ranks."""
        raise NotImplementedError

    def row_columns(self, batch: Any, losses: dict[str, float]) -> dict[str, Any]:
        """The stage's own metrics columns for this iteration."""
        raise NotImplementedError

    def eval_policy(self) -> Any:
        """The policy :attr:`evaluate_fn` is called with."""
        raise NotImplementedError

    @contextlib.contextmanager
    def evaluating(self) -> Iterator[None]:
        """Around an evaluation (the teacher: its networks in eval mode)."""
        yield

    # ------------------------------------------------------------------ the loop's own parts

    def payload(self) -> dict[str, Any]:
        return {
            "kind": self.stage,
            "iteration": self.iteration,
            "env_steps": self.env_steps,
            "wall_s": self.wall_s,
            "config": asdict(self.cfg),
            "layout": self.layout,
            **self.algorithm_state(),
            "rng": torch.get_rng_state(),
            "common_step_counter": self.unwrapped.common_step_counter,
            # curriculum (terrain levels), episode clocks, every random stream
            **collect_state(self.unwrapped, self.device, self.generators),
        }

    def save(self) -> Path:
        # Every rank's random states go in (a collective); rank 0 alone writes the files.
        return save_checkpoint(
            distributed.with_rank_states(self.payload()), self.ckpt_dir, self.iteration
        )

    def try_resume(self) -> bool:
        """Continue from ``<run>/<stage>/latest.pt`` if it exists (killed run, Slurm requeue)."""
        for tmp in self.ckpt_dir.glob(".*.tmp"):  # a write that a kill cut short
            tmp.unlink(missing_ok=True)
        path = latest_checkpoint(self.ckpt_dir)
        if path is None:
            # Killed before its first checkpoint: the stage starts over, so the rows it logged
            # (metrics.csv, eval.csv) go too, or they would appear twice.
            self.log.resume_from(self.stage, 0)
            truncate_rows(self.run_dir / "eval.csv", self.stage, 0)
            return False
        where = f"resume={self.run_dir}: {path}"
        payload = load_checkpoint(path, self.stage, self.device, source=where)
        # N ranks: this rank's own levels, clocks and streams (another rank count: refused).
        payload = rank_payload(payload, where)
        if path.name == "latest.pt":  # a kill may have cut the write of its model_<it>.pt
            ensure_model_file(payload, self.ckpt_dir)
        check_layout(payload["layout"], self.layout, self.stage, path)
        self.load_algorithm_state(payload)
        self.iteration = int(payload["iteration"])
        self.env_steps = int(payload["env_steps"])
        self.wall_s = float(payload.get("wall_s", 0.0))
        # Levels, episode clocks and random streams (a runner's own generators too; across
        # devices they are reseeded) last: the env's reset here draws from them.
        notes = restore_state(
            self.unwrapped, payload, self.device, self.cfg.seed, where, self.generators
        )
        self.resumed(payload)
        self.unwrapped.common_step_counter = payload.get("common_step_counter", 0)
        self.log.resume_from(self.stage, self.iteration)
        truncate_rows(self.run_dir / "eval.csv", self.stage, self.iteration)
        print(f"[{self.stage}] resuming from {path} at iteration {self.iteration}")
        for line in notes:
            print(f"[{self.stage}] {line}")
        return True

    def evaluate(self) -> None:
        """Evaluate the current policy (a ``stage=<stage>`` row of eval.csv)."""
        if self.evaluate_fn is None:
            return
        with self.evaluating():
            self.evaluate_fn(self.eval_policy(), self.iteration, self.env_steps)

    def learn(self, total_iterations: int) -> Path:
        s = self.stage_cfg
        self.start()
        stats = EpisodeStats(self.unwrapped.num_envs, self.device)
        progress = Progress(self.stage, self.iteration, total_iterations)
        last = distributed.agree(latest_checkpoint(self.ckpt_dir))  # rank 0 owns the files
        for it in range(self.iteration, total_iterations):
            t0 = time.time()
            batch = self.collect(stats)
            # The rollout's share of the iteration, for the [eta] line's evaluation estimate
            # (an evaluation step costs about a rollout step, not a rollout step plus its share
            # of the update). On a GPU the host's clock would time kernel launches, not their
            # work, and a sync per iteration is not worth the split: CPU only.
            rollout_s = time.time() - t0 if self.device == "cpu" else None
            self.guard.before()
            losses = self.update(batch)
            # A non-finite update is undone; too many in a row stop before this checkpoint.
            self.guard.after(losses, it + 1, last)
            self.iteration = it + 1
            self.env_steps += s.num_steps_per_env * self.unwrapped.num_envs * self.world
            self.wall_s += time.time() - t0
            row = {
                "stage": self.stage,
                "iteration": self.iteration,
                "env_steps": self.env_steps,
                "wall_s": self.wall_s,
                **({"rollout_s": rollout_s} if rollout_s is not None else {}),
                **distributed.pop_episode_stats(stats),
                **distributed.mean_over_ranks(
                    {"mean_terrain_level": mean_terrain_level(self.unwrapped)}
                ),
                # reward/<term>, termination/<term>, terrain_level_std: one device read
                **distributed.mean_over_ranks(pop_terms(self.unwrapped)),
                **self.row_columns(batch, losses),
                "nonfinite_resets": distributed.sum_over_ranks(self.faults.pop()),
                "nonfinite_updates": self.guard.pop(),
            }
            self.log.log(row)
            fields = {label: row[col] for label, col in self.progress_columns.items() if col in row}
            print(progress.line(it, fields), flush=True)
            final = self.iteration == total_iterations
            # Evaluate before the checkpoint: a run killed in between resumes from the previous
            # checkpoint (its later eval.csv rows truncated) and redoes both; the other order
            # lost this evaluation for good.
            if s.eval_interval and self.iteration % s.eval_interval == 0 and not final:
                self.evaluate()
            saved = self.iteration % s.save_interval == 0 or final
            if saved:
                last = self.save()
            # SIGTERM / USR2: stop here with this iteration checkpointed (march.learn.preemption).
            preemption.stop_if_requested(
                self.stage, self.iteration, None if saved else self.save, last
            )
        if last is None:
            last = self.save()
        # The stage's last iteration is evaluated once here where the stage says so (also when
        # a finished stage is resumed, or a run died during this evaluation).
        if (
            self.evaluates_last
            and self.evaluate_fn is not None
            and not distributed.agree(
                has_row(self.run_dir / "eval.csv", self.stage, self.iteration)
            )
        ):
            self.evaluate()
        return self.ckpt_dir / "latest.pt"
