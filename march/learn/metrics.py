"""Per-iteration metrics: metrics.csv (always), plus tensorboard or wandb when selected."""

from __future__ import annotations

import csv
import errno
import math
import os
import time
from pathlib import Path
from typing import IO, Any

from march.config import ConfigError, LoggerCfg
from march.config.schema import EVAL_METRICS
from march.learn.distributed import writes_files
from march.store.bounded_read import FileRefused, read_bytes
from march.store.checkpoint import replace_durably, write_text_durably
from march.store.run_tables import MAX_TABLE_BYTES, Table, read_table

METRIC_COLUMNS = (
    "stage",
    "iteration",
    "env_steps",
    "wall_s",
    # seconds this iteration spent in its rollout (env steps and inference; the rest of wall_s's
    # increment is the update); CPU runs only, empty on a GPU (march.learn.stage_runner)
    "rollout_s",
    "mean_reward",
    "mean_episode_length",
    "mean_distance_m",
    "mean_terrain_level",  # mean curriculum level over the training envs after the iteration
    "terrain_level_std",  # their spread (standard deviation over the envs)
    "value_loss",
    "surrogate_loss",
    "entropy",
    "learning_rate",
    "action_std",
    "kl_normaliser",  # teacher: KL of the normaliser updates alone (march.learn.teacher)
    "loss",
    "action_error",
    "teacher_reward",
    "mode_weight_0",
    "mode_weight_1",
    "nonfinite_resets",  # envs reset for a NaN or inf in their state, observation, action or reward
    "nonfinite_updates",  # updates undone for a non-finite loss or parameter (march.learn.faults)
    "touchdowns",  # teacher, reward=clf: touchdowns in the iteration (all envs)
    "deferred_replans",  # teacher, reward=clf: env-steps a due touchdown / timeout waited for
    # the planner batch in the iteration (>= the replans deferred; march.env.replan_queue)
)

EVAL_COLUMNS = (
    ("stage", "iteration", "env_steps", "n_rollouts")
    + tuple(f"{p}_{m}" for m in EVAL_METRICS for p in ("mean", "se"))
    + ("n_torque", "n_jerk", "n_torque_success", "n_jerk_success", "deferred_replans")
)
"""eval.csv: one row per evaluation. ``stage`` is teacher (the teacher during PPO, iteration and
env_steps of the teacher) or student (during distillation and the final evaluation);
``n_torque`` / ``n_jerk`` count the rollouts long enough for the torque / jerk means,
``n_torque_success`` / ``n_jerk_success`` the successful ones behind ``torque_success`` /
``jerk_success`` (the same metrics over successful rollouts only: gait without falls);
``reward_per_step`` is the episode return / its control steps (the ablation metric: it does not
pay for standing); ``deferred_replans`` the env-steps a due touchdown waited for the planner
over all rollouts (0 by construction: the evaluation env plans every touchdown at once).

EVAL_LEVEL_COLUMNS (eval_levels.csv): per evaluation and difficulty level, the rollouts and the
means of success, distance, torque, jerk (all and successful rollouts).
EVAL_ROLLOUT_COLUMNS (eval_rollouts.csv): one row per rollout of every evaluation, with its
course cell (level, column): every arm of one seed runs rollout i on the same cell under the same
randomisation draws, so analysis can pair arms cell by cell."""
EVAL_LEVEL_COLUMNS = (
    "stage",
    "iteration",
    "level",
    "rollouts",
    "success",
    "distance",
    "torque",
    "jerk",
    "torque_success",
    "jerk_success",
)
EVAL_ROLLOUT_COLUMNS = (
    "stage",
    "iteration",
    "rollout",
    "level",
    "column",
    "success",
    "distance",
    "torque",
    "jerk",
    "reward",
    "reward_per_step",
    "episode_steps",
    "deferred_replans",
    "pelvis_distance",  # the pelvis's progress (the distance before issue 56; it pays a fall)
)


def open_run_file(path: Path, mode: str = "a") -> IO[str]:
    """``path`` opened for writing (``a``: append, ``w``: truncate) without following a link:
    a symbolic link there is refused in one line, and nothing is written through it."""
    how = os.O_APPEND if mode == "a" else os.O_TRUNC
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC | how, 0o644)
    except OSError as err:
        if err.errno != errno.ELOOP:
            raise
        raise _link_error(path) from None
    return os.fdopen(fd, mode, newline="")


def _link_error(path: Path) -> ConfigError:
    return ConfigError(
        f"{path} is a symbolic link; march writes no run file through a link (remove it, "
        "then continue with resume=<run dir>)"
    )


