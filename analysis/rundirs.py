"""Find MARCH run directories and load what they hold (config, status, CSVs, summary).

A run is a directory holding ``config.yaml`` (the resolved config) or ``.hydra/config.yaml``; a
Hydra sweep directory (``multirun.yaml`` + ``0/``, ``1/``, ...) is searched, never taken as a run.
CSV files cut off mid-write or with malformed rows still load (the bad rows are dropped and named
in the run's ``issues``); an ``eval.csv`` written by an older version with fewer columns loads with
the columns it has.

Every file is read once through march's gate (:mod:`march.store.bounded_read`): no symbolic
link, its size bounded before it is read, ``config.yaml`` with no YAML anchor, alias or tag
(checked on the parser's events before OmegaConf builds it: a "billion laughs" file never
expands), ``summary.json`` strict. A file the gate refuses raises
:class:`~march.store.bounded_read.FileRefused` (one line naming it: the figures stop there);
one that is only cut short or not valid text is a run issue, as before.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd
from omegaconf import OmegaConf

from march.store.bounded_read import (
    MAX_SUMMARY_BYTES,
    FileRefused,
    NotParsed,
    read_json,
    read_yaml_text,
)
from march.store.run_tables import read_table
from march.store.status import read_status

STRING_COLUMNS = {"stage"}  # as march.store.run_tables.TEXT_COLUMNS


@dataclass
class Run:
    path: Path
    label: str = ""
    reward: str = "?"
    variant: str = "?"
    curriculum: str = "?"
    seed: object = None
    stage: str = "?"
    compute: str = "?"
    teacher_budget: object = None  # teacher.max_iterations x teacher.budget_scale
    distill_budget: object = None  # distill.max_iterations
    budget_scale: object = None
    observe_reference: bool = False
    checkpoints: str = ""  # teacher_ckpt|student_ckpt a stage student / eval run started from
    mtime: float = 0.0  # newest of the run's files: "the newest run" of duplicates
    levels: pd.DataFrame | None = None  # eval_levels.csv
    rollouts: pd.DataFrame | None = None  # eval_rollouts.csv
    state: str = "no status.json"
    error: str | None = None
    metrics: pd.DataFrame | None = None
    evals: pd.DataFrame | None = None
    summary: dict | None = None
    issues: list[str] = field(default_factory=list)
    csv_problem: bool = False
    meta: dict = field(default_factory=dict)  # group -> {label, color, order} from config.yaml
    figures: dict = field(default_factory=dict)  # the run's figures.* config (comparisons)
    config: dict = field(default_factory=dict)  # the whole config.yaml, flattened (groups)

    @property
    def complete(self) -> bool:
        needs_summary = self.stage != "teacher"
        return (
            self.state == "done"
            and (self.summary is not None or not needs_summary)
            and not self.csv_problem
        )

    @property
    def status_label(self) -> str:
        if self.complete:
            return "complete"
        if self.state == "done":
            if self.stage != "teacher" and self.summary is None:
                return "incomplete (done, no summary.json)"
            return "incomplete (unreadable CSV)"
        if self.state == "failed":
            return "failed"
        if self.state == "running":
            return "incomplete (running)"
        return f"incomplete ({self.state})"


def norm(value) -> str:
    """A config value as text that compares equal when the values are (10 and 10.0 alike)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        x = float(value)
        return str(int(x)) if x.is_integer() and abs(x) < 1e15 else repr(x)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(norm(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k}: {norm(v)}" for k, v in sorted(value.items())) + "}"
    return str(value)


def flatten(node, prefix: str = "") -> dict[str, str]:
    """Nested config -> {dotted key: :func:`norm` text}; an empty mapping is one value."""
    if isinstance(node, dict) and node:
        out: dict[str, str] = {}
        for k, v in node.items():
            out.update(flatten(v, f"{prefix}{k}."))
        return out
    return {prefix.rstrip("."): norm(node)} if prefix else {}


