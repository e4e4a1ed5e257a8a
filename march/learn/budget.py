"""The paper pipeline's cost in GPU hours, estimated before it runs (``python -m march.inspect
budget compute=gpu``).

Per stage (teacher, distillation, evaluation) of one run of the composed config, and per sweep
(``sweeps/*.yaml``: baseline, ablation, optuna_clf), the env steps the config asks for and the
hours they take at the speeds below, each row with the source of its speed:

- **the H100 anchor** (SPEC.md section 3, one H100, 4096 envs, bare mjlab G1):
  rough 74.0k env steps/s, rough + 32x24 depth camera 71.2k, a rough PPO iteration of 24 steps
  per env 1.59 s. The anchor's learning time per iteration is what the iteration takes beyond
  its env steps (1.59 s - 98,304 / 74.0k = 0.26 s), scaled by the batch;
- **measured** (``budget.bench=FILE``: a ``march.bench env`` JSON, e.g. the GPU check's
  ``bench_env.json``): march's teacher env speed over bare rough's on the random workload,
  applied to the anchor's rough speed (and depth speed for the student's env). Without a file,
  the newest committed bench in ``docs/results/`` (a CPU bench: its ratio is physics-bound and
  says little about a GPU's launch-bound step, which the row says);
- **measured on a GPU** (``budget.check=FILE``: a GPU check's ``gpu_check.json``): the clf
  teacher's seconds per iteration from its second iteration on, used as is when its run had the
  config's envs and steps per env.

Left out, and said so: the student's update (DAgger epochs; no figure yet), env construction and
kernel compilation (minutes per process), checkpoint writes. The figures are estimates of one GPU
of the anchor's class; a run over N GPUs divides the wall time, not the GPU hours.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from march.config import ConfigError, MarchConfig

ANCHOR = {
    "gpu": "H100",
    "num_envs": 4096,
    "rough_steps_per_s": 74.0e3,
    "rough_depth_steps_per_s": 71.2e3,
    "ppo_iteration_s": 1.59,
    "ppo_steps_per_env": 24,
}
"""SPEC.md section 3: bare mjlab G1 on one H100 at 4096 envs (measured 2026-11-22)."""
ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "docs" / "results"
SWEEPS = {
    "baseline (2 arms x 3 seeds)": [("clf", 1.0, "all")] * 3 + [("modelfree", 2.0, "all")] * 3,
    "ablation (3 students x 3 seeds)": [("clf", 0.0, "student")] * 9,
    "optuna_clf (20 trials)": [("clf", 1.0, "all")] * 20,
}
"""Each sweep's runs (``sweeps/*.yaml``): (reward, teacher budget scale, stage)."""


@dataclass
class Speeds:
    """Env steps per second of march's teacher and student envs and where they come from."""

    teacher: float
    student: float
    learn_s_per_step: float
    """PPO learning seconds per env step of a batch (the anchor's)."""
    teacher_s_per_iteration: float | None
    source: str
    ratio: float


def learn_s_per_step() -> float:
    """The anchor's PPO learning time per env step of its batch."""
    a = ANCHOR
    steps = a["num_envs"] * a["ppo_steps_per_env"]
    return (a["ppo_iteration_s"] - steps / a["rough_steps_per_s"]) / steps


def newest_bench() -> Path | None:
    files = sorted(RESULTS.glob("bench_env_*.json"), key=lambda p: p.name)
    gpu = [p for p in files if "gpu" in p.name]
    return (gpu or files or [None])[-1]


def read_json(path: Path, what: str) -> dict[str, Any]:
    """A bench / check JSON file through the gate (:func:`march.store.bounded_read.read_json`:
    no link, bounded, strict: a key given twice refused); one :class:`ConfigError` line."""
    from march.store.bounded_read import FileRefused
    from march.store.bounded_read import read_json as read_checked

    label = f"budget.{what}={path}"
    try:
        data = read_checked(Path(path), label, wanted="a JSON file python -m march.bench wrote")
    except FileRefused as err:
        raise ConfigError(str(err)) from None
    if not isinstance(data, dict):
        raise ConfigError(f"{label}: not a JSON object")
    return data


def speeds(cfg: MarchConfig, bench: Path | None, check: Path | None) -> Speeds:
    bench = bench or newest_bench()
    ratio, source = 1.0, "H100 anchor (march assumed as fast as bare rough)"
    if bench is not None:
        b = read_json(bench, "bench")
        by_w = b.get("ratio_march_vs_rough_by_workload") or {}
        r = by_w.get("random", b.get("ratio_march_vs_rough"))
        if not isinstance(r, (int, float)) or r <= 0:
            raise ConfigError(f"budget.bench={bench}: no ratio_march_vs_rough in it")
        ratio = float(r)
        source = (
            f"H100 anchor x march/rough {ratio:.2f} measured on {b.get('device')} at "
            f"{b.get('num_envs')} envs ({bench.name})"
        )
        if not str(b.get("device", "")).startswith("cuda"):
            source += "; a CPU ratio, not a GPU's, at most 1 (march adds work to rough's step)"
            ratio = min(ratio, 1.0)
    per_it = None
    if check is not None:
        c = read_json(check, "check")
        t = (c.get("results") or {}).get("teacher_clf") or {}
        envs = [a for a in (c.get("args") or {}).items() if a[0] == "train_envs"]
        if t.get("s_per_iteration") and envs and envs[0][1] == cfg.compute.num_envs:
            per_it = float(t["s_per_iteration"])
    a = ANCHOR
    return Speeds(
        teacher=a["rough_steps_per_s"] * ratio,
        student=a["rough_depth_steps_per_s"] * ratio,
        learn_s_per_step=learn_s_per_step(),
        teacher_s_per_iteration=per_it,
        source=source,
        ratio=ratio,
    )


