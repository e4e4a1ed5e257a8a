"""Synthetic MARCH run directories with known numbers, for the analysis tests.

Every source of numbers carries a distinctive value so a test can tell which rows a figure read:

* ``eval.csv`` teacher rows (every ``TEACHER_EVAL_EVERY`` teacher iterations): distance =
  ``TEACHER_EVAL_SLOPE[reward] * iteration`` + a per-seed offset that cancels over seeds 0 and 1.
* ``eval.csv`` student rows (iterations ``STUDENT_EVAL_ITS``): ``FINAL`` scaled by
  ``0.5 + 0.5 * it / 49``, so the last row equals ``summary.json`` (as in a real run).
* ``metrics.csv`` training rows: teacher ``mean_distance_m`` = ``TRAIN_DISTANCE0 + TRAIN_SLOPE * it`` (far above
  any evaluation distance, as on flat_first's flat levels), student ``teacher_reward`` =
  ``TRAIN_TEACHER_REWARD``; a figure showing them read the wrong rows.
* the standing floor (``make_run(..., floor=x)``): ``floor_distance_m`` = x and
  ``floor_se_distance_m`` = ``FLOOR_SE`` in every eval.csv row and summary.json, as evaluations
  write them since issue 56; without ``floor`` the run has none (a run from before it).
"""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd

STEPS_PER_IT = 98304  # teacher env steps per iteration
STUDENT_STEPS_PER_IT = 1000
TEACHER_EVAL_EVERY = 10
TEACHER_EVAL_SLOPE = {"clf": 0.06, "modelfree": 0.03}  # m per teacher iteration
TEACHER_ITERS = {"clf": 60, "modelfree": 120}  # modelfree trains 2x (the baseline arm)
SEED_OFF = {0: -0.1, 1: 0.1, 2: 0.0}
TRAIN_DISTANCE0 = 50.0
TRAIN_SLOPE = {"clf": 1.0, "modelfree": 2.0}  # m per teacher iteration in metrics.csv
TRAIN_TEACHER_REWARD = -500.0
STUDENT_ITERS = 50
STUDENT_EVAL_ITS = (0, 25, 49)
EVAL_SE = 0.05
RUN_SE = 0.3  # rollout SE in summary.json
FLOOR_SE = 0.008  # the standing floor's rollout SE [m]
KEYS = ["distance_m", "success_rate", "abs_torque_nm", "abs_ang_jerk", "reward"]
# final evaluation per (reward, variant, seed): distance, success, torque, jerk, return.
# Seed means: clf/full (4.0, 0.8, 8.8, 30.5, 1.5), modelfree/full (3.2, 0.4, 10.0, 50.0, 1.2).
FINAL = {
    ("clf", "full", 0): (3.8, 0.7, 8.6, 30.0, 1.4),
    ("clf", "full", 1): (4.2, 0.9, 9.0, 31.0, 1.6),
    ("clf", "full", 2): (4.0, 0.8, 8.8, 30.5, 1.5),
    ("modelfree", "full", 0): (3.0, 0.3, 9.5, 45.0, 1.1),
    ("modelfree", "full", 1): (3.4, 0.5, 10.5, 55.0, 1.3),
    ("clf", "no_transformer", 0): (3.6, 0.6, 9.68, 36.6, 1.2),
    ("clf", "no_mdn", 0): (3.0, 0.4, 11.0, 45.75, 0.9),
}


def config_yaml(
    reward: str, variant: str, seed: int, stage: str = "all", extra: dict | None = None
) -> str:
    """A run's config.yaml; ``extra`` (nested) is merged over it (e.g. ``{"eval": {"pushes":
    False}}``, ``{"compute": {"name": "gpu"}}``)."""
    from omegaconf import OmegaConf

    curriculum = "flat_first" if reward == "modelfree" else "stones"
    cfg = {
        "reward": {"name": reward},
        "student": {"variant": variant},
        "curriculum": {"name": curriculum},
        "seed": seed,
        "stage": stage,
        "compute": {"name": "smoke"},
    }
    merged = OmegaConf.merge(OmegaConf.create(cfg), OmegaConf.create(extra or {}))
    return OmegaConf.to_yaml(merged)


def teacher_train_rows(reward: str, n_iter: int) -> list[dict]:
    return [
        {
            "stage": "teacher",
            "iteration": it,
            "env_steps": it * STEPS_PER_IT,
            "wall_s": 0.5 * it,
            "mean_reward": 0.5 * it,
            "mean_episode_length": 100 + it,
            "mean_distance_m": TRAIN_DISTANCE0 + TRAIN_SLOPE[reward] * it,
            "value_loss": 0.1,
            "surrogate_loss": -0.01,
            "entropy": 1.0,
            "learning_rate": 5e-5,
        }
        for it in range(n_iter)
    ]


def student_train_rows(n_iter: int = STUDENT_ITERS) -> list[dict]:
    return [
        {
            "stage": "student",
            "iteration": it,
            "env_steps": it * STUDENT_STEPS_PER_IT,
            "wall_s": 0.1 * it,
            "mean_reward": 0.2,
            "mean_episode_length": 300,
            "mean_distance_m": TRAIN_DISTANCE0,
            "loss": 1.0 / (it + 1),
            "action_error": 0.1,
            "teacher_reward": TRAIN_TEACHER_REWARD,
        }
        for it in range(n_iter)
    ]


def teacher_eval_distance(reward: str, seed: int, it: int) -> float:
    return TEACHER_EVAL_SLOPE[reward] * it + SEED_OFF[seed]


