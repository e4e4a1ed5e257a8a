"""march.bench (options, the step profiler, the env and planner jobs) and the prepared GPU check
(scripts/gpu_check.py, run at tiny sizes on CPU)."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from march.bench.command import JOB_DEFAULTS, job_options, pop_bench_options
from march.bench.profiler import StepProfiler

ROOT = Path(__file__).resolve().parent.parent


def run_module(*args: str, timeout: int = 1800) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", *args], cwd=ROOT, capture_output=True, text=True, timeout=timeout
    )


def test_bench_options_are_popped_and_checked():
    rest, given = pop_bench_options(["compute.num_envs=8", "bench.steps=7", "seed=2"])
    assert rest == ["compute.num_envs=8", "seed=2"]
    assert given == {"steps": 7}
    assert job_options("env", given) == {**JOB_DEFAULTS["env"], "steps": 7}
    assert job_options("planner", {})["steps"] == 100
    _, given = pop_bench_options(["bench.profile_steps=0", "bench.rounds=3", "bench.warmup=0"])
    assert given == {"profile_steps": 0, "rounds": 3, "warmup": 0}
    opts = job_options("env", given)  # bench.warmup sets both workloads' warm-up ...
    assert opts["warmup_random"] == opts["warmup_standing"] == 0
    opts = job_options("env", {"warmup": 2, "warmup_random": 9})  # ... unless one is given
    assert (opts["warmup_random"], opts["warmup_standing"]) == (9, 2)
    assert JOB_DEFAULTS["env"]["warmup_random"] > JOB_DEFAULTS["env"]["warmup_standing"]
    _, given = pop_bench_options(["bench.partial=out/b.json", "bench.steps=3"])
    assert given == {"partial": "out/b.json", "steps": 3}  # a path, not a number
    for bad in (
        "bench.steps=0",
        "bench.bogus=1",
        "bench.rounds=0",
        "bench.steps=x",
        "bench.partial=",
    ):
        with pytest.raises(SystemExit) as exc:
            pop_bench_options([bad])
        assert exc.value.code == 2


def _gpu_check():
    """scripts/gpu_check.py as a module (a script, not a package module)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("gpu_check", ROOT / "scripts" / "gpu_check.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _bench_json(workloads: list[str], **extra) -> dict:
    """A bench JSON of the keys the GPU check reads, for the given finished workloads."""
    work = {
        w: {"steps_per_s": {"march_teacher": 10.0 + i, "bare_rough": 9.0}}
        for i, w in enumerate(workloads)
    }
    return {"num_envs": 4096, "ratio_ops_march_vs_rough": 1.07, "workloads": work, **extra}


def test_the_gpu_check_keeps_a_stopped_benchs_finished_workloads(tmp_path):
    """A bench phase stopped by its time limit (the first GPU run: warp and inductor compile
    cold) still reports the workloads it finished, from the partial file the bench rewrites
    after each; a finished phase reports its final JSON; nothing readable, nothing reported."""
    bench_results = _gpu_check().bench_results
    assert bench_results(tmp_path, finished=False) == (None, [], "")
    partial = _bench_json(["random"], partial=True, completed_workloads=["random"])
    (tmp_path / "bench_env.partial.json").write_text(json.dumps(partial))
    summary, files, note = bench_results(tmp_path, finished=False)
    assert files == ["bench_env.partial.json"] and note == "partial results: random finished"
    assert summary["completed_workloads"] == ["random"]
    assert summary["steps_per_s"] == {"random": {"march_teacher": 10.0, "bare_rough": 9.0}}
    assert summary["ratio_ops_march_vs_rough"] == 1.07 and summary["num_envs"] == 4096
    (tmp_path / "bench_env.json").write_text(json.dumps(_bench_json(["random", "standing"])))
    summary, files, note = bench_results(tmp_path, finished=True)
    assert files == ["bench_env.json"] and note == "" and "completed_workloads" not in summary
    assert set(summary["steps_per_s"]) == {"random", "standing"}
    (tmp_path / "bench_env.json").write_text("")  # a phase killed while it printed
    summary, files, _ = bench_results(tmp_path, finished=False)
    assert files == ["bench_env.partial.json"]  # an unfinished phase's stdout is not read
    (tmp_path / "bench_env.partial.json").write_text('{"workloads": ')
    summary, files, note = bench_results(tmp_path, finished=False)
    assert summary is None and files == [] and note.startswith("unreadable bench_env.partial")


def test_the_gpu_check_reads_a_stopped_sync_checks_teacher_part(tmp_path):
    """scripts/sync_check.py writes its file after the teacher iteration and again after the
    distillation rollout; the GPU check reads which phases a file holds and counts its rows."""
    sync_results = _gpu_check().sync_results
    path = tmp_path / "syncs.tsv"
    path.write_text(
        "# recorded: teacher\n"
        "phase\tsource\tmarch\tmessage\n"
        "teacher\tmjlab/managers/command_manager.py:90\t-\tcalled a synchronizing op\n"
        "teacher\tmarch/env/course.py:12\tmarch/env/course.py:12\tcalled a synchronizing op\n"
        "# count\tphase\tsource\tmarch\n"
        "# 1\tteacher\tmjlab/managers/command_manager.py:90\t-\n"
    )
    assert sync_results(path) == {
        "recorded": 2,
        "with_march_on_stack": 1,
        "cuda": True,
        "phases": ["teacher"],
    }


class _Thing:
    def __init__(self) -> None:
        self.calls: list[str] = []

    def outer(self, n: int) -> int:
        time.sleep(0.02)
        return self.inner(n) + self.inner(n)

    def inner(self, n: int) -> int:
        time.sleep(0.01 * n)
        return n


def test_profiler_times_are_exclusive_and_undone():
    thing = _Thing()
    prof = StepProfiler("cpu")
    prof.patch(thing, "outer", "outer")
    prof.patch(thing, "inner", "parts/inner")
    assert thing.outer(3) == 6
    assert prof.calls == {"outer": 1, "parts/inner": 2}
    # inner: 2 x 30 ms; outer's own time: 20 ms (sleep granularity and load only add)
    assert 0.058 <= prof.self_s["parts/inner"] < 0.058 + 0.5
    assert 0.019 <= prof.self_s["outer"] < 0.019 + 0.5
    rep = prof.report(steps=2)
    assert set(rep["categories_ms"]) == {"outer", "parts"}
    assert rep["categories_ms"]["parts"] == pytest.approx(
        1e3 * prof.self_s["parts/inner"] / 2, abs=1e-3
    )
    assert rep["profiled_ms_per_step"] == pytest.approx(
        sum(rep["categories_ms"].values()), abs=1e-2
    )
    assert sum(rep["categories_share"].values()) == pytest.approx(1.0, abs=1e-3)
    assert rep["planner_ms_per_step"] is None
    prof.restore()
    assert "outer" not in vars(thing) and "inner" not in vars(thing)
    thing.outer(1)
    assert prof.calls["outer"] == 1  # no longer timed


def test_profiler_names_sections_from_the_call():
    thing = _Thing()
    prof = StepProfiler("cpu")
    prof.patch(thing, "inner", lambda n: f"events/{n}")
    thing.inner(0)
    thing.inner(1)
    thing.inner(1)
    assert prof.calls == {"events/0": 1, "events/1": 2}


# ---------------------------------------------------------------------------------------------
# Slow: these build real mjlab envs (left out of the default run; pytest -m slow)


@pytest.mark.slow
def test_bench_env_prints_one_json_object_with_both_workloads_and_a_profile(tmp_path):
    res = run_module(
        "march.bench",
        "env",
        "compute=cpu",
        "compute.num_envs=2",
        "bench.steps=2",
        "bench.warmup=1",
        "bench.profile_steps=2",
        "bench.rounds=2",
        f"bench.partial={tmp_path / 'partial.json'}",
    )
    assert res.returncode == 0, res.stderr[-2000:]
    result = json.loads(res.stdout)  # stdout is the JSON object and nothing else
    partial = json.loads((tmp_path / "partial.json").read_text())  # after the last workload
    assert partial["completed_workloads"] == ["random", "standing"] and not partial["partial"]
    assert partial["workloads"] == result["workloads"]
    assert partial["ratio_nonphysics_march_vs_rough"] == result["ratio_nonphysics_march_vs_rough"]
    assert result["num_envs"] == 2 and result["steps"] == 2
    for key in ("march_teacher_steps_per_s", "bare_rough_steps_per_s", "bare_flat_steps_per_s"):
        assert result[key] > 0
    assert result["ratio_march_vs_rough"] == pytest.approx(
        result["march_teacher_steps_per_s"] / result["bare_rough_steps_per_s"]
    )
    assert set(result["build_s"]) == {"march_teacher", "bare_rough", "bare_flat"}
    assert set(result["workloads"]) == {"random", "standing"}
    for workload in result["workloads"].values():
        assert set(workload["profile"]) == {"march_teacher", "bare_rough", "bare_flat"}
        march = workload["profile"]["march_teacher"]
        assert {"physics", "commands", "rewards", "observations"} <= set(march["categories_ms"])
        assert march["planner_ms_per_step"] is not None  # reward=clf: the planner is timed
        assert 0.0 <= march["planner_share"] < 1.0
    assert result["min_ratio_march_vs_rough"] == pytest.approx(
        min(result["ratio_march_vs_rough_by_workload"].values())
    )


@pytest.mark.slow
def test_bench_planner_prints_one_json_object():
    res = run_module(
        "march.bench", "planner", "compute=cpu", "compute.num_envs=2", "bench.steps=30"
    )
    assert res.returncode == 0, res.stderr[-2000:]
    result = json.loads(res.stdout)
    assert result["num_envs"] == 2 and result["feasible_fraction"] == 1.0
    assert 0.0 < result["ms_per_replan_mean"] and 0.0 < result["ms_per_env_step"]
    assert result["planner_share_of_env_step"] == pytest.approx(
        result["ms_per_replan_mean"] / result["ms_per_env_step"]
    )
    assert 0.0 <= result["in_env_planner_share"] < 1.0  # reward=clf: the env runs the planner
    assert 0.0 < result["walk_touchdown_rate_per_env_step"] < 0.1  # steps of 0.45-0.7 s at 50 Hz


@pytest.mark.slow
def test_gpu_check_runs_at_tiny_sizes_on_cpu(tmp_path):
    out = tmp_path / "check"
    env = {**os.environ, "OUT": ""}
    res = subprocess.run(
        [sys.executable, "scripts/gpu_check.py", str(out), "--cpu", "--teacher-seconds", "1"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=3600,
        env=env,
    )
    report = json.loads((out / "gpu_check.json").read_text())
    phases = {p["phase"]: p for p in report["phases"]}
    assert res.returncode == 0, (res.stdout[-3000:], phases)
    assert report["ok"] and report["mode"] == "cpu"
    assert list(phases) == [
        "bench",
        "syncs",  # issue 20's two measurements first
        "teacher_clf",
        "teacher_modelfree",
        "student",
        "export",
    ]
    bench = json.loads((out / "bench_env.json").read_text())
    assert set(bench["workloads"]) == {"random", "standing"}
    assert phases["bench"]["files"] == ["bench_env.json"] and phases["bench"]["note"] == ""
    assert set(bench["ops_per_step"]) == {"random", "standing"}
    assert bench["ops_per_step"]["random"]["march_teacher"] > 0
    syncs = (out / "syncs.tsv").read_text().splitlines()
    assert syncs[0].startswith("# no CUDA") and "phase\tsource\tmarch\tmessage" in syncs
    assert report["results"]["syncs"] == {
        "recorded": 0,
        "with_march_on_stack": 0,
        "cuda": False,
        "phases": ["teacher", "distill"],
    }
    for arm in ("clf", "modelfree"):
        with (out / f"teacher_{arm}_curve.csv").open() as f:
            rows = list(csv.DictReader(f))
        assert len(rows) >= 1 and [int(r["iteration"]) for r in rows] == list(
            range(1, len(rows) + 1)
        )
        assert report["results"][f"teacher_{arm}"]["iterations"] == len(rows)
    with (out / "student_curve.csv").open() as f:
        assert [int(r["iteration"]) for r in csv.DictReader(f)] == [1, 2]
    assert (out / "eval.csv").is_file() and (out / "summary.json").is_file()
    assert (out / "student.onnx").stat().st_size > 10_000
    with (out / "gpu_check.csv").open() as f:
        assert [r["phase"] for r in csv.DictReader(f)] == list(phases)
