"""Kill-and-resume trials: SIGKILL ``python -m march.train`` at seeded random moments, resume it.

    python scripts/kill_trials.py                 # every phase once: 13 trials (make kill-trials)
    python scripts/kill_trials.py --trials 3 --seed 1 --out /tmp/kt
    python scripts/kill_trials.py --first 10 --trials 3   # only the curriculum and device trials

Each trial starts a small ``compute=smoke`` run, kills its process group with SIGKILL at a moment
of one of the phases below (the teacher before its first checkpoint, during a checkpoint write,
at a random moment or during an evaluation; the same for the distillation; the final
evaluation), then runs ``python -m march.train resume=<run dir>`` to completion and checks:

- the resumed run ends with status ``done`` (exit 0);
- it starts from the newest checkpoint present at the kill (no iteration lost beyond it);
- metrics.csv holds every teacher and student iteration exactly once, eval.csv every expected
  evaluation (teacher every eval_interval and at the end, student likewise) exactly once;
- the final teacher and student checkpoints load with ``load_checkpoint`` at the last iteration;
- curriculum trials (envs start on levels 0-2 and are promoted within two iterations): the kill
  comes after a promotion reached a checkpoint, and the resumed envs start from that
  checkpoint's levels, env by env (the digest the resume prints equals the checkpoint's);
- the device trial resumes with ``compute.device=cpu`` a run saved on ``cuda:0``: a real one
  where CUDA is available, else the killed CPU run's directory rewritten as a CUDA run leaves it
  (config.yaml on cuda:0, CUDA generator states); without the override the resume must exit 2
  with one line, with it the run ends ``done`` and says which streams it reseeded.

It prints one line per trial and the tally (trials, killed, resumed, rows lost, rows
duplicated); the exit status is 0 only when every trial passed. A trial whose run finished
before its moment came counts as not killed (a failure). Run it on an otherwise idle machine
when the timings matter: on 2 loaded CPU cores a trial takes 3-5 minutes.
"""

from __future__ import annotations

import argparse
import csv
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

T_ITERS, D_ITERS = 4, 3  # teacher and distillation iterations of a trial run
T_SAVE, D_SAVE = 2, 2  # save intervals: iteration 1 is logged before the first checkpoint
T_EVAL, D_EVAL = 2, 2  # evaluation intervals: one evaluation in each stage before its last
SIZES = (
    "compute=smoke",
    f"teacher.max_iterations={T_ITERS}",
    f"teacher.save_interval={T_SAVE}",
    f"teacher.eval_interval={T_EVAL}",
    f"distill.max_iterations={D_ITERS}",
    f"distill.save_interval={D_SAVE}",
    f"distill.eval_interval={D_EVAL}",
    # 1 s evaluation episodes (3 s in compute=smoke): the checks are about rows, not walking.
    "eval.episode_length_s=1.0",
)
POLL_S = 0.002  # a checkpoint write lasts tens of milliseconds: poll often enough to land in it

PHASES = (
    "teacher: before the first checkpoint",
    "teacher: during a checkpoint write",
    "teacher: at a random moment",
    "teacher: during an evaluation",
    "distillation: before the first checkpoint",
    "distillation: during a checkpoint write",
    "distillation: at a random moment",
    "final evaluation",
    "teacher: during a checkpoint write",
    "final evaluation",
    "teacher: after a curriculum promotion",
    "teacher: after a curriculum promotion",
    "distillation: at a random moment, resumed on another device",
)
CURRICULUM = (
    # Levels only go up (demote 0), ~1.5 cm of progress promotes, and episodes time out every
    # 15 steps: every env is promoted at iteration 2 (16 steps), from a start level of 0-2.
    "curriculum.promote_fraction=0.01",
    "curriculum.demote_fraction=0.0",
    "curriculum.max_init_level=2",
    "env.episode_length_s=0.3",
)


def expected_evals(total: int, interval: int) -> set[int]:
    """Iterations evaluated in a stage: every ``interval`` before the last, and the last."""
    its = set(range(interval, total, interval)) if interval else set()
    return its | {total}


