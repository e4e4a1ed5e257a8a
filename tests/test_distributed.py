"""One run over 2 processes (gloo on CPU): same policy on every rank, rank 0 writes, resume.

The collectives are checked on two spawned gloo ranks against hand-derived values; the real
pipeline runs under ``torchrun`` at smoke size (``tests/ddp_trace.py`` dumps every update).
"""

from __future__ import annotations

import contextlib
import csv
import json
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

from march.evaluation.sharding import rank_waves, waves
from march.learn import distributed
from march.learn.distributed import Dist, rank_seed
from march.store.checkpoint import state_differences

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


@pytest.mark.parametrize(
    "n,size,world", [(4, 2, 2), (5, 2, 2), (7, 3, 3), (2048, 256, 8), (1, 4, 2), (9, 4, 1)]
)
def test_waves_partition_the_rollouts_and_do_not_depend_on_the_ranks(n, size, world):
    dealt = [w for r in range(world) for w in rank_waves(n, size, Dist(rank=r, world=world))]
    assert sorted(dealt) == waves(n, size)  # every wave once, whatever the number of ranks
    idx = [i for _, first, count in sorted(dealt) for i in range(first, first + count)]
    assert idx == list(range(n))  # every rollout once, in the one-process order
    assert all(0 < count <= size for _, _, count in dealt)
    counts = [len(rank_waves(n, size, Dist(rank=r, world=world))) for r in range(world)]
    assert max(counts) - min(counts) <= 1  # the ranks share the waves evenly


def _state(seed: int) -> dict:
    torch.manual_seed(seed)
    return {
        "curriculum": {"terrain_levels": torch.randint(0, 9, (4,))},
        "episode": {"episode_length_buf": torch.randint(0, 999, (4,))},
        "streams": {"torch": torch.get_rng_state(), "planner": torch.Generator().get_state()},
        "rng": torch.get_rng_state(),
    }


def test_each_rank_takes_its_own_entry_and_another_rank_count_is_refused():
    from march.learn.train_state import rank_payload
    from march.store.checkpoint import CheckpointError

    states = [_state(11), _state(22), _state(33)]
    payload = {**states[0], "rank_states": states, "world_size": 3, "iteration": 5}
    for r in range(3):
        mine = distributed.own_rank_state(payload, Dist(rank=r, world=3))
        for key in ("curriculum", "episode", "streams", "rng"):
            assert mine[key] is states[r][key], (r, key)
        assert mine["iteration"] == 5 and mine["rank_states"] is states
    for world in (1, 2, 4):
        assert distributed.world_mismatch(payload, world) == (
            f"written by 3 rank(s), this run has {world}: resume it with 3 process(es) "
            "(torchrun --nproc_per_node / Slurm tasks x nodes = 3)"
        )
    assert distributed.world_mismatch(payload, 3) is None
    assert distributed.world_mismatch({"iteration": 1}, 1) is None  # a one-process run
    with pytest.raises(CheckpointError, match=r"^resume=x: written by 2 rank\(s\), this run has 1"):
        rank_payload({"world_size": 2}, "resume=x")  # this process is a one-process run
    assert "written by 1 rank(s), this run has 2" in distributed.world_mismatch({}, 2)


def test_a_checkpoint_from_before_rank_states_gives_each_rank_its_torch_streams():
    s0, s1 = _state(1), _state(2)
    payload = {**s0, "rank_rng": [{"rng": s0["rng"]}, {"rng": s1["rng"]}], "world_size": 2}
    mine = distributed.own_rank_state(payload, Dist(rank=1, world=2))
    assert mine["rng"] is s1["rng"] and mine["streams"]["torch"] is s1["rng"]
    assert mine["streams"]["planner"] is s0["streams"]["planner"]  # only torch's was per rank
    assert distributed.own_rank_state(payload, Dist(rank=0, world=2)) is payload


def test_the_device_is_what_the_task_sees():
    from march.errors import ConfigError

    assert distributed.visible_device(3, count=1) == "cuda:0"  # one GPU bound per task
    assert distributed.visible_device(3, count=4) == "cuda:3"
    with pytest.raises(ConfigError, match="^local rank 2 sees 2 CUDA device"):
        distributed.visible_device(2, count=2)


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
    r3 = distributed.rank_config(gpu, Dist(rank=3, world=4, local_rank=3, backend="nccl"), 4)
    assert r3.compute.device == "cuda:3" and r3.seed == rank_seed(5, 3)
    r3 = distributed.rank_config(gpu, Dist(rank=3, world=4, local_rank=3, backend="nccl"), 1)
    assert r3.compute.device == "cuda:0"  # Slurm bound one GPU to the task


