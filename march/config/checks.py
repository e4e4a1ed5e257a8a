"""Validation helpers of the config schema: the valid-name tuples, :class:`ConfigError` and the
checks each section's ``__post_init__`` runs (one line saying what is wrong and how to fix it;
:class:`ConfigError` itself lives in :mod:`march.errors`).

Also :func:`cnn_output_hw`, the student CNN's feature-map size that the whole-config check needs.
Pure data: no simulator import.
"""

from __future__ import annotations

import math
import re
from dataclasses import fields
from functools import cache
from typing import Any, get_args, get_origin, get_type_hints

from march.config.registry import names
from march.errors import ConfigError

STAGES = ("all", "teacher", "student", "eval")
REWARDS = names("reward")
"""The reward arms of ``conf/reward/`` (march.config.registry): tests compose every one."""
STUDENTS = names("student")
"""The student variants of ``conf/student/``."""
BUILTIN_PARTS = {
    "full": ("cnn", "transformer", "mdn"),
    "no_transformer": ("cnn", "mlp", "mdn"),
    "no_mdn": ("cnn", "transformer", "deterministic"),
}
"""(image, fusion, head) of the paper's variants, for checkpoints written before the parts were
config fields; the YAMLs in ``conf/student/`` state their parts themselves."""
_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")
CURRICULA = ("stones", "flat_first")
COMPUTES = ("auto", "cpu", "gpu", "smoke")
LOGGERS = ("csv", "tensorboard", "wandb")
DRS = ("paper", "none")
COURSES = ("stones", "hardware")


def check_one_of(section: str, key: str, value: Any, valid: tuple[str, ...]) -> None:
    if value not in valid:
        raise ConfigError(
            f"{section}.{key}={value!r} is not valid; choose one of {', '.join(valid)}"
        )


def check_identifier(section: str, key: str, value: Any) -> None:
    """A name that labels runs, directories and figures: letters, digits, underscores."""
    if not isinstance(value, str) or not _NAME.match(value):
        raise ConfigError(
            f"{section}.{key}={value!r} must be a name of letters, digits and underscores "
            "(starting with a letter)"
        )


def check_positive(section: str, key: str, value: float) -> None:
    if not value > 0:
        raise ConfigError(f"{section}.{key}={value} must be > 0")


SEED_MAX = 2**31 - 1
"""Largest seed every RNG of a run accepts: numpy takes 0..2**32-1, but warp's ``wp.rand_init``
(mjlab's ``seed_rng``) takes an int32 and silently wraps anything larger."""

ACTIVATIONS = ("elu", "relu", "gelu", "silu", "tanh")
"""Activations of march's own networks (march.policies.part_builders.activation)."""
RSL_ACTIVATIONS = ("elu", "selu", "relu", "crelu", "lrelu", "tanh", "sigmoid", "softplus")
RSL_ACTIVATIONS += ("gelu", "swish", "mish", "identity")
"""Activations rsl-rl's actor-critic MLP takes (rsl_rl.utils.resolve_nn_activation)."""
MJ_GEOM_GROUPS = 6
"""MuJoCo's number of geom groups (mjNGROUP): valid groups are 0..5."""


def fmt_value(value: Any) -> str:
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(fmt_value(v) for v in value) + "]"
    return str(value)


def require(section: str, key: str, value: Any, ok: bool, allowed: str) -> None:
    """Raise ``<section>.<key>=<value> must be <allowed>`` unless ``ok``."""
    if not ok:
        name = f"{section}.{key}" if section else key
        raise ConfigError(f"{name}={fmt_value(value)} must be {allowed}")


def check_at_least(section: str, key: str, value: float, lo: float) -> None:
    require(section, key, value, value >= lo, f">= {lo}")


def check_interval(
    section: str, key: str, value: float, lo: float, hi: float, *, lo_open=False, hi_open=False
) -> None:
    ok = (value > lo if lo_open else value >= lo) and (value < hi if hi_open else value <= hi)
    text = f"in {'(' if lo_open else '['}{lo}, {hi}{')' if hi_open else ']'}"
    require(section, key, value, ok, text)


def check_bounds(
    section: str, key: str, pair: Any, lo: float | None = None, *, lo_open: bool = False
) -> None:
    """A range [a, b]: a <= b, and a >= lo (a > lo with ``lo_open``)."""
    a, b = pair
    require(section, key, pair, a <= b, "[lo, hi] with lo <= hi")
    if lo is not None:
        ok = a > lo if lo_open else a >= lo
        require(section, key, pair, ok, f"[lo, hi] with lo {'>' if lo_open else '>='} {lo}")


def check_each(section: str, key: str, values: Any, lo: float, *, nonempty: bool = False) -> None:
    """Every entry >= lo (and at least one entry with ``nonempty``)."""
    if nonempty:
        require(section, key, values, len(values) > 0, "a non-empty list")
    require(section, key, values, all(v >= lo for v in values), f"a list of values >= {lo}")


@cache
def _hints(cls: type) -> dict[str, Any]:
    return get_type_hints(cls)


def check_shapes(section: str, obj: Any) -> None:
    """Every number finite and every fixed-size tuple of its declared length.

    OmegaConf accepts ``nan``/``inf`` for floats and a list of any length for a ``tuple[float,
    float]``; both would fail far from the command line."""
    hints = _hints(type(obj))
    for f in fields(obj):
        value, hint = getattr(obj, f.name), hints[f.name]
        items = list(value.values()) if isinstance(value, dict) else value
        if isinstance(items, (list, tuple)):
            args = get_args(hint)
            if get_origin(hint) is tuple and args and Ellipsis not in args:
                require(
                    section, f.name, value, len(items) == len(args), f"a list of {len(args)} values"
                )
            nums = [v for v in items if isinstance(v, float)]
        else:
            nums = [items] if isinstance(items, float) else []
        require(section, f.name, value, all(math.isfinite(v) for v in nums), "finite")


def cnn_output_hw(hw: tuple[int, int], kernels: Any, strides: Any) -> tuple[int, int]:
    """The student CNN's feature-map size for an image of ``hw`` (height, width) pixels: conv
    layers with same padding (kernel // 2), as march.policies.student builds them."""
    h, w = hw
    for k, s in zip(kernels, strides, strict=True):
        h = (h + 2 * (k // 2) - k) // s + 1
        w = (w + 2 * (k // 2) - k) // s + 1
    return h, w


# The names before issue 54 made these helpers public (a branch written before the rename
# still runs; tests/test_layout.py flags any import of a private name).
_one_of = check_one_of
_identifier = check_identifier
_positive = check_positive
_fmt = fmt_value
_need = require
_at_least = check_at_least
_interval = check_interval
_bounds = check_bounds
_each = check_each
_check_shapes = check_shapes
