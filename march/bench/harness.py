"""What every ``march.bench`` job drives an env with: the workloads' actions, interleaved rounds,
device synchronisation and freeing, and stdout sent to stderr (so that the jobs' stdout is their
JSON object alone).
"""

from __future__ import annotations

import contextlib
import gc
import os
import sys
from collections.abc import Iterator
from typing import Any

WORKLOADS = ("random", "standing")
"""``random``: seeded uniform actions in [-1, 1]; ``standing``: zero actions (default pose)."""


@contextlib.contextmanager
def stdout_to_stderr() -> Iterator[None]:
    """Send everything written to stdout (Python and C level: warp, mujoco) to stderr."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        os.dup2(2, 1)
        with contextlib.redirect_stdout(sys.stderr):
            yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def sync(device: str) -> None:
    import torch

    if device.startswith("cuda"):
        torch.cuda.synchronize()


def free(device: str) -> None:
    import torch

    gc.collect()
    if device.startswith("cuda"):
        torch.cuda.empty_cache()


class Actions:
    """The actions of one workload for one env: ``random`` (seeded uniform in [-1, 1], its own
    generator) or ``standing`` (zeros: the default pose as position target)."""

    def __init__(self, env: Any, workload: str, seed: int) -> None:
        import torch

        if workload not in WORKLOADS:
            raise ValueError(f"workload {workload!r}: use one of {WORKLOADS}")
        self.device = str(env.device)
        self.shape = (env.num_envs, env.action_manager.total_action_dim)
        self.random = workload == "random"
        self.gen = torch.Generator(device=self.device).manual_seed(seed)
        self.zeros = torch.zeros(self.shape, device=self.device)

    def __call__(self) -> Any:
        import torch

        if self.random:
            return 2.0 * torch.rand(self.shape, generator=self.gen, device=self.device) - 1.0
        return self.zeros


def chunks(steps: int, rounds: int) -> list[int]:
    """``steps`` split into ``rounds`` near-equal chunks."""
    return [steps // rounds + (1 if r < steps % rounds else 0) for r in range(rounds)]
