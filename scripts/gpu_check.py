"""The prepared GPU check (issues 11, 41): one command that reports whatever happens.

    python scripts/gpu_check.py OUT --warm     # with the last bundle: build and compile (<= 3 min)
    python scripts/gpu_check.py OUT            # the check (compute=gpu), at most 6.5 minutes
    python scripts/gpu_check.py OUT --cpu      # every phase at tiny sizes on CPU (tests)
    make gpu-check [OUT=folder] [ARGS=--cpu]

A device is lent for 15 minutes in all, 10 per command, cold start included; what it returns is
at most 8 files of ``$OUT``. So the phases run in order of value, each a subprocess with its own
time limit, each figure is printed to stdout the moment it is measured (``[bench]``,
``[syncs]``, ``[gpu_check]`` lines), and ``OUT/gpu_check.json`` is rewritten after every phase
(and at the start, and when the check is stopped by SIGTERM or SIGINT): a check killed at any
point leaves a summary naming the phases it finished.

1. ``bench``: ``march.bench env`` at ``--bench-envs`` (4096) envs, random workload, the march
   teacher env against bare mjlab rough only, with compute ops per step (the CUDA path's kernel
   launches) and a short profile -> ``bench_env.json`` (the final JSON, or the partial one of a
   bench its limit stopped).
2. ``syncs``: ``scripts/sync_check.py --parts=env_march,env_rough`` at 256 envs: syncs per
   env step of march's env and of bare rough's -> ``syncs.tsv``.
3. ``teacher_clf``: ``march.train stage=teacher reward=clf`` at ``--train-envs`` (4096),
   stopped after ``--teacher-iterations`` (5) iterations and that checkpoint ->
   ``teacher_clf_curve.csv`` and ``s_per_iteration`` (from iteration 2 on) in the summary.
4. Optional, only with time left (skipped or stopped by the deadline, they fail nothing):
   ``bench_eager`` (the bench with ``compute.compile_math=false`` -> ``bench_env_eager.json``
   and ``compile_vs_eager``), ``syncs_runners`` (a teacher iteration's rollout and a
   distillation rollout -> ``syncs_runners.tsv``), ``student`` (two distillation iterations from
   the clf teacher and the evaluation protocol -> ``student_curve.csv``, the evaluation in the
   summary), ``bench_graphs`` (the bench with ``compute.compile_mode=reduce-overhead``: the
   compiled maths replayed as CUDA graphs; its figures and ``graphs_vs_default`` in the summary
   only, no file of its own).

``--warm`` runs one phase instead, ``warm``: the bench at the check's size with one step per
env, which builds the envs and fills warp's kernel cache and inductor's on-disk cache (both
stay on a warm machine between commands), and reports the cold build times (``warm.json``).

``OUT`` holds at most :data:`OUT_FILES` (8 files, no folder): run folders, logs and temporary
files go to ``--work`` (a temporary folder); the last lines of each phase's log are appended to
``OUT/logs.txt``. ``gpu_check.json``: ``phases_done`` (names, in order), every phase's command,
return code, seconds and files, the machine, the date, ``results`` and ``targets`` (the step's
speed targets as the bench judged them, the sync targets; met, missed or not measured). Exit
status 0 only if every phase but an optional one the deadline skipped or stopped succeeded (a
missed target does not fail the check). On a machine without a package index source the
bundles' ``gpu.sh`` first (``../shared/gpu/README.md``; README, "GPU check: the device plan").
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # run as a script: import this checkout's march

from march import strict_json  # noqa: E402
from march.bench.check_results import (  # noqa: E402
    BENCH_KEYS,  # noqa: F401 - read by the tests through this script
    bench_results,
    compile_vs_eager,
    judged_targets,
    number,
    read_rows,
    seconds_per_iteration,
    sync_results,
    write_rows,
)
from march.bench.targets import verdict_lines  # noqa: E402

OUT_FILES = (
    "gpu_check.json",
    "bench_env.json",
    "syncs.tsv",
    "teacher_clf_curve.csv",
    "logs.txt",
    "bench_env_eager.json",
    "syncs_runners.tsv",
    "student_curve.csv",
)
"""Every file the check may write into ``OUT`` (``--warm``: ``warm.json`` for
``bench_env_eager.json``), at most 8, the device's limit; nothing else goes there."""
ECHO = ("[bench]", "[syncs]", "[teacher]", "[student]", "[gpu_check]")
"""A phase's output lines echoed to the check's stdout as they come (its figures)."""
BENCH = ["bench.workloads=random", "bench.envs=march_teacher,bare_rough"]
GPU = {
    "compute": ["compute=gpu"],
    "bench": ["compute.num_envs={bench_envs}", *BENCH, "bench.steps=30", "bench.warmup=10"]
    + ["bench.rounds=2", "bench.op_steps=2", "bench.profile_steps=5"],
    "warm": ["compute.num_envs={bench_envs}", *BENCH, "bench.steps=1", "bench.warmup=1"]
    + ["bench.rounds=1", "bench.op_steps=0", "bench.profile_steps=0"],
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
    "bench": ["compute.num_envs=2", *BENCH, "bench.steps=1", "bench.warmup=1"]
    + ["bench.profile_steps=1", "bench.op_steps=1", "bench.rounds=1", "bench.threads=1"],
    "warm": ["compute.num_envs=2", *BENCH, "bench.steps=1", "bench.warmup=0"]
    + ["bench.profile_steps=0", "bench.op_steps=0", "bench.rounds=1", "bench.threads=1"],
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
LIMITS = {"bench": 150.0, "warm": 540.0, "syncs": 80.0, "teacher_clf": 130.0}
"""Each phase's own time limit on a GPU [s] (``--cpu``: twice as long); an optional phase gets
what is left before the deadline, at most ``--phase-timeout``."""


def finite(x: float | None) -> float | None:
    """None for NaN / inf (gpu_check.json is strict JSON)."""
    return x if x is not None and x == x and abs(x) != float("inf") else None


SIGNAL_ARMS = ("clf", "modelfree_ref")
"""The signal phase's teachers (conf/experiment/): the clf arm and its reward-only control."""
SIGNAL_COLUMNS = (
    "iteration",
    "env_steps",
    "wall_s",
    "mean_reward",
    "mean_episode_length",
    "mean_distance_m",
    "clf/v_p10",
    "clf/v_p50",
    "clf/v_p90",
    "clf/saturated",
    "learning_rate",
    "kl_normaliser",
)
"""The per-iteration columns of the signal phase's curves (metrics.csv)."""


class Stopped(Exception):
    """SIGTERM or SIGINT reached the check: the running phase is stopped, the summary written."""


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("out", nargs="?", default=os.environ.get("OUT", "outputs/gpu_check"), type=Path)
    p.add_argument("--cpu", action="store_true", help="tiny sizes on CPU (compute=smoke)")
    p.add_argument("--warm", action="store_true", help="build and compile only (warm.json)")
    p.add_argument("--work", type=Path, default=None, help="run folders and logs (a temp folder)")
    p.add_argument("--bench-envs", type=int, default=4096, help="envs of the env benchmark")
    p.add_argument("--train-envs", type=int, default=4096, help="envs of the teacher run")
    p.add_argument("--teacher-iterations", type=int, default=5, help="teacher iterations")
    p.add_argument("--distill-envs", type=int, default=1024, help="envs of the distillation")
    p.add_argument("--eval-rollouts", type=int, default=128, help="rollouts of the evaluation")
    p.add_argument("--phase-timeout", type=float, default=200.0, help="optional phases' limit [s]")
    p.add_argument(
        "--deadline",
        type=float,
        default=None,
        help="whole check [s]: 390 on a GPU (the README's device plan), 180 with --warm, 600 "
        "with --cpu",
    )
    p.add_argument(
        "--signal-seconds", type=float, default=75.0, help="signal phase: wall time per arm [s]"
    )
    p.add_argument("--skip", nargs="*", default=[], help="phases to leave out")
    args = p.parse_args(argv)
    if args.deadline is None:
        args.deadline = 600.0 if args.cpu else 180.0 if args.warm else 390.0
    if args.teacher_iterations < 2:
        p.error("--teacher-iterations must be >= 2 (seconds per iteration from iteration 2 on)")
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
    """One subprocess phase: command, log (in the work folder), return code, seconds."""

    def __init__(self, name: str, cmd: list[str], work: Path, optional: bool = False) -> None:
        self.name, self.cmd = name, cmd
        self.optional = optional
        """Run only with time to spare: skipped or stopped by its limit, it fails nothing."""
        self.log = work / f"{name}.log"
        self.rc: int | None = None
        self.seconds = 0.0
        self.note = ""
        self.files: list[str] = []

    def run(self, timeout: float, stop_when: Any = None, stdout_file: Path | None = None) -> bool:
        """Run to the end, to ``timeout`` seconds or until ``stop_when()`` is true (then SIGTERM,
        as a Slurm preemption: checkpoints are written atomically, so the last one is whole).
        The output goes to the log; lines starting with one of :data:`ECHO` are also printed
        as they come. A :class:`Stopped` check stops the phase and passes on."""
        if timeout <= 0:
            self.note = "skipped: no time left before the deadline"
            self.rc = -1
            print(f"[gpu_check] {self.name}: {self.note}", flush=True)
            return False
        print(f"[gpu_check] {self.name} (limit {timeout:.0f} s): {' '.join(self.cmd)}", flush=True)
        t0 = time.time()
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        stopped = ""
        with self.log.open("w") as log:
            out = stdout_file.open("w") if stdout_file else subprocess.PIPE
            err = subprocess.PIPE if stdout_file else subprocess.STDOUT
            proc = subprocess.Popen(self.cmd, cwd=ROOT, stdout=out, stderr=err, env=env, text=True)
            stream = proc.stderr if stdout_file else proc.stdout
            reader = threading.Thread(target=_tee, args=(stream, log), daemon=True)
            reader.start()
            try:
                while proc.poll() is None:
                    time.sleep(0.5)
                    if time.time() - t0 > timeout:
                        stopped = f"timed out after {timeout:.0f} s"
                    elif stop_when is not None and stop_when():
                        stopped = "stopped at its budget"
                    if stopped:
                        _stop(proc)
                        break
            except Stopped:
                stopped = "stopped: the check was stopped"
                _stop(proc)
                raise
            finally:
                reader.join(5)
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
            "files": self.files,
            "optional": self.optional,
        }

    def failed(self) -> bool:
        """The phase counts against the check: a nonzero exit status, unless it is an optional
        phase that the deadline skipped or stopped."""
        if self.rc == 0:
            return False
        return not (self.optional and self.note.startswith(("skipped", "timed out")))


