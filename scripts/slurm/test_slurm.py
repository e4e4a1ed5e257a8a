"""End-to-end check of march on a real Slurm cluster (``make test-slurm``; slow, not in CI).

Needs the single-node cluster of ``scripts/slurm/start.sh`` (SLURM_CONF set). Through it:

1. a two-run smoke sweep (``+experiment=clf,modelfree``) with ``hydra/launcher=march_slurm``, sized for
   a CPU node (no GPU, one CPU per job), every job an array task of one sbatch submission;
2. job 0 (clf) is requeued with ``scontrol requeue`` once its first teacher checkpoint exists and
   while it is still running: Slurm kills it and starts it again, submitit re-runs the same Hydra
   job in the same run directory, and march.train resumes from the checkpoint by itself;
3. both runs must end ``done`` with a summary, the requeued one with ``Restarts=1`` in Slurm and a
   "resuming from" line in its log; no (stage, iteration) row of metrics.csv or eval.csv may be
   duplicated or missing, and every stage's final checkpoint must load;
4. ``analysis/figures.py`` reads the sweep directory and lists both runs as done;
5. three data-parallel runs, each one job of 2 tasks (``hydra/launcher=march_slurm_ddp``, gloo,
   one CPU per task), traced per rank (``extra_modules=[tests.ddp_trace]``): Slurm accepts the
   job (its srun line carries ``--kill-on-bad-exit=1``) and it trains;

   - **requeue**: ``scontrol requeue`` once its first teacher checkpoint exists;
   - **usr2**: ``scancel --signal=USR2`` (what ``--signal=USR2@<s>`` sends before a time limit):
     both ranks checkpoint, rank 0's submitit handler requeues the job, ranks > 0 wait for it;

   both must end ``done`` with every row once, env steps summed over both ranks, ``Restarts=1``,
   a "resuming from" line, and each rank's restored state (levels, clocks, commands, every
   random stream) equal to what that rank saved before the requeue, the two ranks' different;
   - **kill**: rank 1's process SIGKILLed after the first checkpoint: the step ends (srun's
     kill-on-bad-exit) well within ``compute.dist_timeout_s``, the job FAILED, rank 0's log and
     ``status.json`` end with the one lost-rank line (``--no-ddp`` skips all three).

Prints one PASS/FAIL line per check and exits 0 only when all pass.

    python scripts/slurm/test_slurm.py [--out DIR] [--timeout-min 60]
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import re
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[2]
PY = sys.executable

# The smoke preset with a few more teacher iterations, so that the requeue lands mid-run (after
# the first checkpoint, before the end) with room to spare; one torch thread per job.
SWEEP_ARGS = [
    "+experiment=clf,modelfree",
    "seed=0",
    "compute=smoke",
    "compute.torch_threads=1",
    "teacher.max_iterations=4",
    "hydra/launcher=march_slurm",
    # A CPU node: no GPU, one CPU and 2 GB per job, both jobs at once on the node's 2 CPUs.
    "hydra.launcher.gpus_per_node=null",
    "hydra.launcher.cpus_per_task=1",
    "hydra.launcher.mem_gb=2",
    "hydra.launcher.timeout_min=60",
]


class Checks:
    def __init__(self) -> None:
        self.results: list[tuple[bool, str]] = []

    def check(self, ok: bool, what: str) -> bool:
        self.results.append((bool(ok), what))
        print(f"[test-slurm] {'PASS' if ok else 'FAIL'}: {what}", flush=True)
        return bool(ok)

    def summary(self) -> int:
        passed = sum(ok for ok, _ in self.results)
        total = len(self.results)
        verdict = "PASSED" if passed == total and total else "FAILED"
        print(f"[test-slurm] {verdict}: {passed}/{total} checks passed", flush=True)
        for ok, what in self.results:
            if not ok:
                print(f"[test-slurm]   failed: {what}", flush=True)
        return 0 if verdict == "PASSED" else 1


def say(msg: str) -> None:
    print(f"[test-slurm] {msg}", flush=True)


def sh(*cmd: str) -> str:
    return subprocess.run(cmd, check=True, capture_output=True, text=True, timeout=60).stdout


def squeue_jobs() -> dict[str, str]:
    """Job id (``<array>_<task>``) -> state of this user's jobs in Slurm's queue."""
    out = sh("squeue", "-h", "-o", "%i %T")
    return dict(line.split() for line in out.splitlines() if line.strip())


def job_field(job_id: str, key: str) -> str | None:
    out = sh("scontrol", "show", "job", job_id)
    m = re.search(rf"\b{key}=(\S+)", out)
    return m.group(1) if m else None


def read_rows(path: Path) -> list[dict[str, str]]:
    if not path.is_file():
        return []
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def label(run: Path) -> str:
    """``0_+experiment-clf_compute...`` -> ``run 0 (+experiment-clf)``."""
    num, _, rest = run.name.partition("_")
    return f"run {num} ({rest.split('_')[0]})"


def check_rows(checks: Checks, run: Path, name: str, expected: dict[str, int | list[int]]) -> None:
    """Each stage's rows in ``name`` are exactly iterations 1..n (or the listed iterations):
    none lost, none duplicated."""
    rows = read_rows(run / name)
    keys = [(r["stage"], int(r["iteration"])) for r in rows]
    dup = sorted(k for k, n in Counter(keys).items() if n > 1)
    checks.check(not dup, f"{label(run)} {name}: no (stage, iteration) row twice {dup or ''}")
    for stage, n in expected.items():
        want = list(range(1, n + 1)) if isinstance(n, int) else n
        its = sorted(i for s, i in keys if s == stage)
        shown = f"1..{n}" if isinstance(n, int) else str(want)
        checks.check(
            its == want, f"{label(run)} {name}: {stage} iterations {its} = {shown} (none lost)"
        )


def evaluated(n: int, interval: int) -> list[int]:
    """The iterations a stage of n iterations evaluates: every ``interval``-th and its last."""
    return sorted({i for i in range(1, n + 1) if interval and i % interval == 0} | {n})


def check_checkpoints(checks: Checks, run: Path) -> None:
    code = (
        "import sys; from march.store.checkpoint import load_checkpoint\n"
        "for kind in ('teacher', 'student'):\n"
        "    p = load_checkpoint(sys.argv[1] + f'/{kind}/latest.pt', kind, 'cpu')\n"
        "    print(kind, int(p['iteration']))\n"
    )
    res = subprocess.run([PY, "-c", code, str(run)], capture_output=True, text=True)
    checks.check(
        res.returncode == 0,
        f"{label(run)}: final teacher and student checkpoints load "
        f"({' '.join(res.stdout.split()) or res.stderr.strip().splitlines()[-1:]})",
    )


# One run over 2 Slurm tasks (2 ranks, gloo, one CPU each) with the DDP launcher; enough teacher
# iterations (~1.5 s each) that a requeue or a kill lands mid-run; every rank traced.
DDP_TIMEOUT_S = 60
DDP_ARGS = [
    "compute=smoke",
    "compute.torch_threads=1",
    "teacher.max_iterations=16",
    f"compute.dist_timeout_s={DDP_TIMEOUT_S}",
    "extra_modules=[tests.ddp_trace]",
    "hydra/launcher=march_slurm_ddp",
    "hydra.launcher.tasks_per_node=2",
    "hydra.launcher.gpus_per_node=null",
    "hydra.launcher.cpus_per_task=1",
    "hydra.launcher.mem_gb=2",
    "hydra.launcher.timeout_min=60",
]


def requeue_when_checkpointed(
    sweep: Path, launcher: subprocess.Popen, deadline: float, single: bool = False
) -> tuple[str | None, str]:
    """``scontrol requeue`` job 0 of ``sweep`` once its first teacher checkpoint exists while it
    still runs; (the requeued job id or None, run 0's state when it was requeued). ``single``:
    a sweep of one run, which submitit submits as a plain job (id ``<n>``, not ``<n>_0``)."""
    run0_state = ""
    while time.time() < deadline and launcher.poll() is None:
        time.sleep(2)
        runs = sorted(sweep.glob("0_*"))
        if not runs:
            continue
        run0 = runs[0]
        status = run0 / "status.json"
        try:
            run0_state = json.loads(status.read_text())["state"] if status.is_file() else ""
        except (json.JSONDecodeError, KeyError):
            continue  # being written
        if (run0 / "teacher" / "latest.pt").is_file() and run0_state == "running":
            jobs = {
                j: s
                for j, s in squeue_jobs().items()
                if j.endswith("_0") or (single and "_" not in j)
            }
            if len(jobs) != 1 or next(iter(jobs.values())) != "RUNNING":
                continue
            requeued = next(iter(jobs))
            ckpts = sorted(p.name for p in (run0 / "teacher").glob("model_*.pt"))
            say(f"requeueing job {requeued} (run {run0.name}, checkpoints {ckpts})")
            sh("scontrol", "requeue", requeued)
            return requeued, run0_state
    return None, run0_state


def wait_for(launcher: subprocess.Popen, deadline: float, timeout_min: float) -> None:
    while time.time() < deadline and launcher.poll() is None:
        time.sleep(5)
    if launcher.poll() is None:
        say(f"timeout after {timeout_min} min: cancelling the sweep")
        subprocess.run(["scancel", "--user", os.environ.get("USER", "root")], check=False)
        launcher.terminate()
        launcher.wait(30)


def check_own_states(checks: Checks, name: str, trace: Path, text: str) -> None:
    """After the requeue each rank restored exactly what it saved at that iteration, and the two
    ranks' states differ (tests/ddp_trace.py wrote both)."""
    found = re.findall(r"\[teacher\] resuming from .* at iteration (\d+)", text)
    if not checks.check(bool(found), f"{name}: the teacher resumed {found}"):
        return
    at = int(found[-1])
    from march.store.checkpoint import CheckpointError, load_plain_file, state_differences

    try:
        saved = [load_plain_file(trace / f"teacher_save_{at}_rank{r}.pt", "trace") for r in (0, 1)]
        restored = [
            load_plain_file(trace / f"teacher_restored_{at}_rank{r}.pt", "trace") for r in (0, 1)
        ]
    except (FileNotFoundError, CheckpointError) as err:
        checks.check(False, f"{name}: rank traces of iteration {at} ({err})")
        return
    for r in (0, 1):
        diff = state_differences(saved[r], restored[r])
        checks.check(
            not diff, f"{name}: rank {r} restored its own state of iteration {at} {diff or ''}"
        )
    differ = state_differences(saved[0], saved[1])
    checks.check(
        "state.streams.torch" in differ and "state.episode.episode_length_buf" in differ,
        f"{name}: the two ranks' states differ ({len(differ)} entries, e.g. {differ[:2]})",
    )


def start_ddp(sweep: Path, *extra: str) -> subprocess.Popen:
    cmd = [PY, "-m", "march.train", "-m", *DDP_ARGS, *extra, f"hydra.sweep.dir={sweep}"]
    say(f"ddp {sweep.name}: " + " ".join(cmd[1:]))
    (sweep / "trace").mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MARCH_TRACE_DIR": str(sweep / "trace")}
    launcher_log = sweep.parent / f"{sweep.name}.launcher.log"
    with launcher_log.open("w") as log:
        return subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT)


