"""``python -m march.train``: teacher PPO -> student distillation -> evaluation.

    python -m march.train reward=clf student=full          # stage=all, compute=auto
    python -m march.train stage=student teacher_ckpt=outputs/<run>/teacher/latest.pt
    python -m march.train stage=eval student_ckpt=outputs/<run>/student/latest.pt
    python -m march.train resume=outputs/<run>               # continue a killed run
    python -m march.train -m +sweep=baseline                 # the paper's baseline comparison
    torchrun --nproc_per_node=N -m march.train ...           # one run over N processes

Returns the final evaluation's ``objective`` value (default mean_distance_m), for sweepers that
optimise (``-m +sweep=optuna_clf``).

A run directory holds config.yaml (resolved), teacher/ and student/ checkpoints, metrics.csv,
eval.csv, summary.json and status.json. A run whose directory already holds checkpoints resumes
from them by itself (this is what makes a Slurm requeue continue).
"""

from __future__ import annotations

import dataclasses
import os
import random
import socket
import sys
from pathlib import Path
from typing import Any

import hydra
import numpy as np
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from march.config import ConfigError, MarchConfig, to_march_config
from march.config.cli import (
    duplicate_overrides,
    fail,
    override_problem,
    renamed_group,
    resolve_compute,
)
from march.config.memory import check_memory
from march.config.terms import check_terms, import_extra_modules
from march.learn import distributed, preemption, tuning
from march.store import run_dir as run_files
from march.store import run_lock
from march.store.checkpoint_file import CheckpointError
from march.store.status import read_status, write_status

# torch (~250 MB resident for the import alone) and what imports it (the gate's full read, the
# metrics log, the fault guards) are imported where they are used, after the checks: a bad file
# or argument is refused without them (issue 59: one line, under 200 MB resident).


def _seed_everything(seed: int) -> None:
    import torch

    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def _write_status(run_dir: Path, state: str, **extra: Any) -> None:
    write_status(run_dir, state, **extra)


def banner(
    cfg: MarchConfig, run_dir: Path, placeholders: dict[str, str], auto: bool = False
) -> str:
    """The start banner: what runs, at which scale (and why), where, and when wall time shows."""
    from march.learn.eta import ETA_ITERATIONS

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
    dist = distributed.current()
    if dist.active:
        lines.insert(
            3,
            f"distributed: {dist.world} ranks ({dist.backend}); compute.num_envs={c.num_envs} "
            f"per rank, {dist.world * c.num_envs} envs in total; eval waves split over the "
            f"ranks; rank seeds from seed={cfg.seed}",
        )
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


