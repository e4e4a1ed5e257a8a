"""march.keyed_random: the hash against an independent integer implementation, the variates'
distributions, and what the streams promise: a row's numbers depend on (seed, rollout, draws it
took part in) only, never on the batch around it."""

from __future__ import annotations

import math
import random

import pytest
import torch

from march.keyed_random import RowStreams, hash32, row_keys


def _lowbias32(x: int) -> int:
    """Chris Wellons' lowbias32 in Python integers (arbitrary precision, masked by hand)."""
    x &= 0xFFFFFFFF
    x ^= x >> 16
    x = (x * 0x7FEB352D) & 0xFFFFFFFF
    x ^= x >> 15
    x = (x * 0x846CA68B) & 0xFFFFFFFF
    x ^= x >> 16
    return x


def test_hash_matches_integer_arithmetic_on_many_inputs():
    rng = random.Random(0)
    xs = [0, 1, 2, 0xFFFFFFFF, 0x80000000, 0x7FFFFFFF] + [rng.getrandbits(32) for _ in range(5000)]
    got = hash32(torch.tensor(xs, dtype=torch.int64)).tolist()
    assert got == [_lowbias32(x) for x in xs]
    # bits above 32 are ignored: the hash reads the low 32 bits only
    assert hash32(torch.tensor([xs[7] + (5 << 32)])).item() == _lowbias32(xs[7])


def test_uniform_variates_have_the_uniform_distribution():
    s = RowStreams(64, "cpu")
    s.assign(seed=3, first_rollout=0)
    u = torch.cat([s.uniform(None, (500,)).flatten() for _ in range(8)]).double()  # 256k
    assert u.min() >= 0.0 and u.max() < 1.0
    n = u.numel()
    # mean 1/2 and variance 1/12, each within 5 standard errors
    assert abs(u.mean().item() - 0.5) < 5 * math.sqrt(1 / 12 / n)
    assert abs(u.var().item() - 1 / 12) < 5 * math.sqrt(1 / 180 / n)
    # 64 equal bins: chi-square with 63 degrees of freedom, far below its 1e-6 tail (~130)
    counts = torch.histc(u, bins=64, min=0.0, max=1.0)
    chi2 = ((counts - n / 64) ** 2 / (n / 64)).sum().item()
    assert chi2 < 130, chi2
    # neighbouring elements and neighbouring rows are uncorrelated
    grid = s.uniform(None, (4000,)).double()
    lag = torch.corrcoef(torch.stack([grid[:, :-1].flatten(), grid[:, 1:].flatten()]))[0, 1]
    rows = torch.corrcoef(torch.stack([grid[:-1].flatten(), grid[1:].flatten()]))[0, 1]
    assert abs(lag.item()) < 5 / math.sqrt(grid.numel()) and abs(rows.item()) < 0.01


def test_normal_and_integer_variates():
    s = RowStreams(32, "cpu")
    s.assign(seed=11, first_rollout=100)
    z = s.normal(None, (4000,)).double().flatten()
    n = z.numel()
    assert abs(z.mean().item()) < 5 / math.sqrt(n)
    assert abs(z.var().item() - 1.0) < 5 * math.sqrt(2 / n)
    # the standard normal's tail: P(|z| > 2) = 0.0455
    assert abs((z.abs() > 2).double().mean().item() - 0.0455) < 5 * math.sqrt(0.0455 * 0.9545 / n)
    k = s.integers(None, -3, 4, (4000,))
    assert k.dtype == torch.int64 and k.min() == -3 and k.max() == 3
    freq = torch.bincount((k + 3).flatten(), minlength=7).double() / k.numel()
    assert (freq - 1 / 7).abs().max() < 5 * math.sqrt((1 / 7) * (6 / 7) / k.numel())


@pytest.mark.parametrize("seed", [0, 1, 2**31 - 1, 2**40 + 7])
def test_a_rollouts_numbers_do_not_depend_on_its_batch(seed):
    """Rollouts 0..11 as one batch of 12, as 3 batches of 4 and as 4 batches of 3, with draws of
    every row, of some rows and with rows that are drawn but not advanced: rollout i's numbers
    are the same every way."""

    def run(batch: int) -> dict[int, list[torch.Tensor]]:
        out: dict[int, list[torch.Tensor]] = {}
        for first in range(0, 12, batch):
            s = RowStreams(batch, "cpu")
            s.assign(seed, first)
            rows = torch.arange(batch)
            drawn = [s.uniform(None, (5,)), s.normal(None, (2, 3)).flatten(1)]
            even = rows[(rows + first) % 2 == 0]  # a subset draw: the even rollouts only
            sub = s.uniform(even, (7,))
            # a padded draw: every row drawn, only the odd rollouts advanced
            odd = (rows + first) % 2 == 1
            s.uniform(None, (3,), advance=odd)
            last = s.integers(None, 0, 1000, (4,))
            for b in range(batch):
                i = first + b
                mine = [d[b] for d in drawn] + [last[b].double()]
                if i % 2 == 0:
                    mine.append(sub[(even == b).nonzero()[0, 0]])
                out[i] = mine
        return out

    one, threes, fours = run(12), run(3), run(4)
    for i in range(12):
        for a, b, c in zip(one[i], threes[i], fours[i], strict=True):
            assert torch.equal(a, b) and torch.equal(a, c), i
    # different rollouts and different seeds draw different numbers
    assert not torch.equal(one[0][0], one[1][0])
    other = RowStreams(1, "cpu")
    other.assign(seed + 1, 0)
    assert not torch.equal(other.uniform(None, (5,))[0], one[0][0])


def test_a_row_left_out_of_a_draw_or_not_advanced_keeps_its_place():
    s = RowStreams(3, "cpu")
    s.assign(seed=5, first_rollout=0)
    first = s.uniform(None, (4,))
    s.uniform(torch.tensor([0, 2]), (4,))  # row 1 left out
    s.uniform(None, (4,), advance=torch.tensor([True, False, True]))  # row 1 not advanced
    third = s.uniform(None, (4,))
    ref = RowStreams(3, "cpu")
    ref.assign(seed=5, first_rollout=0)
    ref.uniform(None, (4,))
    second_of_row1 = ref.uniform(None, (4,))[1]
    assert torch.equal(third[1], second_of_row1)
    assert not torch.equal(third[0], second_of_row1) and not torch.equal(first[1], third[1])
    assert s.counts.tolist() == [4, 2, 4]


def test_row_keys_differ_across_many_rollouts_and_seeds():
    keys = torch.cat([row_keys(seed, torch.arange(2000)) for seed in range(5)])
    assert keys.unique().numel() == keys.numel()
