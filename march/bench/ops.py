"""Compute ops per env step: what a GPU would launch as kernels, counted on any device.

:class:`OpCounter` is a ``TorchDispatchMode``: it sees every aten op a torch call decomposes
into, after autograd (the bench steps under ``inference_mode``, as the teacher's rollouts do),
and counts the ones that compute. Left out: view-only ops (``OpOverload.is_view``: ``view``,
``slice``, ``select``, ``expand``, ``unsqueeze``, ``t``... they change metadata, launch
nothing) and pure metadata queries (``aten.sym_*``, ``is_nonzero``-free shape lookups do not
reach the dispatcher). Everything else counts one, so a GPU's eager step launches about this
many kernels (a few CPU-only ops such as ``_local_scalar_dense``, which is a device-to-host copy
there, count too). mujoco-warp's physics is warp kernels, not torch ops, and is not counted
(mjlab captures it in CUDA graphs on a GPU).

:func:`count_ops` runs ``steps`` steps of one workload per env (after a reset and the workload's
warm-up) under the counter and returns ops per step and the top ops by count.
"""

from __future__ import annotations

from collections import Counter
from typing import Any

from torch.utils._python_dispatch import TorchDispatchMode

from march.bench.harness import Actions


def is_compute(func: Any) -> bool:
    """True for an aten op that launches work (not a view, not a metadata query)."""
    if getattr(func, "is_view", False):
        return False
    name = getattr(func, "__name__", "")
    return not name.startswith(("sym_", "_sym_"))


class OpCounter(TorchDispatchMode):
    """Counts compute ops by aten name (module docstring)."""

    def __init__(self) -> None:
        super().__init__()
        self.counts: Counter[str] = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if is_compute(func):
            self.counts[str(func.overloadpacket.__name__)] += 1
        return func(*args, **(kwargs or {}))

    def count_fused(self, compiled: Any, args: tuple, kwargs: dict) -> Any:
        """Run a ``march.compiled_math.fused`` call outside this mode (under it the call would run
        eagerly) and count what it launches, read from the profiler: every generated kernel
        (inductor's ``cpp_fused_*`` / ``triton_*``) and every top-level aten op the compiled
        code calls (extern kernels, and any op left outside the graph)."""
        from torch.profiler import ProfilerActivity, profile
        from torch.utils._python_dispatch import _disable_current_modes

        with _disable_current_modes(), profile(activities=[ProfilerActivity.CPU]) as prof:
            out = compiled(*args, **kwargs)
        for event in prof.events():
            name = event.name
            if "cpp_fused" in name or name.startswith("triton_"):
                self.counts["fused_kernel"] += 1
            elif name.startswith("aten::"):
                parent = event.cpu_parent
                if parent is None or not parent.name.startswith("aten::"):
                    self.counts[name[len("aten::") :]] += 1
        return out

    @property
    def total(self) -> int:
        return sum(self.counts.values())


def count_ops(env: Any, workload: str, steps: int, warmup: int, seed: int) -> dict[str, Any]:
    """Compute ops per control step of ``env`` over ``steps`` steps of ``workload`` (the action
    draw itself is left out: it is the harness's, not the env's)."""
    import torch

    acts = Actions(env, workload, seed)
    counter = OpCounter()
    with torch.inference_mode():
        env.reset()
        for _ in range(warmup):
            env.step(acts())
        for _ in range(steps):
            a = acts()
            with counter:
                env.step(a)
    return {
        "ops_per_step": counter.total / steps,
        "top_ops": {k: round(v / steps, 1) for k, v in counter.counts.most_common(12)},
    }
