"""The study loop: ask Optuna for trials, launch them through Hydra's launcher, record the results.

Each trial is one Hydra job (the configured launcher: local, submitit local or Slurm) whose job
number is the trial number (its directory ``<sweep dir>/<number>``). The job learns which trial
it is from environment variables set through ``hydra.job.env_set`` (:mod:`march.learn.tuning`
reads them to report its evaluation rows, to prune, to mark itself alive and to record how it
ended).

- A trial's job records its own outcome: its final objective as the trial's value (COMPLETE),
  PRUNED when the study's pruner stopped it, FAIL with its error. A job that could not (killed,
  or failed before the run began) is recorded here from what the launcher returned.
- Failures: the sweep stops with one line once more than ``max_failures`` trials failed **in
  this sweep**; running the same command again goes on (earlier failures stay recorded and do
  not count again), ``hydra.sweeper.max_failures`` raises the budget.
- One driver per study: the sweep holds the study's driver lock (:mod:`.storage`); a second
  sweep on the same study refuses in one line. A RUNNING trial found at start-up is decided by
  evidence, its job's heartbeat: alive -> waited for (its job records its outcome); gone ->
  recorded FAIL with ``interrupted`` set, not counted, its parameters asked again.
- At the end: ``optimization_results.yaml`` (the best trial's number, value, parameters and
  directory), ``best_config.yaml`` (that run's config) and ``trials.csv`` in the sweep
  directory, and the trial table printed.
"""

from __future__ import annotations

import csv
import io
import logging
import math
import shutil
import sys
import time
from decimal import Decimal
from pathlib import Path
from typing import Any

import optuna
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import ChoiceSweep, IntervalSweep, Override, RangeSweep
from hydra.core.plugins import Plugins
from hydra.plugins.sweeper import Sweeper
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from optuna.distributions import (
    BaseDistribution,
    CategoricalDistribution,
    FloatDistribution,
    IntDistribution,
)
from optuna.trial import TrialState

from hydra_plugins.march_optuna_sweeper.storage import (
    StudyDriven,
    frozen_by_number,
    heartbeat_path,
    job_alive,
    lock_path,
    open_storage,
    take_driver_lock,
    trial_by_number,
)

log = logging.getLogger(__name__)

ENV_TRIAL = "MARCH_OPTUNA_TRIAL"
ENV_STORAGE = "MARCH_OPTUNA_STORAGE"
ENV_STUDY = "MARCH_OPTUNA_STUDY"
ENV_HEARTBEAT = "MARCH_OPTUNA_HEARTBEAT"
ENV_HEARTBEAT_S = "MARCH_OPTUNA_HEARTBEAT_S"
FINISHED = (TrialState.COMPLETE, TrialState.PRUNED, TrialState.FAIL)
STALE_BEATS = 4
"""A trial's job that has not renewed its heartbeat for this many intervals is gone."""


def distribution(override: Override) -> BaseDistribution:
    """An Optuna distribution from a Hydra sweep override (interval, range, choice; log tag)."""
    value = override.value()
    key = override.get_key_element()
    if isinstance(value, ChoiceSweep):
        return CategoricalDistribution(list(value.list))
    if isinstance(value, RangeSweep):
        # Hydra's own values (its range, like Python's, excludes stop; floats counted exactly).
        values = list(value.range())
        if not values:
            raise ValueError(f"hydra.sweeper.params.{key}: {override.input_line} is empty")
        step = abs(value.step)
        if isinstance(value.range(), range):
            return IntDistribution(min(values), max(values), step=int(step))
        # The grid from the numbers as written (Hydra's Decimal(0.3) x 3 is 0.8999999999999999,
        # which Optuna would cut to 0.6: not a multiple of the step).
        low = Decimal(repr(min(values)))
        high = low + (len(values) - 1) * Decimal(repr(float(step)))
        return FloatDistribution(float(low), float(high), step=float(step))
    if isinstance(value, IntervalSweep):
        log_scale = "log" in value.tags
        if "int" in value.tags:  # Hydra parses interval bounds as floats
            return IntDistribution(int(value.start), int(value.end), log=log_scale)
        return FloatDistribution(float(value.start), float(value.end), log=log_scale)
    raise ValueError(f"hydra.sweeper.params.{key}: not a sweep the Optuna sweeper can search")