def _natural_key(name: str):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def find_run_dirs(root: Path) -> list[Path]:
    """Run dirs under ``root`` (``root`` included): dirs with config.yaml or .hydra/config.yaml.

    Sweep dirs (with multirun.yaml) are searched, not taken as runs; the search does not descend
    into a run dir, nor into hidden dirs or a ``figures`` output dir.
    """
    found: list[Path] = []
    for dirpath, dirnames, filenames in os.walk(root):
        d = Path(dirpath)
        is_sweep = "multirun.yaml" in filenames
        is_run = not is_sweep and (
            "config.yaml" in filenames or (d / ".hydra" / "config.yaml").is_file()
        )
        if is_run:
            found.append(d)
            dirnames[:] = []
            continue
        dirnames[:] = sorted(
            (n for n in dirnames if not n.startswith(".") and n != "figures"), key=_natural_key
        )
    return found


def _cfg_get(cfg, key: str):
    """``key`` (dotted) of a config read WITHOUT resolving interpolations: a value that is an
    interpolation (``${...}``, which could name an environment variable or a resolver) or is
    missing reads as None."""
    node = cfg
    for part in key.split("."):
        if not isinstance(node, dict) or part not in node:
            return None
        node = node[part]
    if isinstance(node, str) and "${" in node:
        return None
    return node


def read_csv_tolerant(path: Path) -> tuple[pd.DataFrame | None, list[str], bool]:
    """Read a run's CSV table, which may be cut off mid-write. Returns (frame or None, issues,
    problem).

    Through :func:`march.store.run_tables.read_table` (no link, bounded, every row checked):
    the header defines the columns, so a file from an older version with fewer columns loads as
    it is; a last row cut off by a kill is dropped and named; any other bad row (a field that
    is not a number, a row with other fields than its header) is no row march wrote and raises
    :class:`~march.store.bounded_read.FileRefused` (one line).
    """
    name = path.name
    table = read_table(path)
    if table is None:
        return None, [], False
    if not table.header:
        return None, [f"{name} empty"], True
    issues: list[str] = []
    problem = False
    if table.torn is not None:
        issues.append(f"{name}: last line cut off (dropped)")
        problem = True
    df = pd.DataFrame(table.rows, columns=table.header)
    for col in df.columns:
        if col not in STRING_COLUMNS:
            df[col] = pd.to_numeric(df[col].replace("", None), errors="coerce")
    if "stage" in df.columns:
        df["stage"] = df["stage"].astype(str).str.strip()
    return df.reset_index(drop=True), issues, problem


def load_run(path: Path) -> Run:
    run = Run(path=path)
    cfg_path = path / "config.yaml"
    if not os.path.lexists(cfg_path):
        cfg_path = path / ".hydra" / "config.yaml"
    try:
        if not os.path.lexists(cfg_path):  # a run killed before it wrote one: listed, not fatal
            raise NotParsed(f"{cfg_path}: no such file")
        text = read_yaml_text(cfg_path, str(cfg_path))  # a refusal (alias, link, size) raises
        cfg = OmegaConf.to_container(OmegaConf.create(text), resolve=False)
    except NotParsed as exc:
        cfg = {}
        run.issues.append(f"{cfg_path.name} unreadable ({exc})")
    except FileRefused:
        raise  # not a file march wrote: one line, the figures stop
    except Exception as exc:  # noqa: BLE001
        cfg = {}
        run.issues.append(f"{cfg_path.name} unreadable ({type(exc).__name__})")
    if not isinstance(cfg, dict):
        cfg = {}
    run.config = flatten(cfg)
    for attr, key in [
        ("reward", "reward.name"),
        ("variant", "student.variant"),
        ("curriculum", "curriculum.name"),
        ("stage", "stage"),
        ("compute", "compute.name"),
    ]:
        val = _cfg_get(cfg, key)
        if val is not None:
            setattr(run, attr, str(val))
    run.seed = _cfg_get(cfg, "seed")
    iters, scale = _cfg_get(cfg, "teacher.max_iterations"), _cfg_get(cfg, "teacher.budget_scale")
    run.budget_scale = 1.0 if scale is None else scale
    try:
        run.teacher_budget = (
            None if iters is None else round(float(iters) * float(run.budget_scale))
        )
    except (TypeError, ValueError):
        run.teacher_budget = None
    run.distill_budget = _cfg_get(cfg, "distill.max_iterations")
    run.observe_reference = bool(_cfg_get(cfg, "reward.observe_reference") or False)
    run.checkpoints = "|".join(
        str(_cfg_get(cfg, k) or "") for k in ("teacher_ckpt", "student_ckpt")
    ).strip("|")
    for group in ("reward", "student"):
        run.meta[group] = {k: _cfg_get(cfg, f"{group}.{k}") for k in ("label", "color", "order")}
    figures = _cfg_get(cfg, "figures")
    if figures is not None:
        run.figures = figures if isinstance(figures, dict) else {}

    # Through march's reader: a "running" status whose pid is gone on this host reads "killed".
    status = read_status(path)
    if status is not None and status["state"] == "unreadable":
        run.state = "unreadable status.json"
        run.issues.append(f"status.json unreadable ({status.get('error')})")
    elif status is not None:
        run.state = str(status["state"])
        run.error = status.get("error")

    for attr, fname in [("metrics", "metrics.csv"), ("evals", "eval.csv")]:
        df, issues, problem = read_csv_tolerant(path / fname)
        setattr(run, attr, df)
        run.issues.extend(issues)
        run.csv_problem |= problem
    if run.metrics is None and not (path / "metrics.csv").is_file():
        run.issues.append("metrics.csv missing")

    for attr, fname in [("levels", "eval_levels.csv"), ("rollouts", "eval_rollouts.csv")]:
        df, issues, _ = read_csv_tolerant(path / fname)  # optional files (newer runs)
        setattr(run, attr, df)
        run.issues.extend(issues)
    run.mtime = max((p.stat().st_mtime for p in path.iterdir() if p.is_file()), default=0.0)

    summary_path = path / "summary.json"
    if os.path.lexists(summary_path):
        try:
            run.summary = read_json(summary_path, str(summary_path), MAX_SUMMARY_BYTES)
        except NotParsed as exc:
            run.issues.append(f"summary.json unreadable ({exc})")
    return run


