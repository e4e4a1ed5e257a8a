"""The PPO teacher runner: rsl-rl's PPO (algorithm, models, storage) on the mjlab env.

The loop (logging, checkpoints, resume, evaluation rows, faults) is :class:`StageRunner`'s,
shared with distillation; this runner supplies the PPO rollout and update and what its
checkpoint holds. mjlab's own ``train`` CLI is not used: it assumes a GPU.
"""

from __future__ import annotations

import contextlib
import copy
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from rsl_rl.algorithms import PPO
from rsl_rl.models import MLPModel
from tensordict import TensorDict

from march.config import MarchConfig, TeacherCfg
from march.env.build import rsl_rl_env
from march.env.joint_groups import action_joint_names, per_joint
from march.learn import distributed, rank_normalizers
from march.learn.metrics import MetricsLog
from march.learn.stage_runner import EpisodeStats, StageRunner
from march.learn.update_readout import UpdateReadout, set_initial_std
from march.store.checkpoint import check_layout

if TYPE_CHECKING:
    from mjlab.envs import ManagerBasedRlEnv

UPDATE_COLUMNS = (
    "lr_mean",
    "lr_min",
    "lr_max",
    "kl_update",
    "kl_normaliser",
    "clip_fraction",
    "action_std",
    "action_std_legs",
    "action_std_waist",
    "action_std_arms",
)
"""The update's metrics.csv columns (march.learn.update_readout.UpdateReadout.pop)."""

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


class TeacherRunner(StageRunner):
    """PPO on the teacher env; checkpoints in ``<run>/teacher/``; resumes by itself.

    The loop, resume, checkpoints, rows and faults are :class:`StageRunner`'s; rsl-rl's PPO
    collects (``act`` / ``process_env_step``) and updates. With ``evaluate_fn`` the current
    teacher is evaluated every ``teacher.eval_interval`` iterations and at the end of the stage
    (``stage=teacher`` rows of eval.csv); an evaluation runs before that iteration's checkpoint,
    so a resumed run drops and redoes exactly the rows past its checkpoint.
    """

    stage = "teacher"
    group = "teacher"
    evaluates_last = True
    progress_columns = {
        "reward": "mean_reward",
        "ep_len": "mean_episode_length",
        "dist_m": "mean_distance_m",
        "value_loss": "value_loss",
        "V/Vmax_p50": "clf/v_p50",  # arms with the reference (march.env.clf_meter)
        "saturated": "clf/saturated",
        # the update (march.learn.update_readout): lr over its mini-batches, the KL it moved
        # the policy by (its normaliser's part), clip fraction, std per joint group
        "lr": "lr_mean",
        "lr_min": "lr_min",
        "lr_max": "lr_max",
        "kl": "kl_update",
        "kl_norm": "kl_normaliser",
        "clip": "clip_fraction",
        "std_legs": "action_std_legs",
        "std_waist": "action_std_waist",
        "std_arms": "action_std_arms",
    }

    def __init__(
        self,
        env: ManagerBasedRlEnv,
        cfg: MarchConfig,
        run_dir: Path,
        log: MetricsLog,
        evaluate_fn: TeacherEval | None = None,
    ):
        super().__init__(env, cfg, run_dir, log, evaluate_fn)
        self.env = rsl_rl_env(env)
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
        # The initial action std per joint group (teacher.init_std x init_std_<group>; the
        # paper's 1.0 on every joint by default): rsl-rl builds one scalar for every action.
        joints = action_joint_names(env)
        set_initial_std(self.alg.actor, per_joint(joints, cfg.teacher.group_init_std))
        self.readout = UpdateReadout(self.alg, joints)
        if self.alg.is_multi_gpu:  # N ranks: rank 0's networks everywhere, shared normalisers
            self.alg.broadcast_parameters()
            rank_normalizers.sync_normalizers(self.alg.actor, self.alg.critic)
        self.obs: TensorDict | None = None  # the rollout's current observations

    # ---- the update guard: networks and optimizer, as rsl-rl saves them

    def snapshot(self) -> dict[str, Any]:
        return self.alg.save()

    def restore(self, saved: dict[str, Any]) -> None:
        """Put back the networks and optimizer of :meth:`UpdateGuard.before` (an undone update)."""
        # The normalizers' buffers were last written under inference mode (the rollout), and
        # only there can they be written again; the optimizer state is loaded outside it.
        with torch.inference_mode():
            self.alg.load(saved, {"actor": True, "critic": True}, strict=True)
        self.alg.load(saved, {"optimizer": True}, strict=True)

    def parameters(self) -> list[torch.nn.Parameter]:
        return [*self.alg.actor.parameters(), *self.alg.critic.parameters()]

    # ---- the checkpoint

    def algorithm_state(self) -> dict[str, Any]:
        return {"ppo": self.train_cfg, **self.alg.save(), "learning_rate": self.alg.learning_rate}

    def load_algorithm_state(self, payload: dict[str, Any]) -> None:
        self.alg.load(payload, None, strict=True)
        self.alg.learning_rate = payload.get("learning_rate", self.alg.learning_rate)
        for group in self.alg.optimizer.param_groups:
            group["lr"] = self.alg.learning_rate

    def resumed(self, payload: dict[str, Any]) -> None:
        self.clocks_restored = "episode" in payload

    # ---- rollout and update

    def start(self) -> None:
        # Episodes start at seeded random steps: at the start, and after a resume from a
        # checkpoint without episode clocks (an older one); clocks a resume restored go on as
        # they were, so a resumed run continues the uninterrupted one's schedule.
        if not self.clocks_restored:
            stagger_episodes(self.unwrapped, self.cfg.seed, self.iteration)
        self.obs = self.env.get_observations().to(self.device)
        self.alg.train_mode()
        self.replans = ReplanReadout(self.unwrapped)

    def collect(self, stats: EpisodeStats) -> None:
        obs = self.obs
        with torch.inference_mode():
            for _ in range(self.cfg.teacher.num_steps_per_env):
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
        self.obs = obs

    def update(self, batch: None) -> dict[str, float]:
        # rsl-rl's update, watched: lr per mini-batch, KL, clip fraction, std per group (one
        # host read per iteration, as rsl-rl's losses; march.learn.update_readout)
        return distributed.mean_over_ranks(self.readout.update())

    def row_columns(self, batch: None, losses: dict[str, float]) -> dict[str, Any]:
        return {
            "value_loss": losses.get("value", losses.get("value_function", float("nan"))),
            "surrogate_loss": losses.get("surrogate", float("nan")),
            "entropy": losses.get("entropy", float("nan")),
            "learning_rate": self.alg.learning_rate,  # after the update: the next one's start
            **{k: losses.get(k, float("nan")) for k in UPDATE_COLUMNS},
            **self.replans.pop(),
        }

    # ---- evaluation: the deterministic actor, networks in eval mode

    def eval_policy(self) -> MLPModel:
        return self.alg.get_policy()

    @contextlib.contextmanager
    def evaluating(self) -> Iterator[None]:
        self.alg.eval_mode()
        try:
            yield
        finally:
            self.alg.train_mode()
