"""The prepared GPU check (issue 11): one command, one folder of JSON and CSV results.

    python scripts/gpu_check.py OUT            # on a GPU machine (compute=gpu), ~9 minutes
    python scripts/gpu_check.py OUT --cpu      # the same phases at tiny sizes on CPU (tests)
    make gpu-check [OUT=folder] [ARGS=--cpu]

Phases, each a subprocess with its own time limit (a failed or timed-out phase is recorded and
the check goes on with the phases that do not need its output):

1. ``bench``: ``python -m march.bench env`` at ``--bench-envs`` (4096) envs: the march teacher
   env against bare mjlab rough and flat, both workloads, with the profile -> ``bench_env.json``
   (at most ``--bench-timeout`` s, 330: the targets of issue 20 come first).
   The bench rewrites ``bench_env.partial.json`` after each workload (``bench.partial``): a
   bench stopped by its time limit (warp's and inductor's first compiles are minutes on a cold
   machine) still reports the workloads it finished (``completed_workloads``).
2. ``syncs``: ``scripts/sync_check.py`` at 256 envs: a teacher iteration's rollout, a
   distillation rollout, then the march teacher env and bare mjlab rough stepped alone, under
   ``torch.cuda.set_sync_debug_mode("warn")``, each sync's source line (and the march line on
   its stack) -> ``syncs.tsv`` (at most ``--sync-timeout`` s; rewritten after each part).
   Second, so that the sync list of issue 20 is never starved by the training phases on a
   cold machine.
3. ``teacher_clf``, ``teacher_modelfree``: ``march.train stage=teacher`` of each arm, stopped
   once its training time (the ``wall_s`` of ``metrics.csv``, which leaves out the env build and
   warp's kernel compilation) passes ``--teacher-seconds``; a checkpoint every iteration, so
   the last completed one is kept -> ``teacher_<arm>_curve.csv`` (the learning curve: one row
   per iteration) and ``teacher_<arm>.json`` (iterations, env steps, env steps per second).
4. ``student``: ``march.train stage=student`` from the clf teacher, ``distill.max_iterations=2``,
   which ends with the evaluation protocol on ``--eval-rollouts`` rollouts -> ``student_curve.csv``,
   ``eval.csv``, ``summary.json``.
5. ``export``: ``python -m march.export`` of that student -> ``student.onnx``, ``export.txt``.
6. ``bench_eager`` (optional: only with time to spare; skipped or stopped by the deadline, it
   fails nothing): the bench again with ``compute.compile_math=false`` -> ``bench_env_eager.json``,
   and ``compile_vs_eager`` in ``gpu_check.json``: march's env steps per second and non-physics
   time compiled and eager, per workload, i.e. whether the gpu preset's compiled maths wins on
   this GPU.

At the end ``analysis/bench_figure.py`` draws each bench JSON (``bench_env*.png``: non-physics
ms per step by category, march against bare rough and flat, the 1.5x line), listed under
``figures`` in ``gpu_check.json``.

The bench phase also counts compute ops per env step on the GPU (``bench.op_steps``) and, with
the gpu preset's ``compute.compile_math``, records what compiling cost: graphs and seconds per
compiled function and the recompiles (``compile`` in ``bench_env.json`` and ``gpu_check.json``).

``gpu_check.json`` holds every phase's command, return code, seconds and result files, the
machine (GPU name, torch/CUDA versions), the date and ``targets``: the step's speed targets as
the bench judged them and the sync targets (no march line that syncs in more than one env
step, march's env no more syncs per step than bare rough's), each met, missed or not measured, also printed one
line each at the end; ``gpu_check.csv`` one row per phase. Exit status 0 only if every phase
but an optional one the deadline skipped or stopped succeeded (a missed target does not fail
the check). Dependencies on a machine without a package index:
``../shared/gpu/README.md`` (source the bundles' ``gpu.sh`` first).
"""

from __future__ import annotations

import argparse
import csv
import datetime as dt
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # run as a script: import this checkout's march

from march.bench.targets import STEP_TARGETS, SYNC_TARGETS, verdict_lines  # noqa: E402

