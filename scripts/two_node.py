"""Two nodes on one machine: two ``torchrun`` processes, one per "node", meet by c10d rendezvous on
127.0.0.1 and train one smoke run together (teacher PPO then distillation, gloo on CPU).

    python scripts/two_node.py [--out outputs/two_node] [--port 29517] [--order both]  (make two-node)

Which node holds global rank 0 is the rendezvous's choice, not ``--node_rank``'s: c10d ignores it
and ranks the nodes by their agents' (host, pid) (torch warns). ``--order swapped`` starts the
``--node_rank=1`` launch first, so that it becomes rank 0; the run directory, its logs and
checkpoints must follow global rank 0 wherever it is. ``--order both`` (the default) runs the
usual order, then the swapped one.

Each launch is what a real node runs (``torchrun --nnodes=2 --node_rank=<0|1>
--nproc_per_node=1 --rdzv_backend=c10d --rdzv_endpoint=<host>:<port>``); here both endpoints are
127.0.0.1. ``tests/ddp_trace.py`` is the entry point (``march.train`` with every update's
networks dumped per rank). Checked and printed: both launches exit 0; one run directory (rank
0's: one ``.hydra/``, one metrics row per iteration, rank 1's log under ``ranks/``); after every
PPO and distillation update every parameter and normaliser buffer is bitwise equal on the two
nodes, while the rollouts each learned from differ. Exit 1 if any check fails.
"""

from __future__ import annotations

import argparse
import csv
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # this checkout's march, whatever python runs the script
from march.store.checkpoint import load_checkpoint  # noqa: E402

TORCHRUN = str(Path(sys.executable).with_name("torchrun"))
RUN = [
    "compute=smoke", "compute.eval_num_envs=1", "eval.num_rollouts=2",
    "eval.episode_length_s=0.5", "teacher.eval_interval=0", "distill.eval_interval=0",
    "compute.torch_threads=1",
]  # fmt: skip


def launch(node: int, port: int, run: Path, trace: Path) -> subprocess.Popen:
    cmd = [
        TORCHRUN, "--nnodes=2", f"--node_rank={node}", "--nproc_per_node=1",
        "--rdzv_backend=c10d", f"--rdzv_endpoint=127.0.0.1:{port}", "--rdzv_id=march-two-node",
        "tests/ddp_trace.py", *RUN, f"hydra.run.dir={run}",
    ]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    env["MARCH_TRACE_DIR"] = str(trace)
    print(f"[node {node}] {' '.join(cmd[1:7])}", flush=True)
    return subprocess.Popen(
        cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )


def rank0_launch(outputs: dict[int, str]) -> int | None:
    """The ``--node_rank`` of the launch whose worker is global rank 0 (it alone prints the
    banner; a rank > 0 prints into ``ranks/rank<r>.log``)."""
    found = [node for node, out in outputs.items() if "march.train  stage=" in out]
    return found[0] if len(found) == 1 else None


