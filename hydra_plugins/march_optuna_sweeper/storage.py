"""Where a study lives and who may drive it: the storage, trials by number, the driver's lock,
a trial job's heartbeat. Public Optuna API only (a storage object's own methods, ``Study`` and
``Trial``), so the sweeper and the trial jobs work on any Optuna >= 4 storage.

Evidence a sweep decides by, before it touches a RUNNING trial:

- **the driver lock** ``<journal>.driver.lock`` (``<sweep dir>/<study>.driver.lock`` for a
  database URL): an exclusive ``flock`` the sweep holds for its whole life. The kernel drops it
  when the process ends, however it ends, so a lock that cannot be taken means a live sweep
  drives the study: a second one refuses in one line instead of failing its trials.
- **a trial's heartbeat** ``<sweep dir>/<trial>/.optuna_heartbeat`` (host, pid, time), renewed
  by the trial's job (:mod:`march.learn.tuning`). Optuna's own heartbeat (``RDBStorage`` with
  ``heartbeat_interval``) is recorded by the process that runs ``study.optimize``, which is
  neither the driver nor a Hydra job here, and ``JournalStorage`` (Optuna 5.1) has none; a file
  the job renews works for every storage and every launcher.
"""

from __future__ import annotations

import fcntl
import os
import socket
import time
from pathlib import Path
from typing import Any, TextIO

import optuna


def open_storage(storage: str) -> Any:
    """An Optuna storage object from a journal file path or an RDB URL."""
    if "://" in storage:
        return optuna.storages.get_storage(storage)
    from optuna.storages import JournalStorage
    from optuna.storages.journal import JournalFileBackend

    Path(storage).parent.mkdir(parents=True, exist_ok=True)
    return JournalStorage(JournalFileBackend(str(storage)))


def frozen_by_number(study: optuna.Study, number: int) -> optuna.trial.FrozenTrial:
    """Trial ``number`` of ``study`` as the storage holds it now."""
    for t in study.get_trials(deepcopy=False):
        if t.number == number:
            return t
    raise KeyError(f"study {study.study_name!r} has no trial {number}")


def trial_by_number(study: optuna.Study, storage: Any, number: int) -> optuna.trial.Trial:
    """A live ``optuna.Trial`` for trial ``number`` (to report to, prune, set attributes), from
    the storage's own public look-ups (study name -> id, trial number -> id)."""
    study_id = storage.get_study_id_from_name(study.study_name)
    trial_id = storage.get_trial_id_from_study_id_trial_number(study_id, number)
    return optuna.trial.Trial(study, trial_id)


# -- the driver lock --------------------------------------------------------------------------------


class StudyDriven(RuntimeError):
    """Another live sweep drives the study."""


def lock_path(where: str, sweep_dir: Path, study_name: str) -> Path:
    if "://" in where:
        return sweep_dir / f"{study_name}.driver.lock"
    return Path(f"{where}.driver.lock")


def take_driver_lock(path: Path) -> TextIO:
    """Hold ``path``'s exclusive lock for the life of this process (the returned file must stay
    open); :class:`StudyDriven` naming the holder when a live sweep holds it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    f = path.open("a+")
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        f.seek(0)
        holder = f.read().strip() or "unknown"
        f.close()
        raise StudyDriven(holder) from None
    f.seek(0)
    f.truncate()
    f.write(f"pid {os.getpid()} on {socket.gethostname()} since {time.strftime('%F %T')}\n")
    f.flush()
    return f


# -- a trial job's heartbeat ------------------------------------------------------------------------


def heartbeat_path(sweep_dir: Path, number: int) -> Path:
    return sweep_dir / str(number) / ".optuna_heartbeat"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process: alive
        return True
    return True


def job_alive(path: Path, stale_s: float, now: float | None = None) -> tuple[bool, str]:
    """(whether the job of a RUNNING trial is alive, the evidence in words). Alive: its heartbeat
    file was renewed within ``stale_s`` seconds and, when it ran on this host, its process still
    exists. A job that never wrote the file has not started (a queued Slurm job, or a sweep
    killed before the launch); when it starts it finds its trial given up and does not run it."""
    if not path.is_file():
        return False, "its job never started"
    try:
        host, pid, _ = path.read_text().split()
        age = (time.time() if now is None else now) - path.stat().st_mtime
    except (OSError, ValueError):
        return False, "its heartbeat file is unreadable"
    if host == socket.gethostname() and not _pid_alive(int(pid)):
        return False, f"its job (pid {pid} on {host}) is gone"
    if age > stale_s:
        return False, f"its job (pid {pid} on {host}) has not marked itself alive for {age:.0f} s"
    return True, f"its job (pid {pid} on {host}) marked itself alive {age:.0f} s ago"
