"""march's Optuna sweeper (hydra/sweeper=march_optuna, Optuna >= 4): the study lives in a journal
file under the sweep directory and survives a killed sweep; failed trials are recorded and the
study goes on; the median pruner stops a trial from its evaluation rows; the best is reported."""

from __future__ import annotations

import csv
import io
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parent.parent
optuna = pytest.importorskip("optuna", minversion="4.0", reason="pip install -e '.[optuna]'")

SWEEP = [
    "-m", "+sweep=optuna_clf", "compute=smoke", "stage=teacher", "teacher.max_iterations=2",
    "teacher.eval_interval=1", "eval.num_rollouts=2", "compute.eval_num_envs=2",
    "compute.torch_threads=1", "eval.episode_length_s=0.5", "hydra.sweeper.n_trials=4",
    "hydra.sweeper.max_failures=1", "hydra.sweeper.pruner.n_startup_trials=1",
]  # fmt: skip


def _env() -> dict[str, str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    return env | {"MARCH_CRASH_TRIAL": "1", "MARCH_BAD_TRIAL": "3"}


def _study(sweep: Path):
    from hydra_plugins.march_optuna_sweeper.sweeper import open_storage

    storage = open_storage(str(sweep / "clf_weights.journal"))
    return optuna.load_study(study_name="clf_weights", storage=storage)


def test_a_hydra_sweep_value_becomes_an_optuna_distribution():
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from hydra_plugins.march_optuna_sweeper.sweeper import distribution

    parse = OverridesParser.create().parse_overrides
    cases = {
        "a=interval(2.0, 20.0)": optuna.distributions.FloatDistribution(2.0, 20.0),
        "a=tag(log, interval(1e-5, 1e-3))": optuna.distributions.FloatDistribution(
            1e-5, 1e-3, log=True
        ),
        "a=tag(int, interval(1, 8))": optuna.distributions.IntDistribution(1, 8),
        "a=range(2, 10, 2)": optuna.distributions.IntDistribution(2, 8, step=2),
        "a=range(2, 9, 2)": optuna.distributions.IntDistribution(2, 8, step=2),
        "a=range(10, 2, -3)": optuna.distributions.IntDistribution(4, 10, step=3),
        # Hydra's float range excludes its stop as Python's range does: 1.0 is not a value.
        "a=range(0.0, 1.0, 0.25)": optuna.distributions.FloatDistribution(0.0, 0.75, step=0.25),
        "a=range(0.0, 1.01, 0.25)": optuna.distributions.FloatDistribution(0.0, 1.0, step=0.25),
        "a=range(0.1, 0.7, 0.2)": optuna.distributions.FloatDistribution(0.1, 0.5, step=0.2),
        "a=choice(x, y)": optuna.distributions.CategoricalDistribution(["x", "y"]),
    }
    for text, expected in cases.items():
        assert distribution(parse([text])[0]) == expected, text


@pytest.mark.parametrize(
    "text",
    ["range(0.0, 1.0, 0.25)", "range(0.0, 1.0, 0.3)", "range(-1.0, 1.0, 0.4)", "range(1, 10, 3)",
     "range(2.5, 3.5, 0.125)", "range(0, 7)", "range(1.0, 0.0, -0.25)", "range(0.0, 0.9, 0.3)"],
)  # fmt: skip
def test_an_optuna_range_holds_exactly_hydras_values(text):
    """Every value Hydra's basic sweeper would run is one the distribution can propose, and no
    other: the grid of low + k * step up to high (Optuna's proposals), value for value."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from hydra_plugins.march_optuna_sweeper.sweeper import distribution

    override = OverridesParser.create().parse_overrides([f"a={text}"])[0]
    hydra_values = sorted(override.value().range())
    dist = distribution(override)
    grid = [dist.low + k * dist.step for k in range(round((dist.high - dist.low) / dist.step) + 1)]
    assert grid == pytest.approx(hydra_values), (grid, hydra_values)


@pytest.mark.sim
@pytest.mark.slow
def test_a_killed_study_resumes_records_failures_prunes_and_reports_the_best(tmp_path):
    sweep = tmp_path / "sweep"
    cmd = [sys.executable, "tests/optuna_trial.py", *SWEEP, f"hydra.sweep.dir={sweep}"]
    first = subprocess.Popen(
        cmd, cwd=ROOT, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    deadline = time.time() + 900
    try:  # kill the sweep while its third trial runs (two trials recorded)
        while not (sweep / "2" / "status.json").is_file():
            assert first.poll() is None, first.stdout.read()[-3000:]
            assert time.time() < deadline, "no third trial after 900 s"
            time.sleep(0.2)
        os.kill(first.pid, signal.SIGKILL)
    finally:
        if first.poll() is None:
            first.kill()
        first.wait()
    before = _study(sweep).trials
    assert [t.state.name for t in before] == ["COMPLETE", "FAIL", "RUNNING"]
    assert before[1].user_attrs["error"] == "RuntimeError: injected crash"

    out = subprocess.run(cmd, cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    print(out.stdout[out.stdout.index("[optuna] trials of") :])
    assert "2 of 4 trials recorded, 2 to run" in out.stdout
    # The killed sweep ran trial 2 in its own process: its job is gone, no waiting for it.
    assert f"trial 2 was cut short (its job (pid {first.pid} on " in out.stdout
    assert "is gone): asked again" in out.stdout
    assert "[optuna] trial 3: pruned at step 1" in out.stdout
    assert "Error executing job" not in out.stdout + out.stderr  # pruned is no error
    trials = _study(sweep).trials
    states = [t.state.name for t in trials]
    assert states[:4] == ["COMPLETE", "FAIL", "FAIL", "PRUNED"], states
    assert trials[2].user_attrs["interrupted"] and trials[3].params == trials[2].params
    assert states[4] in ("COMPLETE", "PRUNED") and len(trials) == 5
    assert sorted(trials[3].intermediate_values) == [1]  # stopped at its first evaluation row
    # A complete trial's final evaluation (iteration 2) is its value, not a pruner's step.
    assert sorted(trials[0].intermediate_values) == [1] and trials[0].value is not None
    assert trials[4].intermediate_values and trials[4].params != trials[0].params  # no repeat
    assert json.loads((sweep / "3" / "status.json").read_text())["state"] == "pruned"
    counted = [t for t in trials if not t.user_attrs.get("interrupted")]
    assert len(counted) == 4  # n_trials is the study's total
    complete = [t for t in trials if t.state.name == "COMPLETE"]
    best = max(complete, key=lambda t: t.value)
    result = yaml.safe_load((sweep / "optimization_results.yaml").read_text())
    assert result["best_trial"] == best.number and result["best_value"] == best.value
    assert result["n_trials"] == 4
    best_cfg = yaml.safe_load((sweep / "best_config.yaml").read_text())
    assert best_cfg["reward"]["terms"]["clf"] == pytest.approx(best.params["reward.terms.clf"])
    rows = list(csv.DictReader(io.StringIO((sweep / "trials.csv").read_text())))
    assert [r["state"] for r in rows][:4] == ["COMPLETE", "FAIL", "INTERRUPTED", "PRUNED"]

    again = subprocess.run(cmd, cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=900)
    assert again.returncode == 0 and "4 of 4 trials recorded, 0 to run" in again.stdout
    assert len(_study(sweep).trials) == 5  # a finished study runs no new trial

    # optuna-dashboard reads the journal: its API lists the study with its 5 trials.
    dashboard = pytest.importorskip("optuna_dashboard")
    from hydra_plugins.march_optuna_sweeper.sweeper import open_storage

    app = dashboard.wsgi(open_storage(str(sweep / "clf_weights.journal")))
    got: list[str] = []
    from wsgiref.util import setup_testing_defaults

    environ = {"REQUEST_METHOD": "GET", "PATH_INFO": "/api/studies"}
    setup_testing_defaults(environ)
    body = app(environ, lambda status, headers, exc_info=None: got.append(status))
    studies = json.loads(b"".join(body))["study_summaries"]
    assert got[0].startswith("200") and [s["study_name"] for s in studies] == ["clf_weights"]


@pytest.mark.sim
@pytest.mark.slow
def test_a_trial_that_trained_to_its_end_is_complete_whatever_its_final_value(tmp_path):
    """Trial 1's only evaluation is its final one, 100 m below trial 0's: the median pruner
    would stop it (n_startup_trials=1), but a final evaluation is the trial's value, never the
    pruner's to judge: COMPLETE with that value, and the best-trial choice sees it."""
    sweep = tmp_path / "sweep"
    args = [a for a in SWEEP if not a.startswith(("teacher.max_iterations", "hydra.sweeper.n_"))]
    cmd = [sys.executable, "tests/optuna_trial.py", *args, "teacher.max_iterations=1"]
    cmd += ["hydra.sweeper.n_trials=2", f"hydra.sweep.dir={sweep}"]
    env = _env() | {"MARCH_CRASH_TRIAL": "none", "MARCH_BAD_TRIAL": "1"}
    out = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    trials = _study(sweep).trials
    assert [t.state.name for t in trials] == ["COMPLETE", "COMPLETE"], out.stdout[-2000:]
    for t in trials:  # the value is the run's final evaluation row, reported to no pruner
        rows = list(csv.DictReader((sweep / str(t.number) / "eval.csv").open()))
        assert [r["iteration"] for r in rows] == ["1"] and t.intermediate_values == {}
        shift = 100.0 if t.number == 1 else 0.0
        assert t.value == pytest.approx(float(rows[0]["mean_distance_m"]) - shift, rel=1e-5)
    assert trials[1].value < trials[0].value - 90
    assert json.loads((sweep / "1" / "status.json").read_text())["state"] == "done"
