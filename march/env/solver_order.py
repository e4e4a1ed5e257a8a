"""The contact solver's summation order made independent of the batch size, for evaluation.

mujoco_warp's Newton solver builds each world's Hessian H = M + J^T D J by adding one block per
constraint group with ``atomic_add`` (``solver._JTDAJ_sparse`` and its incremental update, the
sparse path the G1 takes since nv = 35 > 32). The groups of a world are dealt to
``solver._jtdaj_groups_per_world(nworld, njmax)`` slots that grid-stride over them; that count is
``min(njmax, 6 x device warps // nworld)``: 6 / 3 / 1 / 1 slots for 1 / 2 / 4 / 8 worlds on the
CPU. The slot count decides the order in which the blocks reach a shared entry of H, so the same
world gives different last bits in batches of different sizes, and an evaluation split into
waves of another size (``compute.eval_num_envs``, N ranks) drifts apart (issue 57).

:func:`pinned` holds the slot count at :data:`SLOTS` while it is open: every world's groups are
summed in the order of the group list, whatever ``nworld`` is. On the CPU (threads run one after
another) that makes H, and so the step, the same bits in any batch; on a GPU one warp per world
walks its groups in order, so the atomic adds into one world's H come from one warp in a fixed
order (run-to-run deterministic too) instead of up to 6 x device warps / nworld warps racing. The
price is that parallelism: the GPU's warps per world drop from that count to one in this one
kernel (priced in docs/scaling.md; the CPU cost is none measurable).

It is opened where evaluation envs are built (``march.env.build.make_env``, purpose ``eval``: CUDA
graphs capture the launch's grid when the simulation is built) and around their rollouts
(``march.evaluation.protocol.rollout_metrics``: on the CPU the count is read at every solver
iteration). A training env beside it keeps mujoco_warp's own count: the patch reads a counter that
only :func:`pinned` raises.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterator
from contextlib import contextmanager

SLOTS: int | None = 1
"""Slots per world while pinned: 1, the one count that fixes the order on a GPU as well (None:
mujoco_warp's own count even while pinned, for probes that show the difference)."""
_SOLVER = "mujoco_warp._src.solver"
_NAME = "_jtdaj_groups_per_world"
_depth = 0  # how many pinned() blocks are open
_original: Callable[[int, int], int] | None = None


def _groups_per_world(nworld: int, njmax: int) -> int:
    """mujoco_warp's function, or :data:`SLOTS` (at most ``njmax``) while pinned."""
    if _depth > 0 and SLOTS is not None:
        return max(1, min(njmax, SLOTS))
    assert _original is not None
    return _original(nworld, njmax)


def install() -> None:
    """Put :func:`_groups_per_world` in mujoco_warp's solver module (once; idempotent). The
    solver calls the function by its module-global name at each launch, so replacing the module
    attribute reaches every launch site. Raises if mujoco_warp no longer has the function (its
    internals moved: the pin would silently do nothing)."""
    global _original
    solver = importlib.import_module(_SOLVER)
    current = getattr(solver, _NAME, None)
    if current is None:
        raise RuntimeError(f"{_SOLVER}.{_NAME} not found: the solver-order pin needs updating")
    if current is _groups_per_world:
        return
    _original = current
    setattr(solver, _NAME, _groups_per_world)


def groups_per_world(nworld: int, njmax: int) -> int:
    """What the solver uses now for ``nworld`` worlds (for probes and tests)."""
    install()
    return getattr(importlib.import_module(_SOLVER), _NAME)(nworld, njmax)


@contextmanager
def pinned(active: bool = True) -> Iterator[None]:
    """While open (and ``active``), every launch sums each world's constraint groups in one
    fixed order, whatever the batch size."""
    global _depth
    if not active:
        yield
        return
    install()
    _depth += 1
    try:
        yield
    finally:
        _depth -= 1
