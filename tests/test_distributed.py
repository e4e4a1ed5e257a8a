"""One run over 2 processes (gloo on CPU): same policy on every rank, rank 0 writes, resume.

The collectives are checked on two spawned gloo ranks against hand-derived values; the real
pipeline runs under ``torchrun`` at smoke size (``tests/ddp_trace.py`` dumps every update).
"""

from __future__ import annotations

import contextlib
import csv
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
import torch.multiprocessing as mp

from march.learn import distributed
from march.learn.distributed import Dist, eval_share, rank_seed, restore_rank_states

ROOT = Path(__file__).resolve().parent.parent
TORCHRUN = str(Path(sys.executable).with_name("torchrun"))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# -- pure functions ------------------------------------------------------------------------------


def test_rank_seeds_rank0_is_the_run_seed_others_distinct_and_int32():
    seeds = [0, 1, 7, 12345, 2**31 - 1]
    for seed in seeds:
        assert rank_seed(seed, 0) == seed  # one process = today's numbers
    drawn = {rank_seed(s, r) for s in range(50) for r in range(1, 9)}
    assert len(drawn) == 50 * 8  # no collisions among 400 (seed, rank) pairs
    assert all(0 <= x < 2**31 for x in drawn)
    # rank r of seed s is not rank 0 of a nearby seed (a seed sweep of an N-rank run)
    assert not drawn & set(range(60))


@pytest.mark.parametrize("n,world", [(4, 2), (5, 2), (7, 3), (2048, 8), (1, 2)])
def test_eval_shares_partition_the_rollout_indices(n, world):
    idx: list[int] = []
    for r in range(world):
        first, count = eval_share(n, Dist(rank=r, world=world))
        idx += list(range(first, first + count))
        assert n // world <= count <= -(-n // world)
    assert idx == list(range(n))  # every rollout once, in the one-process order


def test_resume_restores_each_ranks_stream_or_says_why(monkeypatch):
    states = []
    for s in (11, 22):
        torch.manual_seed(s)
        states.append({"rng": torch.get_rng_state(), "generator": torch.Generator().get_state()})
    payload = {"rank_rng": states, "world_size": 2, "config": {"seed": 3}, "iteration": 5}
    monkeypatch.setattr(distributed, "_DIST", Dist(rank=1, world=2))
    assert restore_rank_states(payload) is None
    assert torch.equal(torch.get_rng_state(), states[1]["rng"])
    # A third rank (resume with N=3 of a 2-rank run): a fresh stream, and one line saying so.
    monkeypatch.setattr(distributed, "_DIST", Dist(rank=2, world=3))
    note = restore_rank_states(payload)
    assert note == f"rank 2: checkpoint written by 2 rank(s); fresh random stream {rank_seed(8, 2)}"
    expected = torch.Generator().manual_seed(rank_seed(8, 2)).get_state()
    torch.manual_seed(0)
    restore_rank_states(payload)
    assert torch.equal(torch.get_rng_state(), expected)


def test_ranks_from_a_slurm_step_of_several_tasks():
    # srun / submitit's 2-node, 4-task step: rank 3 on the second node; no torchrun variables.
    env = {k: v for k, v in os.environ.items() if k not in ("WORLD_SIZE", "RANK", "LOCAL_RANK")}
    env |= {"SLURM_NTASKS": "4", "SLURM_PROCID": "3", "SLURM_LOCALID": "1", "SLURM_NODEID": "1"}
    env |= {"SLURM_JOB_ID": "4242", "SLURM_JOB_NODELIST": "gpu[07-08]"}
    env |= {"SLURM_JOB_NUM_NODES": "2", "PYTHONPATH": str(ROOT)}
    code = (
        "import os; from march.learn.distributed import env_world; print(*env_world(), "
        "os.environ['MASTER_ADDR'], os.environ['LOCAL_WORLD_SIZE'])"
    )
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert out.stdout.split() == ["3", "4", "1", "gpu07", "2"], out.stderr
    env["SLURM_NTASKS"] = "1"  # one task per job (hydra/launcher=march_slurm): one process
    out = subprocess.run(
        [
            sys.executable,
            "-c",
            code.replace(", os.environ['MASTER_ADDR'], os.environ['LOCAL_WORLD_SIZE']", ""),
        ],
        env=env,
        capture_output=True,
        text=True,
    )
    assert out.stdout.split() == ["0", "1", "0"], out.stderr


def test_rank_config_changes_seed_and_device_only():
    from march.config.cli import load

    cfg = load(["compute=smoke", "seed=5"])
    assert distributed.rank_config(cfg, Dist()) is cfg
    r1 = distributed.rank_config(cfg, Dist(rank=1, world=2, local_rank=1, backend="gloo"))
    assert r1.seed == rank_seed(5, 1) and r1.compute.device == "cpu"
    assert r1.compute.num_envs == cfg.compute.num_envs and r1.curriculum == cfg.curriculum
    gpu = load(["compute=gpu", "seed=5"])
    r3 = distributed.rank_config(gpu, Dist(rank=3, world=4, local_rank=3, backend="nccl"))
    assert r3.compute.device == "cuda:3" and r3.seed == rank_seed(5, 3)


