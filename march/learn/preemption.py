"""Preemption: SIGTERM (Slurm's preemption, ``scancel``, torchrun's agent) and SIGUSR2 (Slurm's
``--signal=USR2@<s>`` before a time limit) end a run at its next complete iteration, with
that iteration checkpointed, status ``preempted`` and a non-zero exit (128 + the signal, as a
shell reports a signal's death), so a requeue (or ``resume=<run>``) continues from there.

One handler for every runner and launcher:

- :func:`install` (``march.train``) records the signal and returns at once; nothing is cut
  mid-step or mid-write.
- The training loop (:class:`march.learn.stage_runner.StageRunner`, both stages) calls
  :func:`stop_if_requested` at the end of every iteration, after that iteration's checkpoint
  would be written: if a signal came, it writes the checkpoint when the iteration was not a
  save point and raises :class:`Preempted`. In a run over N ranks the decision is rank 0's
  (one broadcast per iteration) so that every rank joins the same save.
- :func:`exit_preempted` (``march.train``) writes ``status.json`` = ``preempted`` (stage,
  iteration, checkpoint, signal), prints one line, hands the signal to the handler that was
  there before (submitit's requeue on USR2), then exits with 128 + the signal; in a run over N
  ranks, ranks > 0 exit only once rank 0's handler has asked for the requeue.

A second signal stops at once (:class:`Preempted` raised from the handler): the run directory
keeps its last complete checkpoint (checkpoints are written atomically), and the status still
says ``preempted``. With ``install(immediate=True)`` (``stage=eval``: no iterations to finish)
the first signal does the same.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

SIGNALS = (signal.SIGTERM, signal.SIGUSR2)

_state: dict[str, Any] = {"signum": None, "previous": {}, "immediate": False, "where": None}


class Preempted(BaseException):
    """The run stops for a signal. A BaseException: no ``except Exception`` on the way up may
    take it for a failure of the run."""

    def __init__(
        self, signum: int, stage: str | None, iteration: int | None, checkpoint: Path | None
    ) -> None:
        self.signum, self.stage, self.iteration, self.checkpoint = (
            signum,
            stage,
            iteration,
            checkpoint,
        )
        super().__init__(self.line())

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name

    @property
    def exit_code(self) -> int:
        return 128 + self.signum

    def line(self) -> str:
        if self.iteration is None:
            done = "stopped at once; the last complete checkpoint stays"
        else:
            saved = f" ({self.checkpoint})" if self.checkpoint else ""
            done = f"{self.stage} iteration {self.iteration} checkpointed{saved}"
        return f"[preempted] {self.name}: {done}; status preempted, resume=<run dir> continues"


def _handler(signum: int, frame: Any) -> None:
    if _state["signum"] is not None or _state["immediate"]:
        _state["signum"] = signum
        stage = (_state["where"] or (None, None))[0]
        raise Preempted(signum, stage, None, None)
    _state["signum"] = signum
    print(
        f"[preempted] {signal.Signals(signum).name} received: stopping after the current "
        "iteration, once it is checkpointed (a second signal stops at once)",
        flush=True,
    )


def install(immediate: bool = False) -> bool:
    """Handle SIGTERM and SIGUSR2 from now on (the main thread only; False elsewhere)."""
    if threading.current_thread() is not threading.main_thread():
        return False
    _state["immediate"] = immediate
    for sig in SIGNALS:
        previous = signal.signal(sig, _handler)
        if previous is not _handler:
            _state["previous"][sig] = previous
    return True


def uninstall() -> None:
    """Put back the handlers :func:`install` replaced, and forget any signal received."""
    if threading.current_thread() is threading.main_thread():
        for sig, previous in _state["previous"].items():
            signal.signal(sig, previous if previous is not None else signal.SIG_DFL)
    _state.update(signum=None, previous={}, immediate=False, where=None)


def requested() -> int | None:
    """The signal received (rank 0's, on every rank of a run over N processes), or None."""
    from march.learn import distributed

    signum = _state["signum"]
    return distributed.agree(signum) if distributed.current().active else signum


def stop_if_requested(
    stage: str, iteration: int, save: Callable[[], Path] | None, path: Path | None = None
) -> None:
    """At the end of an iteration: raise :class:`Preempted` if a signal came. ``save``: writes
    this iteration's checkpoint (None when the iteration was just saved, at ``path``)."""
    _state["where"] = (stage, iteration)
    signum = requested()
    if signum is None:
        return
    if save is not None:
        path = save()
    raise Preempted(signum, stage, iteration, path)


def exit_preempted(stop: Preempted, write_status: Callable[..., None]) -> None:
    """Status ``preempted``, one line, the previous handler (submitit requeues on USR2), then
    ``SystemExit(128 + signal)``.

    In a run over N ranks rank 0 is the job's master: submitit's handler requeues the job there
    and does nothing on the other ranks ("do not sys.exit, because it might kill the master
    task"). With ``--kill-on-bad-exit`` a rank > 0 that exits non-zero ends the whole step, so
    ranks > 0 wait (:func:`_after_master`) until rank 0's handler has returned or raised, i.e.
    until the requeue has been asked for, before they exit."""
    from march.learn import distributed

    write_status(
        "preempted",
        stage=stop.stage,
        iteration=stop.iteration,
        checkpoint=str(stop.checkpoint) if stop.checkpoint else None,
        signal=stop.name,
    )
    print(stop.line(), flush=True)
    previous = _state["previous"].get(stop.signum)
    uninstall()
    raised: BaseException | None = None
    try:
        if callable(previous):
            previous(stop.signum, None)
    except BaseException as err:  # submitit's requeue ends in sys.exit(-1)
        raised = err
    _after_master(distributed.current())
    if raised is not None and not isinstance(raised, SystemExit):
        raise raised  # submitit's "not requeued" error: it records the job as over
    raise SystemExit(stop.exit_code)


def _after_master(dist: Any) -> None:
    """Every rank of a run over N processes meets here once rank 0's previous handler is done (a
    barrier). A rank already gone (the scheduler's kill) leaves nothing to wait for."""
    if not dist.active:
        return
    from march.learn import distributed

    try:
        distributed.barrier()
    except Exception as err:  # noqa: BLE001 - a peer already gone: nothing left to protect
        print(f"[preempted] rank {dist.rank}: not waiting for rank 0 ({err})", flush=True)
