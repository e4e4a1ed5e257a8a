"""``torch.compile`` for the pure-math parts of a step (``compute.compile_math``).

On a GPU every eager torch op of a step is one kernel launch; the footstep planner's search, the
step reference, the measured CLF outputs and the height scan are fixed-size, sync-free tensor
maths, so inductor fuses each into a handful of kernels. :func:`fused` compiles a function once per process (dynamic
batch size) and keeps the launch count measurable: under an op counter that defines
``count_fused`` (``march.bench.ops.OpCounter``), the compiled call is handed to the counter,
which counts the kernels it launches (a ``TorchDispatchMode`` alone would make it run eagerly).
Results equal the eager path's within float32 rounding (tests/test_compiled_math.py).

``compute.compile_mode`` picks torch.compile's mode for every compiled function of the process
(:func:`set_compile_mode`, called once by the env bridge, ``march.env.build.make_env``):
``default``, or ``reduce-overhead``, where inductor also captures each compiled graph in a CUDA
graph per input shape and replays it with one launch (on a GPU only; on CPU torch skips the
capture and the code is the default mode's). A CUDA graph writes its outputs into the same
memory on every replay, so in that mode every output is cloned before it is returned and each
call starts a new cudagraph step (``torch.compiler.cudagraph_mark_step_begin``): no caller holds
memory the next replay overwrites. Replays need static shapes: the planner's batch takes a few
fixed sizes (``march.env.replan_queue``), each captured once.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import Any

import torch
import torch._dynamo.config as dynamo_config
from torch._dynamo.utils import counters
from torch.utils._python_dispatch import _get_current_dispatch_mode

_COMPILED: dict[tuple[Callable, str], Callable] = {}

COMPILE_MODES = ("default", "reduce-overhead")
"""torch.compile modes ``compute.compile_mode`` may name."""
_mode = "default"


def set_compile_mode(mode: str) -> None:
    """The torch.compile mode of the functions :func:`fused` compiles from now on (module
    docstring); one per process in practice (a function compiled in each mode keeps both)."""
    global _mode
    if mode not in COMPILE_MODES:
        raise ValueError(f"compile mode {mode!r}: choose one of {', '.join(COMPILE_MODES)}")
    _mode = mode


def compile_mode() -> str:
    """The mode :func:`fused` compiles with now."""
    return _mode


COMPILES: dict[str, list[float]] = {}
"""Wall seconds of every call that compiled a graph, by compiled function name (its first call,
and any recompile): what ``compute.compile_math`` costs a process. ``python -m march.bench env``
reports them (:func:`compile_report`)."""

INDUCTOR_OPTIONS = {"cpp.enable_kernel_profile": True}
"""Each generated CPU kernel records a profiler event, so its launches can be counted (one
``RECORD_FUNCTION`` per kernel call: negligible against the kernel)."""


def fused(fn: Callable) -> Callable:
    """``fn`` under ``torch.compile(dynamic=True)``, made once per process and function.

    Python floats (config values) stay constants of the graph (``specialize_float``): left
    dynamic, each would be wrapped in a tensor on every call, three host-built ops apiece.

    One graph per function: dynamo guards the grad mode and each input's dispatch keys, which
    differ between the env's construction (grad on), the teacher's rollouts (``inference_mode``,
    inference tensors) and evaluation or distillation (``no_grad``, normal tensors, and the
    teacher env's inference tensors read outside inference mode), so a smoke training run
    compiled 11 graphs for 4 functions (``TORCH_LOGS=recompiles``; on the gpu preset minutes
    each, some in the middle of the run). The compiled code therefore always runs under
    ``inference_mode`` on inference tensors: every normal input tensor is copied into one
    (:func:`_inference_tensors`), so the same run compiles 4 graphs. A caller outside inference
    mode gets the outputs cloned into normal tensors (an inference tensor may not be updated in
    place there): one copy per output tensor, on those paths only."""
    mode = _mode
    if (fn, mode) not in _COMPILED:
        if mode == "default":
            compiled = torch.compile(fn, dynamic=True, options=INDUCTOR_OPTIONS)
        else:  # torch.compile takes mode or options, not both; the kernel profile is CPU-only
            compiled = torch.compile(fn, dynamic=True, mode=mode)
        graph_outputs = mode == "reduce-overhead"

        def run(*args: Any, **kwargs: Any) -> Any:
            count = getattr(_get_current_dispatch_mode(), "count_fused", None)
            # Set and restored by hand: ``config.patch`` costs ~15 us a call (4 us this way),
            # and the setting only matters when a call compiles.
            before, dynamo_config.specialize_float = dynamo_config.specialize_float, True
            try:
                if count is not None:
                    return count(compiled, args, kwargs)
                return compiled(*args, **kwargs)
            finally:
                dynamo_config.specialize_float = before

        def call(*args: Any, **kwargs: Any) -> Any:
            graphs, t0 = counters["stats"]["unique_graphs"], time.perf_counter()
            if graph_outputs:  # the previous replay's outputs were cloned: nobody holds them
                torch.compiler.cudagraph_mark_step_begin()
            if torch.is_inference_mode_enabled():  # (entering it again costs host time)
                out = run(*_inference_tensors(args), **_inference_tensors(kwargs))
                if graph_outputs:
                    out = map_tensors(out, torch.clone)
            else:
                with torch.inference_mode():
                    out = run(*_inference_tensors(args), **_inference_tensors(kwargs))
                out = _normal_tensors(out)  # a clone of every output: also graph-safe
            if counters["stats"]["unique_graphs"] != graphs:  # this call compiled (host clock)
                COMPILES.setdefault(fn.__name__, []).append(time.perf_counter() - t0)
            return out

        call.__wrapped__ = fn  # type: ignore[attr-defined]
        call.compile_mode = mode  # type: ignore[attr-defined]
        _COMPILED[fn, mode] = call
    return _COMPILED[fn, mode]


_LEAVES = (bool, int, float, str, type(None), torch.dtype, torch.device)
"""Values :func:`map_tensors` returns as they are without looking inside (config fields)."""

_INIT_FIELDS: dict[type, tuple[str, ...]] = {}
"""The ``__init__`` fields of each dataclass type :func:`map_tensors` has walked."""


def map_tensors(obj: Any, fn: Callable[[torch.Tensor], torch.Tensor]) -> Any:
    """``obj`` (tensors inside tuples, named tuples, lists, dicts and dataclasses, at any depth)
    with ``fn`` applied to every tensor. A container none of whose tensors ``fn`` replaced is
    returned as the same object: a config is not rebuilt on every call (a compiled call's
    inputs pass through here: host time on every step)."""
    if isinstance(obj, torch.Tensor):
        return fn(obj)
    if isinstance(obj, _LEAVES):
        return obj
    if isinstance(obj, (tuple, list)):
        items = [map_tensors(x, fn) for x in obj]
        if all(a is b for a, b in zip(items, obj, strict=True)):
            return obj
        if isinstance(obj, list):
            return items
        return type(obj)(*items) if hasattr(obj, "_fields") else tuple(items)
    if isinstance(obj, dict):
        values = {k: map_tensors(v, fn) for k, v in obj.items()}
        return obj if all(values[k] is v for k, v in obj.items()) else values
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        names = _INIT_FIELDS.get(type(obj))
        if names is None:
            names = tuple(f.name for f in dataclasses.fields(obj) if f.init)
            _INIT_FIELDS[type(obj)] = names
        changes = {}
        for name in names:
            value = getattr(obj, name)
            if not isinstance(value, _LEAVES) and (mapped := map_tensors(value, fn)) is not value:
                changes[name] = mapped
        return dataclasses.replace(obj, **changes) if changes else obj
    return obj


def _inference_tensors(args: Any) -> Any:
    """``args`` with every normal tensor in it copied into an inference tensor (called inside
    ``inference_mode``; sizes and strides kept: :func:`_copy_strided`). Dynamo guards each
    input's dispatch keys, so compiled code called with normal tensors (env construction,
    evaluation, distillation) and with inference tensors (teacher rollouts) made two graphs per
    function, the second compiled mid-run. The compiled functions never write into their inputs
    (checked over a 40-step env rollout, and by a test), so a copy reads the same. A rollout
    passes few normal tensors (buffers made at construction)."""
    return map_tensors(args, lambda t: t if t.is_inference() else _copy_strided(t))


def _copy_strided(t: torch.Tensor) -> torch.Tensor:
    """A copy of ``t`` with its sizes and strides (dynamo guards relations between them: a
    contiguous copy of a sliced view would compile a graph of its own); a plain clone where
    elements share memory (an expanded view: a tensor like that cannot be written into)."""
    if torch._debug_has_internal_overlap(t) == 1:  # 1: elements overlap (0: no, 2: unknown)
        return t.clone()
    return torch.empty_strided(t.shape, t.stride(), dtype=t.dtype, device=t.device).copy_(t)


def _normal_tensors(out: Any) -> Any:
    """``out`` with every inference tensor in it cloned outside inference mode, which makes it
    a normal tensor."""
    return map_tensors(out, lambda t: t.clone() if t.is_inference() else t)


def maybe_fused(fn: Callable, compile_math: bool) -> Callable:
    """:func:`fused` ``fn`` when ``compile_math`` is set, else ``fn`` itself."""
    return fused(fn) if compile_math else fn


def compile_report() -> dict[str, Any]:
    """What this process compiled so far: graphs and wall seconds per compiled function, their
    totals, and ``recompiles`` (graphs beyond one per function: each a stall of the run, and
    torch falls back to eager after ``torch._dynamo.config.recompile_limit`` of them)."""
    graphs = {name: len(times) for name, times in COMPILES.items()}
    return {
        "graphs": graphs,
        "seconds": {name: round(sum(times), 2) for name, times in COMPILES.items()},
        "total_s": round(sum(sum(times) for times in COMPILES.values()), 2),
        "recompiles": sum(graphs.values()) - len(graphs),
    }