def rows(path: Path) -> list[tuple[str, int]]:
    """(stage, iteration) of each complete row of a CSV being written by another process."""
    if not path.is_file():
        return []
    out = []
    with path.open(newline="") as f:
        for r in csv.DictReader(f):
            try:
                out.append((r["stage"], int(r["iteration"])))
            except (KeyError, TypeError, ValueError):
                continue  # a row half written at this instant
    return out


def terrain_levels(path: Path) -> dict[int, float]:
    """Teacher iteration -> mean_terrain_level of metrics.csv's complete rows."""
    if not path.is_file():
        return {}
    out = {}
    with path.open(newline="") as f:
        for r in csv.DictReader(f):
            try:
                if r["stage"] == "teacher":
                    out[int(r["iteration"])] = float(r["mean_terrain_level"])
            except (KeyError, TypeError, ValueError):
                continue
    return out


def checkpoint_levels(path: Path, kind: str) -> tuple[int, str, float] | None:
    """(iteration, levels digest, mean level) of the newest checkpoint in ``path``'s directory."""
    from march.env.env_state import levels_digest
    from march.store.checkpoint import load_checkpoint

    files = [*path.parent.glob("model_*.pt"), path] if path.parent.is_dir() else []
    best = None
    for p in files:
        if p.is_file():
            payload = load_checkpoint(p, kind)
            if best is None or int(payload["iteration"]) > int(best["iteration"]):
                best = payload
    if best is None or "curriculum" not in best:
        return None
    lv = best["curriculum"]["terrain_levels"]
    return int(best["iteration"]), levels_digest(lv), float(lv.float().mean())


def resumed_levels(text: str, stage: str) -> str | None:
    """The levels digest a resume printed for ``stage``'s envs."""
    m = re.search(rf"\[{stage}\] curriculum: \d+ envs start from .* digest (\w+)\)", text)
    return m.group(1) if m else None


def craft_cuda_run(run: Path) -> None:
    """The run directory as a ``cuda:0`` run leaves it: config.yaml on cuda:0, every checkpoint's
    config and device generator states (planner, distillation, CUDA default) in CUDA format."""
    import torch

    from march.store.checkpoint import load_checkpoint, save_atomic

    def cuda_state(offset: int) -> torch.Tensor:
        return torch.tensor([0, offset], dtype=torch.int64).view(torch.uint8).clone()

    text = (run / "config.yaml").read_text()
    assert "\n  device: cpu\n" in text, "config.yaml without compute.device: cpu"
    (run / "config.yaml").write_text(text.replace("\n  device: cpu\n", "\n  device: cuda:0\n", 1))
    for kind in ("teacher", "student"):
        for path in sorted((run / kind).glob("*.pt")):
            payload = load_checkpoint(path, kind)
            payload["config"]["compute"]["device"] = "cuda:0"
            streams = payload["streams"]
            streams.update(device="cuda:0", cuda=cuda_state(2**20))
            for name in ("planner", "distill"):
                if name in streams:
                    streams[name] = cuda_state(2**12)
            if "generator" in payload:
                payload["generator"] = cuda_state(2**12)
            save_atomic(payload, path)


def tmp_files(directory: Path) -> list[str]:
    try:
        return [e.name for e in os.scandir(directory) if e.name.endswith(".tmp")]
    except FileNotFoundError:
        return []


