"""``torch.compile`` for the pure-math parts of a step (``compute.compile_math``).

On a GPU every eager torch op of a step is one kernel launch; the footstep planner's search, the
step reference, the measured CLF outputs and the height scan are fixed-size, sync-free tensor
maths, so inductor fuses each into a handful of kernels. :func:`fused` compiles a function once per process (dynamic
batch size) and keeps the launch count measurable: under an op counter that defines
``count_fused`` (``march.bench.ops.OpCounter``), the compiled call is handed to the counter,
which counts the kernels it launches (a ``TorchDispatchMode`` alone would make it run eagerly).
Results equal the eager path's within float32 rounding (tests/test_fusion.py).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch.utils._python_dispatch import _get_current_dispatch_mode

_COMPILED: dict[Callable, Callable] = {}

INDUCTOR_OPTIONS = {"cpp.enable_kernel_profile": True}
"""Each generated CPU kernel records a profiler event, so its launches can be counted (one
``RECORD_FUNCTION`` per kernel call: negligible against the kernel)."""


def fused(fn: Callable) -> Callable:
    """``fn`` under ``torch.compile(dynamic=True)``, made once per process and function.

    Python floats (config values) stay constants of the graph (``specialize_float``): left
    dynamic, each would be wrapped in a tensor on every call, three host-built ops apiece."""
    if fn not in _COMPILED:
        compiled = torch.compile(fn, dynamic=True, options=INDUCTOR_OPTIONS)

        def call(*args: Any, **kwargs: Any) -> Any:
            count = getattr(_get_current_dispatch_mode(), "count_fused", None)
            with torch._dynamo.config.patch(specialize_float=True):
                if count is not None:
                    return count(compiled, args, kwargs)
                return compiled(*args, **kwargs)

        call.__wrapped__ = fn  # type: ignore[attr-defined]
        _COMPILED[fn] = call
    return _COMPILED[fn]


def maybe_fused(fn: Callable, compile_math: bool) -> Callable:
    """:func:`fused` ``fn`` when ``compile_math`` is set, else ``fn`` itself."""
    return fused(fn) if compile_math else fn
