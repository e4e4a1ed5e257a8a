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

import os
import random
import time
from pathlib import Path
from typing import Any

import hydra
import numpy as np
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from march.cli import fail, resolve_compute
from march.config import ConfigError, MarchConfig, to_march_config
from march.learn.checkpoint import CheckpointError, write_json_atomic


def _seed_everything(seed: int) -> None:
    import torch

    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def _write_status(run_dir: Path, state: str, **extra: Any) -> None:
    write_json_atomic({"state": state, "time": time.time(), **extra}, run_dir / "status.json")


def banner(cfg: MarchConfig, run_dir: Path, placeholders: dict[str, str]) -> str:
    c, t, d, e = cfg.compute, cfg.teacher, cfg.distill, cfg.eval
    lines = [
        "=" * 78,
        f"march.train  stage={cfg.stage}  reward={cfg.reward.name}  student={cfg.student.variant}"
        f"  curriculum={cfg.curriculum.name}  dr={cfg.dr.name}  seed={cfg.seed}",
        f"scale: compute={c.name} on {c.device}: {c.num_envs} envs; teacher {t.iterations} it x "
        f"{t.num_steps_per_env} steps; distill {d.max_iterations} it x {d.num_steps_per_env} steps;"
        f" eval {e.num_rollouts} rollouts x {e.episode_length_s:g} s on {c.eval_num_envs} envs",
        f"run dir: {run_dir}",
    ]
    if placeholders:
        lines.append("placeholders (not yet the paper's method):")
        lines += [f"  - {k}: {v}" for k, v in placeholders.items()]
    lines.append("=" * 78)
    return "\n".join(lines)


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
    if cfg.compute.device.startswith("cuda"):
        import torch

        if not torch.cuda.is_available():
            raise ConfigError(
                f"compute.device={cfg.compute.device} but CUDA is not available; use compute=cpu"
            )


def run_pipeline(cfg: MarchConfig, run_dir: Path) -> dict[str, Any] | None:
    """Run the configured stage(s) in ``run_dir``; returns the final summary (if any)."""
    import torch

    from march.env.build import PLACEHOLDERS, make_env
    from march.evaluate import evaluate, format_summary, policy_from_checkpoint, write_summary
    from march.learn.checkpoint import load_checkpoint
    from march.learn.distill import DistillRunner, student_policy
    from march.learn.metrics import MetricsLog
    from march.learn.teacher import (
        TeacherRunner,
    )

    if cfg.compute.torch_threads:
        torch.set_num_threads(cfg.compute.torch_threads)
    _seed_everything(cfg.seed)
    print(banner(cfg, run_dir, PLACEHOLDERS), flush=True)
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
    log = MetricsLog(run_dir, cfg.logger, run_dir.name)
    teacher_path = cfg.teacher_ckpt
    summary = None
    try:
        if cfg.stage in ("all", "teacher"):
            env = make_env(cfg, "teacher", log=run_dir / "env.log")
            runner = TeacherRunner(env, cfg, run_dir, log)
            runner.try_resume()
            teacher_path = str(runner.learn(cfg.teacher.iterations))
            env.close()
            del runner, env
            print(f"[teacher] done: {teacher_path}", flush=True)
        if cfg.stage == "teacher":
            return None

        eval_env = make_env(cfg, "eval", log=run_dir / "env.log")

        def eval_student(student, iteration: int, env_steps: int) -> dict[str, Any]:
            row = evaluate(
                eval_env,
                student_policy(eval_env, student),
                cfg.eval.num_rollouts,
                run_dir,
                "student",
                iteration,
                env_steps,
            )
            print(
                f"[eval] it {iteration}: distance {row['mean_distance_m']:.3g} m, success "
                f"{100 * row['mean_success_rate']:.0f}%, reward {row['mean_reward']:.3g}",
                flush=True,
            )
            return row

        if cfg.stage in ("all", "student"):
            if teacher_payload is None:
                teacher_payload = load_checkpoint(teacher_path, "teacher", dev)
            env = make_env(cfg, "student", log=run_dir / "env.log")
            runner = DistillRunner(
                env, cfg, run_dir, log, teacher_payload, teacher_path, eval_student
            )
            runner.try_resume()
            student_path = runner.learn(cfg.distill.max_iterations)
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
    try:
        dcfg = resolve_compute(dcfg, list(hc.overrides.task))
        cfg = to_march_config(dcfg)
        _check_inputs(cfg)
    except ConfigError as err:
        if hc.mode == RunMode.MULTIRUN:
            raise
        fail(str(err))
    run_dir = Path(cfg.resume) if cfg.resume else Path(hc.runtime.output_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    if cfg.resume and (run_dir / "config.yaml").is_file():
        # Continue with the run's own config (its sizes and seed), not today's defaults.
        saved = to_march_config(
            OmegaConf.merge(
                OmegaConf.structured(MarchConfig), OmegaConf.load(run_dir / "config.yaml")
            )
        )
        saved.resume = cfg.resume
        cfg = saved
    OmegaConf.save(OmegaConf.structured(cfg), run_dir / "config.yaml")
    os.environ.setdefault("WANDB_MODE", "offline")
    _write_status(run_dir, "running", stage=cfg.stage, pid=os.getpid())
    try:
        run_pipeline(cfg, run_dir)
    except BaseException as err:
        _write_status(run_dir, "failed", stage=cfg.stage, error=f"{type(err).__name__}: {err}")
        # A single run ends with one clear line; in a sweep the error is raised so that Hydra
        # records this job as failed and goes on with the others.
        if hc.mode == RunMode.RUN and isinstance(err, (ConfigError, CheckpointError)):
            fail(str(err))
        raise
    _write_status(run_dir, "done", stage=cfg.stage)


if __name__ == "__main__":
    main()
