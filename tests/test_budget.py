"""``python -m march.inspect budget``: the pipeline's GPU hours from the bench figures and the
H100 anchor (issue 41), against hand-derived values."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from march.config.cli import load
from march.learn.budget import ANCHOR, budget, learn_s_per_step, table

ROOT = Path(__file__).resolve().parent.parent


def _bench(tmp_path: Path, ratio: float, device: str) -> Path:
    path = tmp_path / f"bench_{device}.json"
    path.write_text(
        json.dumps(
            {
                "device": device,
                "num_envs": 4096,
                "ratio_march_vs_rough_by_workload": {"random": ratio, "standing": 2.0},
            }
        )
    )
    return path


def test_the_anchor_learning_time_is_what_an_iteration_takes_beyond_its_steps():
    # 1.59 s per iteration of 4096 x 24 = 98,304 steps; the steps alone 98,304 / 74,000 s
    assert learn_s_per_step() * 98_304 == pytest.approx(1.59 - 98_304 / 74_000.0)
    assert ANCHOR["rough_steps_per_s"] == 74.0e3 and ANCHOR["rough_depth_steps_per_s"] == 71.2e3


def test_gpu_hours_per_stage_from_a_measured_gpu_ratio(tmp_path):
    cfg = load(["compute=gpu"])
    report = budget(cfg, bench=_bench(tmp_path, 0.9, "cuda:0"))
    rows = {r["stage"]: r for r in report["run"]}
    n, t, d = cfg.compute.num_envs, cfg.teacher, cfg.distill
    steps = t.max_iterations * n * t.num_steps_per_env
    assert rows["teacher"]["env_steps"] == steps
    want = steps / (74_000.0 * 0.9) + steps * (1.59 - 98_304 / 74_000.0) / 98_304
    assert rows["teacher"]["gpu_hours"] == pytest.approx(want / 3600)
    # distillation: iterations x envs x steps per env at the depth anchor x the ratio
    steps = d.max_iterations * n * d.num_steps_per_env
    assert rows["distillation"]["gpu_hours"] == pytest.approx(steps / (71_200.0 * 0.9) / 3600)
    # evaluations: rollouts x control steps of an episode, every eval_interval iterations
    dt = cfg.env.sim_dt * cfg.env.decimation
    per_eval = cfg.eval.num_rollouts * round(cfg.eval.episode_length_s / dt)
    assert rows["teacher evaluations"]["count"] == t.max_iterations // t.eval_interval
    assert (
        rows["student evaluations"]["env_steps"] == (d.max_iterations // d.eval_interval) * per_eval
    )
    assert report["run_gpu_hours"] == pytest.approx(sum(r["gpu_hours"] for r in report["run"]))
    # the baseline sweep: 3 clf runs and 3 model-free runs with twice the teacher iterations
    base = next(s for s in report["sweeps"] if s["sweep"].startswith("baseline"))
    one_more_teacher = rows["teacher"]["gpu_hours"] + rows["teacher evaluations"]["gpu_hours"]
    assert base["gpu_hours"] == pytest.approx(6 * report["run_gpu_hours"] + 3 * one_more_teacher)
    assert "| teacher | 10000 |" in table(report)


def test_a_cpu_ratio_is_capped_at_one_and_a_gpu_checks_iteration_time_wins(tmp_path):
    cfg = load(["compute=gpu"])
    cpu = budget(cfg, bench=_bench(tmp_path, 1.07, "cpu"))
    assert cpu["march_vs_rough"] == 1.0 and "a CPU ratio" in cpu["speeds_source"]
    check = tmp_path / "gpu_check.json"
    check.write_text(
        json.dumps(
            {"args": {"train_envs": 4096}, "results": {"teacher_clf": {"s_per_iteration": 2.0}}}
        )
    )
    rows = {r["stage"]: r for r in budget(cfg, _bench(tmp_path, 0.9, "cuda"), check)["run"]}
    assert rows["teacher"]["gpu_hours"] == pytest.approx(cfg.teacher.max_iterations * 2.0 / 3600)
    assert rows["teacher"]["source"].startswith("measured")
    small = json.loads(check.read_text())
    small["args"]["train_envs"] = 256  # another size: not this config's iteration
    check.write_text(json.dumps(small))
    rows = {r["stage"]: r for r in budget(cfg, _bench(tmp_path, 0.9, "cuda"), check)["run"]}
    assert not rows["teacher"]["source"].startswith("measured")


def test_the_budget_job_prints_the_table_and_refuses_bad_input(tmp_path):
    def run(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(
            [sys.executable, "-m", "march.inspect", "budget", *args],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=300,
        )

    ok = run("compute=gpu", f"budget.bench={_bench(tmp_path, 0.9, 'cuda')}")
    assert ok.returncode == 0, ok.stderr[-2000:]
    assert "| teacher | 10000 |" in ok.stdout and "| baseline (2 arms x 3 seeds) | 6 |" in ok.stdout
    for bad in ("budget.bench=/no/such.json", "budget.bogus=1"):
        res = run("compute=gpu", bad)
        both = [ln for ln in [*res.stdout.splitlines(), *res.stderr.splitlines()] if ln.strip()]
        assert res.returncode == 2 and len(both) == 1, res.stdout + res.stderr
