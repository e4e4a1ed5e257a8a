"""march.bench (options, the step profiler, the env and planner jobs) and the prepared GPU check
(scripts/gpu_check.py, run at tiny sizes on CPU)."""

from __future__ import annotations

import csv
import json
import os
import signal
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
    """scripts/sync_check.py writes its file after each part; the GPU check reads which phases
    a file holds and their steps, counts its rows, and lists the march source lines that synced
    in more than one env step of a part: a read once per iteration falls in one step however
    often it syncs there, and what precedes the first step (step 0) is no step."""
    sync_results = _gpu_check().sync_results
    path = tmp_path / "syncs.tsv"

    def row(step: int, source: str, march: str = "-") -> str:
        return f"teacher\t{step}\t{source}\t{march}\tcalled a synchronizing op\n"

    runner = "march/learn/teacher.py:80"
    rows = [row(s, "mjlab/managers/command_manager.py:90", runner) for s in (1, 2, 3)]
    rows += [row(3, "march/learn/teacher.py:120", "march/learn/teacher.py:120")] * 5
    rows += [row(0, "march/learn/teacher.py:50", "march/learn/teacher.py:50")] * 2
    rows += [row(0, "march/env/course.py:12"), row(1, "march/env/course.py:12")]
    rows += [row(s, "march/env/course.py:40") for s in (2, 3)]  # not in every step: still found
    path.write_text(
        "# recorded: teacher\n# steps: teacher 3\nphase\tstep\tsource\tmarch\tmessage\n"
        + "".join(rows)
        + "# count\tphase\tsource\tmarch\n# 3\tteacher\tmjlab/managers/command_manager.py:90\t-\n"
    )
    assert sync_results(path) == {
        "recorded": 14,
        "with_march_on_stack": 10,  # the runner's line lies below every sync inside mjlab
        "cuda": True,
        "phases": ["teacher"],
        "steps": {"teacher": 3},
        "march_lines_per_step": ["teacher march/env/course.py:40"],
    }


def test_the_gpu_check_compares_march_and_rough_env_syncs_per_step(tmp_path):
    sync_results = _gpu_check().sync_results
    path = tmp_path / "syncs.tsv"
    rows = "".join(f"env_march\t{1 + i % 8}\tmjlab/sim/sim.py:5\t-\tsync\n" for i in range(16))
    rows += "".join(f"env_rough\t{1 + i % 4}\tmjlab/x.py:1\t-\ts\n" for i in range(8))
    path.write_text(
        "# recorded: teacher, distill, env_march, env_rough\n"
        "# steps: teacher 8, distill 8, env_march 8, env_rough 4\n"
        "phase\tstep\tsource\tmarch\tmessage\n" + rows
    )
    result = sync_results(path)
    assert result["env_syncs_per_step"] == {"march": 2.0, "rough": 2.0}
    assert result["march_lines_per_step"] == []  # mjlab lines: compared, not listed
    judged = _gpu_check().judged_targets({"syncs": result})
    assert judged["env_syncs_per_step_march_minus_rough"]["met"] is True
    path.write_text(path.read_text().replace("env_rough 4", "env_rough 8"))
    judged = _gpu_check().judged_targets({"syncs": sync_results(path)})
    assert judged["env_syncs_per_step_march_minus_rough"]["value"] == 1.0
    assert judged["env_syncs_per_step_march_minus_rough"]["met"] is False


def test_the_gpu_check_compares_compiled_and_eager_benches():
    """compile_vs_eager: per workload both benches finished, march's speed and non-physics time
    compiled and eager (ratios compiled / eager); a workload one bench lacks is left out."""
    compile_vs_eager = _gpu_check().compile_vs_eager
    compiled = {
        "steps_per_s": {
            "random": {"march_teacher": 300.0, "bare_rough": 250.0},
            "standing": {"march_teacher": 330.0, "bare_rough": 260.0},
        },
        "nonphysics_ms_per_step": {"random": {"march_teacher": 6.0, "bare_rough": 5.0}},
    }
    eager = {
        "steps_per_s": {"random": {"march_teacher": 200.0, "bare_rough": 251.0}},
        "nonphysics_ms_per_step": {"random": {"march_teacher": 12.0, "bare_rough": 5.1}},
    }
    assert compile_vs_eager(compiled, eager) == {
        "random": {
            "steps_per_s": {"compiled": 300.0, "eager": 200.0},
            "speed_ratio": 1.5,
            "nonphysics_ms": {"compiled": 6.0, "eager": 12.0},
            "nonphysics_ratio": 0.5,
        }
    }
    del eager["nonphysics_ms_per_step"]  # profile_steps=0: the speeds alone
    assert set(compile_vs_eager(compiled, eager)["random"]) == {"steps_per_s", "speed_ratio"}


