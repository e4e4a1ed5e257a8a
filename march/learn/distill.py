"""Teacher -> student distillation (DAgger): the student acts, the frozen teacher labels.

Our own algorithm, because rsl-rl 5.4.2's Distillation offers only MSE/Huber and mjlab 1.6.0
ships no distillation runner; the loop (resume, checkpoints, evaluation rows, metrics, faults)
is :class:`march.learn.stage_runner.StageRunner`'s, shared with the teacher. The loss is the student's own (:meth:`StudentPolicy.distill_loss`): NLL of
``teacher_samples`` actions drawn from N(teacher mean, (teacher_std_scale * teacher std)^2) for
the MDN students, Huber against the teacher mean for ``no_mdn``. The losses of every
``gradient_length`` consecutive steps of a rollout are summed into one optimiser step (rsl-rl's
convention, :func:`distill_update`); ``num_learning_epochs`` passes per rollout.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from tensordict import TensorDict

from march.config import MarchConfig
from march.learn import distributed, rank_normalizers
from march.learn.metrics import MetricsLog
from march.learn.stage_runner import EpisodeStats, StageRunner
from march.learn.teacher import build_teacher_actor, teacher_obs
from march.policies.student import StudentPolicy
from march.store.checkpoint import check_layout

if TYPE_CHECKING:
    from mjlab.envs import ManagerBasedRlEnv

COMMAND = "twist"
Rollout = tuple[list[tuple[torch.Tensor, ...]], torch.Tensor]
"""A rollout's steps (student inputs, teacher mean and std) and its mean teacher reward."""


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
    return StudentPolicy.from_layout(cfg.student, layout).to(device)


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


class DistillRunner(StageRunner):
    """Distils a frozen teacher into the configured student on the student env.

    The loop, resume, checkpoints, rows and faults are :class:`StageRunner`'s; this runner
    supplies the DAgger rollout (the student acts, the teacher labels), the update
    (:func:`distill_update`) and what its checkpoint holds.
    """

    stage = "student"
    group = "distill"
    progress_columns = {
        "loss": "loss",
        "action_err": "action_error",
        "teacher_reward": "teacher_reward",
        "ep_len": "mean_episode_length",
    }

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
        super().__init__(env, cfg, run_dir, log, evaluate_fn)
        self.env = env
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
        self.optimizer = torch.optim.Adam(self.student.parameters(), lr=cfg.distill.learning_rate)
        self.generator = torch.Generator(device=self.device).manual_seed(cfg.seed)
        self.generators = {"distill": self.generator}  # checkpointed, restored on resume

    # ---- the update guard: the student and its optimizer

    def snapshot(self) -> dict[str, Any]:
        return {"student": self.student.state_dict(), "opt": self.optimizer.state_dict()}

    def restore(self, saved: dict[str, Any]) -> None:
        self.student.load_state_dict(saved["student"])
        self.optimizer.load_state_dict(saved["opt"])

    def parameters(self) -> Any:
        return self.student.parameters()

    # ---- the checkpoint

    def algorithm_state(self) -> dict[str, Any]:
        return {
            "teacher_ckpt": str(self.teacher_path),
            "student_state_dict": self.student.state_dict(),
            "optimizer_state_dict": self.optimizer.state_dict(),
            "generator": self.generator.get_state(),
        }

    def load_algorithm_state(self, payload: dict[str, Any]) -> None:
        # The generator comes back with the other random streams (restore_state).
        self.student.load_state_dict(payload["student_state_dict"])
        self.optimizer.load_state_dict(payload["optimizer_state_dict"])

    def resumed(self, payload: dict[str, Any]) -> None:
        self.obs = self.env.obs_buf  # the observations of the resume's reset

    # ---- rollout and update

    def _teacher_obs(self, obs: dict[str, Any]) -> TensorDict:
        return teacher_obs(obs, self.env.num_envs)

    @torch.no_grad()
    def _rollout(self, stats: EpisodeStats) -> Rollout:
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
            before = self.ruler.foothold_progress()  # both feet's (docs/evaluation.md)
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

    def collect(self, stats: EpisodeStats) -> Rollout:
        return self._rollout(stats)

    def update(self, batch: Rollout) -> dict[str, float]:
        return distributed.mean_over_ranks(self._update(batch[0]))

    def row_columns(self, batch: Rollout, losses: dict[str, float]) -> dict[str, Any]:
        teacher_reward = distributed.mean_over_ranks({"r": batch[1]})["r"]
        return {
            **{f"loss/{k}": v for k, v in losses.items()},  # nll / huber, mode weights, ...
            "loss": losses.get("loss", float("nan")),
            "action_error": losses.get("action_error", float("nan")),
            "teacher_reward": float(teacher_reward),
            "mode_weight_0": losses.get("mode_weight_0", float("nan")),
            "mode_weight_1": losses.get("mode_weight_1", float("nan")),
        }

    # ---- evaluation: the student as it is (student_policy puts it in eval mode)

    def eval_policy(self) -> StudentPolicy:
        return self.student
