"""The Optuna rules, fast: a run's final evaluation is the trial's value and never the pruner's
to cut, and every evaluation of a run has its own, increasing step (the slow tests in
test_optuna_study.py run them through whole sweeps)."""

from __future__ import annotations

import dataclasses
import os

import pytest

optuna = pytest.importorskip("optuna", minversion="4.0", reason="pip install -e '.[optuna]'")

from march.config import MarchConfig  # noqa: E402
from march.learn import tuning  # noqa: E402
from march.train import trial_step  # noqa: E402


class AlwaysPrune(optuna.pruners.BasePruner):
    """A pruner that stops every trial it is asked about."""

    def prune(self, study, trial) -> bool:
        return True


@pytest.fixture
def live_trial(tmp_path, monkeypatch):
    """Trial 0 of a study whose pruner stops everything, as march.learn.tuning opens it."""
    storage = f"sqlite:///{tmp_path / 'study.db'}"
    study = optuna.create_study(study_name="s", storage=storage, pruner=AlwaysPrune())
    trial = study.ask()
    monkeypatch.setenv(tuning.ENV_TRIAL, "0")
    monkeypatch.setenv(tuning.ENV_STORAGE, storage)
    monkeypatch.setenv(tuning.ENV_STUDY, "s")
    monkeypatch.setattr(tuning, "_trial", {"key": tuning._key(), "study": study, "trial": trial})
    yield study
    assert os.environ[tuning.ENV_TRIAL] == "0"


def test_the_final_evaluation_is_never_sent_to_the_pruner(live_trial):
    tuning.report(2.5, 7, final=True)  # the run's last evaluation: no report, no prune
    assert live_trial.trials[0].intermediate_values == {}
    with pytest.raises(optuna.TrialPruned):
        tuning.report(1.0, 3)  # an intermediate one is the pruner's to judge
    assert live_trial.trials[0].intermediate_values == {3: 1.0}


@pytest.mark.parametrize("scale", [0.5, 1.0, 2.0, 3.0])
@pytest.mark.parametrize("stage", ["all", "teacher"])
def test_every_evaluation_has_its_own_increasing_step_and_one_is_final(scale, stage):
    cfg = MarchConfig()
    cfg = dataclasses.replace(
        cfg,
        stage=stage,
        teacher=dataclasses.replace(cfg.teacher, max_iterations=6, budget_scale=scale),
        distill=dataclasses.replace(cfg.distill, max_iterations=4),
    )
    ran = cfg.teacher.iterations  # the teacher iterations that ran: 3, 6, 12, 18
    # Evaluations at every iteration from 1 (eval_interval 1) to each stage's last.
    evals = [("teacher", i) for i in range(1, ran + 1)]
    if stage == "all":
        evals += [("student", i) for i in range(1, cfg.distill.max_iterations + 1)]
    steps = [trial_step(cfg, s, i) for s, i in evals]
    numbers = [n for n, _ in steps]
    assert numbers == sorted(set(numbers)), numbers  # distinct and increasing
    assert [final for _, final in steps] == [False] * (len(steps) - 1) + [True]
