"""``python -m march.train``: teacher PPO -> student distillation -> evaluation.

    python -m march.train reward=clf student=full          # stage=all, compute=auto
    python -m march.train stage=student teacher_ckpt=outputs/<run>/teacher/latest.pt
    python -m march.train stage=eval student_ckpt=outputs/<run>/student/latest.pt
    python -m march.train resume=outputs/<run>               # continue a killed run
    python -m march.train -m +sweep=baseline                 # the paper's baseline comparison

A run directory holds config.yaml (resolved), teacher/ and student/ checkpoints, metrics.csv,
eval.csv, summary.json and status.json. A run whose directory already holds checkpoints resumes
from them by itself (this is what makes a Slurm requeue continue).
"""

from __future__ import annotations

import math
import os
import random
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import hydra
import numpy as np
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from march.config import ConfigError, MarchConfig, to_march_config
from march.config.cli import fail, resolve_compute
from march.learn.checkpoint import CheckpointError, write_json_atomic
from march.learn.faults import NumericalFault
from march.learn.metrics import MetricsLog


def _seed_everything(seed: int) -> None:
    import torch

    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def _write_status(run_dir: Path, state: str, **extra: Any) -> None:
    write_json_atomic({"state": state, "time": time.time(), **extra}, run_dir / "status.json")


def banner(
    cfg: MarchConfig, run_dir: Path, placeholders: dict[str, str], auto: bool = False
) -> str:
    """The start banner: what runs, at which scale (and why), where, and when wall time shows."""
    c, t, d, e = cfg.compute, cfg.teacher, cfg.distill, cfg.eval
    why = ""
    if auto:
        why = " (compute=auto: CUDA available)" if c.name == "gpu" else " (compute=auto: no CUDA)"
    lines = [
        "=" * 78,
        f"march.train  stage={cfg.stage}  reward={cfg.reward.name}  student={cfg.student.variant}"
        f"  curriculum={cfg.curriculum.name}  dr={cfg.dr.name}  seed={cfg.seed}",
        f"scale: compute={c.name}{why} on {c.device}: {c.num_envs} envs; teacher {t.iterations} "
        f"it x {t.num_steps_per_env} steps; distill {d.max_iterations} it x "
        f"{d.num_steps_per_env} steps; eval {e.num_rollouts} rollouts x {e.episode_length_s:g} s "
        f"on {c.eval_num_envs} envs",
        f"run dir: {run_dir}",
    ]
    first = {"all": "teacher", "teacher": "teacher", "student": "distillation"}.get(cfg.stage)
    if first:
        n = t.iterations if first == "teacher" else d.max_iterations
        k = ETA_ITERATIONS + 1 if n > ETA_ITERATIONS else n  # + the unmeasured warm-up one
        lines.append(
            f"wall time: an [eta] line after the first {k} {first} iterations gives the "
            "expected duration of this scale, from the measured speed"
        )
    if placeholders:
        lines.append("placeholders (not yet the paper's method):")
        lines += [f"  - {k}: {v}" for k, v in placeholders.items()]
    lines.append("=" * 78)
    return "\n".join(lines)


# ---------------------------------------------------------------------------- wall-time estimate

ETA_ITERATIONS = 3
"""Iterations measured before the [eta] line is printed (fewer if the stage is shorter)."""


@dataclass(frozen=True)
class StepCosts:
    """Seconds of one env step of another stage per second of one teacher PPO env step (its
    rollout step plus its share of the update), at equal env counts. Rough: the [eta] line says
    so, and distillation is measured again once it runs."""

    eval: float
    """An evaluation step: depth rendering and inference, no update."""
    distill_rollout: float
    """A distillation rollout step: depth rendering, student and teacher inference."""
    distill_epoch: float
    """The student update per rollout step and per epoch (student forward + backward)."""