def drop_torn_row(path: Path) -> bool:
    """Drop a torn last row of the CSV ``path`` (a write a kill cut short); says so in one line.

    A row is torn when the file does not end with a line break, or when its last line has fewer
    fields than the header. Rows are appended one per iteration before that iteration's
    checkpoint, so a torn row is always past the checkpoint a resume starts from.
    """
    if not path.is_file():
        return False
    try:  # no link, bounded (march.store.bounded_read)
        data = read_bytes(path, str(path), MAX_TABLE_BYTES, "a table march.train wrote")
    except FileRefused as err:
        raise ConfigError(str(err)) from None
    if not data:
        return False
    lines = data.splitlines(keepends=True)
    last = lines[-1]
    torn = not last.endswith((b"\n", b"\r"))
    if not torn and len(lines) > 1:
        header = next(csv.reader([lines[0].decode(errors="replace")]), [])
        fields = next(csv.reader([last.decode(errors="replace")]), [])
        torn = len(fields) < len(header)
    if not torn:
        return False
    shown = last.decode(errors="replace").strip()
    shown = shown if len(shown) <= 60 else shown[:57] + "..."
    print(f"[resume] {path.name}: dropped a torn last row ({shown!r}), cut short by a kill")
    write_text_durably(path, b"".join(lines[:-1]).decode())
    return True


def truncate_rows(path: Path, stage: str, after_iteration: int) -> None:
    """Drop rows of ``stage`` past ``after_iteration`` (a resumed run re-does them), and a torn
    last row (:func:`drop_torn_row`)."""
    if not writes_files():  # N processes: rank 0 owns the run's files
        return
    if not path.is_file():
        return
    table = checked_table(path)  # every row checked before the file changes
    drop_torn_row(path)
    rows = table.rows
    keep = [r for r in rows if r["stage"] != stage or int(r["iteration"]) <= after_iteration]
    if len(keep) == len(rows):
        return
    tmp = path.with_suffix(".tmp")
    with open_run_file(tmp, "w") as f:
        writer = csv.DictWriter(f, fieldnames=table.header)
        writer.writeheader()
        writer.writerows(keep)
        f.flush()
        os.fsync(f.fileno())
    replace_durably(tmp, path)


def checked_table(path: Path) -> Table:
    """The run table ``path`` read through the gate (:func:`march.store.run_tables.read_table`:
    no link, bounded, every row checked; a torn last row left out), an empty one without the
    file; a bad row is one :class:`ConfigError` line."""
    try:
        table = read_table(path)
    except FileRefused as err:
        raise ConfigError(str(err)) from None
    return table if table is not None else Table(header=[])


def has_row(path: Path, stage: str, iteration: int) -> bool:
    """Whether ``path`` (a CSV with stage and iteration columns) holds a row of that stage and
    iteration."""
    if not path.is_file():
        return False
    return any(
        r.get("stage") == stage and r.get("iteration") == str(iteration)
        for r in checked_table(path).rows
    )


def append_row(path: Path, columns: tuple[str, ...], row: dict[str, Any]) -> None:
    """Append ``row`` under ``columns`` (:func:`append_rows` with one row)."""
    append_rows(path, columns, [row])


def append_rows(path: Path, columns: tuple[str, ...], rows: list[dict[str, Any]]) -> None:
    """Append ``rows`` under ``columns`` in one write; a file written with other columns (an
    older run being resumed) is first rewritten under the current ones, its missing values left
    empty. In a run over N processes only rank 0 writes (march.learn.distributed)."""
    if not writes_files():
        return
    if path.is_symlink():
        raise _link_error(path)
    new = not path.is_file()
    if not new:
        with path.open(newline="") as f:
            header = next(csv.reader([f.readline(1 << 20)]), None)  # its first line only
        if header is not None and header != list(columns):
            old_rows = checked_table(path).rows  # an older run's file: read through the gate
            tmp = path.with_suffix(".tmp")
            with open_run_file(tmp, "w") as f:
                writer = csv.DictWriter(f, fieldnames=list(columns), extrasaction="ignore")
                writer.writeheader()
                writer.writerows(old_rows)
                f.flush()
                os.fsync(f.fileno())
            replace_durably(tmp, path)
    # One row per iteration: flushed and fsynced before the iteration's checkpoint is written.
    with open_run_file(path, "a") as f:
        writer = csv.DictWriter(f, fieldnames=list(columns), extrasaction="ignore")
        if new:
            writer.writeheader()
        writer.writerows({k: _fmt(row.get(k)) for k in columns} for row in rows)
        f.flush()
        os.fsync(f.fileno())


def _fmt(v: Any) -> Any:
    if v is None:
        return ""
    if isinstance(v, float):
        return "" if math.isnan(v) else f"{v:.6g}"
    return v


PER_TERM_PREFIXES = ("reward/", "termination/", "loss/")
"""Columns named after the run's own terms: ``reward/<term>``, ``termination/<term>``
(march.env.term_meter) and the distillation's ``loss/<part>``. Every column a row brings that
``METRIC_COLUMNS`` lacks (these, or any other a meter adds, e.g. ``clf/...``) is added after
them as it appears: nothing a row carries is dropped."""
EXTERNAL_NAMES = {"reward/": "Episode_Reward/", "termination/": "Episode_Termination/"}
"""How tensorboard and wandb name the per-term scalars (as mjlab and rsl-rl do), under the
stage's prefix."""
STAGE_PREFIX = {"teacher": "Teacher", "student": "Distill"}
"""Each stage's scalars live under their own prefix in tensorboard and wandb, so the student's
``Distill/Episode_Reward/clf`` never lands on the teacher's curve."""