def _eval_row(stage: str, it: int, steps: int, values: dict[str, float]) -> dict:
    row = {"stage": stage, "iteration": it, "env_steps": steps, "n_rollouts": 64}
    for k in KEYS:
        row[f"mean_{k}"] = values[k]
        row[f"se_{k}"] = EVAL_SE
    # The ablation metric: the return over a 50-step episode, per step.
    row["mean_reward_per_step"] = values["reward"] / 50.0
    row["se_reward_per_step"] = EVAL_SE / 50.0
    row["n_torque"] = 64  # extra count columns at the end (rollouts long enough for the metric)
    row["n_jerk"] = 63
    return row


def teacher_eval_rows(reward: str, seed: int, n_iter: int) -> list[dict]:
    rows = []
    for it in range(0, n_iter, TEACHER_EVAL_EVERY):
        d = teacher_eval_distance(reward, seed, it)
        values = {
            "distance_m": d,
            "success_rate": min(1.0, d / 4.0),
            "abs_torque_nm": 20.0,
            "abs_ang_jerk": 80.0,
            "reward": 10.0 * d,
        }
        rows.append(_eval_row("teacher", it, it * STEPS_PER_IT, values))
    return rows


def student_eval_value(reward: str, variant: str, seed: int, key: str, it: int) -> float:
    return FINAL[(reward, variant, seed)][KEYS.index(key)] * (0.5 + 0.5 * it / 49)


def student_eval_rows(reward: str, variant: str, seed: int) -> list[dict]:
    return [
        _eval_row(
            "student",
            it,
            it * STUDENT_STEPS_PER_IT,
            {k: student_eval_value(reward, variant, seed, k, it) for k in KEYS},
        )
        for it in STUDENT_EVAL_ITS
    ]


def make_run(
    d: Path,
    reward: str,
    variant: str,
    seed: int,
    *,
    stage: str = "all",
    hydra_only: bool = False,
    state: str = "done",
    teacher_iters: int | None = None,
    student: bool = True,
    final: bool = True,
    truncate: bool = False,
    status: bool = True,
    extra: dict | None = None,
    floor: float | None = None,
) -> Path:
    """One run dir. stage "student" runs (the ablation sweep: a fixed teacher checkpoint) and
    stage "eval" runs have no teacher rows; ``teacher_iters`` defaults to TEACHER_ITERS[reward]."""
    d.mkdir(parents=True)
    cfg = config_yaml(reward, variant, seed, stage, extra)
    if hydra_only:
        (d / ".hydra").mkdir()
        (d / ".hydra" / "config.yaml").write_text(cfg)
    else:
        (d / "config.yaml").write_text(cfg)
    n_teacher = 0 if stage in ("student", "eval") else (teacher_iters or TEACHER_ITERS[reward])
    rows = teacher_train_rows(reward, n_teacher) + (student_train_rows() if student else [])
    if rows:  # a stage=eval run writes no metrics.csv
        text = pd.DataFrame(rows).to_csv(index=False)
        if truncate:
            text += "teacher,30,2949120,15.0,1"  # cut off mid-row, no newline
        (d / "metrics.csv").write_text(text)
    evals = teacher_eval_rows(reward, seed, n_teacher)
    if student:
        evals += student_eval_rows(reward, variant, seed)
    floor_cols = (
        {} if floor is None else {"floor_distance_m": floor, "floor_se_distance_m": FLOOR_SE}
    )
    evals = [{**row, **floor_cols} for row in evals]
    if evals:
        pd.DataFrame(evals).to_csv(d / "eval.csv", index=False)
    if final:
        summary = {
            "stage": "student",
            "iteration": STUDENT_ITERS - 1,
            "env_steps": (STUDENT_ITERS - 1) * STUDENT_STEPS_PER_IT,
            "n_rollouts": 64,
            "n_torque": 64,
            "n_jerk": 63,
        }
        for k, v in zip(KEYS, FINAL[(reward, variant, seed)], strict=True):
            summary[f"mean_{k}"] = v
            summary[f"se_{k}"] = RUN_SE
        summary.update(floor_cols)
        (d / "summary.json").write_text(json.dumps(summary))
    if status:
        error = "RuntimeError: simulated crash in PPO update" if state == "failed" else None
        (d / "status.json").write_text(json.dumps({"state": state, "error": error}))
    return d


def build_tree(root: Path) -> tuple[Path, Path]:
    """A baseline sweep (clf, modelfree x seeds 0, 1) and an ablation sweep (clf students full
    seed 2, no_transformer, no_mdn; one crashed in the teacher stage, one without status)."""
    base = root / "sweep_base"
    base.mkdir(parents=True)
    (base / "multirun.yaml").write_text("hydra:\n  mode: MULTIRUN\n")
    make_run(base / "0", "clf", "full", 0)
    make_run(base / "1", "clf", "full", 1, hydra_only=True)
    make_run(base / "2", "modelfree", "full", 0)
    make_run(base / "3", "modelfree", "full", 1)
    abl = root / "sweep_abl"
    abl.mkdir()
    (abl / "multirun.yaml").write_text("hydra:\n  mode: MULTIRUN\n")
    make_run(abl / "0", "clf", "full", 2, stage="student")
    make_run(abl / "1", "clf", "no_transformer", 0, stage="student")
    make_run(abl / "2", "clf", "no_mdn", 0, stage="student")
    # crashed in its teacher stage: metrics.csv cut off mid-row, teacher eval rows at 0, 10, 20
    make_run(
        abl / "3",
        "clf",
        "no_mdn",
        2,
        state="failed",
        teacher_iters=30,
        student=False,
        final=False,
        truncate=True,
    )
    # never reported a status (killed before status.json was written)
    make_run(
        abl / "4",
        "clf",
        "no_transformer",
        1,
        teacher_iters=10,
        student=False,
        final=False,
        status=False,
    )
    return base, abl