# -- collectives on two real gloo ranks ---------------------------------------------------------


def _collectives_rank(rank: int, port: int, out: str) -> None:
    os.environ.update(
        {"MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port), "RANK": str(rank)}
        | {"WORLD_SIZE": "2", "LOCAL_RANK": str(rank)}
    )
    from rsl_rl.modules.normalization import EmpiricalNormalization

    d = distributed.init("cpu")
    gen = torch.Generator().manual_seed(100 + rank)
    # Normaliser: rank 0 sees 3 rows, rank 1 five, twice.
    norm = EmpiricalNormalization(4)
    assert distributed.sync_normalizers(torch.nn.Sequential(norm)) == 1
    batches = [torch.randn(3 + 2 * rank, 4, generator=gen) * (1 + rank) for _ in range(2)]
    for b in batches:
        norm.update(b)
    # Gradients: rank r's gradient is r + 1 everywhere -> mean 1.5.
    lin = torch.nn.Linear(3, 2)
    for p in lin.parameters():
        p.grad = torch.full_like(p, float(rank + 1))
    distributed.average_gradients(lin.parameters())
    means = distributed.mean_over_ranks({"a": float(rank), "b": float("nan") if rank else 1.0})
    total = distributed.sum_over_ranks(rank + 2)
    # Episode stats: rank 0 ended 2 episodes (returns 1, 3), rank 1 one (return 10).
    from march.learn.teacher import EpisodeStats

    stats = EpisodeStats(2, "cpu", window=4)
    ret = torch.tensor([1.0, 3.0]) if rank == 0 else torch.tensor([10.0, 0.0])
    done = torch.tensor([True, True]) if rank == 0 else torch.tensor([True, False])
    stats.step(ret, done, torch.tensor([0.5, 1.5]) if rank == 0 else torch.tensor([4.0, 0.0]))
    ep = distributed.pop_episode_stats(stats)
    first, mine = eval_share(5)
    per = {"distance_m": torch.arange(first, first + mine, dtype=torch.float32)}
    gathered = distributed.gather_rollouts(per)
    torch.save(
        {
            "norm": {k: v.clone() for k, v in norm.state_dict().items()},
            "batches": batches,
            "grads": [p.grad.clone() for p in lin.parameters()],
            "means": means,
            "total": total,
            "ep": ep,
            "gathered": gathered,
            "agree": distributed.agree(f"rank {rank}"),
            "world": d.world,
        },
        Path(out) / f"rank{rank}.pt",
    )
    distributed.shutdown()


def test_collectives_on_two_gloo_ranks(tmp_path):
    from rsl_rl.modules.normalization import EmpiricalNormalization

    mp.spawn(_collectives_rank, args=(_free_port(), str(tmp_path)), nprocs=2, join=True)
    r0, r1 = (torch.load(tmp_path / f"rank{r}.pt") for r in (0, 1))
    # Normalisers: bitwise the same on both ranks, and equal to one normaliser fed both batches.
    for k in r0["norm"]:
        assert torch.equal(r0["norm"][k], r1["norm"][k]), k
    ref = EmpiricalNormalization(4).double()
    for i in range(2):
        ref.update(torch.cat([r0["batches"][i], r1["batches"][i]]).double())
    assert int(r0["norm"]["count"]) == 2 * (3 + 5)
    for k in ("_mean", "_var", "_std"):
        torch.testing.assert_close(
            r0["norm"][k].double(), ref.state_dict()[k], rtol=1e-5, atol=1e-6
        )
    for g0, g1 in zip(r0["grads"], r1["grads"], strict=True):
        assert torch.equal(g0, g1) and torch.all(g0 == 1.5)
    assert r0["means"]["a"] == r1["means"]["a"] == 0.5
    assert r0["means"]["b"] != r0["means"]["b"] and r1["means"]["b"] != r1["means"]["b"]  # NaN
    assert r0["total"] == r1["total"] == 5
    # Episodes: returns (1, 3, 10) -> 14/3; lengths 1; distances (0.5, 1.5, 4) -> 2.
    for r in (r0, r1):
        assert r["ep"]["mean_reward"] == pytest.approx(14 / 3)
        assert r["ep"]["mean_episode_length"] == 1.0
        assert r["ep"]["mean_distance_m"] == pytest.approx(2.0)
        assert r["gathered"]["distance_m"].tolist() == [0.0, 1.0, 2.0, 3.0, 4.0]
        assert r["agree"] == "rank 0" and r["world"] == 2


# -- the real pipeline under torchrun -----------------------------------------------------------

SMALL = [
    "compute=smoke",
    "compute.eval_num_envs=1",
    "eval.num_rollouts=2",
    "eval.episode_length_s=0.5",
    "teacher.eval_interval=0",
    "distill.eval_interval=0",
]


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}


def _torchrun(script: list[str], *overrides: str, timeout: int = 900, **kw):
    cmd = [TORCHRUN, "--standalone", "--nproc_per_node=2", *script, *overrides]
    return subprocess.run(
        cmd,
        cwd=ROOT,
        env=_env() | kw.pop("env", {}),
        capture_output=True,
        text=True,
        timeout=timeout,
        **kw,
    )


