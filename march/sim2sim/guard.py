"""Inputs outside training, flagged: what deployment code calls on every control step.

:func:`check_command` refuses a velocity command outside the trained ranges
(``deploy.json``'s ``command_ranges``) with one line; :class:`RangeGuard` reports, per step, the
proprioception elements outside the range seen in training by more than the bundle's margin
(``observation.training_range``: mean +- 4 sigma of the student's normaliser, flagged past one
more sigma). numpy only, so a robot's loop can import it without MuJoCo::

    from march.sim2sim.guard import RangeGuard, check_command
    spec = json.load(open("student.deploy.json"))
    check_command(spec, (0.5, 0.0, 0.0))           # raises CommandRefused outside the ranges
    guard = RangeGuard(spec)
    for flag in guard.check(proprio_vector):       # one control step's proprioception (P,)
        print(flag.line())
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

COMMAND_KEYS = ("lin_vel_x", "lin_vel_y", "ang_vel_z")
_TOL = 1e-9


class CommandRefused(ValueError):
    """A command outside the trained ranges: one line naming the value and its range."""


def check_command(spec: dict[str, Any], command: Sequence[float]) -> None:
    """Raise :class:`CommandRefused` if any of (v_x, v_y, yaw rate) is outside its trained range."""
    ranges = spec["command_ranges"]
    for key, value in zip(COMMAND_KEYS, command, strict=True):
        lo, hi = ranges[key]
        if not lo - _TOL <= float(value) <= hi + _TOL:
            raise CommandRefused(
                f"command {key}={float(value):g} is outside the trained range [{lo:g}, {hi:g}]; "
                "the policy never saw it (deploy.json command_ranges)"
            )


@dataclass(frozen=True)
class Flag:
    """One observation element outside the training range."""

    term: str
    index: int
    element: str
    value: float
    sigmas: float
    lo: float
    hi: float

    def line(self, step: int | None = None) -> str:
        at = f"step {step}: " if step is not None else ""
        return (
            f"{at}{self.term}[{self.element}] = {self.value:.4g} outside training "
            f"[{self.lo:.4g}, {self.hi:.4g}] ({self.sigmas:+.1f} sigma)"
        )


class RangeGuard:
    """Per-step check of a proprioception vector against the range seen in training."""

    def __init__(self, spec: dict[str, Any]) -> None:
        obs = spec["observation"]
        rng = obs["training_range"]
        eps = float(rng["eps"])
        margin = float(rng["margin_sigmas"])
        self.terms: list[tuple[str, slice, list[str]]] = []
        means, sig, lo, hi = [], [], [], []
        start = 0
        for term in obs["terms"]:
            name, dim = term["name"], int(term["dim"])
            self.terms.append((name, slice(start, start + dim), list(term["elements"])))
            r = rng[name]
            means += r["mean"]
            sig += [s + eps for s in r["std"]]
            lo += r["lo"]
            hi += r["hi"]
            start += dim
        self.dim = start
        self.mean = np.asarray(means)
        self.sigma = np.asarray(sig)
        self.lo, self.hi = np.asarray(lo), np.asarray(hi)
        self.lo_flag = self.lo - margin * self.sigma
        self.hi_flag = self.hi + margin * self.sigma

    def check(self, proprio: np.ndarray) -> list[Flag]:
        """The flagged elements of one step's proprioception vector (P,), in term order."""
        x = np.asarray(proprio, dtype=np.float64).reshape(-1)
        if x.shape[0] != self.dim:
            raise ValueError(f"proprioception of size {x.shape[0]}, the bundle's is {self.dim}")
        bad = np.flatnonzero((x < self.lo_flag) | (x > self.hi_flag) | ~np.isfinite(x))
        flags = []
        for k in bad:
            name, sl, elements = next(t for t in self.terms if t[1].start <= k < t[1].stop)
            i = int(k - sl.start)
            flags.append(
                Flag(
                    term=name,
                    index=i,
                    element=elements[i],
                    value=float(x[k]),
                    sigmas=float((x[k] - self.mean[k]) / self.sigma[k]),
                    lo=float(self.lo[k]),
                    hi=float(self.hi[k]),
                )
            )
        return flags