@pytest.mark.parametrize(
    ("optional", "rc", "note", "failed"),
    [
        (False, 0, "", False),
        (False, 0, "stopped at its budget", False),
        (False, -1, "skipped: no time left before the deadline", True),
        (False, -15, "timed out after 240 s; partial results: random finished", True),
        (False, 1, "", True),
        (True, -1, "skipped: no time left before the deadline", False),
        (True, -15, "timed out after 60 s; partial results: random finished", False),
        (True, 1, "", True),  # an optional phase that ran and broke is a failure
    ],
)
def test_only_an_optional_phase_the_deadline_cut_short_fails_nothing(
    tmp_path, optional, rc, note, failed
):
    phase = _gpu_check().Phase("p", ["true"], tmp_path, optional=optional)
    phase.rc, phase.note = rc, note
    assert phase.failed() is failed


def _workload(ops: float, ratios: dict[str, float], nonphys: dict[str, float]) -> dict:
    """One workload's results as ``run_workload`` returns them: march / rough speed ratio and
    non-physics ratio per thread count, ops ratio."""
    by_threads = {
        t: {"ratio_march_vs_rough": r, "ratio_nonphysics_march_vs_rough": nonphys[t]}
        for t, r in ratios.items()
    }
    for b in by_threads.values():
        b["nonphysics_ms_per_step"] = {"march_teacher": b["ratio_nonphysics_march_vs_rough"]}
    return {
        "ratio_march_vs_rough": ratios["1"],
        "by_threads": by_threads,
        "ops_per_step": {"march_teacher": 100.0 * ops, "bare_rough": 100.0},
        "ratio_ops_march_vs_rough": ops,
        "nonphysics_ms_per_step": by_threads["1"]["nonphysics_ms_per_step"],
        "worst_ratio_nonphysics_march_vs_rough": max(nonphys.values()),
    }


@pytest.mark.parametrize(
    ("random", "standing", "expected"),
    [
        # Every figure within its bound, the bounds themselves included.
        (
            _workload(1.5, {"1": 1.0, "2": 1.2}, {"1": 1.5, "2": 1.1}),
            _workload(1.2, {"1": 1.1, "2": 1.0}, {"1": 1.2, "2": 1.4}),
            (True, True, True),
        ),
        # The standing workload's ops, the second thread count's non-physics time and speed
        # decide: the worst workload and thread count, not the first.
        (
            _workload(1.1, {"1": 1.3, "2": 1.2}, {"1": 1.2, "2": 1.3}),
            _workload(1.51, {"1": 1.2, "2": 0.99}, {"1": 1.4, "2": 1.6}),
            (False, False, False),
        ),
        # The random workload's ops and non-physics time decide; the speed holds.
        (
            _workload(2.3, {"1": 1.04, "2": 1.05}, {"1": 2.91, "2": 2.84}),
            _workload(1.09, {"1": 1.08, "2": 1.07}, {"1": 1.3, "2": 1.2}),
            (False, False, True),
        ),
    ],
)
def test_the_bench_judges_the_worst_workload_and_thread_count(random, standing, expected):
    from march.bench.env_speed import _headline

    head = _headline({"random": random, "standing": standing})
    keys = ("ratio_ops_march_vs_rough", "ratio_nonphysics_march_vs_rough")
    judged = head["targets"]
    assert tuple(judged[k]["met"] for k in (*keys, "min_ratio_march_vs_rough")) == expected
    assert judged["ratio_ops_march_vs_rough"]["value"] == max(
        random["ratio_ops_march_vs_rough"], standing["ratio_ops_march_vs_rough"]
    )
    assert judged["ratio_nonphysics_march_vs_rough"]["at_most"] == 1.5
    assert judged["min_ratio_march_vs_rough"] == {
        "value": min(
            b["ratio_march_vs_rough"] for w in (random, standing) for b in w["by_threads"].values()
        ),
        "at_least": 1.0,
        "met": expected[2],
    }


