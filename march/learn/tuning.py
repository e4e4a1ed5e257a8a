"""A run as one trial of march's Optuna sweeper (``hydra/sweeper=march_optuna``): report each
evaluation row's objective to the study, stop early when its pruner says so, and record the
trial's own outcome.

The sweeper (``hydra_plugins/march_optuna_sweeper``) sets ``MARCH_OPTUNA_TRIAL`` (the trial's
number), ``MARCH_OPTUNA_STORAGE``, ``MARCH_OPTUNA_STUDY``, ``MARCH_OPTUNA_HEARTBEAT`` (a file)
and ``MARCH_OPTUNA_HEARTBEAT_S`` in the job's environment (``hydra.job.env_set``); outside a
trial every function here does nothing, and Optuna is not imported. The pruner is the sweep's own
(``hydra.sweeper.pruner`` of the job's Hydra config). In a run over N ranks rank 0 reports,
decides and writes, and every rank follows its decision.

A trial's job, not only the sweep that launched it, says how it ended (:func:`finish`,
:func:`pruned`, :func:`failed`): a sweep killed while its Slurm jobs run loses nothing, and the
next sweep finds the trials those jobs finished recorded. While it runs, the job marks itself
alive in its heartbeat file (host, pid, time; every ``MARCH_OPTUNA_HEARTBEAT_S`` seconds): the
evidence a later sweep reads before it gives up a RUNNING trial. A job whose trial the study has
already given up does not run it (:func:`begin`). Public Optuna API only.
"""

from __future__ import annotations

import math
import os
import socket
import threading
import time
from pathlib import Path
from typing import Any

from march.learn import distributed

ENV_TRIAL = "MARCH_OPTUNA_TRIAL"
ENV_STORAGE = "MARCH_OPTUNA_STORAGE"
ENV_STUDY = "MARCH_OPTUNA_STUDY"
ENV_HEARTBEAT = "MARCH_OPTUNA_HEARTBEAT"
ENV_HEARTBEAT_S = "MARCH_OPTUNA_HEARTBEAT_S"

_trial: dict[str, Any] = {}
_beat: dict[str, Any] = {}


def in_trial() -> bool:
    return ENV_TRIAL in os.environ


def _key() -> tuple[str, str, str]:
    return (os.environ[ENV_STORAGE], os.environ[ENV_STUDY], os.environ[ENV_TRIAL])


def _open() -> tuple[Any, Any]:
    """This job's (``optuna.Study``, ``optuna.Trial``), opened once per trial."""
    if _trial.get("key") != _key():  # a local launcher runs every trial in one process
        import optuna
        from hydra.core.hydra_config import HydraConfig
        from hydra.utils import instantiate

        from hydra_plugins.march_optuna_sweeper.storage import open_storage, trial_by_number

        pruner_cfg = HydraConfig.get().sweeper.get("pruner") if HydraConfig.initialized() else None
        pruner = instantiate(pruner_cfg) if pruner_cfg else optuna.pruners.NopPruner()
        storage = open_storage(os.environ[ENV_STORAGE])
        study = optuna.load_study(study_name=os.environ[ENV_STUDY], storage=storage, pruner=pruner)
        trial = trial_by_number(study, storage, int(os.environ[ENV_TRIAL]))
        _trial.update(key=_key(), study=study, trial=trial)
    return _trial["study"], _trial["trial"]


def _state() -> str:
    """The trial's state in the study now (``RUNNING``, ``COMPLETE``, ``FAIL``, ...)."""
    from hydra_plugins.march_optuna_sweeper.storage import frozen_by_number

    study, _ = _open()
    return frozen_by_number(study, int(os.environ[ENV_TRIAL])).state.name


# -- the heartbeat --------------------------------------------------------------------------------


def _write_beat(path: Path) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(f"{socket.gethostname()} {os.getpid()} {time.time():.3f}\n")
    os.replace(tmp, path)