GPU = {
    "compute": ["compute=gpu"],
    "bench": ["compute.num_envs={bench_envs}", "bench.steps=40"]
    + ["bench.profile_steps=10", "bench.op_steps=3", "bench.rounds=2"],
    "syncs": ["compute.num_envs=256", "teacher.num_steps_per_env=8", "distill.num_steps_per_env=8"],
    "teacher": ["compute.num_envs={train_envs}", "compute.eval_num_envs=64"],
    "student": [
        "compute.num_envs={distill_envs}",
        "compute.eval_num_envs={eval_rollouts}",
        "eval.num_rollouts={eval_rollouts}",
    ],
}
"""Overrides per phase on a GPU (``{...}``: the command-line sizes)."""
CPU = {
    "compute": ["compute=smoke"],
    "bench": ["compute.num_envs=2", "bench.steps=1", "bench.warmup=0"]
    + ["bench.profile_steps=1", "bench.op_steps=1", "bench.rounds=1", "bench.threads=1"],
    "syncs": ["compute.num_envs=2", "teacher.num_steps_per_env=2", "distill.num_steps_per_env=2"],
    "teacher": ["compute.num_envs=4", "compute.eval_num_envs=2", "teacher.num_steps_per_env=4"],
    "student": [
        "compute.num_envs=2",
        "compute.eval_num_envs=2",
        "eval.num_rollouts=2",
        "eval.episode_length_s=1.0",
        "distill.num_steps_per_env=4",
    ],
}
"""The same phases at tiny sizes on CPU (``--cpu``): proves the script, measures nothing."""


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("out", nargs="?", default=os.environ.get("OUT", "outputs/gpu_check"), type=Path)
    p.add_argument("--cpu", action="store_true", help="tiny sizes on CPU (compute=smoke)")
    p.add_argument("--bench-envs", type=int, default=4096, help="envs of the env benchmark")
    p.add_argument("--train-envs", type=int, default=4096, help="envs of each teacher run")
    p.add_argument("--teacher-seconds", type=float, default=45.0, help="training time per arm [s]")
    p.add_argument("--distill-envs", type=int, default=1024, help="envs of the distillation")
    p.add_argument("--eval-rollouts", type=int, default=128, help="rollouts of the evaluation")
    p.add_argument("--phase-timeout", type=float, default=240.0, help="limit per phase [s]")
    p.add_argument(
        "--deadline",
        type=float,
        default=None,
        help="whole check [s]: later phases get what is left (540 on a GPU, 1800 with --cpu)",
    )
    p.add_argument("--skip", nargs="*", default=[], help="phases to leave out")
    p.add_argument("--sync-timeout", type=float, default=150.0, help="limit of the syncs phase [s]")
    p.add_argument(
        "--bench-timeout",
        type=float,
        default=330.0,
        help="limit of the bench phase [s]: on a cold machine it pays warp's and inductor's "
        "first compiles (~2-3 min + ~1-2 min) before its ~1.5 min of steps",
    )
    args = p.parse_args(argv)
    if args.deadline is None:  # tiny CPU sizes prove the script; a loaded CPU builds envs slowly
        args.deadline = 1800.0 if args.cpu else 540.0
    return args


def sizes(args: argparse.Namespace) -> dict[str, list[str]]:
    table = CPU if args.cpu else GPU
    fmt = {
        "bench_envs": args.bench_envs,
        "train_envs": args.train_envs,
        "distill_envs": args.distill_envs,
        "eval_rollouts": args.eval_rollouts,
    }
    return {k: [v.format(**fmt) for v in vals] for k, vals in table.items()}


def machine() -> dict[str, Any]:
    import torch

    info: dict[str, Any] = {
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "python": sys.version.split()[0],
        "torch": torch.__version__,
        "cuda": torch.version.cuda,
        "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
    }
    try:
        from importlib.metadata import version

        info["mjlab"] = version("mjlab")
        info["mujoco_warp"] = version("mujoco-warp")
    except Exception:  # noqa: BLE001 - a missing version is not a failed check
        pass
    return info