def _counted(study: optuna.Study) -> list[optuna.trial.FrozenTrial]:
    return [t for t in study.trials if t.state in FINISHED and not t.user_attrs.get("interrupted")]


class MarchOptunaSweeper(Sweeper):
    def __init__(
        self,
        direction: str,
        study_name: str,
        storage: str | None,
        n_trials: int,
        n_jobs: int,
        max_failures: int,
        sampler: Any,
        pruner: Any,
        params: dict[str, str] | None,
        heartbeat_s: float = 30.0,
    ) -> None:
        if direction not in ("maximize", "minimize"):
            raise ValueError(f"hydra.sweeper.direction={direction!r}: maximize or minimize")
        if n_trials < 1 or n_jobs < 1 or max_failures < 0 or heartbeat_s <= 0:
            raise ValueError(
                "hydra.sweeper: n_trials, n_jobs >= 1, max_failures >= 0 and heartbeat_s > 0"
            )
        self.direction, self.study_name, self.storage = direction, study_name, storage
        self.n_trials, self.n_jobs, self.max_failures = n_trials, n_jobs, max_failures
        self.sampler_cfg, self.pruner_cfg = sampler, pruner
        self.params = dict(params or {})
        self.heartbeat_s = float(heartbeat_s)
        self.failed = 0  # trials that failed in this sweep (the budget's count)

    def setup(self, *, hydra_context: Any, task_function: Any, config: DictConfig) -> None:
        self.hydra_context, self.config = hydra_context, config
        self.launcher = Plugins.instance().instantiate_launcher(
            hydra_context=hydra_context, task_function=task_function, config=config
        )
        self.sweep_dir = Path(config.hydra.sweep.dir)

    # -- the search space ---------------------------------------------------------------------

    def _space(self, arguments: list[str]) -> tuple[dict[str, BaseDistribution], list[str]]:
        parser = OverridesParser.create(config_loader=self.hydra_context.config_loader)
        items = [f"{k}={v}" for k, v in self.params.items()] + list(arguments)
        space: dict[str, BaseDistribution] = {}
        fixed: list[str] = []
        for override in parser.parse_overrides(items):
            key = override.get_key_element()
            if override.is_sweep_override():
                space[key] = distribution(override)
            else:
                fixed.append(f"{key}={override.get_value_element_as_str()}")
        return space, fixed

    # -- the loop -------------------------------------------------------------------------------

    def storage_location(self) -> str:
        return self.storage or str(self.sweep_dir / f"{self.study_name}.journal")

    def sweep(self, arguments: list[str]) -> Any:
        space, fixed = self._space(arguments)
        self.sweep_dir.mkdir(parents=True, exist_ok=True)
        where = self.storage_location()
        lock = lock_path(where, self.sweep_dir, self.study_name)
        try:  # held until this process ends (self._lock stays open)
            self._lock = take_driver_lock(lock)
        except StudyDriven as holder:
            print(
                f"error: study {self.study_name!r} in {where} is being driven by another sweep "
                f"({holder}; lock {lock}): its trials are left running; run this command again "
                "once that sweep has ended",
                file=sys.stderr,
            )
            sys.exit(1)
        OmegaConf.save(self.config, self.sweep_dir / "multirun.yaml")
        self._storage = open_storage(where)
        names = [s.study_name for s in optuna.get_all_study_summaries(self._storage)]
        existing = 0
        if self.study_name in names:
            existing = len(
                optuna.load_study(study_name=self.study_name, storage=self._storage).trials
            )
        study = optuna.create_study(
            study_name=self.study_name,
            storage=self._storage,
            sampler=_built(self.sampler_cfg, existing),
            pruner=_built(self.pruner_cfg) or optuna.pruners.NopPruner(),
            direction=self.direction,
            load_if_exists=True,
        )
        self._settle_running(study)
        done = len(_counted(study))
        print(
            f"[optuna] study {self.study_name!r} in {where}: {done} of {self.n_trials} trials "
            f"recorded, {max(self.n_trials - done, 0)} to run",
            flush=True,
        )
        while True:
            if self.failed > self.max_failures:
                self._finish(study)
                print(
                    f"error: {self.failed} trials of this sweep failed, more than "
                    f"hydra.sweeper.max_failures={self.max_failures}; the study is kept in "
                    f"{where} (trials.csv names each error): fix the cause and run the same "
                    "command to go on (a new sweep counts only its own failures), or allow "
                    "more with hydra.sweeper.max_failures=<n>",
                    file=sys.stderr,
                )
                sys.exit(1)
            counted = _counted(study)
            remaining = self.n_trials - len(counted)
            if remaining <= 0:
                break
            trials = [study.ask(space) for _ in range(min(self.n_jobs, remaining))]
            batch = [self._overrides(t, fixed, where) for t in trials]
            results = self.launcher.launch(batch, initial_job_idx=trials[0].number)
            for trial, ret in zip(trials, results, strict=True):
                self._tell(study, trial, ret)
        return self._finish(study)

    def _overrides(self, trial: optuna.Trial, fixed: list[str], where: str) -> list[str]:
        params = [f"{k}={_as_override(v)}" for k, v in trial.params.items()]
        env = {
            ENV_TRIAL: trial.number,
            ENV_STORAGE: where,
            ENV_STUDY: self.study_name,
            ENV_HEARTBEAT: heartbeat_path(self.sweep_dir, trial.number),
            ENV_HEARTBEAT_S: self.heartbeat_s,
        }
        env_set = [f"+hydra.job.env_set.{k}={_as_override(str(v))}" for k, v in env.items()]
        # The trial's directory is its number (the override-named default outgrows a file name).
        return [*fixed, *params, *env_set, f"hydra.sweep.subdir={trial.number}"]

    def _settle_running(self, study: optuna.Study) -> None:
        """RUNNING trials left by an earlier sweep (this one holds the driver lock: no live
        sweep launched them now). A trial whose job is alive (heartbeat) is waited for: the job
        records its outcome. One whose job is gone is recorded FAIL (``interrupted``: not
        counted) and its parameters are asked again."""
        stale_s = STALE_BEATS * self.heartbeat_s
        said: set[int] = set()
        while running := study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):
            waiting = []
            for t in running:
                alive, why = job_alive(heartbeat_path(self.sweep_dir, t.number), stale_s)
                if alive:
                    waiting.append(t.number)
                    if t.number not in said:
                        print(f"[optuna] trial {t.number} is still running ({why}): waiting")
                        said.add(t.number)
                    continue
                trial = trial_by_number(study, self._storage, t.number)
                trial.set_user_attr("interrupted", True)
                trial.set_user_attr("error", f"interrupted: {why}")
                study.tell(t.number, state=TrialState.FAIL)
                study.enqueue_trial(t.params, skip_if_exists=False)
                print(f"[optuna] trial {t.number} was cut short ({why}): asked again", flush=True)
            if not waiting:
                break
            time.sleep(min(self.heartbeat_s, 5.0))
        for number in sorted(said):
            t = frozen_by_number(study, number)
            if t.state != TrialState.RUNNING and not t.user_attrs.get("interrupted"):
                print(f"[optuna] trial {number} ended while waited for: {_outcome(t)}")

    def _tell(self, study: optuna.Study, trial: optuna.Trial, ret: Any) -> None:
        """Record what the trial's job did not record itself (it was killed, or failed before its
        run began), from what the launcher returned; print the trial's outcome."""
        if frozen_by_number(study, trial.number).state == TrialState.RUNNING:
            try:
                value = ret.return_value  # raises the job's exception
            except optuna.TrialPruned:
                study.tell(trial, state=TrialState.PRUNED)
            except Exception as err:  # noqa: BLE001 - every failure of a trial is recorded
                text = str(err).strip().splitlines()
                trial.set_user_attr(
                    "error", f"{type(err).__name__}: {text[0] if text else ''}"[:300]
                )
                study.tell(trial, state=TrialState.FAIL)
            else:
                if value is None or not math.isfinite(float(value)):
                    trial.set_user_attr("error", f"non-finite objective {value!r}")
                    study.tell(trial, state=TrialState.FAIL)
                else:
                    study.tell(trial, float(value))
        frozen = frozen_by_number(study, trial.number)
        self.failed += frozen.state == TrialState.FAIL
        print(f"[optuna] trial {trial.number}: {_outcome(frozen)}", flush=True)

    # -- the results ----------------------------------------------------------------------------

    def _finish(self, study: optuna.Study) -> dict[str, Any] | None:
        table = trial_table(study, self.sweep_dir)
        (self.sweep_dir / "trials.csv").write_text(table)
        print(f"[optuna] trials of {self.study_name!r}:\n{table}", end="", flush=True)
        complete = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
        if not complete:
            return None
        best = study.best_trial
        run = self.sweep_dir / str(best.number)
        result = {
            "name": "optuna",
            "study_name": self.study_name,
            "storage": self.storage_location(),
            "direction": self.direction,
            "best_trial": best.number,
            "best_value": best.value,
            "best_params": dict(best.params),
            "best_dir": str(run),
            "n_trials": len(_counted(study)),
        }
        OmegaConf.save(OmegaConf.create(result), self.sweep_dir / "optimization_results.yaml")
        if (run / "config.yaml").is_file():
            shutil.copyfile(run / "config.yaml", self.sweep_dir / "best_config.yaml")
        print(f"[optuna] best: trial {best.number}, value {best.value:.6g}, {dict(best.params)}")
        return result