def run_rows(
    cfg: MarchConfig, sp: Speeds, scale: float = 1.0, stage: str = "all"
) -> list[dict[str, Any]]:
    """One run's stages: teacher (``scale`` x its iterations), distillation, evaluations."""
    dt = cfg.env.sim_dt * cfg.env.decimation
    n, t, d, ev = cfg.compute.num_envs, cfg.teacher, cfg.distill, cfg.eval
    rows = []
    eval_steps = ev.num_rollouts * round(ev.episode_length_s / dt)
    if stage == "all" and scale > 0:
        its = max(1, round(t.max_iterations * scale))
        steps = its * n * t.num_steps_per_env
        if sp.teacher_s_per_iteration is not None:
            seconds, src = its * sp.teacher_s_per_iteration, "measured: GPU check s/iteration"
        else:
            seconds = steps / sp.teacher + steps * sp.learn_s_per_step
            src = "speeds above; PPO learning time: anchor"
        rows.append(_row("teacher", its, steps, seconds, src))
        n_eval = max(1, its // t.eval_interval) if t.eval_interval else 1
        rows.append(
            _row(
                "teacher evaluations",
                n_eval,
                n_eval * eval_steps,
                n_eval * eval_steps / sp.teacher,
                "speeds above",
            )
        )
    steps = d.max_iterations * n * d.num_steps_per_env
    rows.append(
        _row(
            "distillation",
            d.max_iterations,
            steps,
            steps / sp.student,
            "speeds above, depth env; rollouts only (the update is not measured)",
        )
    )
    n_eval = max(1, d.max_iterations // d.eval_interval) if d.eval_interval else 1
    rows.append(
        _row(
            "student evaluations",
            n_eval,
            n_eval * eval_steps,
            n_eval * eval_steps / sp.student,
            "speeds above, depth env",
        )
    )
    return rows


def _row(stage: str, count: int, steps: int, seconds: float, source: str) -> dict[str, Any]:
    return {
        "stage": stage,
        "count": count,
        "env_steps": steps,
        "gpu_hours": seconds / 3600.0,
        "source": source,
    }


def budget(
    cfg: MarchConfig, bench: Path | None = None, check: Path | None = None
) -> dict[str, Any]:
    """The table of :func:`run_rows` for one run and the sweeps' totals."""
    sp = speeds(cfg, bench, check)
    run = run_rows(cfg, sp)
    sweeps = []
    for name, runs in SWEEPS.items():
        hours = sum(
            r["gpu_hours"] for reward, scale, stage in runs for r in run_rows(cfg, sp, scale, stage)
        )
        sweeps.append({"sweep": name, "runs": len(runs), "gpu_hours": hours})
    return {
        "compute": cfg.compute.name,
        "num_envs": cfg.compute.num_envs,
        "anchor": ANCHOR,
        "march_vs_rough": sp.ratio,
        "speeds_source": sp.source,
        "teacher_steps_per_s": sp.teacher,
        "student_steps_per_s": sp.student,
        "run": run,
        "run_gpu_hours": sum(r["gpu_hours"] for r in run),
        "sweeps": sweeps,
        "left_out": "env construction and kernel compilation (minutes per process), the "
        "student's update, checkpoint writes",
    }


def table(report: dict[str, Any]) -> str:
    """The report as Markdown: one run's stages, then the sweeps."""
    lines = [
        f"GPU hours at compute={report['compute']} ({report['num_envs']} envs), one GPU of the "
        f"anchor's class; speeds: {report['speeds_source']}",
        "",
        "| stage | iterations / evaluations | env steps | GPU h | source |",
        "|---|---:|---:|---:|---|",
    ]
    for r in report["run"]:
        lines.append(
            f"| {r['stage']} | {r['count']} | {r['env_steps'] / 1e6:.0f} M | "
            f"{r['gpu_hours']:.2f} | {r['source']} |"
        )
    lines.append(f"| **one run (stage=all)** | | | **{report['run_gpu_hours']:.2f}** | |")
    lines += ["", "| sweep | runs | GPU h |", "|---|---:|---:|"]
    for s in report["sweeps"]:
        lines.append(f"| {s['sweep']} | {s['runs']} | {s['gpu_hours']:.1f} |")
    lines += ["", f"Left out: {report['left_out']}."]
    return "\n".join(lines)