class Phase:
    """One subprocess phase: command, log, return code, seconds."""

    def __init__(self, name: str, cmd: list[str], out: Path, optional: bool = False) -> None:
        self.name, self.cmd, self.out = name, cmd, out
        self.optional = optional
        """Run only with time to spare: skipped or stopped by its limit, it fails nothing."""
        self.log = out / f"{name}.log"
        self.rc: int | None = None
        self.seconds = 0.0
        self.note = ""
        self.files: list[str] = []

    def run(self, timeout: float, stop_when: Any = None, stdout_file: Path | None = None) -> bool:
        if timeout <= 0:
            self.note = "skipped: no time left before the deadline"
            self.rc = -1
            print(f"[gpu_check] {self.name}: {self.note}", flush=True)
            return False
        """Run to the end, to ``timeout`` seconds or until ``stop_when()`` is true (then SIGTERM,
        as a Slurm preemption: checkpoints are written atomically, so the last one is whole)."""
        print(f"[gpu_check] {self.name}: {' '.join(self.cmd)}", flush=True)
        t0 = time.time()
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        with self.log.open("w") as log:
            out = stdout_file.open("w") if stdout_file else log
            try:
                proc = subprocess.Popen(self.cmd, cwd=ROOT, stdout=out, stderr=log, env=env)
                stopped = ""
                while proc.poll() is None:
                    time.sleep(0.5)
                    if time.time() - t0 > timeout:
                        stopped = f"timed out after {timeout:.0f} s"
                    elif stop_when is not None and stop_when():
                        stopped = "stopped at its budget"
                    if stopped:
                        proc.terminate()
                        try:
                            proc.wait(15)
                        except subprocess.TimeoutExpired:
                            proc.kill()
                            proc.wait()
                        break
            finally:
                if stdout_file:
                    out.close()
        self.seconds = time.time() - t0
        self.rc = proc.returncode
        self.note = stopped
        ok = self.rc == 0 or stopped == "stopped at its budget"
        print(f"[gpu_check] {self.name}: rc={self.rc} {stopped} ({self.seconds:.0f} s)", flush=True)
        return ok

    def record(self) -> dict[str, Any]:
        return {
            "phase": self.name,
            "command": " ".join(self.cmd),
            "rc": self.rc,
            "seconds": round(self.seconds, 1),
            "note": self.note,
            "log": self.log.name,
            "files": self.files,
            "optional": self.optional,
        }

    def failed(self) -> bool:
        """The phase counts against the check: a nonzero exit status, unless it is an optional
        phase that the deadline skipped or stopped."""
        if self.rc == 0:
            return False
        return not (self.optional and self.note.startswith(("skipped", "timed out")))


def read_rows(path: Path, stage: str) -> list[dict[str, str]]:
    if not path.is_file():
        return []
    with path.open() as f:
        return [r for r in csv.DictReader(f) if r.get("stage") == stage]


def write_rows(rows: list[dict[str, str]], path: Path) -> None:
    if not rows:
        return
    keys = list(rows[0])
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)


def number(text: str | None) -> float | None:
    """A CSV cell as a float; None for an empty cell (no episode ended yet: NaN in the log)."""
    try:
        return float(text) if text not in (None, "") else None
    except ValueError:
        return None


BENCH_KEYS = (
    "num_envs",
    "ratio_march_vs_rough_by_workload",
    "build_s",
    "ops_per_step",
    "ratio_ops_march_vs_rough",
    "nonphysics_ms_per_step",
    "ratio_nonphysics_march_vs_rough",
    "min_ratio_march_vs_rough",
    "targets",
    "compile",
)
"""What ``gpu_check.json`` keeps of the bench's JSON (and ``steps_per_s`` per workload)."""


def bench_results(
    out: Path, finished: bool, stem: str = "bench_env"
) -> tuple[dict[str, Any] | None, list[str], str]:
    """The bench phase's figures for ``gpu_check.json``, its result files and a note. From
    ``bench_env.json`` when the phase finished; otherwise (failed, or stopped by its time
    limit) from ``bench_env.partial.json``, which the bench rewrites after each workload, so a
    first GPU run that runs out of time still reports the workloads it finished."""
    for name, usable in ((f"{stem}.json", finished), (f"{stem}.partial.json", True)):
        path = out / name
        if not usable or not path.is_file():
            continue
        try:
            bench = json.loads(path.read_text())
            summary = {k: bench.get(k) for k in BENCH_KEYS}
            summary["steps_per_s"] = {w: v["steps_per_s"] for w, v in bench["workloads"].items()}
        except (json.JSONDecodeError, KeyError, TypeError, AttributeError) as err:
            return None, [], f"unreadable {name}: {err}"
        if name == f"{stem}.json":
            return summary, [name], ""
        done = bench.get("completed_workloads", [])
        summary["completed_workloads"] = done
        return summary, [name], f"partial results: {', '.join(done) or 'no workload'} finished"
    return None, [], ""


