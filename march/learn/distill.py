"""Teacher -> student distillation (DAgger): the student acts, the frozen teacher labels.

Our own runner, because rsl-rl 5.4.2's Distillation offers only MSE/Huber and mjlab 1.6.0 ships no
distillation runner. The loss is the student's own (:meth:`StudentPolicy.distill_loss`): NLL of
``teacher_samples`` actions drawn from N(teacher mean, (teacher_std_scale * teacher std)^2) for
the MDN students, Huber against the teacher mean for ``no_mdn``. The losses of every
``gradient_length`` consecutive steps of a rollout are summed into one optimiser step (rsl-rl's
convention, :func:`distill_update`); ``num_learning_epochs`` passes per rollout.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from tensordict import TensorDict

from march.config import MarchConfig
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
from march.learn.metrics import MetricsLog, Progress, truncate_rows
from march.learn.teacher import EpisodeStats, build_teacher_actor, teacher_obs
from march.learn.train_state import (
    collect_state,
    mean_terrain_level,
    rank_payload,
    restore_state,
)
from march.policies.student import StudentPolicy

if TYPE_CHECKING:
    from mjlab.envs import ManagerBasedRlEnv

COMMAND = "twist"


def student_inputs(env: ManagerBasedRlEnv, obs: dict[str, Any]) -> tuple[torch.Tensor, ...]:
    """(proprio history (E,H,P), command (E,3), depth (E,1,H,W)) from the env's observations."""
    return obs["student"], env.command_manager.get_command(COMMAND), obs["depth"]


def student_layout(obs: dict[str, Any], cfg: MarchConfig, num_actions: int) -> dict[str, Any]:
    return {
        "variant": cfg.student.variant,
        "proprio_dim": int(obs["student"].shape[-1]),
        "history_len": int(obs["student"].shape[1]),
        "image_hw": [int(obs["depth"].shape[-2]), int(obs["depth"].shape[-1])],
        "num_actions": int(num_actions),
    }


def build_student(cfg: MarchConfig, layout: dict[str, Any], device: str) -> StudentPolicy:
    return StudentPolicy(
        cfg.student,
        proprio_dim=layout["proprio_dim"],
        history_len=layout["history_len"],
        command_dim=3,
        image_hw=tuple(layout["image_hw"]),
        num_actions=layout["num_actions"],
    ).to(device)


def load_student(
    payload: dict[str, Any], cfg: MarchConfig, obs: dict[str, Any], num_actions: int, path: str
) -> StudentPolicy:
    """The student of a loaded checkpoint, checked against the env's observation layout."""
    check_layout(payload["layout"], student_layout(obs, cfg, num_actions), "student", path)
    student = build_student(cfg, payload["layout"], cfg.compute.device)
    student.load_state_dict(payload["student_state_dict"])
    student.eval()
    return student


def student_policy(
    env: ManagerBasedRlEnv, student: StudentPolicy
) -> Callable[[dict], torch.Tensor]:
    def act(obs: dict[str, Any]) -> torch.Tensor:
        student.eval()
        return student.act_inference(*student_inputs(env, obs))

    return act


def distill_update(
    model: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    steps: Sequence[Any],
    step_loss: Callable[[Any], tuple[torch.Tensor, dict[str, float]]],
    num_epochs: int,
    gradient_length: int,
    max_grad_norm: float,
    reduce_gradients: Callable[[], None] | None = None,
) -> dict[str, float]:
    """``num_epochs`` passes over a rollout's ``steps``; the losses of every ``gradient_length``
    consecutive steps are summed into one optimiser step.

    rsl-rl 5.4.2's ``Distillation.update`` exactly: the step counter runs on across epochs (a
    group may span two), the summed loss is back-propagated when the count reaches a multiple of
    ``gradient_length``, gradients are clipped to ``max_grad_norm``, and steps left over at the
    very end (when ``num_epochs * len(steps)`` is not a multiple) make no optimiser step. Returns
    the mean of each ``info`` entry over every step seen. ``reduce_gradients`` runs between the
    backward pass and the clipping (N ranks: the all-reduce to the mean gradient).
    """
    totals: dict[str, float] = {}
    count = 0
    loss: torch.Tensor | None = None
    for _ in range(num_epochs):
        for step in steps:
            step_value, info = step_loss(step)
            loss = step_value if loss is None else loss + step_value  # a sum, not a mean
            for k, v in info.items():
                totals[k] = totals.get(k, 0.0) + float(v)
            count += 1
            if count % gradient_length == 0:
                optimizer.zero_grad()
                loss.backward()
                if reduce_gradients is not None:
                    reduce_gradients()
                if max_grad_norm:
                    torch.nn.utils.clip_grad_norm_(model.parameters(), max_grad_norm)
                optimizer.step()
                loss = None
    return {k: v / max(count, 1) for k, v in totals.items()}


