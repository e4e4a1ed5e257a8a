"""Fixed tensors a step would otherwise rebuild on every call (rollout 0's ring and the
candidate pick table of the footstep planner, the Bezier binomials of the reference), made once
per key (their configuration, dtype and device) and kept. Plain torch.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable
from typing import Any, TypeVar

import torch

T = TypeVar("T")

STORE: dict[Hashable, Any] = {}
"""The kept values by key."""


def kept(key: Hashable, make: Callable[[], T]) -> T:
    """``make()`` the first time ``key`` is asked for, the kept value afterwards.

    Under ``torch.compile`` the store is not touched at all and ``make()`` runs inside the graph:
    a traced tensor must not outlive its graph, and a graph that read the store was guarded on
    its keys, so it compiled again as soon as an eager call added one (``reference_at`` compiled
    twice). ``make`` therefore builds from device ops only (no tensor from Python data, which
    could mean a host-to-device copy per call)."""
    if torch.compiler.is_compiling():
        return make()
    if key not in STORE:
        STORE[key] = make()
    return STORE[key]