@dataclass
class Trigger:
    """When to kill: a condition on the run directory, then a delay [s]."""

    phase: str
    rng: random.Random
    delay: float = 0.0
    armed_at: float | None = None
    seen_tmp: set[str] = field(default_factory=set)
    nth_tmp: int = 1
    tmp_prefix: str = ""

    def __post_init__(self) -> None:
        r = self.rng
        if "checkpoint write" in self.phase:
            # Each save writes latest.pt, then model_<it>.pt: pick one of them, of some save.
            self.tmp_prefix = r.choice([".latest.pt.", ".model_"])
            self.nth_tmp = r.randint(1, 2)
        elif "before the first checkpoint" in self.phase:
            self.delay = r.uniform(0.0, 2.0)
        elif "random moment" in self.phase:
            self.delay = r.uniform(0.0, 25.0)
        elif "curriculum" in self.phase:
            self.delay = r.uniform(0.0, 6.0)
        elif "evaluation" in self.phase:
            self.delay = r.uniform(0.5, 6.0)

    def condition(self, run: Path) -> bool:
        m = rows(run / "metrics.csv")
        if self.phase == "teacher: before the first checkpoint":
            return ("teacher", 1) in m
        if self.phase == "teacher: at a random moment":
            return (run / "metrics.csv").is_file()
        if self.phase == "teacher: during an evaluation":
            return ("teacher", T_EVAL) in m
        if self.phase == "teacher: after a curriculum promotion":
            levels = terrain_levels(run / "metrics.csv")
            return (run / "teacher" / f"model_{T_SAVE:06d}.pt").is_file() and levels.get(
                T_SAVE, -1.0
            ) > levels.get(1, float("inf"))
        if self.phase == "distillation: before the first checkpoint":
            return ("student", 1) in m
        if self.phase.startswith("distillation: at a random moment"):
            return ("teacher", T_ITERS) in rows(run / "eval.csv")
        if self.phase == "final evaluation":
            return (run / "student" / f"model_{D_ITERS:06d}.pt").is_file()
        raise ValueError(self.phase)

    def fire(self, run: Path) -> bool:
        if "checkpoint write" in self.phase:
            stage = "teacher" if self.phase.startswith("teacher") else "student"
            for name in tmp_files(run / stage):
                if name.startswith(self.tmp_prefix):
                    self.seen_tmp.add(name)
            return len(self.seen_tmp) >= self.nth_tmp
        if self.armed_at is None:
            if self.condition(run):
                self.armed_at = time.monotonic()
            return False
        return time.monotonic() - self.armed_at >= self.delay

    def describe(self) -> str:
        if "checkpoint write" in self.phase:
            return f"on {self.tmp_prefix}*.tmp #{self.nth_tmp}"
        return f"{self.delay:.1f} s after its mark"


def ckpt_iteration(path: Path, kind: str) -> int:
    """Iteration of the newest complete checkpoint on disk, latest.pt or any model_<it>.pt
    (0: none): what a resume must start from, so that no checkpointed iteration is lost."""
    from march.store.checkpoint import load_checkpoint

    files = [*path.parent.glob("model_*.pt"), path] if path.parent.is_dir() else []
    its = [int(load_checkpoint(p, kind)["iteration"]) for p in files if p.is_file()]
    return max(its, default=0)


def resumed_at(text: str, stage: str) -> int:
    """The iteration a resume said it continued from (0: it started the stage over)."""
    m = re.search(rf"\[{stage}\] resuming from \S+ at iteration (\d+)", text)
    return int(m.group(1)) if m else 0


def cuda_available() -> bool:
    import torch

    return torch.cuda.is_available()


def train_env() -> dict[str, str]:
    env = dict(os.environ)
    env.setdefault("WARP_CACHE_PATH", str(ROOT / ".warp_cache"))
    env.setdefault("WANDB_MODE", "offline")
    return env