def run_pipeline(
    cfg: MarchConfig, run_dir: Path, *, auto: bool = False, notes: list[str] | None = None
) -> dict[str, Any] | None:
    """Run the configured stage(s) in ``run_dir``; returns the final summary (stage=teacher: the
    teacher's final evaluation row; None if a finished stage was resumed without one).

    A checkpoint the stage runs defines its policy (:func:`apply_policy_checkpoint`; ``main``
    has already applied it with the command line's explicit choices). ``auto``: the compute
    preset was chosen by compute=auto (said in the banner). ``notes``: lines printed after the
    banner (main's account of what the checkpoint changed).
    """
    import torch

    from march.env.build import PLACEHOLDERS, make_env
    from march.evaluation.protocol import evaluate, policy_from_checkpoint
    from march.evaluation.summary import eval_line, format_summary, write_summary
    from march.learn.distill import DistillRunner, student_policy
    from march.learn.eta import EtaMetricsLog, EtaWatch
    from march.learn.metrics import truncate_rows
    from march.learn.teacher import TeacherRunner, teacher_policy
    from march.store.gate import apply_policy_checkpoint, read_checkpoint

    if cfg.compute.torch_threads:
        torch.set_num_threads(cfg.compute.torch_threads)
    _seed_everything(cfg.seed)
    dev = cfg.compute.device
    # Checkpoints the user passed are read (through the gate) before any simulation starts.
    named = cfg.extra_modules
    teacher_payload = (
        read_checkpoint(cfg.teacher_ckpt, "teacher", named, dev)[0]
        if cfg.teacher_ckpt and cfg.stage in ("student", "eval")
        else None
    )
    student_payload = (
        read_checkpoint(cfg.student_ckpt, "student", named, dev)[0]
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
    env_log = run_dir / "env.log" if distributed.writes_files() else None
    teacher_path = cfg.teacher_ckpt
    summary = None
    last_eval: dict[str, dict[str, Any]] = {}
    try:
        # One eval env, built once: the teacher's evaluations during PPO and the student's.
        # ... with the run's seed on every rank (its startup randomisation is part of the
        # protocol; an evaluation's waves then do not depend on the rank that runs them).
        eval_cfg = dataclasses.replace(cfg, seed=distributed.agree(cfg.seed))
        eval_env = make_env(eval_cfg, "eval", log=env_log)

        def eval_policy(policy, stage: str, iteration: int, env_steps: int) -> dict[str, Any]:
            row = evaluate(
                eval_env,
                policy,
                cfg.eval.num_rollouts,
                run_dir,
                stage,
                iteration,
                env_steps,
                sees_depth=stage == "student",
            )
            print(eval_line(row), flush=True)  # the distance beside the standing floor
            # An Optuna trial (hydra/sweeper=march_optuna): report, maybe stop here (pruned).
            # The run's last evaluation is the trial's value, never the pruner's to cut.
            step, final = trial_step(cfg, stage, iteration)
            tuning.report(float(row[cfg.objective]), step, final=final)
            return row

        def eval_teacher(actor, iteration: int, env_steps: int) -> dict[str, Any]:
            row = eval_policy(teacher_policy(eval_env, actor), "teacher", iteration, env_steps)
            last_eval["teacher"] = row
            return row

        def eval_student(student, iteration: int, env_steps: int) -> dict[str, Any]:
            return eval_policy(student_policy(eval_env, student), "student", iteration, env_steps)

        if cfg.stage in ("all", "teacher"):
            env = make_env(cfg, "teacher", log=env_log)
            runner = TeacherRunner(env, cfg, run_dir, log, eval_teacher)
            runner.try_resume()
            log.eta.start("teacher", runner.iteration, runner.wall_s)
            teacher_path = str(runner.learn(cfg.teacher.iterations))
            env.close()
            del runner, env
            print(f"[teacher] done: {teacher_path}", flush=True)
        if cfg.stage == "teacher":
            eval_env.close()
            return last_eval.get("teacher")  # the stage's final evaluation (for a sweeper)

        if cfg.stage in ("all", "student"):
            if teacher_payload is None:  # the run's own teacher, just written
                teacher_payload = read_checkpoint(teacher_path, "teacher", named, dev)[0]
            env = make_env(cfg, "student", log=env_log)
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
                sees_depth=kind == "student",
            )
        eval_env.close()
        write_summary(summary, run_dir, extra)
        print("summary (mean ± standard error):\n" + format_summary(summary), flush=True)
        print(f"wrote {run_dir / 'summary.json'}", flush=True)
        return summary
    finally:
        log.close()


def trial_step(cfg: MarchConfig, stage: str, iteration: int) -> tuple[int, bool]:
    """(the Optuna step, whether it is the run's last evaluation) of an evaluation of ``stage``
    at ``iteration``: the student's steps follow the teacher iterations that ran
    (``teacher.iterations``, the budget scale applied), so no two evaluations share a step."""
    step = iteration + (cfg.teacher.iterations if stage == "student" else 0)
    last = cfg.distill.max_iterations if stage == "student" else cfg.teacher.iterations
    return step, iteration >= last and (stage == "student" or cfg.stage == "teacher")