def sync_results(path: Path) -> dict[str, Any]:
    """What ``gpu_check.json`` keeps of ``syncs.tsv``: syncs recorded, those with march code on
    the stack, whether CUDA recorded anything, the phases in the file and their env steps; the
    march source lines that synced in more than one env step of a part (a read once per
    iteration falls in one step: it is listed in the file, not here); and the syncs per env
    step of march's env and bare rough's, stepped alone (once both are recorded)."""
    lines = path.read_text().splitlines()
    rows = [ln.split("\t") for ln in lines if ln and not ln.startswith(("#", "phase"))]
    rows = [r for r in rows if len(r) >= 4]

    def header(key: str) -> list[str]:
        text = next((ln.split(":", 1)[1] for ln in lines if ln.startswith(f"# {key}:")), "")
        return [p.strip() for p in text.split(",") if p.strip()]

    steps = {k: int(v) for k, _, v in (p.rpartition(" ") for p in header("steps")) if k}
    in_steps: dict[tuple[str, str], set[str]] = {}
    for ph, step, src, *_ in rows:
        if src.startswith("march/") and step != "0":
            in_steps.setdefault((ph, src), set()).add(step)
    result: dict[str, Any] = {
        "recorded": len(rows),
        "with_march_on_stack": sum(1 for r in rows if r[3] != "-"),
        "cuda": not (lines and lines[0].startswith("# no CUDA")),
        "phases": header("recorded"),
        "steps": steps,
        "march_lines_per_step": sorted(
            f"{ph} {src}" for (ph, src), s in in_steps.items() if len(s) > 1
        ),
    }
    if "env_march" in steps and "env_rough" in steps:
        result["env_syncs_per_step"] = {
            env: sum(1 for r in rows if r[0] == f"env_{env}") / max(steps[f"env_{env}"], 1)
            for env in ("march", "rough")
        }
    return result


def compile_vs_eager(compiled: dict[str, Any], eager: dict[str, Any]) -> dict[str, Any]:
    """What ``compute.compile_math`` gains on this machine, per workload both benches finished:
    march's env steps per second and non-physics ms per step, compiled and eager, and their
    ratios (compiled / eager: above 1 for the speed, below 1 for the time, where it wins)."""
    both = {"compiled": compiled, "eager": eager}

    def march(key: str, workload: str) -> dict[str, Any]:
        """March's figure ``key`` of ``workload`` in each bench (None where it lacks it)."""
        return {
            k: ((b.get(key) or {}).get(workload) or {}).get("march_teacher")
            for k, b in both.items()
        }

    out: dict[str, Any] = {}
    for w in sorted(set(compiled.get("steps_per_s") or {}) & set(eager.get("steps_per_s") or {})):
        speed = march("steps_per_s", w)
        row: dict[str, Any] = {
            "steps_per_s": speed,
            "speed_ratio": speed["compiled"] / speed["eager"],
        }
        times = march("nonphysics_ms_per_step", w)
        if all(times.values()):
            row["nonphysics_ms"] = times
            row["nonphysics_ratio"] = times["compiled"] / times["eager"]
        out[w] = row
    return out


def draw_bench_figures(out: Path) -> list[str]:
    """``analysis/bench_figure.py`` on the benches in ``out`` (where the non-physics time goes,
    one PNG per bench JSON): the files it wrote. A figure is a reading aid: a failure to draw is
    printed and fails nothing."""
    if not any(out.glob("bench_env*.json")):
        return []
    cmd = [sys.executable, str(ROOT / "analysis" / "bench_figure.py"), str(out)]
    try:
        done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=120)
    except subprocess.TimeoutExpired:
        print("[gpu_check] bench figures: timed out", flush=True)
        return []
    for line in (done.stdout + done.stderr).strip().splitlines()[-6:]:
        print(f"[gpu_check] {line}", flush=True)
    return sorted(p.name for p in out.glob("bench_env*.png"))


