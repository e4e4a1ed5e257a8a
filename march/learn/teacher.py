"""The PPO teacher runner: rsl-rl's PPO (algorithm, models, storage) on the mjlab env.

The runner owns the loop (rollout, logging, checkpoints, resume); rsl-rl's PPO owns the update.
mjlab's own ``train`` CLI is not used: it assumes a GPU.
"""

from __future__ import annotations

import contextlib
import copy
import os
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from rsl_rl.algorithms import PPO
from rsl_rl.models import MLPModel
from tensordict import TensorDict

from march.config import MarchConfig, TeacherCfg
from march.env.build import rsl_rl_env
from march.env.course import CourseRuler
from march.env.term_meter import pop_terms
from march.learn import distributed, preemption, rank_normalizers
from march.learn.checkpoint import (
    check_layout,
    ensure_model_file,
    latest_checkpoint,
    load_checkpoint,
    save_checkpoint,
)
from march.learn.faults import EnvFaults, UpdateGuard
from march.learn.metrics import MetricsLog, Progress, has_row, truncate_rows
from march.learn.train_state import (
    collect_state,
    mean_terrain_level,
    rank_payload,
    restore_state,
)

if TYPE_CHECKING:
    from mjlab.envs import ManagerBasedRlEnv

TeacherEval = Callable[[MLPModel, int, int], dict[str, Any]]
"""(deterministic actor, teacher iteration, teacher env steps) -> the eval.csv row it appended."""


def ppo_train_cfg(t: TeacherCfg, multi_gpu: dict[str, int] | None = None) -> dict[str, Any]:
    """The rsl-rl runner dict for the paper's PPO table (SPEC §2); ``multi_gpu``: rsl-rl's
    data-parallel entry (march.learn.distributed.ppo_multi_gpu), None for one process."""
    return {
        "num_steps_per_env": t.num_steps_per_env,
        "obs_groups": {"actor": ["actor"], "critic": ["critic"]},
        "multi_gpu": multi_gpu,
        "actor": {
            "class_name": "MLPModel",
            "hidden_dims": list(t.hidden_dims),
            "activation": t.activation,
            "obs_normalization": True,
            "distribution_cfg": {
                "class_name": "GaussianDistribution",
                "init_std": t.init_std,
                "std_type": "scalar",
            },
        },
        "critic": {
            "class_name": "MLPModel",
            "hidden_dims": list(t.hidden_dims),
            "activation": t.activation,
            "obs_normalization": True,
        },
        "algorithm": {
            "class_name": "PPO",
            "num_learning_epochs": t.num_learning_epochs,
            "num_mini_batches": t.num_mini_batches,
            "clip_param": t.clip_param,
            "gamma": t.gamma,
            "lam": t.lam,
            "value_loss_coef": t.value_loss_coef,
            "entropy_coef": t.entropy_coef,
            "learning_rate": t.learning_rate,
            "max_grad_norm": t.max_grad_norm,
            "use_clipped_value_loss": True,
            "schedule": t.schedule,
            "desired_kl": t.desired_kl,
            "rnd_cfg": None,
            "symmetry_cfg": None,
        },
    }


def teacher_layout(obs: TensorDict | dict, num_actions: int) -> dict[str, Any]:
    """What a teacher checkpoint must agree on with the env it is used in."""
    return {"actor_obs_dim": int(obs["actor"].shape[-1]), "num_actions": int(num_actions)}


def build_teacher_actor(
    payload: dict[str, Any], obs: TensorDict, num_actions: int, device: str, path: str
) -> MLPModel:
    """The frozen teacher policy from a teacher checkpoint (for distillation and evaluation)."""
    check_layout(payload["layout"], teacher_layout(obs, num_actions), "teacher", path)
    actor_cfg = copy.deepcopy(payload["ppo"]["actor"])
    actor_cfg.pop("class_name")
    actor = MLPModel(obs, {"actor": ["actor"]}, "actor", num_actions, **actor_cfg).to(device)
    actor.load_state_dict(payload["actor_state_dict"])
    actor.eval()
    for p in actor.parameters():
        p.requires_grad_(False)
    return actor


def teacher_obs(obs: dict[str, Any], num_envs: int) -> TensorDict:
    """The teacher's view of an env observation dict."""
    return TensorDict({"actor": obs["actor"]}, batch_size=[num_envs])