@hydra.main(config_path="../conf", config_name="config", version_base="1.3")
def main(dcfg: DictConfig) -> float | None:
    hc = HydraConfig.get()
    overrides = list(hc.overrides.task)
    auto = dcfg.compute.name == "auto"
    notes: list[str] = []
    try:
        dcfg = resolve_compute(dcfg, overrides)
        import_extra_modules(dcfg.get("extra_modules") or [])  # plug-ins before the checks
        cfg = to_march_config(dcfg)
        _check_inputs(cfg)
        if not cfg.resume:  # a resumed run continues with its saved (already applied) config
            from march.store.gate import apply_policy_checkpoint

            cfg, notes = apply_policy_checkpoint(cfg, overrides)
        # Every reward term known, its params valid (one line). After the files and the
        # checkpoint: the term registry imports the simulator (~5 s), so a missing file or a
        # refused checkpoint is told in ~2 s, and the terms checked are the ones that will run.
        check_terms(cfg)
    except (ConfigError, CheckpointError) as err:
        job_dir = Path(hc.runtime.output_dir)
        if hc.mode == RunMode.MULTIRUN:
            # The sweep records this job as failed in its own directory (the figures list it)
            # and Hydra goes on with the others; another run's directory is left alone.
            if not run_files.holds_run(job_dir):
                job_dir.mkdir(parents=True, exist_ok=True)
                _write_status(
                    job_dir, "failed", stage=str(dcfg.stage), error=f"{type(err).__name__}: {err}"
                )
            raise
        run_files.drop_refused(job_dir)
        fail(str(err))
    # N processes (torchrun, srun): join the group; rank 0's run directory is everyone's.
    dist = distributed.init(cfg.compute.device, cfg.compute.dist_timeout_s)
    run_dir = Path(cfg.resume) if cfg.resume else Path(hc.runtime.output_dir)
    run_dir = Path(distributed.agree(str(run_dir)))
    run_dir.mkdir(parents=True, exist_ok=True)
    option = "resume" if cfg.resume else "hydra.run.dir"
    try:
        if dist.main:  # one writer per run directory, for the whole run; no link written through
            notes += run_files.claim(run_dir, option)
        status = read_status(run_dir)
        if status and status.get("note"):  # e.g. "running" with its pid gone: it was killed
            notes.append(f"[status] {status['note']}")
        if cfg.resume and (run_dir / "config.yaml").is_file():
            # Continue with the run's own config (its sizes and seed), not today's defaults; an
            # override safe on resume applies (and goes into config.yaml), any other is refused.
            from march.store.resume_rules import resume_config

            cfg, resumed = resume_config(run_dir, cfg, overrides)
            notes += resumed
            auto = False  # the run's own compute preset, whatever compute= composed to today
        elif run_files.holds_run(run_dir):  # a new run pointed at a run: the same comparison
            from march.store.resume_rules import adopt_config

            if not (run_dir / "config.yaml").is_file():
                raise ConfigError(
                    f"{option}={run_dir} holds a run's files but no config.yaml; a new run does "
                    "not take them over: give it its own hydra.run.dir"
                )
            cfg, adopted = adopt_config(run_dir, cfg)
            notes += adopted
        check_memory(cfg)
        # before any env; a resume only on the number of ranks that wrote it
        notes += run_files.check_run_checkpoints(run_dir, cfg, option, distributed.world_mismatch)
    except (ConfigError, CheckpointError) as err:
        run_lock.release_all()  # ours only (a lock another process holds was never ours)
        if hc.mode == RunMode.MULTIRUN:
            raise
        run_files.drop_refused(Path(hc.runtime.output_dir))  # the one Hydra made, not the run's
        fail(str(err))
    # Ranks > 0 print into <run>/ranks/rank<r>.log, once the run is accepted: a refused one
    # (another rank count, a conflicting override) has said so on each rank's own stderr and
    # written nothing into the run directory.
    distributed.rank_log(run_dir)
    distributed.barrier()  # every rank has read config.yaml before rank 0 rewrites it
    from march.learn.faults import NumericalFault
    from march.store.checkpoint import write_text_durably

    if dist.main:
        write_text_durably(run_dir / "config.yaml", OmegaConf.to_yaml(OmegaConf.structured(cfg)))
    os.environ.setdefault("WANDB_MODE", "offline")
    _write_status(run_dir, "running", stage=cfg.stage, pid=os.getpid(), host=socket.gethostname())
    preemption.install(immediate=cfg.stage == "eval")
    try:
        tuning.begin()  # an Optuna trial: alive from now on; one the study gave up is not run
        summary = run_pipeline(distributed.rank_config(cfg), run_dir, auto=auto, notes=notes)
        if dist.main:
            _write_status(run_dir, "done", stage=cfg.stage)
        tuning.finish(None if summary is None else float(summary[cfg.objective]))
    except preemption.Preempted as stop:
        preemption.exit_preempted(stop, lambda state, **kw: _write_status(run_dir, state, **kw))
    except BaseException as err:
        if tuning.is_pruned(err):  # an Optuna trial stopped by the study's pruner: recorded
            _write_status(run_dir, "pruned", stage=cfg.stage, error=str(err))
            tuning.pruned()  # PRUNED in the study; an outcome, not the job's error
            return None
        tuning.failed(err)  # an Optuna trial: FAIL with this error (rank 0, before any abort)
        if lost := distributed.lost_rank(err):  # a dead or hung rank: stop now, in one line
            _write_status(run_dir, "failed", stage=cfg.stage, error=lost)
            distributed.abort()  # no teardown collective: the others may be gone
            fail(f"{lost}; the run's checkpoints are in {run_dir}: resume={run_dir}")
        _write_status(run_dir, "failed", stage=cfg.stage, error=f"{type(err).__name__}: {err}")
        # A single run ends with one clear line; in a sweep the error is raised so that Hydra
        # records this job as failed and goes on with the others.
        if hc.mode == RunMode.RUN and isinstance(
            err, (ConfigError, CheckpointError, NumericalFault)
        ):
            fail(str(err))
        raise
    finally:
        tuning.end()
        preemption.uninstall()
        distributed.shutdown()  # after this every process reads as rank 0: decide before
        run_lock.release_all()  # the run's last write is done (a sweep's next job may start)
    # What a sweeper optimises: the final evaluation's objective (None without one).
    return None if summary is None else float(summary[cfg.objective])