def _descendants(pid: int) -> list[int]:
    """Every process below ``pid`` (from /proc), children first."""
    out: list[int] = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        with contextlib.suppress(OSError):
            for child in (task / "children").read_text().split():
                out += [int(child), *_descendants(int(child))]
    return out


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


@pytest.mark.sim
def test_two_ranks_run_one_policy_and_rank0_writes(tmp_path):
    run, trace = tmp_path / "run", tmp_path / "trace"
    out = _torchrun(
        ["tests/ddp_trace.py"],
        *SMALL,
        "compute.torch_threads=1",
        f"hydra.run.dir={run}",
        env={"MARCH_TRACE_DIR": str(trace)},
    )
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    for stage, n in (("teacher", 2), ("student", 2)):
        for k in range(1, n + 1):
            r0, r1 = (torch.load(trace / f"{stage}_{k}_rank{r}.pt") for r in (0, 1))
            assert r0["writes_files"] and not r1["writes_files"]
            # After every update: every parameter and normaliser buffer bitwise identical.
            assert r0["state"].keys() == r1["state"].keys()
            for key, v in r0["state"].items():
                assert torch.equal(v, r1["state"][key]), f"{stage} update {k}: {key} differs"
            # ... learned from different rollouts (each rank its own seed stream).
            for key, v in r0["rollout"].items():
                assert not torch.equal(v, r1["rollout"][key]), f"{stage} {k}: same {key}"
            # The normalisers count both ranks' samples: 8 steps x 4 envs x 2 ranks per
            # iteration (the student's proprioception: x 5 history rows).
            state = r0["state"]
            if stage == "teacher":
                assert int(state["actor.obs_normalizer.count"]) == 64 * k
                assert int(state["critic.obs_normalizer.count"]) == 64 * k
            else:
                assert int(state["proprio_normalizer.count"]) == 320 * k
                assert int(state["command_normalizer.count"]) == 64 * k
    assert not (trace / "teacher_3_rank0.pt").exists()
    # Rank 0 alone wrote: one row per iteration, env steps summed over the ranks.
    rows = _rows(run / "metrics.csv")
    assert [(r["stage"], r["iteration"], r["env_steps"]) for r in rows] == [
        ("teacher", "1", "64"),
        ("teacher", "2", "128"),
        ("student", "1", "64"),
        ("student", "2", "128"),
    ]
    evals = _rows(run / "eval.csv")
    assert [(r["stage"], r["iteration"], r["n_rollouts"]) for r in evals] == [
        ("teacher", "2", "2"),
        ("student", "2", "2"),
    ]
    log = (run / "env.log").read_text()
    assert log.count("Actor Model") == 1  # rsl-rl's network print: rank 0's only
    assert {p.name for p in run.iterdir()} == {
        ".hydra", "config.yaml", "env.log", "eval.csv", "metrics.csv", "status.json",
        "student", "summary.json", "teacher", "train.log",
    }  # fmt: skip
    ckpt = torch.load(run / "teacher" / "latest.pt", weights_only=True)
    assert ckpt["world_size"] == 2 and len(ckpt["rank_rng"]) == 2
    assert not torch.equal(ckpt["rank_rng"][0]["rng"], ckpt["rank_rng"][1]["rng"])
    assert "distributed: 2 ranks (gloo); compute.num_envs=4 per rank, 8 envs in total" in out.stdout
    assert out.stdout.count("[teacher] it 1/2") == 1  # rank 1 prints nothing


@pytest.mark.sim
@pytest.mark.slow
def test_kill_and_resume_of_a_two_rank_run(tmp_path):
    run = tmp_path / "run"
    args = [*SMALL, "stage=teacher", "teacher.max_iterations=3", f"hydra.run.dir={run}"]
    cmd = [TORCHRUN, "--standalone", "--nproc_per_node=2", "-m", "march.train", *args]
    proc = subprocess.Popen(
        cmd,
        cwd=ROOT,
        env=_env(),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    deadline = time.time() + 600
    try:
        while not (run / "teacher" / "model_000001.pt").exists():
            assert proc.poll() is None, "the run ended before its first checkpoint"
            assert time.time() < deadline, "no checkpoint after 600 s"
            time.sleep(0.5)
    finally:
        # torchrun starts each rank in its own session: kill torchrun and every rank at once
        # (as Slurm does with a job's processes), by their ids.
        for pid in [proc.pid, *_descendants(proc.pid)]:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        proc.wait()
    time.sleep(1.0)
    killed_at = max(int(r["iteration"]) for r in _rows(run / "metrics.csv"))
    assert killed_at < 3
    out = _torchrun(["-m", "march.train"], f"resume={run}")
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    assert "[teacher] resuming from" in out.stdout
    rows = _rows(run / "metrics.csv")
    assert [(r["iteration"], r["env_steps"]) for r in rows] == [
        ("1", "64"),
        ("2", "128"),
        ("3", "192"),
    ]
    assert [r["iteration"] for r in _rows(run / "eval.csv")] == ["3"]
    assert '"done"' in (run / "status.json").read_text()