def teacher_policy(env: ManagerBasedRlEnv, actor: MLPModel):
    """obs -> deterministic teacher action (the mean)."""

    def act(obs: dict[str, Any]) -> torch.Tensor:
        return actor(teacher_obs(obs, env.num_envs))

    return act


class EpisodeStats:
    """Return, length [control steps] and course progress of finished episodes.

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


def stagger_episodes(env: ManagerBasedRlEnv, seed: int, iteration: int) -> torch.Tensor:
    """Start every env at a seeded random episode step in [0, max episode length), as rsl-rl's
    ``init_at_random_ep_len``: time-outs, and with them resets and touchdowns, spread over the
    episode instead of running in lockstep. The draw comes from its own generator seeded with
    (seed, iteration), so the global random stream is untouched (a resume restores the saved
    clocks instead; only a checkpoint without them is staggered again). Returns the new
    episode steps (E,)."""
    buf = env.episode_length_buf
    g = torch.Generator().manual_seed(
        int(np.random.SeedSequence([seed, iteration]).generate_state(1, np.uint64)[0])
    )
    steps = torch.randint(0, int(env.max_episode_length), tuple(buf.shape), generator=g)
    buf.copy_(steps.to(buf.device, buf.dtype))
    return steps


class ReplanReadout:
    """Touchdowns and deferred replans of the reference command per iteration (reward=clf; NaN
    without a reference command). Reads the term's counters once per iteration (a sync there
    is fine); nothing on the per-step path."""

    def __init__(self, env: ManagerBasedRlEnv) -> None:
        manager = env.command_manager
        self.term = manager.get_term("reference") if "reference" in manager.active_terms else None
        self.last = self._totals()  # on the device: the only host read is in pop()

    def _totals(self) -> torch.Tensor | None:
        if self.term is None:
            return None
        return torch.stack([self.term.touchdown_count.sum(), self.term.queue.deferred_count.sum()])

    def pop(self) -> dict[str, float]:
        if self.term is None:
            return {"touchdowns": float("nan"), "deferred_replans": float("nan")}
        now = self._totals()
        touchdowns, deferred = (now - self.last).tolist()  # once per iteration
        self.last = now
        # N processes: every rank's envs count, as for the other episode statistics
        return {
            "touchdowns": distributed.sum_over_ranks(int(touchdowns)),
            "deferred_replans": distributed.sum_over_ranks(int(deferred)),
        }


class TeacherRunner:
    """PPO on the teacher env; checkpoints in ``<run>/teacher/``; resumes by itself.

    With ``evaluate_fn`` the current teacher is evaluated every ``teacher.eval_interval``
    iterations and at the end of the stage (``stage=teacher`` rows of eval.csv); an evaluation
    runs before that iteration's checkpoint, so a resumed run drops and redoes exactly the rows
    past its checkpoint.
    """

    def __init__(
        self,
        env: ManagerBasedRlEnv,
        cfg: MarchConfig,
        run_dir: Path,
        log: MetricsLog,
        evaluate_fn: TeacherEval | None = None,
    ):
        self.cfg, self.run_dir, self.log = cfg, run_dir, log
        self.evaluate_fn = evaluate_fn
        self.device = cfg.compute.device
        self.env = rsl_rl_env(env)
        self.ruler = CourseRuler(env)
        self.ckpt_dir = run_dir / "teacher"
        self.clocks_restored = False  # a resume put the episode clocks back (no re-stagger)
        self.train_cfg = ppo_train_cfg(cfg.teacher, distributed.ppo_multi_gpu())
        obs = self.env.get_observations()
        self.layout = teacher_layout(obs, self.env.num_actions)
        # rsl-rl prints both networks; they belong in the run's log, not on the console.
        log_to = run_dir / "env.log" if distributed.writes_files() else Path(os.devnull)
        with log_to.open("a") as f, contextlib.redirect_stdout(f):
            self.alg = PPO.construct_algorithm(
                obs, self.env, copy.deepcopy(self.train_cfg), self.device
            )
        if self.alg.is_multi_gpu:  # N ranks: rank 0's networks everywhere, shared normalisers
            self.alg.broadcast_parameters()
            rank_normalizers.sync_normalizers(self.alg.actor, self.alg.critic)
        self.iteration = 0  # iterations completed
        self.env_steps = 0
        self.wall_s = 0.0
        self.world = distributed.current().world
        self.faults = EnvFaults(env)
        self.guard = UpdateGuard(
            "teacher",
            cfg.teacher.max_nonfinite_updates,
            self.alg.save,
            self._restore,
            lambda: [*self.alg.actor.parameters(), *self.alg.critic.parameters()],
        )

    def _restore(self, saved: dict[str, Any]) -> None:
        """Put back the networks and optimizer of :meth:`UpdateGuard.before` (an undone update)."""
        # The normalizers' buffers were last written under inference mode (the rollout), and
        # only there can they be written again; the optimizer state is loaded outside it.
        with torch.inference_mode():
            self.alg.load(saved, {"actor": True, "critic": True}, strict=True)
        self.alg.load(saved, {"optimizer": True}, strict=True)

    def payload(self) -> dict[str, Any]:
        return {
            "kind": "teacher",
            "iteration": self.iteration,
            "env_steps": self.env_steps,
            "wall_s": self.wall_s,
            "config": asdict(self.cfg),
            "layout": self.layout,
            "ppo": self.train_cfg,
            **self.alg.save(),
            "learning_rate": self.alg.learning_rate,
            "rng": torch.get_rng_state(),
            "common_step_counter": self.env.unwrapped.common_step_counter,
            # curriculum (terrain levels), episode clocks, every random stream
            **collect_state(self.env.unwrapped, self.device),
        }

    def try_resume(self) -> bool:
        """Continue from ``<run>/teacher/latest.pt`` if it exists (killed run, Slurm requeue)."""
        for tmp in self.ckpt_dir.glob(".*.tmp"):  # a write that a kill cut short
            tmp.unlink(missing_ok=True)
        path = latest_checkpoint(self.ckpt_dir)
        if path is None:
            # Killed before its first checkpoint: the stage starts over, so the rows it logged
            # (metrics.csv, eval.csv) go too, or they would appear twice.
            self.log.resume_from("teacher", 0)
            truncate_rows(self.run_dir / "eval.csv", "teacher", 0)
            return False
        where = f"resume={self.run_dir}: {path}"
        payload = load_checkpoint(path, "teacher", self.device, source=where)
        # N ranks: this rank's own levels, clocks and streams (another rank count: refused).
        payload = rank_payload(payload, where)
        if path.name == "latest.pt":  # a kill may have cut the write of its model_<it>.pt
            ensure_model_file(payload, self.ckpt_dir)
        check_layout(payload["layout"], self.layout, "teacher", path)
        self.alg.load(payload, None, strict=True)
        self.alg.learning_rate = payload.get("learning_rate", self.alg.learning_rate)
        for group in self.alg.optimizer.param_groups:
            group["lr"] = self.alg.learning_rate
        self.iteration = int(payload["iteration"])
        self.env_steps = int(payload["env_steps"])
        self.wall_s = float(payload.get("wall_s", 0.0))
        # Levels, episode clocks and random streams last: the env's reset here draws from them.
        notes = restore_state(self.env.unwrapped, payload, self.device, self.cfg.seed, where)
        self.clocks_restored = "episode" in payload
        self.env.unwrapped.common_step_counter = payload.get("common_step_counter", 0)
        self.log.resume_from("teacher", self.iteration)
        truncate_rows(self.run_dir / "eval.csv", "teacher", self.iteration)
        print(f"[teacher] resuming from {path} at iteration {self.iteration}")
        for line in notes:
            print(f"[teacher] {line}")
        return True

    def save(self) -> Path:
        # Every rank's random states go in (a collective); rank 0 alone writes the files.
        return save_checkpoint(
            distributed.with_rank_states(self.payload()), self.ckpt_dir, self.iteration
        )

    def evaluate(self) -> None:
        """Evaluate the current deterministic actor (a ``stage=teacher`` row of eval.csv)."""
        if self.evaluate_fn is None:
            return
        self.alg.eval_mode()
        try:
            self.evaluate_fn(self.alg.get_policy(), self.iteration, self.env_steps)
        finally:
            self.alg.train_mode()

    def learn(self, total_iterations: int) -> Path:
        t = self.cfg.teacher
        # Episodes start at seeded random steps: at the start, and after a resume from a
        # checkpoint without episode clocks (an older one); clocks a resume restored go on as
        # they were, so a resumed run continues the uninterrupted one's schedule.
        if not self.clocks_restored:
            stagger_episodes(self.env.unwrapped, self.cfg.seed, self.iteration)
        obs = self.env.get_observations().to(self.device)
        self.alg.train_mode()
        stats = EpisodeStats(self.env.num_envs, self.device)
        replans = ReplanReadout(self.env.unwrapped)
        progress = Progress("teacher", self.iteration, total_iterations)
        last = distributed.agree(latest_checkpoint(self.ckpt_dir))  # rank 0 owns the files
        for it in range(self.iteration, total_iterations):
            t0 = time.time()
            with torch.inference_mode():
                for _ in range(t.num_steps_per_env):
                    before = self.ruler.progress()
                    actions = self.alg.act(obs)
                    bad_actions = self.faults.actions(actions)  # the stored copy too
                    obs, rewards, dones, extras = self.env.step(actions.to(self.env.device))
                    bad = self.faults.after_step(obs, rewards, bad_actions)
                    # A faulty env's episode ends here: no bootstrap from its faulty state, and
                    # the stored log-probability is that of the action actually taken (the
                    # same as drawn where the action was finite). No host sync: masks only.
                    dones = torch.where(bad, torch.ones_like(dones), dones)
                    if "time_outs" in extras:
                        extras["time_outs"] = extras["time_outs"] & ~bad
                    tr = self.alg.transition
                    tr.actions_log_prob = torch.where(
                        bad_actions,
                        self.alg.actor.get_output_log_prob(tr.actions),
                        tr.actions_log_prob,
                    )
                    obs, rewards, dones = (
                        obs.to(self.device),
                        rewards.to(self.device),
                        dones.to(self.device),
                    )
                    self.alg.process_env_step(obs, rewards, dones, extras)
                    # The env auto-resets: a finished episode's distance is its last pre-reset one.
                    stats.step(rewards, dones.bool(), before)
                rank_normalizers.flush_normalizers()  # N ranks: this iteration's batches, once
                self.alg.compute_returns(obs)
            self.guard.before()
            losses = distributed.mean_over_ranks(self.alg.update())
            # A non-finite update is undone; too many in a row stop before this checkpoint.
            self.guard.after(losses, it + 1, last)
            self.iteration = it + 1
            self.env_steps += t.num_steps_per_env * self.env.num_envs * self.world
            self.wall_s += time.time() - t0
            row = {
                "stage": "teacher",
                "iteration": self.iteration,
                "env_steps": self.env_steps,
                "wall_s": self.wall_s,
                **distributed.pop_episode_stats(stats),
                **distributed.mean_over_ranks(
                    {"mean_terrain_level": mean_terrain_level(self.env.unwrapped)}
                ),
                # reward/<term>, termination/<term>, terrain_level_std: one device read
                **distributed.mean_over_ranks(pop_terms(self.env)),
                "value_loss": losses.get("value", losses.get("value_function", float("nan"))),
                "surrogate_loss": losses.get("surrogate", float("nan")),
                "entropy": losses.get("entropy", float("nan")),
                "learning_rate": self.alg.learning_rate,
                "action_std": self.alg.get_policy().output_std.mean().item(),
                "nonfinite_resets": distributed.sum_over_ranks(self.faults.pop()),
                "nonfinite_updates": self.guard.pop(),
                **replans.pop(),
            }
            self.log.log(row)
            print(
                progress.line(
                    it,
                    {
                        "reward": row["mean_reward"],
                        "ep_len": row["mean_episode_length"],
                        "dist_m": row["mean_distance_m"],
                        "value_loss": row["value_loss"],
                    },
                ),
                flush=True,
            )
            final = self.iteration == total_iterations
            if t.eval_interval and self.iteration % t.eval_interval == 0 and not final:
                self.evaluate()
            saved = self.iteration % t.save_interval == 0 or final
            if saved:
                last = self.save()
            # SIGTERM / USR2: stop here with this iteration checkpointed (march.learn.preemption).
            preemption.stop_if_requested(
                "teacher", self.iteration, None if saved else self.save, last
            )
        if last is None:
            last = self.save()
        # The stage's last teacher is always evaluated once (also when a finished stage is
        # resumed, or a run died during this evaluation).
        if self.evaluate_fn is not None and not distributed.agree(
            has_row(self.run_dir / "eval.csv", "teacher", self.iteration)
        ):
            self.evaluate()
        return self.ckpt_dir / "latest.pt"