def _rank_argv(argv: list[str]) -> list[str]:
    """Ranks > 0 of a torchrun / srun launch keep Hydra's own files out of the run: their Hydra
    output directory is a throw-away temporary one (rank 0's is the run directory, which every
    rank is told once the group is up)."""
    rank, world, _ = distributed.env_world()
    if world <= 1 or rank == 0:
        return argv
    import atexit
    import shutil
    import tempfile

    tmp = tempfile.mkdtemp(prefix=f"march-rank{rank}-")
    atexit.register(shutil.rmtree, tmp, True)
    own = ("hydra.run.dir=", "hydra.output_subdir=")  # rank 0's: replaced, not set twice
    kept = [a for a in argv if not a.lstrip("+").startswith(own)]
    return [*kept, f"hydra.run.dir={tmp}", "hydra.output_subdir=null"]


def _resume_argv(argv: list[str]) -> list[str]:
    """A resumed run keeps Hydra's job log in its own directory. ``resume=<run>`` of a march run
    (a directory holding ``config.yaml``) runs with ``hydra.run.dir=<run>``: Hydra's job log
    appends to the run's ``train.log``, and ``hydra.output_subdir=null`` leaves the run's
    ``.hydra/`` as its first launch wrote it. Otherwise every resume left a new folder under
    ``outputs/`` holding a job log and a ``.hydra/`` of its own. Left alone: sweeps (``-m``),
    a command that sets the Hydra directory itself (ranks > 0 of a torchrun job, tests), and a
    ``resume=`` that names no march run (refused later with one line, nothing created)."""
    from march.config.sweeps import MULTIRUN_FLAGS

    args = [a.lstrip("+") for a in argv[1:]]
    if any(a in MULTIRUN_FLAGS for a in args):
        return argv
    if any(a.startswith(("hydra.run.dir=", "hydra.output_subdir=")) for a in args):
        return argv
    runs = [a.split("=", 1)[1] for a in args if a.startswith("resume=")]
    if not runs or not (Path(runs[-1]) / "config.yaml").is_file():
        return argv
    return [*argv, f"hydra.run.dir={runs[-1]}", "hydra.output_subdir=null"]


if __name__ == "__main__":
    from march.config.sweeps import MULTIRUN_FLAGS, sweep_problem

    if problem := sweep_problem(sys.argv[1:]):
        fail(problem)
    if problem := duplicate_overrides(sys.argv[1:]) or renamed_group(sys.argv[1:]):
        fail(problem)
    argv = _resume_argv(_rank_argv(sys.argv))
    multirun = any(a in MULTIRUN_FLAGS for a in argv[1:])
    rank0 = distributed.env_world()[0] == 0
    try:  # the files handed in, without torch: composing compute=auto imports it (issue 59)
        run_files.check_files_before_hydra(argv, multirun, rank0)
    except ConfigError as err:
        fail(str(err))
    if problem := override_problem(sys.argv[1:]):  # Hydra's refusals, in one line (issue 59)
        fail(problem)
    try:  # the output directory, and a run already there locked, before Hydra writes anything
        sys.argv = run_files.before_hydra(argv, multirun=multirun, rank0=rank0)
    except ConfigError as err:
        fail(str(err))
    main()
