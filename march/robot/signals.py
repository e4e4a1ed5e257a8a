"""SIGINT / SIGTERM as a flag a robot loop polls: the loop ends its own way (damping first for the
policy loop), never inside a handler."""

from __future__ import annotations

import signal
from typing import Any

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def stop_on_signals() -> tuple[dict[str, bool], dict[Any, Any]]:
    """``(stop, previous)``: ``stop["flag"]`` turns True on SIGINT or SIGTERM; ``previous``
    holds the handlers replaced, for a caller that puts them back."""
    stop = {"flag": False}

    def on_signal(signum, frame):  # noqa: ARG001
        stop["flag"] = True

    previous = {s: signal.signal(s, on_signal) for s in STOP_SIGNALS}
    return stop, previous
