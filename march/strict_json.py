"""Strict JSON: what every JSON file march writes goes through, so any parser can read it.

Python's ``json`` writes ``NaN`` and ``Infinity`` for non-finite floats, which JSON does not have:
JavaScript's ``JSON.parse``, Go's ``encoding/json`` and serde_json refuse the whole file. A mean
over no successful rollout is undefined, not a number; :func:`strict` writes it as ``null``, and
the writer puts the count that says why beside it (``summary.json``: ``n_torque_success: 0``
and ``null_because``). :func:`dumps` refuses anything non-finite that is left
(``allow_nan=False``), and :func:`loads` is the reader that refuses NaN and Infinity, for tests
and tools. Pure Python: no torch, no simulator.
"""

from __future__ import annotations

import json
import math
from typing import Any


def strict(obj: Any) -> Any:
    """``obj`` with every non-finite float (NaN, +-inf; numpy scalars and 0-d arrays included)
    replaced by None, tuples as lists; containers copied, other values kept."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: strict(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [strict(v) for v in obj]
    item = getattr(obj, "item", None)
    if callable(item) and getattr(obj, "shape", None) == ():  # numpy / torch scalars
        return strict(item())
    return obj


def dumps(obj: Any, **kwargs: Any) -> str:
    """``json.dumps`` of :func:`strict` ``(obj)`` with ``allow_nan=False``."""
    return json.dumps(strict(obj), allow_nan=False, **kwargs)


def _refuse(name: str) -> Any:
    raise ValueError(f"not strict JSON: {name} (write null and say why)")


def loads(text: str) -> Any:
    """``json.loads`` that refuses ``NaN``, ``Infinity`` and ``-Infinity`` as a strict parser
    does (ValueError)."""
    return json.loads(text, parse_constant=_refuse)


def null_because(row: dict[str, Any], counts: dict[str, str], total: str) -> dict[str, str]:
    """For each ``mean_<m>`` / ``se_<m>`` of ``row`` that is not a finite number: the count that
    says why (``counts[m]``, the key of ``row`` counting the values behind metric ``m``, else
    ``total``), as ``"n_torque_success = 0"`` (a mean needs 1 value, an SE 2)."""
    out = {}
    for key, value in row.items():
        if not key.startswith(("mean_", "se_")) or strict(value) is not None:
            continue
        metric = key.split("_", 1)[1]
        count = counts.get(metric, total)
        need = "a mean needs 1" if key.startswith("mean_") else "a standard error needs 2"
        out[key] = f"{count} = {row.get(count)} ({need})"
    return out