def run_trial(i: int, phase: str, rng: random.Random, out: Path) -> dict:
    from march.store.checkpoint import CheckpointError, load_checkpoint

    run = out / f"trial_{i:02d}"
    # A fresh run directory: a previous invocation's trial_NN would be resumed (already finished,
    # or holding that trial's broken rows), and the trial would measure nothing of its own.
    shutil.rmtree(run, ignore_errors=True)
    trig = Trigger(phase, rng)
    log = (out / f"trial_{i:02d}.killed.log").open("w")
    curriculum = "curriculum" in phase
    device_trial = "another device" in phase
    has_cuda = device_trial and cuda_available()
    sizes = [*SIZES, *(CURRICULUM if curriculum else ())]
    if has_cuda:
        sizes.append("compute.device=cuda:0")
    cmd = [sys.executable, "-m", "march.train", *sizes, f"hydra.run.dir={run}"]
    proc = subprocess.Popen(
        cmd, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, env=train_env(), start_new_session=True
    )
    t0 = time.monotonic()
    killed = False
    while proc.poll() is None:
        if trig.fire(run):
            os.killpg(proc.pid, signal.SIGKILL)
            killed = True
            break
        time.sleep(POLL_S)
    proc.wait()
    log.close()
    kill_s = time.monotonic() - t0
    tmp_left = tmp_files(run / "teacher") + tmp_files(run / "student")
    t_ck = ckpt_iteration(run / "teacher" / "latest.pt", "teacher")
    s_ck = ckpt_iteration(run / "student" / "latest.pt", "student")
    where = (
        "teacher"
        if t_ck < T_ITERS or ("teacher", T_ITERS) not in rows(run / "eval.csv")
        else "distillation"
        if s_ck < D_ITERS
        else "final evaluation"
    )
    problems = []
    saved_levels = checkpoint_levels(run / "teacher" / "latest.pt", "teacher")
    resume = [sys.executable, "-m", "march.train", f"resume={run}"]
    if device_trial:
        if not has_cuda and killed:
            craft_cuda_run(run)
        # Without the override a cuda:0 run on a machine without CUDA stops in one line.
        if not cuda_available():
            no = subprocess.run(resume, cwd=ROOT, capture_output=True, text=True, env=train_env())
            err = no.stderr.strip().splitlines()
            if no.returncode != 2 or len(err) != 1 or "compute.device=cpu" not in err[0]:
                problems.append(f"resume without the override: exit {no.returncode}, {err}")
        resume.append("compute.device=cpu")
    res = subprocess.run(resume, cwd=ROOT, capture_output=True, text=True, env=train_env())
    (out / f"trial_{i:02d}.resume.log").write_text(res.stdout + res.stderr)
    if device_trial and killed and "saved on cuda:0, resumed on cpu" not in res.stdout:
        problems.append("the resume on the CPU did not say which streams it reseeded")
    if curriculum:
        if saved_levels is None or saved_levels[0] < T_SAVE:
            problems.append(f"killed before a promotion reached a checkpoint ({saved_levels})")
        else:
            got = resumed_levels(res.stdout, "teacher")
            if got != saved_levels[1]:
                problems.append(
                    f"teacher envs resumed on levels {got}, checkpoint {saved_levels[0]} holds "
                    f"{saved_levels[1]} (mean {saved_levels[2]:.3g})"
                )
    status = ""
    if (run / "status.json").is_file():
        import json

        status = json.loads((run / "status.json").read_text()).get("state", "")
    if res.returncode != 0 or status != "done":
        problems.append(f"resume exit {res.returncode}, status {status!r}")
    # No iteration lost beyond the last checkpoint: the resume starts where it stands.
    lost_its = 0
    for stage, ck in (("teacher", t_ck), ("student", s_ck)):
        at = resumed_at(res.stdout, stage)
        if at != ck:
            lost_its += max(0, ck - at)
            problems.append(f"{stage} resumed at {at}, newest checkpoint {ck}")
    # Every row exactly once.
    expected = {
        "metrics.csv": [("teacher", k) for k in range(1, T_ITERS + 1)]
        + [("student", k) for k in range(1, D_ITERS + 1)],
        "eval.csv": [("teacher", k) for k in sorted(expected_evals(T_ITERS, T_EVAL))]
        + [("student", k) for k in sorted(expected_evals(D_ITERS, D_EVAL))],
    }
    lost = dup = 0
    for name, want in expected.items():
        got = Counter(rows(run / name))
        miss = [w for w in want if got[w] == 0]
        extra = {k: c - 1 for k, c in got.items() if c > 1}
        unexpected = [k for k in got if k not in want]
        lost += len(miss)
        dup += sum(extra.values())
        if miss or extra or unexpected:
            problems.append(f"{name}: missing {miss}, duplicated {extra}, unexpected {unexpected}")
    loadable = True
    for kind, want_it in (("teacher", T_ITERS), ("student", D_ITERS)):
        try:
            it = int(load_checkpoint(run / kind / "latest.pt", kind)["iteration"])
        except CheckpointError as err:
            loadable = False
            problems.append(str(err))
            continue
        if it != want_it:
            loadable = False
            problems.append(f"final {kind} checkpoint at iteration {it}, expected {want_it}")
    for kind, its in (
        ("teacher", expected_evals(T_ITERS, T_SAVE)),
        ("student", expected_evals(D_ITERS, D_SAVE)),
    ):
        gaps = [k for k in sorted(its) if not (run / kind / f"model_{k:06d}.pt").is_file()]
        if gaps:
            problems.append(f"{kind}/: no model file for save points {gaps}")
    left = tmp_files(run / "teacher") + tmp_files(run / "student")
    if left:
        problems.append(f"temporary files left after the resume: {left}")
    if not (run / "summary.json").is_file():
        problems.append("no summary.json")
    if not killed:
        problems.append("the run finished before its kill moment")
    return {
        "trial": i,
        "phase": phase,
        "killed_in": where if killed else "-",
        "trigger": trig.describe(),
        "kill_s": kill_s,
        "ckpts": (t_ck, s_ck),
        "tmp_left": tmp_left,
        "killed": killed,
        "resumed": res.returncode == 0 and status == "done" and lost_its == 0,
        "lost": lost + lost_its,
        "dup": dup,
        "loadable": loadable,
        "problems": problems,
        "levels": (
            f"checkpoint {saved_levels[0]} mean {saved_levels[2]:.3g} digest {saved_levels[1]}"
            if curriculum and saved_levels
            else ""
        ),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--trials", type=int, default=len(PHASES), help=f"number of trials (default {len(PHASES)})"
    )
    ap.add_argument("--seed", type=int, default=0, help="seeds the kill moments (default 0)")
    ap.add_argument("--first", type=int, default=0, help="start at this trial of the schedule")
    ap.add_argument("--out", type=Path, default=ROOT / "outputs" / "kill_trials")
    args = ap.parse_args(argv)
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    print(f"kill trials: {args.trials}, seed {args.seed}, runs in {out}", flush=True)
    print(f"each run: {' '.join(SIZES)}", flush=True)
    results = []
    for i in range(args.first, args.first + args.trials):
        rng = random.Random(args.seed * 1000 + i)
        phase = PHASES[i % len(PHASES)]
        t0 = time.monotonic()
        r = run_trial(i, phase, rng, out)
        results.append(r)
        extra = f"; levels at the kill: {r['levels']}" if r["levels"] else ""
        ok = "ok" if not r["problems"] else "FAILED: " + "; ".join(r["problems"])
        print(
            f"trial {i:2d} [{phase}] killed after {r['kill_s']:.1f} s ({r['trigger']}) in "
            f"{r['killed_in']}; checkpoints teacher {r['ckpts'][0]} student {r['ckpts'][1]}"
            f"{'; temp files left ' + ','.join(r['tmp_left']) if r['tmp_left'] else ''}; "
            f"{time.monotonic() - t0:.0f} s{extra}: {ok}",
            flush=True,
        )
    n = len(results)
    killed = sum(r["killed"] for r in results)
    resumed = sum(r["resumed"] for r in results)
    lost = sum(r["lost"] for r in results)
    dup = sum(r["dup"] for r in results)
    loadable = sum(r["loadable"] for r in results)
    phases = Counter(r["killed_in"] for r in results)
    cur = [r for r in results if "curriculum" in r["phase"]]
    levels_ok = sum(1 for r in cur if not r["problems"])
    dev = [r for r in results if "another device" in r["phase"]]
    dev_ok = sum(1 for r in dev if not r["problems"])
    print(
        f"tally: trials {n}, killed {killed}/{n} "
        f"({', '.join(f'{k} {v}' for k, v in sorted(phases.items()))}), resumed {resumed}/{n}, "
        f"rows lost {lost}, rows duplicated {dup}, final checkpoints loadable {loadable}/{n}, "
        f"levels resumed env by env {levels_ok}/{len(cur)}, device override {dev_ok}/{len(dev)}",
        flush=True,
    )
    passed = all(not r["problems"] for r in results)
    print("PASSED" if passed else "FAILED", flush=True)
    return 0 if passed else 1


if __name__ == "__main__":
    raise SystemExit(main())