def _tee(stream: Any, log: Any) -> None:
    for line in stream:
        log.write(line)
        log.flush()
        if line.startswith(ECHO):
            print(line.rstrip("\n"), flush=True)


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is not None:
        return
    proc.terminate()
    try:
        proc.wait(15)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def teacher_done(run: Path, iterations: int, seen: list[int]) -> Any:
    """True once ``iterations`` rows are in the teacher's ``metrics.csv`` and that iteration's
    checkpoint is on disk (the row is logged before the save); prints each new row's figure."""

    def reached() -> bool:
        rows = read_rows(run / "metrics.csv", "teacher")
        for r in rows[len(seen) :]:
            seen.append(int(r["iteration"]))
            per_it = seconds_per_iteration(rows[: len(seen)])
            print(
                f"[gpu_check] teacher_clf iteration {r['iteration']}: wall {float(r['wall_s']):.1f}"
                f" s, {r['env_steps']} env steps"
                + ("" if per_it is None else f"; {per_it:.2f} s/iteration from iteration 2"),
                flush=True,
            )
        if len(rows) < iterations:
            return False
        return (run / "teacher" / f"model_{int(rows[-1]['iteration']):06d}.pt").is_file()

    return reached


class Check:
    """The check's state: phases run, results, and the summary rewritten after each phase."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        self.out: Path = args.out.resolve()
        self.out.mkdir(parents=True, exist_ok=True)
        (self.out / "logs.txt").unlink(missing_ok=True)  # this check's logs only
        work = args.work or Path(tempfile.mkdtemp(prefix="gpu_check_"))
        self.work = work.resolve()
        self.work.mkdir(parents=True, exist_ok=True)
        self.s = sizes(args)
        self.common = self.s["compute"] + ["logger=csv"]
        self.phases: list[Phase] = []
        self.results: dict[str, Any] = {}
        self.t0 = time.time()
        self.stopped = ""
        self.machine = machine()

    def guard(self, name: str, phase: Any) -> Any:
        """Run ``phase()``; an error of the check itself (not of the phase's subprocess) is
        recorded on that phase and the check goes on: it always reports."""
        try:
            return phase()
        except Stopped:
            raise
        except Exception as err:  # noqa: BLE001 - recorded, then the next phase
            ph = next((p for p in self.phases if p.name == name), None) or self.add(name, [])
            ph.rc = ph.rc if ph.rc not in (0, None) else 1
            ph.note = "; ".join(n for n in (ph.note, f"check error: {err!r}"[:300]) if n)
            print(f"[gpu_check] {name}: {ph.note}", flush=True)
            self.write()
            return None

    def limit(self, name: str) -> float:
        own = LIMITS.get(name, self.args.phase_timeout) * (2.0 if self.args.cpu else 1.0)
        return min(own, self.args.deadline - (time.time() - self.t0))

    def add(self, name: str, cmd: list[str], optional: bool = False) -> Phase:
        ph = Phase(name, cmd, self.work, optional)
        self.phases.append(ph)
        return ph

    def finish(self, ph: Phase) -> None:
        """After a phase: its log's tail into ``logs.txt``, the summary rewritten."""
        if ph.log.is_file():
            tail = ph.log.read_text(errors="replace").splitlines()[-60:]
            with (self.out / "logs.txt").open("a") as f:
                f.write(f"===== {ph.name}: rc={ph.rc} {ph.note} ({ph.seconds:.0f} s)\n")
                f.write("\n".join(tail) + "\n")
        self.write()

    def write(self) -> dict[str, Any]:
        records = [ph.record() for ph in self.phases]
        ok = bool(records) and not self.stopped and not any(ph.failed() for ph in self.phases)
        report = {
            "ok": ok,
            "mode": ("cpu" if self.args.cpu else "gpu") + ("-warm" if self.args.warm else ""),
            "phases_done": [ph.name for ph in self.phases if ph.rc is not None],
            "stopped": self.stopped,
            "seconds": round(time.time() - self.t0, 1),
            "machine": self.machine,
            "work": str(self.work),
            "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(self.args).items()},
            "phases": records,
            "results": self.results,
            "targets": judged_targets(self.results),
        }
        tmp = self.out / "gpu_check.json.tmp"
        tmp.write_text(strict_json.dumps(report, indent=2, default=str) + "\n")
        tmp.replace(self.out / "gpu_check.json")
        return report

    # ------------------------------------------------------------------------------- phases

    def bench(self, name: str, stem: str, extra: list[str], optional: bool = False) -> None:
        """A ``march.bench env`` phase: ``OUT/{stem}.json`` (the final JSON, else the partial
        one) and its figures as ``results[name]``."""
        py, work = sys.executable, self.work
        partial = work / f"{stem}.partial.json"
        partial.unlink(missing_ok=True)
        sizes_ = self.s["warm" if name == "warm" else "bench"]
        cmd = [py, "-m", "march.bench", "env", *self.common[:1], *sizes_, *extra]
        ph = self.add(name, [*cmd, f"bench.partial={partial}"], optional)
        try:
            ph.run(self.limit(name), stdout_file=work / f"{stem}.json")
        finally:
            summary, files, note = bench_results(work, ph.rc == 0, stem)
            if files and f"{stem}.json" in OUT_FILES:  # else its figures are in the summary
                shutil.copy(work / files[0], self.out / f"{stem}.json")
                ph.files.append(f"{stem}.json")
            ph.note = "; ".join(n for n in (ph.note, note) if n)
            if summary is not None:
                if name == "warm" and ph.rc == 0:
                    summary["build_s"] = json.loads((work / f"{stem}.json").read_text())["build_s"]
                self.results[name] = summary
            self.finish(ph)

    def syncs(self, name: str, parts: str, optional: bool = False) -> None:
        tsv = f"{name}.tsv"
        cmd = [sys.executable, "scripts/sync_check.py", f"--parts={parts}", str(self.out / tsv)]
        ph = self.add(name, [*cmd, *self.common, *self.s["syncs"]], optional)
        (self.out / tsv).unlink(missing_ok=True)
        try:
            ph.run(self.limit(name))
        finally:
            if (self.out / tsv).is_file():  # a stopped run's too: its finished parts are kept
                ph.files.append(tsv)
                self.results[name] = sync_results(self.out / tsv)
                if ph.rc != 0:
                    recorded = ", ".join(self.results[name]["phases"]) or "nothing"
                    ph.note = "; ".join(n for n in (ph.note, f"partial: {recorded}") if n)
            self.finish(ph)

    def teacher(self) -> Path | None:
        name, run = "teacher_clf", self.work / "runs" / "teacher_clf"
        shutil.rmtree(run, ignore_errors=True)
        cmd = [sys.executable, "-m", "march.train", "stage=teacher", "reward=clf", *self.common]
        cmd += [*self.s["teacher"], "teacher.max_iterations=1000000", "teacher.save_interval=1"]
        cmd += ["teacher.eval_interval=0", f"hydra.run.dir={run}"]
        ph = self.add(name, cmd)
        seen: list[int] = []
        try:
            ph.run(self.limit(name), teacher_done(run, self.args.teacher_iterations, seen))
        finally:
            rows = read_rows(run / "metrics.csv", "teacher")
            ckpt = run / "teacher" / "latest.pt"
            if rows:
                write_rows(rows, self.out / f"{name}_curve.csv")
                ph.files.append(f"{name}_curve.csv")
                last = rows[-1]
                wall = float(last["wall_s"])
                self.results[name] = {
                    "iterations": int(last["iteration"]),
                    "env_steps": int(last["env_steps"]),
                    "train_wall_s": wall,
                    "s_per_iteration": seconds_per_iteration(rows),
                    "first_iteration_s": float(rows[0]["wall_s"]),
                    "env_steps_per_s": int(last["env_steps"]) / wall if wall > 0 else None,
                    "first_mean_reward": number(rows[0].get("mean_reward")),
                    "last_mean_reward": number(last.get("mean_reward")),
                }
            if len(rows) >= 2 and ckpt.is_file():
                ph.rc = 0 if ph.note == "stopped at its budget" else ph.rc
            else:
                ph.note = (ph.note + "; fewer than 2 iterations").strip("; ")
                ph.rc = ph.rc if ph.rc not in (0, None) else 1
            self.finish(ph)
        return ckpt if rows and ckpt.is_file() else None

    def signal(self) -> None:
        """The learning signal (issue 50): the clf teacher and its control (modelfree_ref: the
        same stones, budget and reference observation, only the reward differs; V is measured
        for both) at the teacher phase's env count, each for the same wall time (env build
        included), their per-iteration curves into ``gpu_check.json`` (``results.signal``)."""
        left = self.args.deadline - (time.time() - self.t0)
        each = min(
            self.args.signal_seconds * (2.0 if self.args.cpu else 1.0), left / len(SIGNAL_ARMS)
        )
        out: dict[str, Any] = {"wall_s_per_arm": round(each, 1), "arms": {}}
        self.results["signal"] = out
        for arm in SIGNAL_ARMS:
            name, run = f"signal_{arm}", self.work / "runs" / f"signal_{arm}"
            shutil.rmtree(run, ignore_errors=True)
            cmd = [sys.executable, "-m", "march.train", "stage=teacher", f"+experiment={arm}"]
            cmd += [*self.common, *self.s["teacher"], "teacher.max_iterations=1000000"]
            cmd += ["teacher.eval_interval=0", "teacher.save_interval=1000000"]
            cmd += [f"hydra.run.dir={run}"]
            ph = self.add(name, cmd, optional=True)
            start = time.time()
            try:
                # stopped at its budget (SIGTERM: the last checkpoint whole); the limit only
                # catches a phase that does not stop
                grace = self.args.deadline - (time.time() - self.t0)
                ph.run(min(each + 30.0, grace), lambda t=start: time.time() - t >= each)
            finally:
                rows = read_rows(run / "metrics.csv", "teacher")
                curve = [{k: finite(number(r.get(k))) for k in SIGNAL_COLUMNS} for r in rows]
                out["arms"][arm] = {"iterations": len(rows), "curve": curve}
                if rows:
                    ph.rc = 0 if ph.note in ("stopped at its budget", "") else ph.rc
                    first, last = curve[0], curve[-1]
                    print(
                        f"[gpu_check] signal {arm}: {len(rows)} iterations in {each:.0f} s; "
                        + ", ".join(
                            f"{k} {first[k]} -> {last[k]}"
                            for k in ("clf/v_p50", "clf/saturated", "mean_episode_length")
                        ),
                        flush=True,
                    )
                self.finish(ph)

    def student(self, teacher_ckpt: Path) -> None:
        run = self.work / "runs" / "student"
        shutil.rmtree(run, ignore_errors=True)
        cmd = [sys.executable, "-m", "march.train", "stage=student", f"teacher_ckpt={teacher_ckpt}"]
        cmd += [*self.common, *self.s["student"], "distill.max_iterations=2"]
        cmd += ["distill.eval_interval=0", "distill.save_interval=1", f"hydra.run.dir={run}"]
        ph = self.add("student", cmd, optional=True)
        try:
            ph.run(self.limit("student"))
        finally:
            rows = read_rows(run / "metrics.csv", "student")
            if rows:
                write_rows(rows, self.out / "student_curve.csv")
                ph.files.append("student_curve.csv")
            if (run / "summary.json").is_file():
                self.results["eval"] = json.loads((run / "summary.json").read_text())
            self.finish(ph)


def main(argv: list[str] | None = None) -> int:
    args = parse(argv)
    check = Check(args)

    def stop(signum: int, _frame: Any) -> None:
        raise Stopped(signal.Signals(signum).name)

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    check.write()  # a summary before the first phase: the check has started
    skip = set(args.skip)
    guard = check.guard
    try:
        if args.warm:
            guard("warm", lambda: check.bench("warm", "warm", []))
        else:
            if "bench" not in skip:
                guard("bench", lambda: check.bench("bench", "bench_env", []))
            if "syncs" not in skip:
                guard("syncs", lambda: check.syncs("syncs", "env_march,env_rough"))
            ckpt = None if "teacher_clf" in skip else guard("teacher_clf", check.teacher)
            if "signal" not in skip:  # optional from here: only with time left
                guard("signal", check.signal)
            if "bench_eager" not in skip:
                eager = ["compute.compile_math=false"]
                guard(
                    "bench_eager",
                    lambda: check.bench("bench_eager", "bench_env_eager", eager, True),
                )
                if "bench" in check.results and "bench_eager" in check.results:
                    check.results["compile_vs_eager"] = compile_vs_eager(
                        check.results["bench"], check.results["bench_eager"]
                    )
            if "syncs_runners" not in skip:
                guard(
                    "syncs_runners", lambda: check.syncs("syncs_runners", "teacher,distill", True)
                )
            if "student" not in skip and ckpt is not None:
                guard("student", lambda: check.student(ckpt))
            if "bench_graphs" not in skip:  # CUDA-graph replays of the compiled maths
                graphs = ["compute.compile_mode=reduce-overhead"]
                guard(
                    "bench_graphs",
                    lambda: check.bench("bench_graphs", "bench_env_graphs", graphs, True),
                )
                if "bench" in check.results and "bench_graphs" in check.results:
                    check.results["graphs_vs_default"] = compile_vs_eager(
                        check.results["bench_graphs"],
                        check.results["bench"],
                        names=("graphs", "default"),
                    )
    except Stopped as err:
        check.stopped = f"stopped by {err}"
        print(f"[gpu_check] {check.stopped}: writing the summary", flush=True)
    report = check.write()
    for line in verdict_lines(report["targets"], "[gpu_check]"):
        print(line, flush=True)
    for w, row in check.results.get("compile_vs_eager", {}).items():
        print(
            f"[gpu_check] compile_math, {w}: march {row['steps_per_s']['compiled']:.0f} vs "
            f"{row['steps_per_s']['eager']:.0f} env steps/s eager (x{row['speed_ratio']:.2f})",
            flush=True,
        )
    for w, row in check.results.get("graphs_vs_default", {}).items():
        print(
            f"[gpu_check] compile_mode=reduce-overhead, {w}: march "
            f"{row['steps_per_s']['graphs']:.0f} vs {row['steps_per_s']['default']:.0f} env "
            f"steps/s in the default mode (x{row['speed_ratio']:.2f})",
            flush=True,
        )
    extra = sorted(p.name for p in check.out.iterdir() if p.name not in (*OUT_FILES, "warm.json"))
    if extra:  # never expected: the device returns 8 files at most
        print(f"[gpu_check] WARNING: unexpected files in {check.out}: {extra}", flush=True)
    ok = report["ok"]
    print(f"[gpu_check] {'ok' if ok else 'FAILED'} in {report['seconds']:.0f} s: {check.out}")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