class DistillRunner:
    """Distils a frozen teacher into the configured student on the student env."""

    def __init__(
        self,
        env: ManagerBasedRlEnv,
        cfg: MarchConfig,
        run_dir: Path,
        log: MetricsLog,
        teacher_payload: dict[str, Any],
        teacher_path: str,
        evaluate_fn: Callable[[StudentPolicy, int, int], dict[str, Any]] | None = None,
    ) -> None:
        self.env, self.cfg, self.run_dir, self.log = env, cfg, run_dir, log
        self.device = cfg.compute.device
        self.ruler = CourseRuler(env)
        self.ckpt_dir = run_dir / "student"
        self.evaluate_fn = evaluate_fn
        obs, _ = env.reset()
        self.obs = obs
        num_actions = env.action_manager.total_action_dim
        self.teacher = build_teacher_actor(
            teacher_payload, self._teacher_obs(obs), num_actions, self.device, teacher_path
        )
        self.teacher_path = teacher_path
        self.layout = student_layout(obs, cfg, num_actions)
        self.student = build_student(cfg, self.layout, self.device)
        # N ranks: rank 0's initial student everywhere, normalisers learning from every rank.
        distributed.broadcast_module(self.student)
        rank_normalizers.sync_normalizers(self.student)
        self.world = distributed.current().world
        d = cfg.distill
        self.optimizer = torch.optim.Adam(self.student.parameters(), lr=d.learning_rate)
        self.generator = torch.Generator(device=self.device).manual_seed(cfg.seed)
        self.iteration = 0
        self.env_steps = 0
        self.wall_s = 0.0
        self.faults = EnvFaults(env)
        self.guard = UpdateGuard(
            "distill",
            d.max_nonfinite_updates,
            lambda: {"student": self.student.state_dict(), "opt": self.optimizer.state_dict()},
            self._restore,
            self.student.parameters,
        )

    def _restore(self, saved: dict[str, Any]) -> None:
        self.student.load_state_dict(saved["student"])
        self.optimizer.load_state_dict(saved["opt"])

    def _teacher_obs(self, obs: dict[str, Any]) -> TensorDict:
        return teacher_obs(obs, self.env.num_envs)

    def payload(self) -> dict[str, Any]:
        return {
            "kind": "student",
            "iteration": self.iteration,
            "env_steps": self.env_steps,
            "wall_s": self.wall_s,
            "config": asdict(self.cfg),
            "layout": self.layout,
            "teacher_ckpt": str(self.teacher_path),
            "student_state_dict": self.student.state_dict(),
            "optimizer_state_dict": self.optimizer.state_dict(),
            "generator": self.generator.get_state(),
            "rng": torch.get_rng_state(),
            "common_step_counter": self.env.common_step_counter,
            # curriculum (terrain levels), episode clocks, every random stream
            **collect_state(self.env, self.device, {"distill": self.generator}),
        }

    def _save(self) -> Path:
        # Every rank's random states go in (a collective); rank 0 alone writes the files.
        payload = distributed.with_rank_states(self.payload())
        return save_checkpoint(payload, self.ckpt_dir, self.iteration)

    def try_resume(self) -> bool:
        for tmp in self.ckpt_dir.glob(".*.tmp"):  # a write that a kill cut short
            tmp.unlink(missing_ok=True)
        path = latest_checkpoint(self.ckpt_dir)
        if path is None:
            # Killed before its first checkpoint: the stage starts over, and so do its rows.
            self.log.resume_from("student", 0)
            truncate_rows(self.run_dir / "eval.csv", "student", 0)
            return False
        where = f"resume={self.run_dir}: {path}"
        payload = load_checkpoint(path, "student", self.device, source=where)
        # N ranks: this rank's own levels, clocks and streams (another rank count: refused).
        payload = rank_payload(payload, where)
        if path.name == "latest.pt":  # a kill may have cut the write of its model_<it>.pt
            ensure_model_file(payload, self.ckpt_dir)
        check_layout(payload["layout"], self.layout, "student", path)
        self.student.load_state_dict(payload["student_state_dict"])
        self.optimizer.load_state_dict(payload["optimizer_state_dict"])
        self.iteration = int(payload["iteration"])
        self.env_steps = int(payload["env_steps"])
        self.wall_s = float(payload.get("wall_s", 0.0))
        # Levels, episode clocks and random streams (the distillation generator's too; across
        # devices it is reseeded): the env's reset here draws from them, so they come last.
        notes = restore_state(
            self.env, payload, self.device, self.cfg.seed, where, {"distill": self.generator}
        )
        self.obs = self.env.obs_buf  # the observations of that reset
        self.env.common_step_counter = payload.get("common_step_counter", 0)
        self.log.resume_from("student", self.iteration)
        truncate_rows(self.run_dir / "eval.csv", "student", self.iteration)
        print(f"[student] resuming from {path} at iteration {self.iteration}")
        for line in notes:
            print(f"[student] {line}")
        return True

    @torch.no_grad()
    def _rollout(self, stats: EpisodeStats) -> tuple[list[tuple[torch.Tensor, ...]], torch.Tensor]:
        """The iteration's steps and the mean teacher reward per step (0-d, on the device: the
        caller reads it once per iteration)."""
        steps = []
        reward_sum = torch.zeros((), device=self.device)
        obs = self.obs
        self.student.eval()
        for _ in range(self.cfg.distill.num_steps_per_env):
            inputs = student_inputs(self.env, obs)
            self.teacher(self._teacher_obs(obs), stochastic_output=True)
            teacher_mean = self.teacher.output_mean.clone()
            teacher_std = self.teacher.output_std.expand_as(teacher_mean).clone()
            actions = self.student.act_inference(*inputs)
            steps.append(tuple(x.clone() for x in inputs) + (teacher_mean, teacher_std))
            before = self.ruler.progress()
            bad_actions = self.faults.actions(actions)
            obs, reward, terminated, truncated, _ = self.env.step(actions)
            done = terminated | truncated
            bad = self.faults.after_step(obs, reward, bad_actions)
            done = done | bad  # a NaN or inf: that episode ends here
            stats.step(reward, done, before)
            reward_sum = reward_sum + reward.mean()  # on the device: read once below
        self.obs = obs
        return steps, reward_sum / len(steps)

    def _update(self, steps: list[tuple[torch.Tensor, ...]]) -> dict[str, float]:
        d = self.cfg.distill
        self.student.train()
        for proprio, command, _, _, _ in steps:
            self.student.update_normalization(proprio, command)
        rank_normalizers.flush_normalizers()  # N ranks: every rank's batches, once

        def step_loss(step: tuple[torch.Tensor, ...]) -> tuple[torch.Tensor, dict[str, float]]:
            proprio, command, depth, mean, std = step
            return self.student.distill_loss(
                proprio,
                command,
                depth,
                mean,
                std,
                num_samples=d.teacher_samples,
                std_scale=d.teacher_std_scale,
                generator=self.generator,
            )

        return distill_update(
            self.student,
            self.optimizer,
            steps,
            step_loss,
            d.num_learning_epochs,
            d.gradient_length,
            d.max_grad_norm,
            (lambda: distributed.average_gradients(self.student.parameters()))
            if self.world > 1
            else None,
        )

    def learn(self, total_iterations: int) -> Path:
        d = self.cfg.distill
        stats = EpisodeStats(self.env.num_envs, self.device)
        progress = Progress("student", self.iteration, total_iterations)
        for it in range(self.iteration, total_iterations):
            t0 = time.time()
            steps, teacher_reward = self._rollout(stats)
            self.guard.before()
            info = distributed.mean_over_ranks(self._update(steps))
            teacher_reward = distributed.mean_over_ranks({"r": teacher_reward})["r"]
            # A non-finite update is undone; too many in a row stop before this checkpoint.
            self.guard.after(info, it + 1, latest_checkpoint(self.ckpt_dir))
            self.iteration = it + 1
            self.env_steps += d.num_steps_per_env * self.env.num_envs * self.world
            self.wall_s += time.time() - t0
            row = {
                "stage": "student",
                "iteration": self.iteration,
                "env_steps": self.env_steps,
                "wall_s": self.wall_s,
                **distributed.pop_episode_stats(stats),
                **distributed.mean_over_ranks({"mean_terrain_level": mean_terrain_level(self.env)}),
                **distributed.mean_over_ranks(pop_terms(self.env)),  # the teacher's terms
                **{f"loss/{k}": v for k, v in info.items()},  # nll / huber, mode weights, ...
                "loss": info.get("loss", float("nan")),
                "action_error": info.get("action_error", float("nan")),
                "teacher_reward": float(teacher_reward),
                "mode_weight_0": info.get("mode_weight_0", float("nan")),
                "mode_weight_1": info.get("mode_weight_1", float("nan")),
                "nonfinite_resets": distributed.sum_over_ranks(self.faults.pop()),
                "nonfinite_updates": self.guard.pop(),
            }
            self.log.log(row)
            print(
                progress.line(
                    it,
                    {
                        "loss": row["loss"],
                        "action_err": row["action_error"],
                        "teacher_reward": float(teacher_reward),
                        "ep_len": row["mean_episode_length"],
                    },
                ),
                flush=True,
            )
            last = self.iteration == total_iterations
            # Evaluate before the checkpoint, as the teacher does: a run killed in between resumes
            # from the previous checkpoint (its later eval.csv rows truncated) and redoes both;
            # the other order lost this evaluation for good. The final iteration's evaluation is
            # the pipeline's eval stage (summary.json).
            if (
                self.evaluate_fn is not None
                and not last
                and (d.eval_interval and self.iteration % d.eval_interval == 0)
            ):
                self.evaluate_fn(self.student, self.iteration, self.env_steps)
            saved = self.iteration % d.save_interval == 0 or last
            if saved:
                self._save()
            # SIGTERM / USR2: stop here with this iteration checkpointed (march.learn.preemption).
            preemption.stop_if_requested("student", self.iteration, None if saved else self._save)
        if distributed.agree(latest_checkpoint(self.ckpt_dir) is None):  # rank 0 owns the files
            self._save()
        return self.ckpt_dir / "latest.pt"