def test_a_figure_the_bench_did_not_measure_is_judged_not_measured():
    """bench.op_steps=0 and bench.profile_steps=0 leave the ops and non-physics figures out:
    neither met nor missed, and the printed line says so."""
    from march.bench.env_speed import _headline
    from march.bench.targets import verdict_lines

    work = _workload(1.0, {"1": 0.9}, {"1": 1.0})
    for key in ("ops_per_step", "nonphysics_ms_per_step"):
        del work[key]
    judged = _headline({"random": work})["targets"]
    assert judged["ratio_ops_march_vs_rough"] == {"value": None, "at_most": 1.5, "met": None}
    assert judged["ratio_nonphysics_march_vs_rough"]["met"] is None
    lines = verdict_lines(judged, "[bench]")
    assert lines[0].startswith("[bench] target ratio_ops_march_vs_rough <= 1.5: - (")
    assert lines[0].endswith(": not measured")
    assert lines[2].startswith("[bench] target min_ratio_march_vs_rough >= 1: 0.90 (")
    assert lines[2].endswith(": NOT MET")


def test_the_gpu_check_judges_the_bench_targets_and_the_syncs():
    """gpu_check.json's targets: the bench's judgement where the bench phase left one (else not
    measured), and the sync targets, judged only where CUDA recorded."""
    judged_targets = _gpu_check().judged_targets
    nothing = judged_targets({})
    assert list(nothing) == [
        "ratio_ops_march_vs_rough",
        "ratio_nonphysics_march_vs_rough",
        "min_ratio_march_vs_rough",
        "march_sync_lines_per_step",
        "env_syncs_per_step_march_minus_rough",
    ]
    assert all(j["met"] is None for j in nothing.values())
    bench = {"targets": {"ratio_ops_march_vs_rough": {"value": 1.09, "at_most": 1.5, "met": True}}}
    cuda = {"cuda": True, "phases": ["teacher"], "march_lines_per_step": ["teacher m.py:1"]}
    judged = judged_targets({"bench": bench, "syncs": cuda})
    assert judged["ratio_ops_march_vs_rough"]["met"] is True
    assert judged["ratio_nonphysics_march_vs_rough"]["met"] is None  # partial: not in the bench
    assert judged["march_sync_lines_per_step"] == {"value": 1, "at_most": 0.0, "met": False}
    assert judged["env_syncs_per_step_march_minus_rough"]["met"] is None  # env parts not reached
    clean = judged_targets({"syncs": {**cuda, "march_lines_per_step": []}})
    assert clean["march_sync_lines_per_step"]["met"] is True
    cpu = {**cuda, "cuda": False, "env_syncs_per_step": {"march": 0.0, "rough": 0.0}}
    assert all(j["met"] is None for j in judged_targets({"syncs": cpu}).values())
    stopped = {**cuda, "phases": []}  # killed before it recorded
    assert judged_targets({"syncs": stopped})["march_sync_lines_per_step"]["met"] is None


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
    judged = result["targets"]
    assert judged["min_ratio_march_vs_rough"]["value"] == result["min_ratio_march_vs_rough"]
    assert (
        judged["ratio_nonphysics_march_vs_rough"]["value"]
        == (result["ratio_nonphysics_march_vs_rough"])
    )
    assert partial["targets"] == judged
    printed = [ln for ln in res.stderr.splitlines() if ln.startswith("[bench] target ")]
    assert len(printed) == len(judged)


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


def _out_files_ok(out: Path) -> list[str]:
    """The files the device would return from ``out``: at most 8, none in a folder, all named
    in the check's list."""
    names = sorted(p.name for p in out.iterdir())
    assert all((out / n).is_file() for n in names), names
    assert len(names) <= 8 and set(names) <= set(_gpu_check().OUT_FILES), names
    return names


def _start_check(out: Path, work: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "scripts/gpu_check.py", str(out), "--cpu", "--work", str(work), *extra],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, "OUT": ""},
    )


def _summary(out: Path) -> dict:
    try:
        return json.loads((out / "gpu_check.json").read_text())
    except (OSError, json.JSONDecodeError):
        return {}