def judged_targets(results: dict[str, Any]) -> dict[str, Any]:
    """The step's speed targets as the bench judged them (each not measured where the bench
    phase left no figure), and the sync targets, judged only where CUDA recorded the syncs
    (:mod:`march.bench.targets`): no march source line that syncs in more than one env step of
    a part (teacher rollout, distillation rollout, march's env), and march's env no more syncs
    per step than bare rough's."""
    bench = (results.get("bench") or {}).get("targets") or {}
    judged = {t.key: bench.get(t.key) or t.judge(None) for t in STEP_TARGETS}
    syncs = results.get("syncs") or {}
    lines = syncs.get("march_lines_per_step") if syncs.get("cuda") and syncs.get("phases") else None
    per_step = syncs.get("env_syncs_per_step") if syncs.get("cuda") else None
    extra = per_step["march"] - per_step["rough"] if per_step else None
    lines_target, env_target = SYNC_TARGETS
    judged[lines_target.key] = lines_target.judge(None if lines is None else len(lines))
    judged[env_target.key] = env_target.judge(extra)
    return judged


def teacher_budget_reached(run: Path, seconds: float) -> Any:
    """True once the teacher's training time (``wall_s`` of ``metrics.csv``) passed ``seconds``
    and the checkpoint of that iteration is on disk (the row is logged before the save)."""

    def reached() -> bool:
        rows = read_rows(run / "metrics.csv", "teacher")
        if not rows or float(rows[-1]["wall_s"]) < seconds:
            return False
        return (run / "teacher" / f"model_{int(rows[-1]['iteration']):06d}.pt").is_file()

    return reached


