"""The speed targets a march step is held to, judged on the bench's own figures.

``python -m march.bench env`` ends with one line per target and writes them under ``targets``
in its JSON (and in ``bench.partial``); ``scripts/gpu_check.py`` adds the sync targets from its
``syncs`` phase (no march line that syncs in more than one env step: a read once per iteration
is allowed; march's env no more syncs per step than bare rough's), so that a GPU's first run
says which targets hold without reading figures.
The targets come from the issue that made the step GPU-ready (docs/decisions.md, issue 20):

- ``ratio_ops_march_vs_rough`` <= 1.5: compute ops (a GPU's kernel launches) per env step,
  march / bare mjlab rough, the worse workload;
- ``ratio_nonphysics_march_vs_rough`` <= 1.5: everything but physics (ms per env step), march /
  bare rough, the worse workload and thread count;
- ``min_ratio_march_vs_rough`` >= 1.0: env steps per second, march / bare rough, the slowest
  workload and thread count.

A figure the run did not measure (``bench.op_steps=0``, ``bench.profile_steps=0``) is judged
``None``: not measured, which is neither met nor missed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Target:
    """One bound on one figure of the bench's headline."""

    key: str
    """The headline key judged (a ratio, march over bare rough)."""
    bound: float
    """The limit the figure must not pass."""
    at_most: bool
    """True: the figure must be <= ``bound``; False: >= ``bound``."""
    what: str
    """What the figure measures, for the printed line."""

    def judge(self, value: float | None) -> dict[str, Any]:
        """``{"value", "at_most" | "at_least", "met"}``; ``met`` None where ``value`` is."""
        met = (
            None
            if value is None
            else (value <= self.bound if self.at_most else value >= self.bound)
        )
        side = "at_most" if self.at_most else "at_least"
        return {"value": value, side: self.bound, "met": met}


STEP_TARGETS = (
    Target("ratio_ops_march_vs_rough", 1.5, True, "compute ops per env step, march / rough"),
    Target("ratio_nonphysics_march_vs_rough", 1.5, True, "non-physics ms per step, march / rough"),
    Target("min_ratio_march_vs_rough", 1.0, False, "env steps per s, march / rough (slowest)"),
)
"""The bench's targets, in the order they are printed."""

SYNC_TARGETS = (
    Target(
        "march_sync_lines_per_step",
        0.0,
        True,
        "march source lines that sync in more than one env step of a part (GPU)",
    ),
    Target(
        "env_syncs_per_step_march_minus_rough",
        0.0,
        True,
        "syncs per env step, march's env minus bare rough's (GPU)",
    ),
)
"""The GPU check's sync targets, judged on its ``syncs`` phase (``scripts/sync_check.py``)."""


def judge(headline: dict[str, Any], targets: tuple[Target, ...] = STEP_TARGETS) -> dict[str, Any]:
    """Each target of ``targets`` judged on ``headline`` (a key it lacks: not measured)."""
    return {t.key: t.judge(headline.get(t.key)) for t in targets}


def verdict_lines(judged: dict[str, Any], prefix: str) -> list[str]:
    """One readable line per judged target: the figure, the bound and met / NOT MET / not
    measured."""
    by_key = {t.key: t for t in (*STEP_TARGETS, *SYNC_TARGETS)}
    lines = []
    for key, j in judged.items():
        t = by_key.get(key)
        what = t.what if t else key
        op = "<=" if "at_most" in j else ">="
        bound = j.get("at_most", j.get("at_least"))
        if j["met"] is None:
            state, shown = "not measured", "-"
        else:
            state, shown = ("met" if j["met"] else "NOT MET"), f"{j['value']:.2f}"
        lines.append(f"{prefix} target {key} {op} {bound:g}: {shown} ({what}): {state}")
    return lines