def discover(dirs: list[Path]) -> list[Run]:
    seen: set[Path] = set()
    runs: list[Run] = []
    for root in dirs:
        for d in find_run_dirs(root):
            key = d.resolve()
            if key in seen:
                continue
            seen.add(key)
            run = load_run(d)
            rel = d.resolve().relative_to(root.resolve().parent)
            run.label = str(rel)
            runs.append(run)
    return runs


def stage_rows(df: pd.DataFrame | None, stage: str, column: str | None = None):
    """Rows of ``stage`` (one per iteration, the last written wins), sorted by iteration.

    With ``column``: only rows where that column has a value. None when there are no such rows.
    A resumed run re-does rows past its checkpoint, hence "last written wins".
    """
    if df is None or "stage" not in df.columns or "iteration" not in df.columns:
        return None
    rows = df[df["stage"] == stage]
    if column is not None:
        if column not in df.columns:
            return None
        rows = rows[rows[column].notna()]
    if rows.empty:
        return None
    rows = rows.drop_duplicates("iteration", keep="last")
    return rows.sort_values("iteration", kind="stable").reset_index(drop=True)


def eval_rows(run: Run, stage: str) -> pd.DataFrame | None:
    """``eval.csv`` rows of ``stage`` ("teacher" or "student") of one run, or None."""
    return stage_rows(run.evals, stage)


def _count(df: pd.DataFrame | None, stage: str) -> int:
    if df is None or "stage" not in df.columns:
        return 0
    return int((df["stage"] == stage).sum())


def runs_frame(runs: list[Run]) -> pd.DataFrame:
    """One row per run: config keys, state, how many rows of each kind it holds, problems."""
    records = []
    for r in runs:
        records.append(
            {
                "run": r.label,
                "status": r.status_label,
                "state": r.state,
                "reward": r.reward,
                "variant": r.variant,
                "curriculum": r.curriculum,
                "seed": r.seed,
                "stage": r.stage,
                "compute": r.compute,
                "teacher_rows": _count(r.metrics, "teacher"),
                "student_rows": _count(r.metrics, "student"),
                "teacher_eval_rows": _count(r.evals, "teacher"),
                "student_eval_rows": _count(r.evals, "student"),
                "summary": r.summary is not None,
                "error": r.error or "",
                "issues": "; ".join(r.issues),
            }
        )
    return pd.DataFrame(records)
