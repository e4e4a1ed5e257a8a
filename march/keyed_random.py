"""Random numbers keyed by (seed, rollout index, draw number): counter-based streams, one per row.

torch's generators are one stream for a whole batch: the k-th row of a draw depends on how many
rows came before it and on every draw before it, so an evaluation's rollout ``i`` sees other
numbers when the rollouts are split into other waves or ranks. Here every row of a batch carries
its own key (a hash of the evaluation's seed and the row's rollout index) and its own counter of
draws; a draw's element ``j`` of row ``r`` is a hash of (key_r, counter_r, j). What rollout ``i``
draws therefore depends on ``(seed, i)`` and on the draws it took part in, nothing else: not on
the batch size, its place in the batch, or the other rows' draws (march.env.rollout_draws routes
an evaluation env's draws here; docs/evaluation.md).

The hash is Chris Wellons' ``lowbias32`` (xorshift-multiply, two rounds; bias 0.17 of a perfect
32-bit mix), in int64 tensor arithmetic exact modulo 2^32: each 32-bit product is split in two
16-bit halves so no intermediate passes 2^49 (no reliance on signed overflow). Uniform variates
take the hash's high 24 bits (float32's mantissa): values k / 2^24, k = 0 .. 2^24 - 1, as
``torch.rand``'s. Normal variates come from two uniforms (Box-Muller), integers from one.

Plain torch, no host read: a draw is a few elementwise kernels on the device of its rows.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

MASK32 = 0xFFFFFFFF
_M1, _M2 = 0x7FEB352D, 0x846CA68B
"""lowbias32's multipliers."""
_SALT_SEED, _SALT_ROW, _SALT_COUNT, _SALT_ELEMENT = 0x9E3779B9, 0x85EBCA6B, 0xC2B2AE35, 0x27D4EB2F
"""Odd constants xored into each input before it is hashed, so seed 0, row 0, draw 0 and
element 0 do not hash the fixed point 0."""
_U24 = 2.0**-24


def _mul32(x: torch.Tensor, c: int) -> torch.Tensor:
    """(x * c) mod 2^32 for int64 ``x`` in [0, 2^32) and a 32-bit constant ``c``, exact: the two
    16-bit halves of ``c`` keep every product below 2^49."""
    lo = x * (c & 0xFFFF)
    hi = ((x * (c >> 16)) & 0xFFFF) << 16
    return (lo + hi) & MASK32


def hash32(x: torch.Tensor) -> torch.Tensor:
    """lowbias32 of int64 ``x`` (its low 32 bits), as int64 in [0, 2^32)."""
    x = x & MASK32
    x = x ^ (x >> 16)
    x = _mul32(x, _M1)
    x = x ^ (x >> 15)
    x = _mul32(x, _M2)
    return x ^ (x >> 16)


def row_keys(seed: int, rows: torch.Tensor) -> torch.Tensor:
    """(n,) int64 keys of rollout indices ``rows`` in an evaluation seeded ``seed`` (any int)."""
    s = int(seed) & ((1 << 64) - 1)
    s_hi, s_lo = (s >> 32) ^ _SALT_SEED, (s & MASK32) ^ _SALT_SEED
    seed_key = hash32(hash32(torch.tensor(s_lo, dtype=torch.int64)) ^ s_hi)
    return hash32(seed_key.to(rows.device) ^ hash32(rows.long() ^ _SALT_ROW))


class RowStreams:
    """One counter-based stream per row of a batch (module docstring).

    ``keys`` and ``counts`` are (B,) int64 on the batch's device; :meth:`assign` keys the rows by
    rollout index and restarts their counters. A draw names its rows (an index tensor, or None for
    all B), takes ``shape`` elements per row and advances those rows' counters by one.
    """

    def __init__(self, batch: int, device: torch.device | str) -> None:
        self.batch = int(batch)
        self.device = torch.device(device)
        self.keys = torch.zeros(self.batch, dtype=torch.int64, device=self.device)
        self.counts = torch.zeros(self.batch, dtype=torch.int64, device=self.device)
        self.draws = torch.zeros((), dtype=torch.int64, device=self.device)
        """Draws taken since the last :meth:`assign` (a device counter, for the tests and docs)."""

    def assign(self, seed: int, first_rollout: int) -> None:
        """Row ``b`` carries rollout ``first_rollout + b`` of the evaluation seeded ``seed``; every
        counter restarts at 0."""
        index = torch.arange(self.batch, dtype=torch.int64, device=self.device) + int(first_rollout)
        self.keys.copy_(row_keys(seed, index))
        self.counts.zero_()
        self.draws.zero_()

    def _bits(
        self, rows: torch.Tensor | None, per_row: int, advance: torch.Tensor | None = None
    ) -> torch.Tensor:
        """(n, per_row) int64 hashes of the rows' next draw; advances their counters (only where
        ``advance`` (n,) bool is True, if given: rows drawn and discarded keep their place)."""
        keys = self.keys if rows is None else self.keys[rows]
        counts = self.counts if rows is None else self.counts[rows]
        base = hash32(keys ^ hash32(counts ^ _SALT_COUNT))  # (n,)
        element = hash32(
            torch.arange(per_row, dtype=torch.int64, device=self.device) ^ _SALT_ELEMENT
        )
        step = torch.ones_like(counts) if advance is None else advance.long()
        if rows is None:
            self.counts.add_(step)
        else:
            self.counts.index_add_(0, rows, step)
        self.draws.add_(1)
        return hash32(base[:, None] ^ element[None, :])

    def uniform(
        self,
        rows: torch.Tensor | None,
        shape: Sequence[int],
        dtype: torch.dtype = torch.float32,
        advance: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """(n, *shape) uniforms in [0, 1) in steps of 2^-24 for ``rows`` (None: every row);
        ``advance``: see :meth:`_bits`."""
        per_row = math.prod(shape)
        # k / 2^24 is exact in float32 and float64 alike: no rounding up to 1.0.
        wide = torch.float64 if dtype == torch.float64 else torch.float32
        u = (self._bits(rows, per_row, advance) >> 8).to(wide) * _U24
        return u.to(dtype).view(-1, *shape)

    def normal(
        self,
        rows: torch.Tensor | None,
        shape: Sequence[int],
        dtype: torch.dtype = torch.float32,
    ) -> torch.Tensor:
        """(n, *shape) standard normals (Box-Muller on two uniforms of one draw)."""
        per_row = math.prod(shape)
        u = self.uniform(rows, (2, per_row), torch.float64)
        radius = torch.sqrt(-2.0 * torch.log1p(-u[:, 0]))  # 1 - u in (0, 1]: log finite
        z = radius * torch.cos(2.0 * math.pi * u[:, 1])
        return z.to(dtype).view(-1, *shape)

    def integers(
        self,
        rows: torch.Tensor | None,
        low: int,
        high: int,
        shape: Sequence[int],
        dtype: torch.dtype = torch.int64,
    ) -> torch.Tensor:
        """(n, *shape) integers in [low, high) (floor of a uniform times the range; the range's
        bias is below its size / 2^24)."""
        u = self.uniform(rows, shape, torch.float64)
        return (torch.floor(u * (int(high) - int(low))) + int(low)).to(dtype)