def check(run: Path, trace: Path) -> list[str]:
    problems: list[str] = []
    for stage in ("teacher", "student"):
        k = 1
        while (trace / f"{stage}_{k}_rank0.pt").is_file():
            # The traces are plain data read like a checkpoint: weights-only, nothing runs.
            r0, r1 = (load_checkpoint(trace / f"{stage}_{k}_rank{r}.pt", "trace") for r in (0, 1))
            same = [key for key, v in r0["state"].items() if torch.equal(v, r1["state"][key])]
            differ = [key for key, v in r0["state"].items() if key not in same]
            rollouts_differ = all(
                not torch.equal(v, r1["rollout"][key]) for key, v in r0["rollout"].items()
            )
            print(
                f"{stage} update {k}: {len(same)}/{len(r0['state'])} tensors equal on both "
                f"nodes; rollouts differ: {rollouts_differ}",
                flush=True,
            )
            if differ:
                problems.append(f"{stage} update {k}: {differ[:3]} differ")
            if not rollouts_differ:
                problems.append(f"{stage} update {k}: both nodes learned from the same rollout")
            k += 1
        if k == 1:
            problems.append(f"no {stage} update traced")
    with (run / "metrics.csv").open(newline="") as f:
        rows = [(r["stage"], r["iteration"], r["env_steps"]) for r in csv.DictReader(f)]
    print(f"metrics.csv (stage, iteration, env_steps over both nodes): {rows}")
    if len(rows) != len(set(rows)):
        problems.append("metrics.csv holds a row twice (both nodes wrote)")
    ranks = sorted(p.name for p in (run / "ranks").iterdir()) if (run / "ranks").is_dir() else []
    print(f"run directory {run}: {sorted(p.name for p in run.iterdir())}; ranks/: {ranks}")
    if ranks != ["rank1.log"]:
        problems.append(f"ranks/ holds {ranks}, not rank1.log")
    elif "[teacher] it " not in (run / "ranks" / "rank1.log").read_text(errors="replace"):
        problems.append("ranks/rank1.log holds no training lines of rank 1")
    for name in (".hydra", "config.yaml", "teacher/latest.pt", "student/latest.pt"):
        if not (run / name).exists():
            problems.append(f"the run directory has no {name} (rank 0's)")
    flags = [
        load_checkpoint(trace / f"teacher_1_rank{r}.pt", "trace")["writes_files"] for r in (0, 1)
    ]
    if flags != [True, False]:
        problems.append(f"writes run files on ranks 0, 1: {flags} (rank 0 alone must)")
    return problems


def run_once(out: Path, port: int, timeout: float, swapped: bool) -> list[str]:
    """One two-node run; the problems found (empty: passed)."""
    run, trace = out / "run", out / "trace"
    shutil.rmtree(out, ignore_errors=True)
    trace.mkdir(parents=True)
    t0 = time.time()
    order = (1, 0) if swapped else (0, 1)
    procs: dict[int, subprocess.Popen] = {}
    for n in order:
        procs[n] = launch(n, port, run, trace)
        time.sleep(0.5)  # the first launch's agent has the lower pid: c10d makes it rank 0
    outputs: dict[int, str] = {}
    for n in order:
        try:
            outputs[n], _ = procs[n].communicate(timeout=max(timeout - (time.time() - t0), 1))
        except subprocess.TimeoutExpired:
            for p in procs.values():
                p.kill()
            return [f"node {n} still running after {timeout:.0f} s"]
    for n in (0, 1):
        proc, text = procs[n], outputs[n]
        shown = [ln for ln in text.splitlines() if ln.startswith(("[", "distributed", "march"))]
        print(f"--- --node_rank={n} (exit {proc.returncode}), {len(text.splitlines())} lines; "
              "march's:")  # fmt: skip
        print("\n".join(shown[-25:]))
        if proc.returncode != 0:
            print(text[-3000:])
            return [f"--node_rank={n} exited {proc.returncode}"]
    problems = []
    holder = rank0_launch(outputs)
    print(f"global rank 0 ran in the launch with --node_rank={holder}")
    if holder != order[0]:
        problems.append(f"global rank 0 is on --node_rank={holder}, expected {order[0]}")
    problems += check(run, trace)
    print(f"wall time {time.time() - t0:.0f} s")
    return problems


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=ROOT / "outputs" / "two_node")
    ap.add_argument("--port", type=int, default=29517)
    ap.add_argument("--timeout", type=float, default=1200.0)
    ap.add_argument("--order", choices=("usual", "swapped", "both"), default="both")
    args = ap.parse_args()
    orders = {"usual": [False], "swapped": [True], "both": [False, True]}[args.order]
    failed = False
    for swapped in orders:
        what = "node ranks swapped (--node_rank=1 is rank 0)" if swapped else "usual order"
        print(f"=== two nodes, {what}", flush=True)
        out = args.out / ("swapped" if swapped else "usual")
        problems = run_once(out, args.port + swapped, args.timeout, swapped)
        if problems:
            print(f"FAILED ({what}): " + "; ".join(problems))
            failed = True
        else:
            print(f"PASSED ({what}): two nodes (c10d rendezvous on 127.0.0.1), one run "
                  "directory that follows global rank 0, weights equal on both nodes after every "
                  "update")  # fmt: skip
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
