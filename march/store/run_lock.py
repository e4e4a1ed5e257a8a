"""One writer per run directory: ``<run>/run.lock``, held for the whole life of the process.

The lock is an exclusive ``flock`` on ``<run>/run.lock``, a file holding the holder's pid, host
and start time (JSON). ``flock`` belongs to the open file: the kernel releases it when the
holder exits however it exits (SIGKILL, OOM, a node's crash on NFS once its lease ends), so a
lock file whose holder is gone is *stale* and the next run takes it over, saying whose it was -
on the same host only: a lock file left by another host is refused (on a shared file system flock
may be node-local, so that holder may still run) unless ``MARCH_LOCK_TAKEOVER=1`` says it ended.
A second writer (a second ``resume=``, a second sweep job given the same directory) gets one
line naming the holder (:class:`RunLocked`, a :class:`ConfigError`) and writes nothing.

The lock file is opened without following a link and is never unlinked while held; a holder
that finishes removes it (the inode check in :func:`acquire` makes a racing opener retry).
In a run over N processes rank 0 alone holds it (the others write no run files).
"""

from __future__ import annotations

import atexit
import contextlib
import errno
import fcntl
import json
import os
import socket
import time
from pathlib import Path

from march.errors import ConfigError

LOCK_NAME = "run.lock"
TAKEOVER_ENV = "MARCH_LOCK_TAKEOVER"
"""Set to 1 to take over a lock left by a process on another host (this host cannot see it)."""


class RunLocked(ConfigError):
    """The run directory is held by another living process."""


class RunLock:
    """A held lock (an open file descriptor with an exclusive flock)."""

    def __init__(self, path: Path, fd: int, stale: dict | None) -> None:
        self.path, self.fd, self.stale = path, fd, stale

    def release(self) -> None:
        if self.fd < 0:
            return
        with contextlib.suppress(OSError):
            if os.fstat(self.fd).st_ino == os.lstat(self.path).st_ino:
                os.unlink(self.path)
        with contextlib.suppress(OSError):
            os.close(self.fd)
        self.fd = -1
        _HELD.pop(str(self.path.parent.resolve()), None)


_HELD: dict[str, RunLock] = {}
"""Locks this process holds, by resolved run directory (``march.train``'s ``__main__`` takes
the lock before Hydra starts; ``main`` then finds it here)."""


def holder_text(info: dict | None) -> str:
    """``pid 123 on host node7 since 2026-12-03 21:05:18`` (or what the file allowed)."""
    if not info:
        return "an unknown process (the lock file is empty or unreadable)"
    since = info.get("since")
    when = ""
    if isinstance(since, (int, float)):
        when = " since " + time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(since))
    return f"pid {info.get('pid', '?')} on host {info.get('host', '?')}{when}"


def run_summary(run_dir: Path) -> str:
    """``seed 3, stage all`` from the top level of ``<run>/config.yaml`` (read as text, bounded,
    no link followed), or what is known of it."""
    import re

    try:
        fd = os.open(Path(run_dir) / "config.yaml", os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
        with os.fdopen(fd, "rb") as f:
            text = f.read(1 << 16).decode(errors="replace")
    except OSError:
        return "its config.yaml not written yet"
    found = [
        f"{key} {m.group(1)}"
        for key in ("seed", "stage")
        if (m := re.search(rf"^{key}: *([\w.-]{{1,40}}) *$", text, re.M))
    ]
    return ", ".join(found) or "a config.yaml without seed"


def _read(fd: int) -> dict | None:
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        data = os.read(fd, 4096)
        info = json.loads(data.decode()) if data else None
    except (OSError, ValueError, UnicodeDecodeError):
        return None
    return info if isinstance(info, dict) else None


def held(run_dir: Path) -> RunLock | None:
    return _HELD.get(str(Path(run_dir).resolve()))


def acquire(run_dir: Path, option: str = "run directory") -> RunLock:
    """Take ``<run_dir>/run.lock`` (the directory must exist) or raise :class:`RunLocked`
    naming the holder; a lock this process already holds is returned as it is. ``option``:
    how messages name the directory (``resume`` -> ``resume=<dir>``)."""
    run_dir = Path(run_dir)
    what = (
        f"{option}={run_dir}" if option.isidentifier() or "." in option else f"{option} {run_dir}"
    )
    if (mine := held(run_dir)) is not None:
        return mine
    path = run_dir / LOCK_NAME
    for _ in range(20):
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
        except OSError as err:
            if err.errno == errno.ELOOP:
                raise ConfigError(
                    f"{what}: {LOCK_NAME} is a symbolic link; march writes no file "
                    "through a link (remove it)"
                ) from None
            why = os.strerror(err.errno) if err.errno else str(err)
            raise ConfigError(
                f"{what}: cannot create {path.name} ({why}); a run directory must be writable"
            ) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as err:
            info = _read(fd)
            os.close(fd)
            if err.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise ConfigError(f"{what}: cannot lock {path.name} ({err})") from None
            if option == "resume":  # the user's own run, still running: wait or stop it
                advice = "one writer at a time: wait for it to end (or stop it), then run again"
            else:  # a new run given the directory of another one (e.g. two seeds, one second)
                advice = (
                    f"it is another run's directory ({run_summary(run_dir)}), and a new run does "
                    "not share one: give this run its own hydra.run.dir (the default has the "
                    "seed and a unique part)"
                )
            raise RunLocked(
                f"{what} is in use by {holder_text(info)} ({path}); {advice}; nothing was written"
            ) from None
        try:
            same = os.fstat(fd).st_ino == os.lstat(path).st_ino
        except OSError:
            same = False
        if not same:  # its holder finished and removed it between our open and our flock
            os.close(fd)
            continue
        stale = _read(fd)
        me = {"pid": os.getpid(), "host": socket.gethostname(), "since": time.time()}
        other = stale.get("host") if stale else None
        if other is not None and other != me["host"] and os.environ.get(TAKEOVER_ENV) != "1":
            # flock may be node-local on a shared file system: a holder on another host may
            # be alive although this host got the lock. Only a person can tell; nothing written.
            os.close(fd)
            raise RunLocked(
                f"{what}: {LOCK_NAME} names {holder_text(stale)}, another host than this one "
                f"({me['host']}), and a lock on a shared file system may not reach across hosts, "
                f"so march cannot tell whether it still runs; if it has ended, take the directory "
                f"over with {TAKEOVER_ENV}=1; nothing was written"
            )
        os.ftruncate(fd, 0)
        os.lseek(fd, 0, os.SEEK_SET)
        os.write(fd, json.dumps(me).encode())
        os.fsync(fd)
        lock = RunLock(path, fd, stale)
        if not _HELD:
            atexit.register(release_all)  # a run that ends any other way leaves no lock file
        _HELD[str(run_dir.resolve())] = lock
        return lock
    raise RunLocked(f"{what}: {path.name} keeps changing hands; run again")


def stale_note(lock: RunLock) -> str | None:
    """One line when the lock was taken over from a holder that is gone, else None."""
    if not lock.stale:
        return None
    return (
        f"[lock] {lock.path}: took over a stale lock of {holder_text(lock.stale)} "
        "(that process is gone)"
    )


def release_all() -> None:
    for lock in list(_HELD.values()):
        lock.release()