def _beat_loop(path: Path, every_s: float, stop: threading.Event) -> None:
    while not stop.wait(every_s):
        try:
            _write_beat(path)
        except OSError:  # a full or briefly unreachable file system: try again next beat
            pass


def begin() -> None:
    """At the start of a trial's job, before any simulation: mark it alive (heartbeat file, then
    a thread that renews it) and refuse, in one line, a trial the study no longer holds RUNNING
    (a later sweep gave it up: the job started after that sweep's decision)."""
    if not in_trial():
        return
    state = "RUNNING"
    if distributed.writes_files():
        path = Path(os.environ[ENV_HEARTBEAT])
        path.parent.mkdir(parents=True, exist_ok=True)
        _write_beat(path)  # first: a sweep that reads it from now on sees this job alive
        state = _state()
        if state == "RUNNING":
            stop = threading.Event()
            every = float(os.environ.get(ENV_HEARTBEAT_S, "30"))
            thread = threading.Thread(
                target=_beat_loop, args=(path, every, stop), daemon=True, name="optuna-heartbeat"
            )
            thread.start()
            _beat.update(stop=stop, thread=thread)
    state = distributed.agree(state)
    if state != "RUNNING":
        from march.errors import ConfigError

        raise ConfigError(
            f"Optuna trial {os.environ[ENV_TRIAL]} of study {os.environ[ENV_STUDY]!r} is "
            f"{state}, no longer RUNNING (a later sweep gave it up and asked its parameters "
            "again): this job does not run it"
        )


def end() -> None:
    """Stop the heartbeat (the job ends, whatever its outcome; the file stays, ageing)."""
    stop = _beat.pop("stop", None)
    if stop is not None:
        stop.set()
        _beat.pop("thread").join(timeout=5)


# -- during the run -------------------------------------------------------------------------------


def report(value: float, step: int, final: bool = False) -> None:
    """Report an evaluation's objective at ``step``; raise ``optuna.TrialPruned`` (on every rank)
    when the study's pruner stops this trial. A non-finite value is not reported (the trial
    fails when the run returns it). ``final``: the run's last evaluation, whose value is the
    trial's (:func:`finish`): never reported to the pruner, so a trial that trained to the end
    is never pruned for it."""
    if not in_trial() or final:
        return
    prune = False
    if distributed.writes_files():
        _, trial = _open()
        if math.isfinite(value):
            trial.report(float(value), int(step))
        prune = trial.should_prune()
    if distributed.agree(prune):
        import optuna

        raise optuna.TrialPruned(f"pruned at step {step} (objective {value:.6g})")


def is_pruned(err: BaseException) -> bool:
    return type(err).__name__ == "TrialPruned" and in_trial()


# -- how the trial ended (rank 0 records it; a trial already finished is left as it is) -----------


def _tell(state: str, value: float | None = None, error: str | None = None) -> None:
    if not in_trial() or not distributed.writes_files():
        return
    import optuna

    study, trial = _open()
    if _state() != "RUNNING":
        return
    if error:
        trial.set_user_attr("error", error[:300])
    number = int(os.environ[ENV_TRIAL])
    if state == "COMPLETE":
        study.tell(number, float(value))
    else:
        study.tell(number, state=getattr(optuna.trial.TrialState, state))


def finish(value: float | None) -> None:
    """The run ended with ``value`` (its final evaluation's objective): the trial's value; a
    missing or non-finite one fails the trial."""
    if value is None or not math.isfinite(float(value)):
        _tell("FAIL", error=f"non-finite objective {value!r}")
    else:
        _tell("COMPLETE", value=float(value))


def pruned() -> None:
    """The study's pruner stopped the run: the trial is PRUNED (its last step is reported)."""
    _tell("PRUNED")


def failed(err: BaseException) -> None:
    """The run failed: the trial is FAIL, its error (one line) kept as the ``error`` attribute."""
    text = str(err).strip().splitlines()
    _tell("FAIL", error=f"{type(err).__name__}: {text[0] if text else ''}")