def test_a_gpu_check_stopped_after_its_first_phase_leaves_a_summary_naming_it(tmp_path):
    """The check writes its summary before the first phase and after each; stopped by SIGTERM
    during its second phase (a device's time limit), it stops that phase's subprocess, says so
    and keeps the first phase's figures, printed as they were measured; OUT holds only the
    check's files."""
    out, work = tmp_path / "out", tmp_path / "work"
    proc = _start_check(out, work)
    try:
        deadline = time.time() + 900
        while time.time() < deadline and "bench" not in _summary(out).get("phases_done", []):
            assert proc.poll() is None, proc.stdout.read()[-3000:]
            time.sleep(0.5)
        first = _summary(out)
        assert first["phases_done"] == ["bench"] and first["mode"] == "cpu"
        assert first["phases"][0]["rc"] == 0 and first["stopped"] == ""
        assert first["results"]["bench"]["steps_per_s"]["random"]["march_teacher"] > 0
        proc.send_signal(signal.SIGTERM)
        stdout, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 1, stdout[-3000:]
    report = _summary(out)
    assert report["stopped"] == "stopped by SIGTERM" and not report["ok"]
    assert report["phases_done"][0] == "bench"
    assert report["results"]["bench"] == first["results"]["bench"]
    # the bench's figures reached stdout as the bench measured them
    lines = stdout.splitlines()
    speed = next(i for i, ln in enumerate(lines) if ln.startswith("[bench] random, 1 thread(s): "))
    ops = next(i for i, ln in enumerate(lines) if ln.startswith("[bench] random compute ops"))
    done = next(i for i, ln in enumerate(lines) if ln.startswith("[gpu_check] bench: rc=0"))
    assert speed < ops < done
    names = _out_files_ok(out)
    assert {"gpu_check.json", "bench_env.json", "logs.txt"} <= set(names)
    # ops on both code paths: one code path on both devices, so the CUDA path's count is the CPU's
    bench = json.loads((out / "bench_env.json").read_text())
    cuda_path = bench["workloads"]["random"]["ops_per_step_cuda_path"]
    assert cuda_path["bare_rough"] == bench["workloads"]["random"]["ops_per_step"]["bare_rough"]
    assert 0 < cuda_path["march_teacher"] == bench["ops_per_step"]["random"]["march_teacher"]
    assert report["results"]["bench"]["ratio_ops_march_vs_rough_cuda_path"] > 0
    assert "===== bench: rc=0" in (out / "logs.txt").read_text()
    # the phase running at the stop is recorded as stopped, its subprocess gone
    if len(report["phases"]) > 1:
        assert report["phases"][1]["note"].startswith("stopped")


