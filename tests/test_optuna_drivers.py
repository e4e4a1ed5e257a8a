"""Who may drive a study, and what a sweep does with trials it did not launch (issue 45).

Every sweep here is a real Hydra multirun of march's sweeper on a journal file, with the trial
job of ``tests/optuna_app.py`` (``march.learn.tuning`` called as ``march.train`` calls it, no
simulation): a study stopped by its failure budget goes on when run again; a second sweep on a
live study refuses and leaves its trials alone; a sweep that finds a RUNNING trial whose job is
alive waits for it, and gives up one whose job is gone; a job whose trial was given up does not
run it.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

optuna = pytest.importorskip("optuna", minversion="4.0", reason="pip install -e '.[optuna]'")

ROOT = Path(__file__).resolve().parent.parent
APP = """\
defaults:
  - override hydra/sweeper: march_optuna
  - _self_
x: 0.0
steps: 3
step_s: 0.2
hydra:
  sweep:
    dir: {sweep}
  sweeper:
    study_name: app
    n_trials: 3
    max_failures: 0
    heartbeat_s: 0.5
    pruner: null
    sampler: {{_target_: optuna.samplers.RandomSampler, seed: 0}}
    params:
      x: interval(0.0, 1.0)
"""


def _setup(tmp_path: Path) -> tuple[Path, list[str], dict[str, str]]:
    sweep = tmp_path / "sweep"
    (tmp_path / "app.yaml").write_text(APP.format(sweep=sweep))
    cmd = [sys.executable, "tests/optuna_app.py", "-m", "--config-dir", str(tmp_path)]
    cmd += ["--config-name", "app"]
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MARCH_APP_LOG": str(tmp_path / "jobs.log")}
    env.pop("MARCH_CRASH_TRIALS", None)
    return sweep, cmd, env


def _run(cmd: list[str], env: dict[str, str], *args: str, timeout: int = 300):
    return subprocess.run(
        [*cmd, *args], cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout
    )


def _trials(sweep: Path) -> list:
    from hydra_plugins.march_optuna_sweeper.storage import open_storage

    storage = open_storage(str(sweep / "app.journal"))
    return optuna.load_study(study_name="app", storage=storage).trials


def _states(sweep: Path) -> list[str]:
    return [t.state.name for t in _trials(sweep)]


def _wait_for(path: Path, proc: subprocess.Popen, timeout: float = 120) -> None:
    deadline = time.time() + timeout
    while not path.exists():
        assert proc.poll() is None, proc.communicate()[0][-3000:]
        assert time.time() < deadline, f"no {path} after {timeout} s"
        time.sleep(0.05)


def test_a_study_stopped_by_its_failure_budget_goes_on_when_run_again(tmp_path):
    sweep, cmd, env = _setup(tmp_path)
    first = _run(cmd, env | {"MARCH_CRASH_TRIALS": "1"})
    assert first.returncode == 1
    last = first.stderr.strip().splitlines()[-1]
    assert last.startswith("error: 1 trials of this sweep failed, more than ")
    assert "hydra.sweeper.max_failures=0" in last and "max_failures=<n>" in last, last
    assert _states(sweep) == ["COMPLETE", "FAIL"]
    assert _trials(sweep)[1].user_attrs["error"] == "RuntimeError: injected crash"
    # The cause fixed, the same command goes on: the earlier failure stays, counted in
    # n_trials but not in this sweep's failure budget.
    again = _run(cmd, env)
    assert again.returncode == 0, again.stdout[-2000:] + again.stderr[-2000:]
    assert "2 of 3 trials recorded, 1 to run" in again.stdout
    assert _states(sweep) == ["COMPLETE", "FAIL", "COMPLETE"]
    # And once more with a crash in its one new trial: this sweep's first failure is within
    # a budget of 1 (the study's two failures would not be).
    more = _run(
        cmd, env | {"MARCH_CRASH_TRIALS": "3"}, "hydra.sweeper.n_trials=5",
        "hydra.sweeper.max_failures=1",
    )  # fmt: skip
    assert more.returncode == 0, more.stderr[-2000:]
    assert _states(sweep) == ["COMPLETE", "FAIL", "COMPLETE", "FAIL", "COMPLETE"]


def test_a_second_sweep_on_a_live_study_refuses_and_leaves_its_trials_alone(tmp_path):
    sweep, cmd, env = _setup(tmp_path)
    args = ["hydra.sweeper.n_trials=2", "steps=10", "step_s=0.5"]
    first = subprocess.Popen(
        [*cmd, *args], cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
        text=True,
    )  # fmt: skip
    try:
        _wait_for(sweep / "0" / ".optuna_heartbeat", first)
        second = _run(cmd, env, *args)
        out, _ = first.communicate(timeout=300)
    finally:
        if first.poll() is None:
            first.kill()
    assert second.returncode == 1
    lines = second.stderr.strip().splitlines()
    assert len(lines) == 1 and "is being driven by another sweep (pid " in lines[0], lines
    assert f"pid {first.pid} on " in lines[0]
    assert first.returncode == 0, out[-3000:]
    trials = _trials(sweep)
    assert [t.state.name for t in trials] == ["COMPLETE", "COMPLETE"]
    assert not any(t.user_attrs.get("interrupted") for t in trials)
    assert trials[0].value == pytest.approx(trials[0].params["x"])  # the final value, told


def _launch_and_kill_driver(tmp_path: Path, *args: str) -> tuple[Path, list[str], dict, int]:
    """A sweep whose trial jobs are processes of their own (submitit's local launcher, as Slurm
    jobs are): SIGKILL the sweep while trial 0's job runs; (sweep, cmd, env, job 0's pid)."""
    sweep, cmd, env = _setup(tmp_path)
    cmd = [*cmd, "hydra/launcher=submitit_local", "hydra.sweeper.n_trials=2", *args]
    first = subprocess.Popen(
        cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        start_new_session=True,
    )  # fmt: skip
    try:
        _wait_for(sweep / "0" / ".optuna_heartbeat", first)
    finally:
        os.kill(first.pid, signal.SIGKILL)
        first.wait()
    start = (tmp_path / "jobs.log").read_text().split()
    assert start[:2] == ["start", "0"]
    return sweep, cmd, env, int(start[2])


def test_a_sweep_waits_for_a_trial_whose_job_outlived_its_killed_sweep(tmp_path):
    sweep, cmd, env, job = _launch_and_kill_driver(tmp_path, "steps=30", "step_s=0.5")
    assert _states(sweep) == ["RUNNING"]
    os.kill(job, 0)  # the job is alive, its sweep is not
    again = _run(cmd, env, "steps=2")  # trial 0 keeps its 30 steps; trial 1 needs no more
    assert again.returncode == 0, again.stdout[-3000:] + again.stderr[-3000:]
    assert "trial 0 is still running (its job (pid " in again.stdout
    assert "trial 0 ended while waited for: " in again.stdout
    trials = _trials(sweep)
    assert [t.state.name for t in trials] == ["COMPLETE", "COMPLETE"]
    assert trials[0].value == pytest.approx(trials[0].params["x"])
    assert not trials[0].user_attrs.get("interrupted")
    log = (tmp_path / "jobs.log").read_text().splitlines()
    assert log.index("end 0") < next(i for i, ln in enumerate(log) if ln.startswith("start 1"))


def test_a_sweep_gives_up_a_trial_whose_job_is_gone_and_asks_its_parameters_again(tmp_path):
    sweep, cmd, env, job = _launch_and_kill_driver(tmp_path, "steps=40", "step_s=0.5")
    os.kill(job, signal.SIGKILL)
    time.sleep(0.5)
    again = _run(cmd, env, "steps=2")  # the long steps only kept trial 0 alive to be killed
    assert again.returncode == 0, again.stdout[-3000:] + again.stderr[-3000:]
    assert f"trial 0 was cut short (its job (pid {job} on " in again.stdout
    trials = _trials(sweep)
    assert [t.state.name for t in trials] == ["FAIL", "COMPLETE", "COMPLETE"]
    assert trials[0].user_attrs["interrupted"] and trials[1].params == trials[0].params


def test_a_job_whose_trial_was_given_up_does_not_run_it(tmp_path):
    """A Slurm job still queued when its sweep died: the next sweep finds its trial RUNNING
    without a heartbeat and gives it up; when the job starts at last it does not run it."""
    sweep, cmd, env = _setup(tmp_path)
    from hydra_plugins.march_optuna_sweeper.storage import open_storage

    journal = str(sweep / "app.journal")
    study = optuna.create_study(study_name="app", storage=open_storage(journal))
    study.ask({"x": optuna.distributions.FloatDistribution(0.0, 1.0)})  # launched, never started
    again = _run(cmd, env, "hydra.sweeper.n_trials=1", "hydra.sweeper.direction=minimize")
    assert again.returncode == 0, again.stdout[-3000:] + again.stderr[-3000:]
    assert "trial 0 was cut short (its job never started): asked again" in again.stdout
    assert _states(sweep) == ["FAIL", "COMPLETE"]
    job_env = env | {
        "MARCH_OPTUNA_TRIAL": "0", "MARCH_OPTUNA_STORAGE": journal, "MARCH_OPTUNA_STUDY": "app",
        "MARCH_OPTUNA_HEARTBEAT": str(sweep / "0" / ".optuna_heartbeat"),
    }  # fmt: skip
    late = subprocess.run(
        [sys.executable, "tests/optuna_app.py", "--config-dir", str(tmp_path), "--config-name",
         "app", f"hydra.run.dir={tmp_path / 'late'}"],
        cwd=ROOT, env=job_env, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert late.returncode != 0
    assert "trial 0 of study 'app' is FAIL, no longer RUNNING" in late.stderr
    assert "start 0" in (tmp_path / "jobs.log").read_text()
    assert _states(sweep) == ["FAIL", "COMPLETE"]  # the late job recorded nothing