def _outcome(t: optuna.trial.FrozenTrial) -> str:
    """How a finished trial ended, in words."""
    if t.state == TrialState.COMPLETE:
        return f"{t.value:.6g}"
    if t.state == TrialState.PRUNED:
        step = max(t.intermediate_values) if t.intermediate_values else None
        return f"pruned at step {step}"
    if t.state == TrialState.FAIL:
        return f"failed ({t.user_attrs.get('error', 'no error recorded')})"
    return t.state.name


def trial_table(study: optuna.Study, sweep_dir: Path) -> str:
    """Every trial: number, state, value, last reported step, parameters, error, directory."""
    keys = sorted({k for t in study.trials for k in t.params})
    out = io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    w.writerow(["number", "state", "value", "last_step", *keys, "error", "dir"])
    for t in study.trials:
        state = "INTERRUPTED" if t.user_attrs.get("interrupted") else t.state.name
        step = max(t.intermediate_values) if t.intermediate_values else ""
        value = "" if t.value is None else f"{t.value:.6g}"
        params = [t.params.get(k, "") for k in keys]
        error = t.user_attrs.get("error", "")
        w.writerow([t.number, state, value, step, *params, error, sweep_dir / str(t.number)])
    return out.getvalue()


def _built(spec: Any, existing: int = 0) -> Any:
    """A sampler or pruner from its config (None stays None). A seeded sampler of a study that
    already holds ``existing`` trials is seeded ``seed + existing``: restarted with its first
    seed it would propose the first trials' parameters again."""
    if not isinstance(spec, (dict, DictConfig)):
        return spec
    seed = spec.get("seed")
    if existing and seed is not None:
        return instantiate(spec, seed=int(seed) + existing)
    return instantiate(spec)


def _as_override(value: Any) -> str:
    """A value as a Hydra override string (strings quoted where the grammar needs it)."""
    if isinstance(value, str):
        plain = value.replace("_", "").replace("-", "").replace(".", "").replace("/", "")
        return value if plain.isalnum() else "'" + value.replace("'", "\\'") + "'"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)
    return str(value)