def test_leaving_the_group_runs_what_registered_once_and_distributed_imports_none_of_it():
    """Issue 54: distributed <-> rank_normalizers was a circle (shutdown / abort imported
    rank_normalizers.reset). Now the normalisers register their reset with ``on_leave``."""
    import ast
    from pathlib import Path

    calls: list[str] = []

    def forget() -> None:
        calls.append("forget")

    distributed.on_leave(forget)
    distributed.on_leave(forget)  # twice: still run once
    try:
        distributed.shutdown()
        assert calls == ["forget"]
        distributed.abort()
        assert calls == ["forget", "forget"]
    finally:
        distributed._ON_LEAVE.remove(forget)
    tree = ast.parse(Path(distributed.__file__).read_text())
    imported = {
        alias.name
        for node in ast.walk(tree)
        if isinstance(node, (ast.Import, ast.ImportFrom))
        for alias in node.names
    } | {node.module for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)}
    assert not any("rank_normalizers" in str(name) for name in imported)


# -- collectives on two real gloo ranks ---------------------------------------------------------


def _collectives_rank(rank: int, port: int, out: str) -> None:
    os.environ.update(
        {"MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port), "RANK": str(rank)}
        | {"WORLD_SIZE": "2", "LOCAL_RANK": str(rank)}
    )
    from rsl_rl.modules.normalization import EmpiricalNormalization
    from test_syncs import SyncCounter

    from march.learn import rank_normalizers

    d = distributed.init("cpu")
    gen = torch.Generator().manual_seed(100 + rank)
    # Two normalisers (a PPO actor's and critic's), 24 env steps of one iteration: rank 0 sees 3
    # rows per step, rank 1 five. Nothing may be read back or communicated during the steps;
    # one flush then issues exactly one collective for both.
    norm, norm2 = EmpiricalNormalization(4), EmpiricalNormalization(2)
    assert rank_normalizers.sync_normalizers(torch.nn.Sequential(norm, norm2)) == 2
    batches = [torch.randn(3 + 2 * rank, 4, generator=gen) * (1 + rank) for _ in range(24)]
    batches2 = [torch.randn(3 + 2 * rank, 2, generator=gen) + rank for _ in range(24)]
    import torch.distributed as td

    calls: list[str] = []
    names = ("all_gather", "all_gather_into_tensor", "all_reduce", "broadcast", "gather")
    saved = {n: getattr(td, n) for n in names}
    for n, f in saved.items():
        setattr(td, n, lambda *a, _n=n, _f=f, **k: (calls.append(_n), _f(*a, **k))[1])
    with SyncCounter() as steps_sc:
        for b, b2 in zip(batches, batches2, strict=True):
            norm.update(b)
            norm2.update(b2)
    step_calls = list(calls)
    with SyncCounter() as flush_sc:
        issued = rank_normalizers.flush_normalizers()
    flush_calls = calls[len(step_calls) :]
    for n, f in saved.items():
        setattr(td, n, f)
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
    # An evaluation of 5 rollouts in waves of 2: each rank runs its waves (rank 0: 0 and 2,
    # rank 1: 1); every rank gets all rollouts back in order.
    from march.evaluation.sharding import sharded_rollouts

    ran: list[tuple[int, int, int]] = []

    def wave(env, policy, count, first, seed):
        ran.append((first, count, seed))
        return {"distance_m": torch.arange(first, first + count, dtype=torch.float32)}

    env = type("Env", (), {"num_envs": 2, "cfg": type("Cfg", (), {"seed": 9})()})()
    gathered = sharded_rollouts(env, None, 5, wave)
    gathered["ran"] = torch.tensor(ran)
    torch.save(
        {
            "norm": {k: v.clone() for k, v in norm.state_dict().items()},
            "norm2": {k: v.clone() for k, v in norm2.state_dict().items()},
            "batches": batches,
            "batches2": batches2,
            "syncs": (steps_sc.hits, flush_sc.hits, step_calls, flush_calls, issued),
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
    # Normalisers: bitwise the same on both ranks, and equal to one normaliser fed every batch
    # of both ranks (rsl-rl's per-step update in one process).
    for name, dim, key in (("norm", 4, "batches"), ("norm2", 2, "batches2")):
        for k in r0[name]:
            assert torch.equal(r0[name][k], r1[name][k]), k
        ref = EmpiricalNormalization(dim).double()
        for i in range(24):
            ref.update(torch.cat([r0[key][i], r1[key][i]]).double())
        assert int(r0[name]["count"]) == 24 * (3 + 5)
        for k in ("_mean", "_var", "_std"):
            torch.testing.assert_close(
                r0[name][k].double(), ref.state_dict()[k], rtol=1e-5, atol=1e-6
            )
    # Syncs of the 2-rank run: none during the 24 steps (no host read, no collective), one
    # all-gather and still no host read for the iteration's flush of both normalisers.
    for r in (r0, r1):
        step_reads, flush_reads, step_calls, flush_calls, issued = r["syncs"]
        assert step_reads == [] and step_calls == [], (step_reads, step_calls)
        assert flush_reads == [] and flush_calls == ["all_gather"] and issued == 1
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
    # every wave with the run's seed: a rollout's numbers are keyed by (seed, its index)
    assert r0["gathered"]["ran"].tolist() == [[0, 2, 9], [4, 1, 9]]
    assert r1["gathered"]["ran"].tolist() == [[2, 2, 9]]


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


STEPS = 4
"""Steps per env per iteration of the two-rank run (the smoke preset's 8 halved: the counts
below are what is checked, not the learning)."""
SHORTER = [
    *(o for o in SMALL if not o.startswith("eval.episode_length_s=")),
    "eval.episode_length_s=0.1",  # 5 steps: the rows are checked, not the walking
    f"teacher.num_steps_per_env={STEPS}",
    f"distill.num_steps_per_env={STEPS}",
]


@pytest.mark.sim
def test_two_ranks_run_one_policy_and_rank0_writes(tmp_path):
    run, trace = tmp_path / "run", tmp_path / "trace"
    out = _torchrun(
        ["tests/ddp_trace.py"],
        *SHORTER,
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
            # The normalisers count both ranks' samples: 4 steps x 4 envs x 2 ranks per
            # iteration (the student's proprioception: x 5 history rows).
            state = r0["state"]
            if stage == "teacher":
                assert int(state["actor.obs_normalizer.count"]) == 32 * k
                assert int(state["critic.obs_normalizer.count"]) == 32 * k
            else:
                assert int(state["proprio_normalizer.count"]) == 160 * k
                assert int(state["command_normalizer.count"]) == 32 * k
    assert not (trace / "teacher_3_rank0.pt").exists()
    # Rank 0 alone wrote: one row per iteration, env steps summed over the ranks.
    rows = _rows(run / "metrics.csv")
    assert [(r["stage"], r["iteration"], r["env_steps"]) for r in rows] == [
        ("teacher", "1", "32"),
        ("teacher", "2", "64"),
        ("student", "1", "32"),
        ("student", "2", "64"),
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
        "student", "summary.json", "teacher", "train.log", "eval_levels.csv",
        "eval_rollouts.csv", "ranks",
    }  # fmt: skip
    # Rank 1 printed into its own log file; Hydra's files are rank 0's alone.
    assert [p.name for p in (run / "ranks").iterdir()] == ["rank1.log"]
    assert "[teacher] it 2/2" in (run / "ranks" / "rank1.log").read_text()  # its own output
    ckpt = torch.load(run / "teacher" / "latest.pt", weights_only=True)
    assert ckpt["world_size"] == 2 and len(ckpt["rank_states"]) == 2
    r0, r1 = ckpt["rank_states"]
    assert not torch.equal(r0["rng"], r1["rng"]) and torch.equal(r0["rng"], ckpt["rng"])
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


@pytest.mark.sim
@pytest.mark.slow
def test_a_dead_rank_stops_the_other_and_each_rank_resumes_its_own_state(tmp_path):
    """Two ranks started as srun starts them (no torchrun agent to kill the survivor): rank 1
    is SIGKILLed after the first checkpoint; rank 0 must stop by itself within the process
    group's timeout, with one line. A torchrun resume then gives every rank its own pre-kill
    state exactly, and the ranks still roll out different data."""
    run, trace = tmp_path / "run", tmp_path / "trace"
    trace.mkdir()
    timeout_s = 60
    args = [*SMALL, "stage=teacher", "teacher.max_iterations=3", "compute.torch_threads=1"]
    args += [f"compute.dist_timeout_s={timeout_s}", f"hydra.run.dir={run}"]
    port = str(_free_port())
    procs = []
    for r in (0, 1):
        env = _env() | {"MASTER_ADDR": "127.0.0.1", "MASTER_PORT": port, "WORLD_SIZE": "2"}
        env |= {"RANK": str(r), "LOCAL_RANK": str(r), "MARCH_TRACE_DIR": str(trace)}
        env |= {"MARCH_TRACE_TAG": "first_"}
        procs.append(
            subprocess.Popen(
                [sys.executable, "tests/ddp_trace.py", *args],
                cwd=ROOT,
                env=env,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
        )
    deadline = time.time() + 900
    try:
        while not (trace / "first_teacher_save_1_rank1.pt").exists():
            assert all(p.poll() is None for p in procs), procs[0].communicate()[1][-3000:]
            assert time.time() < deadline, "no checkpoint after 900 s"
            time.sleep(0.2)
        os.kill(procs[1].pid, signal.SIGKILL)
        # A hang guard only (gloo's own default would wait 30 min): how soon rank 0 stops is
        # read from its error below, not from a clock that a loaded machine slows down.
        _, err = procs[0].communicate(timeout=10 * timeout_s)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
            p.wait()
    assert procs[0].returncode != 0
    lines = [ln for ln in err.splitlines() if ln.strip() and "Warning" not in ln]
    assert "Traceback" not in err, err[-3000:]
    assert "another rank of this 2-rank run stopped" in lines[-1], err[-2000:]
    if "timed out waiting" in lines[-1].lower():  # the run's timeout, not gloo's default
        assert f"Timed out waiting {timeout_s * 1000}ms" in lines[-1], lines[-1]
    assert lines[-1].endswith(f"resume={run}")
    assert '"failed"' in (run / "status.json").read_text()
    assert (run / "ranks" / "rank1.log").is_file()
    print(f"rank 0 stopped after rank 1 was killed: {lines[-1]}")

    out = _torchrun(
        ["tests/ddp_trace.py"],
        f"resume={run}",
        env={"MARCH_TRACE_DIR": str(trace), "MARCH_TRACE_TAG": "resumed_"},
    )
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    at = int(out.stdout.split("[teacher] resuming from ")[1].split(" at iteration ")[1].split()[0])
    before = [torch.load(trace / f"first_teacher_save_{at}_rank{r}.pt") for r in (0, 1)]
    after = [torch.load(trace / f"resumed_teacher_restored_{at}_rank{r}.pt") for r in (0, 1)]
    for r in (0, 1):  # each rank's levels, clocks, commands and every stream, exactly
        assert state_differences(before[r], after[r]) == [], f"rank {r}"
    differ = state_differences(before[0], before[1])
    assert "state.streams.torch" in differ and "state.streams.numpy.keys" in differ, differ
    assert "state.streams.planner" in differ and "state.episode.episode_length_buf" in differ
    for k in range(1, 4 - at):  # the ranks' rollouts after the resume still differ
        r0, r1 = (torch.load(trace / f"resumed_teacher_{k}_rank{r}.pt") for r in (0, 1))
        for key, v in r0["rollout"].items():
            assert not torch.equal(v, r1["rollout"][key]), f"update {k}: same {key}"
        for key, v in r0["state"].items():
            assert torch.equal(v, r1["state"][key]), f"update {k}: {key} differs"
    rows = _rows(run / "metrics.csv")
    assert [(r["iteration"], r["env_steps"]) for r in rows] == [
        ("1", "64"),
        ("2", "128"),
        ("3", "192"),
    ]
    assert '"done"' in (run / "status.json").read_text()
    ckpt = torch.load(run / "teacher" / "latest.pt", weights_only=True)
    assert ckpt["world_size"] == 2 and len(ckpt["rank_states"]) == 2


def _sbatch_script(launcher: str, *overrides: str) -> str:
    """The sbatch file Hydra's submitit launcher submits for ``hydra/launcher=<launcher>``: the
    composed launcher config turned into submitit's parameters as the launcher turns them
    (``hydra_submitit_launcher.submitit_launcher.BaseSubmititLauncher.launch``), rendered by
    submitit itself. No Slurm needed: submitit's executor refuses to be built where ``srun`` is
    not on the PATH (``SlurmExecutor.affinity``, its only look at the machine before a
    submission), so that probe answers "Slurm here" while the script is rendered; sbatch is
    never called."""
    from hydra import compose, initialize_config_dir
    from hydra_plugins.hydra_submitit_launcher.config import BaseQueueConf
    from omegaconf import OmegaConf
    from submitit import AutoExecutor
    from submitit.slurm.slurm import SlurmExecutor

    import march.config  # noqa: F401 - registers the schema conf/config.yaml extends

    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(
            "config",
            overrides=[f"hydra/launcher={launcher}", "hydra.sweep.dir=/tmp/s", *overrides],
            return_hydra_config=True,
        )
    cfg.hydra.job.name = "train"
    params = OmegaConf.to_container(cfg.hydra.launcher, resolve=True)
    del params["_target_"]
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(SlurmExecutor, "affinity", classmethod(lambda cls: 2))
        executor = AutoExecutor(
            folder=params.pop("submitit_folder"),
            cluster="slurm",
            slurm_max_num_timeout=params.pop("max_num_timeout"),
        )
    base = set(OmegaConf.structured(BaseQueueConf).keys())
    executor.update_parameters(**{k if k in base else f"slurm_{k}": v for k, v in params.items()})
    return executor._executor._make_submission_file_text("python -m march.train", "uid")


# srun's options that sbatch does not know (Slurm's src/common/slurm_opt.c: srun-only entries).
SRUN_ONLY = ("kill-on-bad-exit", "label", "unbuffered", "multi-prog", "task-prolog", "epilog")


@pytest.mark.parametrize("launcher", ["march_slurm_ddp", "march_slurm"])
def test_the_slurm_launchers_put_srun_options_on_the_srun_line(launcher):
    """sbatch refuses a job whose header holds an srun-only option; the DDP launcher's
    kill-on-bad-exit (one task that exits non-zero ends the step) is on the srun line."""
    script = _sbatch_script(launcher)
    header = [ln for ln in script.splitlines() if ln.startswith("#SBATCH")]
    bad = [ln for ln in header if ln.split("=")[0].removeprefix("#SBATCH --") in SRUN_ONLY]
    assert bad == [], bad
    assert "#SBATCH --ntasks-per-node=" + ("2" if launcher.endswith("ddp") else "1") in header
    srun = next(ln for ln in script.splitlines() if ln.startswith("srun "))
    assert ("--kill-on-bad-exit=1" in srun.split()) == launcher.endswith("ddp"), srun


def _preempted_rank(rank: int, port: int, out: str) -> None:
    """Rank ``rank`` of a 2-task Slurm job under submitit's own signal handler; USR2 reaches both
    ranks; rank 0's requeue (``scontrol requeue``, here a 1.5 s stand-in) is timed."""
    import signal as sig

    from submitit.core.job_environment import SignalHandler
    from submitit.core.utils import DelayedSubmission, JobPaths
    from submitit.slurm.slurm import SlurmJobEnvironment

    from march.learn import preemption

    os.environ.update(
        {"MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port), "RANK": str(rank)}
        | {"WORLD_SIZE": "2", "LOCAL_RANK": str(rank), "SLURM_PROCID": str(rank)}
        | {"SLURM_JOB_ID": "77", "SLURM_NTASKS": "2", "SLURM_JOB_NODELIST": "vm"}
    )
    distributed.init("cpu", timeout_s=30)
    env = SlurmJobEnvironment()

    def requeue(countdown: int) -> None:  # scontrol requeue, which takes a moment
        time.sleep(1.5)
        Path(out, "requeued").write_text(f"{time.time()}")

    env._requeue = requeue
    delayed = DelayedSubmission(print)
    delayed.set_timeout(60, 3)
    handler = SignalHandler(env, JobPaths(out, job_id="77", task_id=rank), delayed)
    sig.signal(sig.SIGUSR2, handler.checkpoint_and_try_requeue)  # what submitit installs
    assert preemption.install()
    os.kill(os.getpid(), sig.SIGUSR2)
    time.sleep(0.2)
    try:
        preemption.stop_if_requested("teacher", 1, lambda: Path(out, "model_000001.pt"))
    except preemption.Preempted as stop:
        try:
            preemption.exit_preempted(stop, lambda state, **kw: None)
        except SystemExit as done:
            Path(out, f"rank{rank}").write_text(f"{time.time()} {done.code}")
    distributed.shutdown()


def test_ranks_above_0_exit_on_preemption_only_after_rank0_asked_for_the_requeue(tmp_path):
    """With --kill-on-bad-exit, a rank > 0 exiting 140 ends the step at once: before rank 0's
    submitit handler has requeued the job, the job would not come back."""
    mp.spawn(_preempted_rank, args=(_free_port(), str(tmp_path)), nprocs=2, join=True)
    requeued = float((tmp_path / "requeued").read_text())
    ranks = [(tmp_path / f"rank{r}").read_text().split() for r in (0, 1)]
    assert [int(code) for _, code in ranks] == [140, 140]  # 128 + SIGUSR2 on both
    exited = [float(t) for t, _ in ranks]
    print(f"requeue asked at {requeued:.2f}; rank 1 exited {exited[1] - requeued:+.2f} s after")
    assert exited[1] >= requeued and exited[0] >= requeued


def _hung_rank(rank: int, port: int, out: str) -> None:
    os.environ.update(
        {"MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port), "RANK": str(rank)}
        | {"WORLD_SIZE": "2", "LOCAL_RANK": str(rank)}
    )
    distributed.init("cpu", timeout_s=3)
    if rank == 1:  # alive, but never joins the collective (a stuck or stopped process)
        done = Path(out, "rank0.txt")
        for _ in range(1200):  # until rank 0 has given up on it (at most 60 s)
            if done.exists():
                break
            time.sleep(0.05)
        os._exit(0)
    try:
        distributed.mean_over_ranks({"x": 1.0})
        line = None
    except Exception as err:  # noqa: BLE001 - what the run would see
        line = distributed.lost_rank(err)
    Path(out, "rank0.txt").write_text(f"{line}")
    os._exit(0)


def test_a_hung_rank_is_given_up_after_the_timeout_in_one_line(tmp_path):
    mp.spawn(_hung_rank, args=(_free_port(), str(tmp_path)), nprocs=2, join=True)
    line = (tmp_path / "rank0.txt").read_text()
    # gloo names the timeout it applied: compute.dist_timeout_s=3, not its 30-minute default
    # (what this test once measured with a clock, read from the error instead)
    assert "Timed out waiting 3000ms" in line, line
    assert line.startswith("rank 0: another rank of this 2-rank run stopped or stopped answering")
    assert "\n" not in line


EVAL_ONLY = [
    "stage=eval", "eval.policy=teacher", "eval.num_rollouts=4", "compute.eval_num_envs=2",
    "eval.episode_length_s=1.0", "compute.torch_threads=1",
]  # fmt: skip


@pytest.mark.sim
@pytest.mark.slow
def test_one_and_two_rank_evaluations_of_a_checkpoint_give_the_same_rows(tmp_path):
    """Two waves of two rollouts: one process runs both, two ranks one each (gloo); the rows,
    per rollout and summarised, are the same numbers."""
    teach = tmp_path / "teacher"
    args = [*SMALL, "stage=teacher", "teacher.max_iterations=1", "compute.torch_threads=1"]
    out = subprocess.run(
        [sys.executable, "-m", "march.train", *args, f"hydra.run.dir={teach}"],
        cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=900,
    )  # fmt: skip
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    ckpt = f"teacher_ckpt={teach / 'teacher' / 'latest.pt'}"
    runs, took = {}, {}
    for n in (1, 2):
        run = tmp_path / f"eval{n}"
        cmd = [TORCHRUN, "--standalone", f"--nproc_per_node={n}", "-m", "march.train"]
        t0 = time.time()
        out = subprocess.run(
            [*cmd, *EVAL_ONLY, ckpt, f"hydra.run.dir={run}"],
            cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=900,
        )  # fmt: skip
        took[n] = time.time() - t0
        assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
        runs[n] = run
    print(f"evaluation wall time (process start to exit): 1 rank {took[1]:.1f} s, 2 ranks "
          f"{took[2]:.1f} s")  # fmt: skip
    one, two = (json.loads((runs[n] / "summary.json").read_text()) for n in (1, 2))
    assert one.keys() == two.keys() and one["n_rollouts"] == 4
    for key, v in one.items():
        assert v == two[key] or (v != v and two[key] != two[key]), key  # NaN == NaN
    assert _rows(runs[1] / "eval_rollouts.csv") == _rows(runs[2] / "eval_rollouts.csv")
    assert len({r["distance"] for r in _rows(runs[1] / "eval_rollouts.csv")}) > 1


@pytest.mark.sim
@pytest.mark.slow
def test_two_nodes_on_one_machine_train_one_run(tmp_path):
    """``make two-node``: two torchrun launches, --nnodes=2, c10d rendezvous on 127.0.0.1, in the
    usual order and with the node ranks swapped (the --node_rank=1 launch holds global rank 0):
    the run directory, its logs and checkpoints follow global rank 0."""
    out = subprocess.run(
        [sys.executable, "scripts/two_node.py", "--out", str(tmp_path), "--port", str(_free_port())],
        cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=2400,
    )  # fmt: skip
    assert out.returncode == 0, out.stdout[-4000:] + out.stderr[-2000:]
    assert "PASSED (usual order)" in out.stdout
    assert "PASSED (node ranks swapped (--node_rank=1 is rank 0))" in out.stdout
    usual, swapped = out.stdout.split("=== two nodes, node ranks swapped")
    assert "global rank 0 ran in the launch with --node_rank=0" in usual
    assert "global rank 0 ran in the launch with --node_rank=1" in swapped
    import re

    for part in (usual, swapped):
        for stage in ("teacher", "student"):
            for k in (1, 2):
                pattern = (
                    rf"{stage} update {k}: (\d+)/\1 tensors equal on both nodes; rollouts differ: "
                    "True"
                )
                assert re.search(pattern, part), (stage, k)


def test_a_resume_on_another_rank_count_is_refused_before_any_env(tmp_path):
    from march.config.cli import load
    from march.learn.distributed import world_mismatch
    from march.store.checkpoint import CheckpointError
    from march.store.run_dir import check_run_checkpoints

    (tmp_path / "teacher").mkdir()
    payload = {"kind": "teacher", "iteration": 3, "world_size": 2, "rank_states": [{}, {}]}
    torch.save(payload, tmp_path / "teacher" / "latest.pt")
    with pytest.raises(CheckpointError) as err:  # this process is a one-process run
        check_run_checkpoints(tmp_path, load(["compute=smoke"]), "resume", world_mismatch)
    assert str(err.value) == (
        f"resume={tmp_path}: {tmp_path / 'teacher' / 'latest.pt'}: written by 2 rank(s), this "
        "run has 1: resume it with 2 process(es) (torchrun --nproc_per_node / Slurm tasks x "
        "nodes = 2)"
    )


def _snapshot(run: Path) -> dict[str, bytes]:
    return {str(p.relative_to(run)): p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}


@pytest.mark.slow
def test_a_refused_resume_on_three_ranks_writes_nothing_into_the_run(tmp_path):
    """A 2-rank run resumed on 3 ranks: each rank refuses in one line before any env, and the
    run directory holds the files it held, unchanged (no ranks/rank<r>.log, no lock left)."""
    from omegaconf import OmegaConf

    from march.config.cli import load

    run = tmp_path / "run"
    (run / "teacher").mkdir(parents=True)
    (run / "config.yaml").write_text(OmegaConf.to_yaml(OmegaConf.structured(load(SMALL))))
    (run / "train.log").write_text("the first launch's log\n")
    payload = {"kind": "teacher", "iteration": 3, "world_size": 2, "rank_states": [{}, {}]}
    torch.save(payload, run / "teacher" / "latest.pt")
    before = _snapshot(run)
    cmd = [TORCHRUN, "--standalone", "--nproc_per_node=3", "-m", "march.train", f"resume={run}"]
    out = subprocess.run(cmd, cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=600)
    assert out.returncode != 0
    refusals = [ln for ln in out.stderr.splitlines() if ln.startswith("error: resume=")]
    assert len(refusals) == 3, out.stderr[-3000:]  # each rank, on its own stderr
    assert all("written by 2 rank(s), this run has 3" in ln for ln in refusals)
    after = _snapshot(run)
    assert sorted(after) == sorted(before), sorted(set(after) - set(before))
    # Hydra's job log of rank 0 is the run's train.log (appended to, as every launch does:
    # a library's import-time INFO line may land there); everything else is untouched.
    assert after.pop("train.log").startswith(before.pop("train.log"))
    assert after == before
