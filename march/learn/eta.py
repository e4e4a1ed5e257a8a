"""Wall-time estimate of a march.train run: the ``[eta]`` line printed once the first
iterations of a stage have been measured.

The measured teacher (or distillation) speed is scaled to the other stages per env step by rough
:data:`STEP_COSTS` (:func:`estimate_wall_s`); :class:`EtaWatch` measures the rows metrics.csv
receives and :class:`EtaMetricsLog` feeds it from the run's metrics log. On a CPU the teacher's
rollout is timed apart from its update (metrics.csv ``rollout_s``) and the other stages are scaled
from a rollout step: an evaluation step costs about a rollout step, not a rollout step plus its
share of the update, which at 8-24 steps per iteration is most of the iteration (scaled from the
whole iteration, the smoke run's [eta] said ~7 min for a 1 min run, issue 56).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from march.config import MarchConfig
from march.learn.distributed import current
from march.learn.metrics import MetricsLog

ETA_ITERATIONS = 3
"""Iterations measured before the [eta] line is printed (fewer if the stage is shorter)."""


@dataclass(frozen=True)
class StepCosts:
    """Seconds of one env step of another stage per second of one teacher env step, at equal
    env counts. The teacher step is its rollout step where the rollout is timed apart
    (:attr:`per_rollout_step`), else the whole iteration's (rollout plus its share of the
    update). Rough: the [eta] line says so, and distillation is measured again once it runs."""

    per_rollout_step: bool
    """True: the factors are per teacher rollout step (CPU, ``rollout_s``); False: per teacher
    iteration step (a GPU, whose rollout the host's clock cannot time without a sync)."""
    eval: float
    """An evaluation step: inference (and depth rendering for a student), no update."""
    distill_rollout: float
    """A distillation rollout step: depth rendering, student and teacher inference."""
    distill_epoch: float
    """The student update per rollout step and per epoch (student forward + backward)."""


STEP_COSTS = {
    # 2 CPU cores, per teacher rollout step (`rollout_s` / num_steps_per_env), measured in
    # one run each, 2026-12-06 (a loaded machine; the ratios are what is used):
    # - compute=cpu (32 envs): rollout step 0.42 s (91 % of the iteration); distillation
    #   rollout 0.56 s (1.3x) and 0.34 s per step and epoch (0.8x);
    # - compute=smoke (4 envs): rollout 0.11 s; distillation 1.8x and 0.37x; an evaluation
    #   step 0.66x at the same env count.
    # An evaluation step is taken as a rollout step (no update, no storage: an upper bound),
    # scaled by the eval envs, and its episodes as lasting eval.episode_length_s: a wave whose
    # episodes all end sooner (a policy that falls) ends sooner, so the evaluations' figure is
    # "up to". Scaled from the whole iteration instead, make train's [eta] said ~17 min for a
    # 5 min run (distillation 3.6x over) and the smoke run's ~7 min for 1 min.
    "cpu": StepCosts(per_rollout_step=True, eval=1.0, distill_rollout=1.4, distill_epoch=0.8),
    # GPU: not measured yet; the student's batched forward/backward is cheap next to 4096 envs'
    # physics, so an epoch costs a fraction of a teacher step.
    "cuda": StepCosts(per_rollout_step=False, eval=1.5, distill_rollout=1.5, distill_epoch=0.25),
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
    rollout_s_per_it: float | None = None,
    world: int = 1,
    floor_done: bool = False,
) -> dict[str, float]:
    """Expected seconds of the teacher, distillation and evaluations of ``cfg.stage`` from here.

    One measured speed is needed: the teacher's seconds per PPO iteration, or (stage=student, or
    once distillation runs) the distillation's. The other stages are scaled from it per env step
    with :data:`STEP_COSTS` of the device: from the teacher's rollout step where the factors are
    per rollout step and ``rollout_s_per_it`` (seconds of an iteration's rollout) was measured,
    else from its whole iteration (an older run's rows: an overestimate on a CPU). ``*_from``
    are the iterations already done (a resumed run). Evaluation: ceil(num_rollouts /
    (eval_num_envs x world)) waves (``world`` processes deal the rollouts between them) of
    eval.episode_length_s each, at eval_num_envs envs (step cost taken as linear in the env
    count, an overestimate on a GPU), plus one evaluation's worth for the standing floor (the
    zero action on the same rollouts, once per process's eval env; ``floor_done``: this
    process's eval env has it already, from the teacher's evaluation).
    """
    c, t, d, e = cfg.compute, cfg.teacher, cfg.distill, cfg.eval
    k = step_costs(c.device)
    distill_step_cost = k.distill_rollout + k.distill_epoch * d.num_learning_epochs
    if teacher_s_per_it is not None:
        timed = rollout_s_per_it if k.per_rollout_step and rollout_s_per_it else None
        step_s = (timed or teacher_s_per_it) / t.num_steps_per_env  # all num_envs envs
    elif distill_s_per_it is not None:
        step_s = distill_s_per_it / (d.num_steps_per_env * distill_step_cost)
    else:
        raise ValueError("estimate_wall_s needs a measured teacher or distillation speed")
    if distill_s_per_it is None:
        distill_s_per_it = step_s * d.num_steps_per_env * distill_step_cost
    if teacher_s_per_it is None:
        teacher_s_per_it = step_s * t.num_steps_per_env
    dt = cfg.env.sim_dt * cfg.env.decimation
    waves = math.ceil(e.num_rollouts / (c.eval_num_envs * max(1, world)))
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
    n_evals = n_teacher + n_student
    floor = 1 if n_evals and not floor_done else 0  # the standing floor, once per eval env
    evals = (n_evals + floor) * one_eval
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
        self.rollout_s_per_it: float | None = None  # the teacher's rollout alone (CPU)
        self.rollout_s: dict[str, list[float]] = {}  # the measured rows' ``rollout_s``
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
        rollout = row.get("rollout_s")
        if isinstance(rollout, (int, float)) and math.isfinite(rollout):
            self.rollout_s.setdefault(stage, []).append(float(rollout))
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
            timed = self.rollout_s.get(stage, [])
            if len(timed) == done:  # every measured iteration's rollout was timed
                self.rollout_s_per_it = sum(timed) / done
            est = estimate_wall_s(
                self.cfg,
                teacher_s_per_it=s_per_it,
                teacher_from=it0,
                rollout_s_per_it=self.rollout_s_per_it,
                world=current().world,
            )
            line = (
                f"[eta] measured {s_per_it:.3g} s/it over {over}: "
                f"teacher ~{format_duration(est['teacher'])}, whole run "
                f"~{format_duration(est['total'])}"
            )
            if self.cfg.stage == "all":
                line += (
                    f" (distillation ~{format_duration(est['distill'])} and evaluations up to "
                    f"~{format_duration(est['eval'])}: rough, from the teacher's speed)"
                )
            if row.get("env_steps") and it > 0:
                # env steps per iteration are constant (num_steps_per_env x envs x ranks)
                world = current().world
                envs = self.cfg.compute.num_envs * world
                ranks = f" over {world} processes" if world > 1 else ""
                line += (
                    f"; {int(row['env_steps']) / it / s_per_it:.4g} env steps/s "
                    f"({envs} envs{ranks})"
                )
        else:
            # Evaluations scale with the teacher's speed when it was measured in this process.
            est = estimate_wall_s(
                self.cfg,
                teacher_s_per_it=self.teacher_s_per_it,
                distill_s_per_it=s_per_it,
                teacher_from=self.cfg.teacher.iterations,
                distill_from=it0,
                rollout_s_per_it=self.rollout_s_per_it,
                world=current().world,
                # the teacher ran here and evaluated its last iteration: the floor is cached
                floor_done=self.teacher_s_per_it is not None,
            )
            line = (
                f"[eta] measured {s_per_it:.3g} s/it over {over}: distillation "
                f"~{format_duration(est['distill'])}, with its evaluations up to "
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