def ddp_job_when_checkpointed(
    sweep: Path, launcher: subprocess.Popen, deadline: float
) -> tuple[str | None, Path | None]:
    """(job id, run directory) of the sweep's one 2-task job once its first teacher checkpoint
    exists while it runs (None, None if it never gets there)."""
    while time.time() < deadline and launcher.poll() is None:
        time.sleep(1)
        runs = sorted(p for p in sweep.glob("0_*") if p.is_dir())
        if not runs or not (runs[0] / "teacher" / "model_000001.pt").is_file():
            continue
        jobs = [j for j, s in squeue_jobs().items() if s == "RUNNING"]
        if len(jobs) == 1:
            return jobs[0], runs[0]
    return None, None


def submission(sweep: Path, job: str) -> str:
    path = sweep / ".submitit" / job / f"{job}_submission.sh"
    return path.read_text() if path.is_file() else ""


def check_ddp(
    checks: Checks, sweep: Path, deadline: float, timeout_min: float, how: str = "requeue"
) -> None:
    """One run as one 2-task job (2 ranks), requeued mid-run (``scontrol requeue``, or USR2 as
    before a time limit): it ends done and every rank resumed its own state."""
    name = f"ddp-{how}"
    launcher = start_ddp(sweep)
    job, run = ddp_job_when_checkpointed(sweep, launcher, deadline)
    if not checks.check(job is not None, f"{name}: Slurm accepted the 2-task job and it trains"):
        wait_for(launcher, deadline, timeout_min)
        return
    srun = [ln for ln in submission(sweep, job).splitlines() if ln.startswith("srun ")]
    header = [ln for ln in submission(sweep, job).splitlines() if "kill-on-bad-exit" in ln]
    checks.check(
        bool(srun) and "--kill-on-bad-exit=1" in srun[0].split() and header == srun,
        f"{name}: kill-on-bad-exit on the srun line only ({header})",
    )
    ckpts = sorted(p.name for p in (run / "teacher").glob("model_*.pt"))
    if how == "usr2":
        say(f"{name}: scancel --signal=USR2 {job} (checkpoints {ckpts})")
        sh("scancel", "--signal=USR2", job)
    else:
        say(f"{name}: scontrol requeue {job} (checkpoints {ckpts})")
        sh("scontrol", "requeue", job)
    wait_for(launcher, deadline, timeout_min)
    checks.check(launcher.returncode == 0, f"{name}: launcher exit code {launcher.returncode}")
    status = (
        json.loads((run / "status.json").read_text()) if (run / "status.json").is_file() else {}
    )
    checks.check(
        status.get("state") == "done", f"{name} {label(run)}: status {status.get('state')}"
    )
    checks.check((run / "summary.json").is_file(), f"{name} {label(run)}: summary.json written")
    cfg = OmegaConf.load(run / "config.yaml")
    its = {"teacher": int(cfg.teacher.max_iterations), "student": int(cfg.distill.max_iterations)}
    check_rows(checks, run, "metrics.csv", its)
    evals = {
        "teacher": evaluated(its["teacher"], int(cfg.teacher.eval_interval)),
        "student": evaluated(its["student"], int(cfg.distill.eval_interval)),
    }
    check_rows(checks, run, "eval.csv", evals)
    rows = [r for r in read_rows(run / "metrics.csv") if r["stage"] == "teacher"]
    per_it = 2 * int(cfg.compute.num_envs) * int(cfg.teacher.num_steps_per_env)
    steps = [int(r["env_steps"]) for r in rows]
    checks.check(
        steps == [per_it * (i + 1) for i in range(len(steps))],
        f"{name}: teacher env steps {steps[:3]}...{steps[-1:]} = 2 ranks x "
        f"{cfg.compute.num_envs} envs x {cfg.teacher.num_steps_per_env} steps per iteration",
    )
    check_checkpoints(checks, run)
    code = (
        "import sys, torch; p = torch.load(sys.argv[1], weights_only=True); "
        "print(p['world_size'], len(p['rank_states']))"
    )
    res = subprocess.run(
        [PY, "-c", code, str(run / "teacher" / "latest.pt")], capture_output=True, text=True
    )
    checks.check(
        res.stdout.split() == ["2", "2"],
        f"{name}: the teacher checkpoint holds both ranks' states ({res.stdout.strip()})",
    )
    logs = sorted((sweep / ".submitit").glob("*/*_0_log.out"))
    text = "".join(p.read_text(errors="replace") for p in logs)
    checks.check("distributed: 2 ranks (gloo)" in text, f"{name}: rank 0's log says 2 ranks")
    restarts = job_field(job, "Restarts")
    checks.check(restarts == "1", f"{name}: Slurm reports job {job} Restarts={restarts}")
    if how == "usr2":
        preempted = re.findall(r"\[preempted\] SIGUSR2: teacher iteration (\d+) checkpointed", text)
        requeued = re.findall(r"Requeued job \d+", text)
        checks.check(
            bool(preempted) and bool(requeued),
            f"{name}: teacher iteration {preempted[:1]} checkpointed on USR2 and rank 0's submitit "
            f"handler requeued the job ({requeued[:1]})",
        )
    check_own_states(checks, name, sweep / "trace", text)


