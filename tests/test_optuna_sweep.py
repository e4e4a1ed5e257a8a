"""march.train returns the final evaluation's objective; Hydra's Optuna sweeper optimises it."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.sim
def test_optuna_sweep_reads_three_objective_values(tmp_path):
    pytest.importorskip("optuna", minversion="4.0", reason="pip install -e '.[optuna]'")
    sweep, returns = tmp_path / "sweep", tmp_path / "returns.jsonl"
    cmd = [
        sys.executable, "-m", "march.train", "-m", "+sweep=optuna_clf",
        "compute=smoke", "stage=teacher", "teacher.max_iterations=1",
        "teacher.num_steps_per_env=4",  # what each trial returns is checked, not the learning
        "eval.num_rollouts=2", "compute.eval_num_envs=2", "compute.torch_threads=1",
        "eval.episode_length_s=0.2",  # 10 steps
        "hydra.sweeper.n_trials=3", f"hydra.sweep.dir={sweep}",
        "+hydra.callbacks.returns._target_=tests.sweep_returns.RecordReturns",
        f"+hydra.callbacks.returns.path={returns}",
    ]  # fmt: skip
    out = subprocess.run(
        cmd, cwd=ROOT, capture_output=True, text=True, timeout=900,
        env={**__import__("os").environ, "PYTHONPATH": str(ROOT)},
    )  # fmt: skip
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    jobs = [json.loads(line) for line in returns.read_text().splitlines()]
    assert len(jobs) == 3
    weights = set()
    for job in jobs:
        run = Path(job["dir"])
        # The value each trial returned is its run's final evaluation (teacher, iteration 1).
        with (run / "eval.csv").open(newline="") as f:
            rows = list(csv.DictReader(f))
        assert [r["iteration"] for r in rows] == ["1"]
        assert job["value"] == pytest.approx(float(rows[0]["mean_distance_m"]), rel=1e-5)
        cfg = yaml.safe_load((run / "config.yaml").read_text())
        weights.add((cfg["reward"]["terms"]["clf"], cfg["reward"]["terms"]["dclf"]))
        assert 2.0 <= cfg["reward"]["terms"]["clf"] <= 20.0
        assert 0.1 <= cfg["reward"]["terms"]["dclf"] <= 2.0
    assert len(weights) == 3  # three trials, three weight pairs
    # What Optuna made of them: the best of the three values it read.
    best = yaml.safe_load((sweep / "optimization_results.yaml").read_text())
    assert best["best_value"] == pytest.approx(max(j["value"] for j in jobs))