@pytest.mark.slow
def test_gpu_check_runs_at_tiny_sizes_on_cpu(tmp_path):
    """Every phase at tiny sizes, in order of value, with at most 8 files in OUT. How long it
    takes is a measurement (printed here, recorded in docs/gpu-and-slurm.md), not an assertion: a
    loaded machine is slower, and the check's own deadline (phases skipped or cut short) is
    tested above."""
    out, work = tmp_path / "check", tmp_path / "work"
    t0 = time.time()
    proc = _start_check(out, work)
    stdout, _ = proc.communicate(timeout=1800)
    print(f"GPU check rehearsal on CPU: {time.time() - t0:.0f} s")
    report = _summary(out)
    phases = {p["phase"]: p for p in report["phases"]}
    assert proc.returncode == 0, (stdout[-3000:], phases)
    assert report["ok"] and report["mode"] == "cpu"
    assert (
        list(phases)
        == report["phases_done"]
        == [
            "bench",
            "syncs",
            "teacher_clf",
            "bench_eager",  # optional from here
            "syncs_runners",
            "student",
            "bench_graphs",
        ]
    )
    assert _out_files_ok(out) == sorted(_gpu_check().OUT_FILES)
    bench = json.loads((out / "bench_env.json").read_text())
    assert bench["workload_names"] == ["random"]
    assert bench["env_names"] == ["march_teacher", "bare_rough"]
    assert bench["ops_per_step"]["random"]["march_teacher"] > 0
    assert set(report["results"]["compile_vs_eager"]) == {"random"}
    assert set(report["results"]["graphs_vs_default"]) == {"random"}
    syncs = report["results"]["syncs"]
    assert syncs["phases"] == ["env_march", "env_rough"] and syncs["cuda"] is False
    assert syncs["env_syncs_per_step"] == {"march": 0.0, "rough": 0.0}
    assert report["results"]["syncs_runners"]["phases"] == ["teacher", "distill"]
    teacher = report["results"]["teacher_clf"]
    with (out / "teacher_clf_curve.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [int(r["iteration"]) for r in rows] == list(range(1, len(rows) + 1))
    assert teacher["iterations"] == len(rows) >= 5
    walls = [float(r["wall_s"]) for r in rows]
    assert teacher["s_per_iteration"] == pytest.approx((walls[-1] - walls[0]) / (len(rows) - 1))
    assert "teacher_clf iteration 2: " in stdout and "s/iteration from iteration 2" in stdout
    with (out / "student_curve.csv").open() as f:
        assert [int(r["iteration"]) for r in csv.DictReader(f)] == [1, 2]
    assert "eval" in report["results"]
    for key in ("march_sync_lines_per_step", "env_syncs_per_step_march_minus_rough"):
        assert report["targets"][key]["met"] is None  # no CUDA: not measured
    assert sum(ln.startswith("[gpu_check] target ") for ln in stdout.splitlines()) == 5


def test_the_teacher_seconds_per_iteration_start_at_iteration_two():
    seconds_per_iteration = _gpu_check().seconds_per_iteration
    rows = [{"iteration": str(i), "wall_s": str(w)} for i, w in [(1, 30.0), (2, 31.5), (3, 33.5)]]
    assert seconds_per_iteration(rows) == pytest.approx(1.75)  # (33.5 - 30) / 2, not 33.5 / 3
    assert seconds_per_iteration(rows[:1]) is None
    resumed = [{"iteration": "7", "wall_s": "10"}, {"iteration": "9", "wall_s": "14"}]
    assert seconds_per_iteration(resumed) == 2.0


def _bench_figure():
    import importlib.util

    path = ROOT / "analysis" / "bench_figure.py"
    spec = importlib.util.spec_from_file_location("bench_figure", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


BENCH_RESULT = ROOT / "docs" / "results" / "bench_env_cpu64_2026-12-03_speed_targets.json"


def test_the_bench_figure_draws_every_non_physics_millisecond_of_a_real_bench(tmp_path):
    """analysis/bench_figure.py on a committed 64-env bench: per workload and env the bar
    segments add up to the bench's non-physics time (profiled minus physics, to the rounding of
    the categories), the planner's segment is its profile section and with the rest of the
    commands makes the commands category; the PNG, PDF and data CSV are written."""
    import pandas as pd

    fig = _bench_figure()
    assert fig.main([str(BENCH_RESULT), "--out", str(tmp_path)]) == 0
    stem = tmp_path / BENCH_RESULT.stem
    assert stem.with_suffix(".png").stat().st_size > 10_000 and stem.with_suffix(".pdf").is_file()
    data = pd.read_csv(tmp_path / f"{BENCH_RESULT.stem}_data.csv")
    bench = json.loads(BENCH_RESULT.read_text())
    assert set(data["workload"]) == {"random", "standing"}
    for workload, result in bench["workloads"].items():
        for env, nonphysics in result["nonphysics_ms_per_step"].items():
            rows = data[(data["workload"] == workload) & (data["env"] == env)]
            assert rows["ms"].sum() == pytest.approx(nonphysics, abs=0.01)
            assert "physics" not in set(rows["category"])
        march = data[(data["workload"] == workload) & (data["env"] == "march_teacher")]
        by_cat = march.set_index("category")["ms"]
        prof = result["profile"]["march_teacher"]
        assert by_cat[fig.PLANNER] == prof["sections_ms"]["commands/planner"]
        assert by_cat[fig.PLANNER] + by_cat["commands"] == pytest.approx(
            prof["categories_ms"]["commands"]
        )
        rough = data[(data["workload"] == workload) & (data["env"] == "bare_rough")]
        assert fig.PLANNER not in set(rough["category"])  # no planner in bare mjlab


def test_the_bench_figure_reads_a_gpu_check_folder_and_refuses_bad_input(tmp_path, capsys):
    fig = _bench_figure()
    no_profile = {"device": "cuda", "workloads": {"random": {"steps_per_s": {}}}}
    for name in ("bench_env.json", "bench_env.partial.json", "bench_env_eager.partial.json"):
        (tmp_path / name).write_text(json.dumps(no_profile))
    names = [p.name for p in fig.bench_files([tmp_path])]
    assert names == ["bench_env.json", "bench_env_eager.partial.json"]  # finals win
    (tmp_path / "bench_env_eager.json").write_text('{"workl')  # stopped while it printed
    names = [p.name for p in fig.bench_files([tmp_path])]
    assert names == ["bench_env.json", "bench_env_eager.partial.json"]
    (tmp_path / "bench_env_eager.json").unlink()
    assert fig.main([str(tmp_path)]) == 0
    assert "no profile pass" in capsys.readouterr().out
    (tmp_path / "bench_env.json").write_text("{")
    assert fig.main([str(tmp_path / "bench_env.json")]) == 2
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and "not a bench JSON" in out[0]
    assert fig.main([str(tmp_path / "missing.json")]) == 2
    assert "no bench JSON at" in capsys.readouterr().out
