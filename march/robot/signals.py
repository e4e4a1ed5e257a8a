"""Stop signals as a flag a robot process polls: the process ends its own way (damping first for
the policy loop and the supervisor), never inside a handler.

SIGINT (Ctrl-C), SIGTERM (``kill``, systemd's stop) and SIGHUP (the terminal closed, an SSH
session dropped) all set it: Python's default for SIGHUP is to die at once, which left the robot
on its last policy command (issue 58). ``stop["signal"]`` names the first signal, so that the
loop can tell an operator's Ctrl-C (an orderly stop) from a terminal that went away (a fault).
"""

from __future__ import annotations

import signal
from typing import Any

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
ORDERLY_SIGNALS = ("SIGINT", "SIGTERM")
"""Signals an operator sends on purpose; SIGHUP is a lost terminal, never a request."""


def stop_on_signals() -> tuple[dict[str, Any], dict[Any, Any]]:
    """``(stop, previous)``: ``stop["flag"]`` turns True on SIGINT, SIGTERM or SIGHUP and
    ``stop["signal"]`` holds the first one's name; ``previous`` holds the handlers replaced,
    for a caller that puts them back."""
    stop: dict[str, Any] = {"flag": False, "signal": ""}

    def on_signal(signum, frame):  # noqa: ARG001
        stop["flag"] = True
        stop["signal"] = stop["signal"] or signal.Signals(signum).name

    previous = {s: signal.signal(s, on_signal) for s in STOP_SIGNALS}
    return stop, previous


def say(line: str, err: bool = False) -> None:
    """Print one line, and never fail: after SIGHUP the terminal is gone and a write to it raises
    (EIO, or BrokenPipeError on a closed pipe), which must not end a loop that still has to damp."""
    import sys

    try:
        print(line, file=sys.stderr if err else sys.stdout, flush=True)
    except (OSError, ValueError):
        pass