def check_ddp_kill(checks: Checks, sweep: Path, deadline: float) -> None:
    """Rank 1 of a 2-task job SIGKILLed mid-run: the step ends at once (srun's kill-on-bad-exit),
    well within the process group's timeout, and rank 0 says so in one line."""
    name = "ddp-kill"
    launcher = start_ddp(sweep)
    try:
        job, run = ddp_job_when_checkpointed(sweep, launcher, deadline)
        if not checks.check(job is not None, f"{name}: the 2-task job trains"):
            return
        pids = [ln.split() for ln in sh("scontrol", "listpids", job).splitlines()[1:]]
        rank1 = [int(p[0]) for p in pids if len(p) == 5 and p[2] == "0" and p[4] == "1"]
        if not checks.check(len(rank1) == 1, f"{name}: rank 1's process of job {job} {rank1}"):
            return
        say(f"{name}: SIGKILL rank 1 (pid {rank1[0]}) of job {job}")
        os.kill(rank1[0], signal.SIGKILL)
        killed = time.time()
        while time.time() < killed + 3 * DDP_TIMEOUT_S:
            state = job_field(job, "JobState")
            if state not in ("RUNNING", "COMPLETING"):
                break
            time.sleep(0.2)
        took = time.time() - killed
        checks.check(
            state == "FAILED" and took < DDP_TIMEOUT_S,
            f"{name}: the job ended {state} {took:.1f} s after the kill (process group timeout "
            f"{DDP_TIMEOUT_S} s)",
        )
        err = sweep / ".submitit" / job / f"{job}_0_log.err"
        lines = [ln for ln in err.read_text(errors="replace").splitlines() if "rank 0:" in ln]
        checks.check(
            len(lines) == 1
            and lines[0].startswith("error: rank 0: another rank of this 2-rank run stopped")
            and lines[0].endswith(f"resume={run}"),
            f"{name}: rank 0 said it in one line: {lines[-1][:150] if lines else None}...",
        )
        status = json.loads((run / "status.json").read_text())
        checks.check(
            status.get("state") == "failed" and status.get("error", "") in lines[0],
            f"{name}: status.json {status.get('state')} with the same line",
        )
    finally:  # without Slurm accounting submitit cannot tell that a failed job ended
        if launcher.poll() is None:
            launcher.terminate()
            launcher.wait(30)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=None, help="sweep directory (default: new)")
    ap.add_argument("--timeout-min", type=float, default=60.0, help="give up after [min]")
    ap.add_argument("--no-ddp", action="store_true", help="skip the 2-task data-parallel job")
    ap.add_argument("--only-ddp", action="store_true", help="only the 2-task data-parallel job")
    args = ap.parse_args()
    if not os.environ.get("SLURM_CONF") and not Path("/etc/slurm/slurm.conf").is_file():
        say("error: no cluster: run scripts/slurm/start.sh and export the SLURM_CONF it prints")
        return 2
    stamp = time.strftime("%Y-%m-%d_%H-%M-%S")
    sweep = (args.out or ROOT / "outputs" / "slurm-test" / stamp).resolve()
    sweep.parent.mkdir(parents=True, exist_ok=True)
    checks = Checks()
    deadline = time.time() + 60 * args.timeout_min

    if args.only_ddp:
        ddp_checks(checks, sweep, deadline, args.timeout_min)
        return checks.summary()
    cmd = [PY, "-m", "march.train", "-m", *SWEEP_ARGS, f"hydra.sweep.dir={sweep}"]
    say("sweep: " + " ".join(cmd[1:]))
    launcher_log = sweep.parent / f"{sweep.name}.launcher.log"
    with launcher_log.open("w") as log:
        launcher = subprocess.Popen(cmd, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)

    # Job 0 (clf): requeue once its first teacher checkpoint exists, while it still runs.
    requeued, run0_state = requeue_when_checkpointed(sweep, launcher, deadline)
    checks.check(
        requeued is not None,
        f"job 0 requeued with scontrol requeue mid-run (run state was {run0_state or 'none'})",
    )

    wait_for(launcher, deadline, args.timeout_min)
    checks.check(launcher.returncode == 0, f"sweep launcher exit code {launcher.returncode}")
    if launcher.returncode != 0:
        say(f"launcher log: {launcher_log}")
        print("".join(launcher_log.read_text().splitlines(keepends=True)[-15:]), flush=True)

    runs = sorted(p for p in sweep.iterdir() if p.is_dir() and re.match(r"\d+_", p.name))
    checks.check(len(runs) == 2, f"two run directories in {sweep}: {[r.name for r in runs]}")
    for run in runs:
        status = (
            json.loads((run / "status.json").read_text()) if (run / "status.json").is_file() else {}
        )
        checks.check(status.get("state") == "done", f"{label(run)}: status {status.get('state')}")
        checks.check((run / "summary.json").is_file(), f"{label(run)}: summary.json written")
        cfg = OmegaConf.load(run / "config.yaml") if (run / "config.yaml").is_file() else None
        t = cfg.teacher if cfg is not None else None
        teacher_its = max(1, round(t.max_iterations * t.budget_scale)) if t is not None else -1
        distill_its = int(cfg.distill.max_iterations) if cfg is not None else -1
        check_rows(checks, run, "metrics.csv", {"teacher": teacher_its, "student": distill_its})
        # With eval_interval 1 (smoke) every iteration of both stages has one evaluation row.
        every = cfg is not None and cfg.teacher.eval_interval == cfg.distill.eval_interval == 1
        expected = {"teacher": teacher_its, "student": distill_its} if every else {}
        check_rows(checks, run, "eval.csv", expected)
        check_checkpoints(checks, run)

    if requeued is not None and runs:
        restarts = job_field(requeued, "Restarts")
        checks.check(restarts == "1", f"Slurm reports job {requeued} Restarts={restarts}")
        logs = sorted((sweep / ".submitit").glob(f"{requeued}/*_log.out"))
        text = "".join(p.read_text(errors="replace") for p in logs)
        resumed = re.findall(r"\[(teacher|student)\] resuming from .* at iteration (\d+)", text)
        checks.check(
            bool(resumed), f"job {requeued} log: resumed from its checkpoint {resumed or ''}"
        )

    fig = subprocess.run(
        [PY, "analysis/figures.py", str(sweep), "--out", str(sweep / "figures")],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    checks.check(fig.returncode == 0, f"analysis/figures.py exit code {fig.returncode}")
    if fig.returncode != 0:
        print(fig.stderr[-2000:], flush=True)
    table = read_rows(sweep / "figures" / "runs.csv")
    found = sorted((r.get("reward", ""), r.get("state", "")) for r in table)
    checks.check(
        found == [("clf", "done"), ("modelfree", "done")],
        f"analysis/figures.py runs.csv lists the sweep's runs as (reward, state) {found}",
    )
    figs = [
        n for n in ("baseline.png", "sample_efficiency.png") if (sweep / "figures" / n).is_file()
    ]
    checks.check(len(figs) == 2, f"analysis/figures.py drew {figs} from the sweep")
    say(f"sweep directory: {sweep}")
    if not args.no_ddp:
        ddp_checks(checks, sweep, deadline, args.timeout_min)
    return checks.summary()


def ddp_checks(checks: Checks, sweep: Path, deadline: float, timeout_min: float) -> None:
    check_ddp(checks, sweep.with_name(sweep.name + "_ddp"), deadline, timeout_min)
    check_ddp(checks, sweep.with_name(sweep.name + "_ddp_usr2"), deadline, timeout_min, "usr2")
    check_ddp_kill(checks, sweep.with_name(sweep.name + "_ddp_kill"), deadline)


if __name__ == "__main__":
    sys.exit(main())