def main(argv: list[str] | None = None) -> int:
    args = parse(argv)
    out: Path = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    s = sizes(args)
    py = sys.executable
    common = s["compute"] + ["logger=csv"]
    phases: list[Phase] = []
    results: dict[str, Any] = {}
    t_start = time.time()

    def limit(phase_limit: float | None = None) -> float:
        """This phase's time limit: its own (``--phase-timeout`` unless given), or what is left
        before the deadline."""
        own = args.phase_timeout if phase_limit is None else phase_limit
        return min(own, args.deadline - (time.time() - t_start))

    def bench(name: str, stem: str, extra: list[str], optional: bool = False) -> None:
        """A ``march.bench env`` phase: ``{stem}.json``, or the finished workloads of its
        partial file when a limit stopped it, as ``results[name]``."""
        partial = out / f"{stem}.partial.json"
        partial.unlink(missing_ok=True)
        cmd = [py, "-m", "march.bench", "env", *common[:1], *s["bench"], *extra]
        ph = Phase(name, [*cmd, f"bench.partial={partial}"], out, optional)
        phases.append(ph)
        done = ph.run(limit(args.bench_timeout), stdout_file=out / f"{stem}.json")
        summary, files, note = bench_results(out, done, stem)
        ph.files += files
        ph.note = "; ".join(n for n in (ph.note, note) if n)
        if summary is not None:
            results[name] = summary

    if "bench" not in args.skip:
        bench("bench", "bench_env", [])

    if "syncs" not in args.skip:
        cmd = [py, "scripts/sync_check.py", str(out / "syncs.tsv"), *common, *s["syncs"]]
        ph = Phase("syncs", cmd, out)
        phases.append(ph)
        (out / "syncs.tsv").unlink(missing_ok=True)
        done = ph.run(limit(args.sync_timeout))
        if (out / "syncs.tsv").is_file():  # also a stopped run's: the teacher part is kept
            ph.files.append("syncs.tsv")
            results["syncs"] = sync_results(out / "syncs.tsv")
            if not done:
                recorded = ", ".join(results["syncs"]["phases"]) or "nothing"
                ph.note = "; ".join(n for n in (ph.note, f"partial: {recorded} recorded") if n)

    teacher_ckpt: dict[str, Path] = {}
    for arm in ("clf", "modelfree"):
        name = f"teacher_{arm}"
        if name in args.skip:
            continue
        run = out / "runs" / name
        shutil.rmtree(run, ignore_errors=True)
        cmd = [
            py,
            "-m",
            "march.train",
            "stage=teacher",
            f"reward={arm}",
            *common,
            *s["teacher"],
            "teacher.max_iterations=1000000",
            "teacher.save_interval=1",
            "teacher.eval_interval=0",
            f"hydra.run.dir={run}",
        ]
        ph = Phase(name, cmd, out)
        phases.append(ph)
        ph.run(limit(), stop_when=teacher_budget_reached(run, args.teacher_seconds))
        rows = read_rows(run / "metrics.csv", "teacher")
        write_rows(rows, out / f"{name}_curve.csv")
        ckpt = run / "teacher" / "latest.pt"
        if rows and ckpt.is_file():
            teacher_ckpt[arm] = ckpt
            last = rows[-1]
            wall = float(last["wall_s"])
            results[name] = {
                "iterations": int(last["iteration"]),
                "env_steps": int(last["env_steps"]),
                "train_wall_s": wall,
                "env_steps_per_s": int(last["env_steps"]) / wall if wall > 0 else None,
                "first_mean_reward": number(rows[0].get("mean_reward")),
                "last_mean_reward": number(last.get("mean_reward")),
                "checkpoint": str(ckpt.relative_to(out)),
            }
            ph.files += [f"{name}_curve.csv"]
            ph.rc = 0 if ph.note == "stopped at its budget" else ph.rc
        else:
            ph.note = (ph.note + "; no completed iteration").strip("; ")
            ph.rc = ph.rc if ph.rc not in (0, None) else 1

    student_ckpt: Path | None = None
    if "student" not in args.skip and "clf" in teacher_ckpt:
        run = out / "runs" / "student"
        shutil.rmtree(run, ignore_errors=True)
        cmd = [
            py,
            "-m",
            "march.train",
            "stage=student",
            f"teacher_ckpt={teacher_ckpt['clf']}",
            *common,
            *s["student"],
            "distill.max_iterations=2",
            "distill.eval_interval=0",
            "distill.save_interval=1",
            f"hydra.run.dir={run}",
        ]
        ph = Phase("student", cmd, out)
        phases.append(ph)
        if ph.run(limit()):
            write_rows(read_rows(run / "metrics.csv", "student"), out / "student_curve.csv")
            for name in ("eval.csv", "summary.json"):
                if (run / name).is_file():
                    shutil.copy(run / name, out / name)
            ph.files += [
                f for f in ("student_curve.csv", "eval.csv", "summary.json") if (out / f).is_file()
            ]
            if (run / "summary.json").is_file():
                results["eval"] = json.loads((run / "summary.json").read_text())
            if (run / "student" / "latest.pt").is_file():
                student_ckpt = run / "student" / "latest.pt"

    if "export" not in args.skip and student_ckpt is not None:
        onnx = out / "student.onnx"
        cmd = [py, "-m", "march.export", f"student_ckpt={student_ckpt}", f"out={onnx}"]
        ph = Phase("export", cmd, out)
        phases.append(ph)
        if ph.run(limit(), stdout_file=out / "export.txt") and onnx.is_file():
            ph.files += ["student.onnx", "export.txt"]
            results["export"] = {"onnx_bytes": onnx.stat().st_size}

    if "bench_eager" not in args.skip:  # last: only with time to spare
        bench("bench_eager", "bench_env_eager", ["compute.compile_math=false"], optional=True)
        if "bench" in results and "bench_eager" in results:
            results["compile_vs_eager"] = compile_vs_eager(results["bench"], results["bench_eager"])

    records = [ph.record() for ph in phases]
    ok = bool(records) and not any(ph.failed() for ph in phases)
    figures = draw_bench_figures(out)
    report = {
        "ok": ok,
        "mode": "cpu" if args.cpu else "gpu",
        "seconds": round(time.time() - t_start, 1),
        "machine": machine(),
        "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "phases": records,
        "results": results,
        "targets": judged_targets(results),
        "figures": figures,
    }
    (out / "gpu_check.json").write_text(json.dumps(report, indent=2, default=str) + "\n")
    with (out / "gpu_check.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["phase", "rc", "seconds", "note", "files", "command"])
        w.writeheader()
        for r in records:
            w.writerow(
                {
                    **{k: r[k] for k in ("phase", "rc", "seconds", "note", "command")},
                    "files": " ".join(r["files"]),
                }
            )
    for line in verdict_lines(report["targets"], "[gpu_check]"):
        print(line, flush=True)
    for w, row in results.get("compile_vs_eager", {}).items():
        times = row.get("nonphysics_ms")
        print(
            f"[gpu_check] compile_math, {w}: march {row['steps_per_s']['compiled']:.0f} vs "
            f"{row['steps_per_s']['eager']:.0f} env steps/s eager (x{row['speed_ratio']:.2f})"
            + (
                f", non-physics {times['compiled']:.1f} vs {times['eager']:.1f} ms/step"
                if times
                else ""
            ),
            flush=True,
        )
    print(f"[gpu_check] {'ok' if ok else 'FAILED'} in {report['seconds']:.0f} s: {out}", flush=True)
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