STEP_COSTS = {
    # 2 CPU cores, compute=smoke (4 envs): teacher 0.25 s per step, a 1-epoch distillation
    # iteration 1.37 s per step, evaluation ~0.4 s per step.
    "cpu": StepCosts(eval=1.6, distill_rollout=1.6, distill_epoch=4.0),
    # GPU: not measured yet; the student's batched forward/backward is cheap next to 4096 envs'
    # physics, so an epoch costs a fraction of a teacher step.
    "cuda": StepCosts(eval=1.5, distill_rollout=1.5, distill_epoch=0.25),
}


def step_costs(device: str) -> StepCosts:
    return STEP_COSTS["cuda" if device.startswith("cuda") else "cpu"]


def format_duration(seconds: float) -> str:
    """``45 s``, ``52 min``, ``1 h 10 min``, ``26 h``: minutes are the finest unit past one."""
    s = max(0.0, float(seconds))
    if s < 60:
        return f"{s:.0f} s"
    minutes = round(s / 60)
    if minutes < 60:
        return f"{minutes} min"
    h, m = divmod(minutes, 60)
    return f"{h} h {m} min" if m else f"{h} h"


def evaluation_counts(cfg: MarchConfig) -> tuple[int, int]:
    """(teacher, student) evaluations a run of ``cfg.stage`` makes (eval rows + the summary)."""
    t, d = cfg.teacher, cfg.distill
    # The teacher: every eval_interval iterations and at the end of the stage.
    n_teacher = t.iterations // t.eval_interval if t.eval_interval else 0
    if not t.eval_interval or t.iterations % t.eval_interval:
        n_teacher += 1
    # The student: every eval_interval iterations except the last, whose evaluation is the final.
    n_student = 1 + ((d.max_iterations - 1) // d.eval_interval if d.eval_interval else 0)
    return {
        "all": (n_teacher, n_student),
        "teacher": (n_teacher, 0),
        "student": (0, n_student),
        "eval": (0, 1),
    }[cfg.stage]


def estimate_wall_s(
    cfg: MarchConfig,
    teacher_s_per_it: float | None = None,
    distill_s_per_it: float | None = None,
    teacher_from: int = 0,
    distill_from: int = 0,
) -> dict[str, float]:
    """Expected seconds of the teacher, distillation and evaluations of ``cfg.stage`` from here.

    One measured speed is needed: the teacher's seconds per PPO iteration, or (stage=student, or
    once distillation runs) the distillation's. The other stages are scaled from it per env step
    with :data:`STEP_COSTS` of the device; ``*_from`` are the
    iterations already done (a resumed run). Evaluation: ceil(num_rollouts / eval_num_envs)
    waves of eval.episode_length_s each, at eval_num_envs envs (step cost taken as linear in the
    env count, an overestimate on a GPU).
    """
    c, t, d, e = cfg.compute, cfg.teacher, cfg.distill, cfg.eval
    k = step_costs(c.device)
    distill_step_cost = k.distill_rollout + k.distill_epoch * d.num_learning_epochs
    if teacher_s_per_it is not None:
        step_s = teacher_s_per_it / t.num_steps_per_env  # one env step of all num_envs envs
    elif distill_s_per_it is not None:
        step_s = distill_s_per_it / (d.num_steps_per_env * distill_step_cost)
    else:
        raise ValueError("estimate_wall_s needs a measured teacher or distillation speed")
    if distill_s_per_it is None:
        distill_s_per_it = step_s * d.num_steps_per_env * distill_step_cost
    if teacher_s_per_it is None:
        teacher_s_per_it = step_s * t.num_steps_per_env
    dt = cfg.env.sim_dt * cfg.env.decimation
    waves = math.ceil(e.num_rollouts / c.eval_num_envs)
    one_eval = waves * (e.episode_length_s / dt) * step_s * k.eval
    one_eval *= c.eval_num_envs / c.num_envs
    n_teacher, n_student = evaluation_counts(cfg)
    teacher = distill = 0.0
    if cfg.stage in ("all", "teacher"):
        teacher = teacher_s_per_it * max(0, t.iterations - teacher_from)
    if cfg.stage in ("all", "student"):
        distill = distill_s_per_it * max(0, d.max_iterations - distill_from)
    # Evaluations already made are not repeated.
    if teacher_from >= t.iterations:
        n_teacher = 0
    elif t.eval_interval:
        n_teacher -= teacher_from // t.eval_interval
    if d.eval_interval:
        n_student -= min(n_student - 1, distill_from // d.eval_interval)
    evals = (n_teacher + n_student) * one_eval
    return {
        "teacher": teacher,
        "distill": distill,
        "eval": evals,
        "total": teacher + distill + evals,
    }


class EtaWatch:
    """Prints the [eta] line once the first iterations of a stage have been measured.

    Fed the rows ``metrics.csv`` receives (their ``wall_s`` is the stage's own training time, so
    evaluations in between do not distort the speed); :meth:`start` tells it where a resumed
    stage begins. The first iteration of a process carries one-off costs (kernel compilation,
    lazy initialisation, CUDA graph capture): it is left out of the measurement when the stage
    has more than ``n`` iterations, so the speed is that of the following ``n``.
    """

    def __init__(self, cfg: MarchConfig, n: int = ETA_ITERATIONS, echo: bool = True) -> None:
        self.cfg, self.n, self.echo = cfg, n, echo
        self.origin: dict[str, tuple[int, float]] = {}  # where the stage began in this process
        self.mark: dict[str, tuple[int, float]] = {}  # where the measurement begins
        self.done: set[str] = set()
        self.teacher_s_per_it: float | None = None
        self.lines: list[str] = []

    def start(self, stage: str, iteration: int, wall_s: float) -> None:
        self.origin[stage] = self.mark[stage] = (int(iteration), float(wall_s))

    def observe(self, row: dict[str, Any]) -> str | None:
        stage = row.get("stage")
        if stage not in ("teacher", "student") or stage in self.done:
            return None
        it0, _ = self.origin.setdefault(stage, (0, 0.0))
        total = (
            self.cfg.teacher.iterations if stage == "teacher" else self.cfg.distill.max_iterations
        )
        left = max(1, total - it0)
        it, wall = int(row["iteration"]), float(row["wall_s"])
        if left > self.n and it == it0 + 1:  # the warm-up iteration: measure from its end
            self.mark[stage] = (it, wall)
            return None
        mark_it, mark_wall = self.mark.setdefault(stage, (it0, 0.0))
        done = it - mark_it
        if done < min(self.n, left):
            return None
        self.done.add(stage)
        s_per_it = (wall - mark_wall) / done
        plural = "s" if done > 1 else ""
        kind = "" if stage == "teacher" else "distillation "
        if mark_it == it0:
            over = f"the first {done} {kind}iteration{plural}"
        else:
            over = f"{kind}iterations {mark_it + 1}-{it}"
        if stage == "teacher":
            self.teacher_s_per_it = s_per_it
            est = estimate_wall_s(self.cfg, teacher_s_per_it=s_per_it, teacher_from=it0)
            line = (
                f"[eta] measured {s_per_it:.3g} s/it over {over}: "
                f"teacher ~{format_duration(est['teacher'])}, whole run "
                f"~{format_duration(est['total'])}"
            )
            if self.cfg.stage == "all":
                line += (
                    f" (distillation ~{format_duration(est['distill'])} and evaluations "
                    f"~{format_duration(est['eval'])}: rough, from the teacher's speed)"
                )
        else:
            # Evaluations scale with the teacher's speed when it was measured in this process.
            est = estimate_wall_s(
                self.cfg,
                teacher_s_per_it=self.teacher_s_per_it,
                distill_s_per_it=s_per_it,
                teacher_from=self.cfg.teacher.iterations,
                distill_from=it0,
            )
            line = (
                f"[eta] measured {s_per_it:.3g} s/it over {over}: distillation "
                f"~{format_duration(est['distill'])}, with its evaluations "
                f"~{format_duration(est['distill'] + est['eval'])}"
            )
        self.lines.append(line)
        if self.echo:
            print(line, flush=True)
        return line


class EtaMetricsLog(MetricsLog):
    """metrics.csv (and the selected logger) plus the [eta] line after the first iterations."""

    def __init__(self, run_dir: Path, cfg: MarchConfig, eta: EtaWatch) -> None:
        super().__init__(run_dir, cfg.logger, run_dir.name)
        self.eta = eta

    def log(self, row: dict[str, Any]) -> None:
        super().log(row)
        self.eta.observe(row)


def _check_inputs(cfg: MarchConfig) -> None:
    """Everything a user can get wrong is checked here, before any simulation starts."""
    if cfg.stage == "student" and not cfg.teacher_ckpt:
        raise ConfigError(
            "stage=student needs teacher_ckpt=<file> (outputs/<run>/teacher/latest.pt)"
        )
    if cfg.stage == "eval":
        if cfg.eval.policy == "student" and not cfg.student_ckpt:
            raise ConfigError(
                "stage=eval needs student_ckpt=<file> (or eval.policy=teacher teacher_ckpt=<file>)"
            )
        if cfg.eval.policy == "teacher" and not cfg.teacher_ckpt:
            raise ConfigError("stage=eval eval.policy=teacher needs teacher_ckpt=<file>")
    for key in ("teacher_ckpt", "student_ckpt"):
        path = getattr(cfg, key)
        if path and not Path(path).is_file():
            raise ConfigError(f"{key}={path}: no such file")
    if cfg.resume and not Path(cfg.resume).is_dir():
        raise ConfigError(f"resume={cfg.resume}: no such run directory")
    if cfg.resume and not (
        (Path(cfg.resume) / "config.yaml").is_file()
        or any(Path(cfg.resume).glob("*/model_*.pt"))
        or any(Path(cfg.resume).glob("*/latest.pt"))
    ):
        # An empty or unrelated directory would otherwise silently start a new run there.
        raise ConfigError(
            f"resume={cfg.resume}: not a march run directory (no config.yaml, no checkpoints); "
            "give the directory of a run (outputs/<date>/<time>_...)"
        )
    if cfg.compute.device.startswith("cuda"):
        import torch

        if not torch.cuda.is_available():
            raise ConfigError(
                f"compute.device={cfg.compute.device} but CUDA is not available; use compute=cpu"
            )


def policy_checkpoint(cfg: MarchConfig) -> tuple[str, str, bool] | None:
    """(kind, path, distill) of the checkpoint that defines this run's policy, if any.

    stage=eval: the evaluated checkpoint. stage=student: the teacher, whose reward set and
    observation layout the distillation env must have (the "teacher reward on student rollouts"
    is that reward); the run's own student and curriculum stay the command line's.
    """
    if cfg.stage == "eval":
        kind = cfg.eval.policy
        path = cfg.student_ckpt if kind == "student" else cfg.teacher_ckpt
        return (kind, path, False) if path else None
    if cfg.stage == "student" and cfg.teacher_ckpt:
        return "teacher", cfg.teacher_ckpt, True
    return None


def apply_policy_checkpoint(
    cfg: MarchConfig, explicit_overrides: list[str], payload: dict[str, Any] | None = None
) -> tuple[MarchConfig, list[str]]:
    """``cfg`` with its policy taken from the checkpoint it runs (march.learn.provenance), and
    one line per value the checkpoint changed. Raises ConfigError on a conflicting explicit
    command-line choice, CheckpointError on an unreadable checkpoint: before any simulation."""
    from march.learn.checkpoint import load_checkpoint
    from march.learn.provenance import apply_checkpoint_config, policy_changes

    which = policy_checkpoint(cfg)
    if which is None:
        return cfg, []
    kind, path, distill = which
    if payload is None:
        payload = load_checkpoint(path, kind, "cpu")
    new = apply_checkpoint_config(cfg, payload, explicit_overrides, path, kind, distill=distill)
    changes = policy_changes(cfg, new, kind)
    notes = [f"[checkpoint] {kind}_ckpt={path} defines the policy: {c}" for c in changes]
    return new, notes


def run_pipeline(
    cfg: MarchConfig, run_dir: Path, *, auto: bool = False, notes: list[str] | None = None
) -> dict[str, Any] | None:
    """Run the configured stage(s) in ``run_dir``; returns the final summary (if any).

    A checkpoint the stage runs defines its policy (:func:`apply_policy_checkpoint`; ``main``
    has already applied it with the command line's explicit choices). ``auto``: the compute
    preset was chosen by compute=auto (said in the banner). ``notes``: lines printed after the
    banner (main's account of what the checkpoint changed).
    """
    import torch

    from march.env.build import PLACEHOLDERS, make_env
    from march.evaluation.protocol import (
        evaluate,
        format_summary,
        policy_from_checkpoint,
        write_summary,
    )
    from march.learn.checkpoint import load_checkpoint
    from march.learn.distill import DistillRunner, student_policy
    from march.learn.metrics import truncate_rows
    from march.learn.teacher import TeacherRunner, teacher_policy

    if cfg.compute.torch_threads:
        torch.set_num_threads(cfg.compute.torch_threads)
    _seed_everything(cfg.seed)
    dev = cfg.compute.device
    # Checkpoints the user passed are read before any simulation starts.
    teacher_payload = (
        load_checkpoint(cfg.teacher_ckpt, "teacher", dev)
        if cfg.teacher_ckpt and cfg.stage in ("student", "eval")
        else None
    )
    student_payload = (
        load_checkpoint(cfg.student_ckpt, "student", dev)
        if cfg.stage == "eval" and cfg.eval.policy == "student"
        else None
    )
    # For callers other than main (tests, notebooks): the same policy, no explicit choices.
    cfg, changed = apply_policy_checkpoint(
        cfg, [], student_payload if student_payload is not None else teacher_payload
    )
    print(banner(cfg, run_dir, PLACEHOLDERS, auto), flush=True)
    for line in (notes or []) + changed:
        print(line, flush=True)
    log = EtaMetricsLog(run_dir, cfg, EtaWatch(cfg))
    teacher_path = cfg.teacher_ckpt
    summary = None
    try:
        # One eval env, built once: the teacher's evaluations during PPO and the student's.
        eval_env = make_env(cfg, "eval", log=run_dir / "env.log")

        def eval_policy(policy, stage: str, iteration: int, env_steps: int) -> dict[str, Any]:
            row = evaluate(
                eval_env, policy, cfg.eval.num_rollouts, run_dir, stage, iteration, env_steps
            )
            print(
                f"[eval] {stage} it {iteration}: distance {row['mean_distance_m']:.3g} m, success "
                f"{100 * row['mean_success_rate']:.0f}%, reward {row['mean_reward']:.3g}",
                flush=True,
            )
            return row

        def eval_teacher(actor, iteration: int, env_steps: int) -> dict[str, Any]:
            return eval_policy(teacher_policy(eval_env, actor), "teacher", iteration, env_steps)

        def eval_student(student, iteration: int, env_steps: int) -> dict[str, Any]:
            return eval_policy(student_policy(eval_env, student), "student", iteration, env_steps)

        if cfg.stage in ("all", "teacher"):
            env = make_env(cfg, "teacher", log=run_dir / "env.log")
            runner = TeacherRunner(env, cfg, run_dir, log, eval_teacher)
            runner.try_resume()
            log.eta.start("teacher", runner.iteration, runner.wall_s)
            teacher_path = str(runner.learn(cfg.teacher.iterations))
            env.close()
            del runner, env
            print(f"[teacher] done: {teacher_path}", flush=True)
        if cfg.stage == "teacher":
            eval_env.close()
            return None

        if cfg.stage in ("all", "student"):
            if teacher_payload is None:
                teacher_payload = load_checkpoint(teacher_path, "teacher", dev)
            env = make_env(cfg, "student", log=run_dir / "env.log")
            runner = DistillRunner(
                env, cfg, run_dir, log, teacher_payload, teacher_path, eval_student
            )
            runner.try_resume()
            log.eta.start("student", runner.iteration, runner.wall_s)
            student_path = runner.learn(cfg.distill.max_iterations)
            # A resumed, finished run re-does its final evaluation (same numbers: the evaluation
            # is seeded) instead of appending a second row for it.
            truncate_rows(run_dir / "eval.csv", "student", runner.iteration - 1)
            summary = eval_student(runner.student, runner.iteration, runner.env_steps)
            extra = {"student_ckpt": str(student_path), "teacher_ckpt": str(teacher_path)}
            env.close()
        else:  # stage == eval
            eval_env.reset()
            kind = cfg.eval.policy
            payload = student_payload if kind == "student" else teacher_payload
            path = cfg.student_ckpt if kind == "student" else cfg.teacher_ckpt
            policy = policy_from_checkpoint(eval_env, cfg, kind, payload, path)
            extra = {f"{kind}_ckpt": path}
            summary = evaluate(
                eval_env,
                policy,
                cfg.eval.num_rollouts,
                run_dir,
                cfg.eval.policy,
                int(payload["iteration"]),
                int(payload["env_steps"]),
            )
        eval_env.close()
        write_summary(summary, run_dir, extra)
        print("summary (mean ± standard error):\n" + format_summary(summary), flush=True)
        print(f"wrote {run_dir / 'summary.json'}", flush=True)
        return summary
    finally:
        log.close()


@hydra.main(config_path="../conf", config_name="config", version_base="1.3")
def main(dcfg: DictConfig) -> None:
    hc = HydraConfig.get()
    overrides = list(hc.overrides.task)
    auto = dcfg.compute.name == "auto"
    notes: list[str] = []
    try:
        dcfg = resolve_compute(dcfg, overrides)
        cfg = to_march_config(dcfg)
        _check_inputs(cfg)
        if not cfg.resume:  # a resumed run continues with its saved (already applied) config
            cfg, notes = apply_policy_checkpoint(cfg, overrides)
    except (ConfigError, CheckpointError) as err:
        if hc.mode == RunMode.MULTIRUN:
            # The sweep records this job as failed in its own directory (the figures list it)
            # and Hydra goes on with the others.
            job_dir = Path(hc.runtime.output_dir)
            job_dir.mkdir(parents=True, exist_ok=True)
            _write_status(
                job_dir, "failed", stage=str(dcfg.stage), error=f"{type(err).__name__}: {err}"
            )
            raise
        fail(str(err))
    run_dir = Path(cfg.resume) if cfg.resume else Path(hc.runtime.output_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    if cfg.resume and (run_dir / "config.yaml").is_file():
        # Continue with the run's own config (its sizes and seed), not today's defaults; an
        # override safe on resume applies (and goes into config.yaml), any other is refused.
        from march.config.resume import resume_config

        try:
            cfg, resumed = resume_config(run_dir, cfg, overrides)
        except ConfigError as err:
            if hc.mode == RunMode.MULTIRUN:
                raise
            fail(str(err))
        notes += resumed
        auto = False  # the run's own compute preset, whatever compute= composed to today
    OmegaConf.save(OmegaConf.structured(cfg), run_dir / "config.yaml")
    os.environ.setdefault("WANDB_MODE", "offline")
    _write_status(run_dir, "running", stage=cfg.stage, pid=os.getpid())
    try:
        run_pipeline(cfg, run_dir, auto=auto, notes=notes)
    except BaseException as err:
        _write_status(run_dir, "failed", stage=cfg.stage, error=f"{type(err).__name__}: {err}")
        # A single run ends with one clear line; in a sweep the error is raised so that Hydra
        # records this job as failed and goes on with the others.
        if hc.mode == RunMode.RUN and isinstance(
            err, (ConfigError, CheckpointError, NumericalFault)
        ):
            fail(str(err))
        raise
    _write_status(run_dir, "done", stage=cfg.stage)


if __name__ == "__main__":
    main()