def _scalar_name(stage: str, key: str) -> str:
    head = STAGE_PREFIX.get(stage, stage.capitalize())
    for prefix, name in EXTERNAL_NAMES.items():
        if key.startswith(prefix):
            return f"{head}/{name}{key[len(prefix) :]}"
    return f"{head}/{key}"


def stage_offsets(path: Path) -> dict[str, int]:
    """stage -> the env steps of the stages metrics.csv ``path`` holds before it (in the order
    they first appear, each counted by its largest ``env_steps``): the external loggers' step
    is this offset + the row's ``env_steps``, one axis that only increases across the stages of
    a run, a resumed one included."""
    if not path.is_file():
        return {}
    order: dict[str, int] = {}
    for r in checked_table(path).rows:
        steps = float(r.get("env_steps") or 0)
        steps = int(steps) if math.isfinite(steps) else 0
        order[r["stage"]] = max(order.get(r["stage"], 0), steps)
    out, total = {}, 0
    for stage, steps in order.items():
        out[stage] = total
        total += steps
    return out


class MetricsLog:
    """metrics.csv in the run dir and the selected external logger."""

    def __init__(self, run_dir: Path, logger: LoggerCfg, run_name: str) -> None:
        self.path = run_dir / "metrics.csv"
        self.run_dir = run_dir
        self._writer: Any = None
        self._wandb: Any = None
        self._columns: tuple[str, ...] | None = None
        self._offsets: dict[str, int] = {}  # stage -> its first step on the loggers' axis
        if not writes_files():  # N processes: rank 0 alone logs
            return
        if logger.name == "tensorboard":
            from torch.utils.tensorboard import SummaryWriter

            self._writer = SummaryWriter(log_dir=str(run_dir / "tensorboard"))
        elif logger.name == "wandb":
            os.environ.setdefault("WANDB_MODE", "offline")
            import wandb  # lazy: only when selected

            self._wandb = wandb.init(
                project=logger.project, name=run_name, dir=str(run_dir), reinit=True
            )

    def resume_from(self, stage: str, iteration: int) -> None:
        truncate_rows(self.path, stage, iteration)

    def columns(self, row: dict[str, Any]) -> tuple[str, ...]:
        """METRIC_COLUMNS, then every other column the file or this row has (a student row
        keeps the teacher's per-term columns: a resumed or appended file loses none)."""
        if self._columns is None:
            self._columns = METRIC_COLUMNS
            if self.path.is_file():
                header = checked_table(self.path).header
                self._columns += tuple(c for c in header if c not in METRIC_COLUMNS)
        new = [k for k in row if k not in self._columns]
        self._columns += tuple(new)
        return self._columns

    def step(self, row: dict[str, Any]) -> int:
        """The external loggers' step of ``row``: its stage's offset (:func:`stage_offsets`,
        read once per stage after the stage's first row is in metrics.csv) + its env steps."""
        stage = row["stage"]
        if stage not in self._offsets:
            self._offsets[stage] = stage_offsets(self.path).get(stage, 0)
        return self._offsets[stage] + int(row["env_steps"])

    def log(self, row: dict[str, Any]) -> None:
        append_row(self.path, self.columns(row), row)
        if self._writer is None and self._wandb is None:
            return
        step = self.step(row)
        scalars = {
            _scalar_name(row["stage"], k): float(v)
            for k, v in row.items()
            if k != "stage"
            and isinstance(v, (int, float))
            and not (isinstance(v, float) and not math.isfinite(v))
        }
        if self._writer is not None:
            for k, v in scalars.items():
                self._writer.add_scalar(k, v, step)
        if self._wandb is not None:
            self._wandb.log(scalars, step=step)

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
        if self._wandb is not None:
            self._wandb.finish()


class Progress:
    """One console line per iteration with rate and ETA."""

    def __init__(self, stage: str, start: int, total: int) -> None:
        self.stage, self.start, self.total = stage, start, total
        self.t0 = time.time()

    def line(self, it: int, fields: dict[str, float]) -> str:
        done = it + 1 - self.start
        elapsed = time.time() - self.t0
        eta = elapsed / max(done, 1) * (self.total - it - 1)
        body = "  ".join(f"{k} {v:.3g}" for k, v in fields.items() if v == v)
        return (
            f"[{self.stage}] it {it + 1}/{self.total}  {body}  "
            f"({elapsed:.0f}s elapsed, ETA {_hms(eta)})"
        )


def _hms(s: float) -> str:
    s = int(s)
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"
