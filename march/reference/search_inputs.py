"""What the footstep planner's search reads besides the robot and the stones: the random draws of
one plan and the cached index table of its candidates (:mod:`march.reference.planner`).

Both are independent of the number of envs. The draws stay outside ``torch.compile``
(``plan_footsteps`` makes them eagerly, so the generator is not traced and the compiled plans
are the eager ones); the fixed parts (rollout 0's ring, the pick table) are built once per
configuration and device and kept (:mod:`march.reference.kept`). Plain torch.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from march.reference.kept import kept

if TYPE_CHECKING:
    from march.reference.planner import PlannerCfg


def _ring(k: int, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    """(2, K) rollout 0's fixed ring of points at half the stone's usable extent."""

    def make() -> torch.Tensor:
        theta = 2.0 * torch.pi * (torch.arange(k, device=device, dtype=dtype) + 0.5) / max(k, 1)
        return 0.5 * torch.stack([torch.cos(theta), torch.sin(theta)])

    return kept(("ring", k, torch.device(device), dtype), make)


def planner_draws(
    cfg: PlannerCfg,
    m: int,
    generator: torch.Generator | None,
    device: torch.device,
    dtype: torch.dtype,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The shared random draws of one plan (shapes independent of E; march.reference.planner): unit
    points (N, 2, R, M, K) in [-1, 1] (rollout 0's a fixed ring) and Gumbel noise
    (N, R, T * M * (K + 2)) (rollout 0's zero)."""
    r, n, k, nt = cfg.num_rollouts, cfg.num_steps, cfg.samples_per_stone, cfg.num_durations
    gen_device = generator.device if generator is not None else device
    unit = torch.rand((n, 2, r, m, k), generator=generator, device=gen_device).to(device, dtype)
    unit = 2.0 * unit - 1.0
    # Rollout 0 is deterministic.
    unit[:, :, 0] = _ring(k, device, dtype)[None, :, None, :]
    u = torch.rand((n, r, nt * m * (k + 2)), generator=generator, device=gen_device)
    gumbel = -torch.log(-torch.log(u.clamp(1e-12, 1.0 - 1e-7))).to(device, dtype)
    gumbel[:, 0] = 0.0  # rollout 0 is plain greedy
    return unit, gumbel


def pick_table(nt: int, m: int, k: int, fuse: bool, device: torch.device) -> torch.Tensor:
    """(3, T * M * (K + 2)) int64: for a candidate's flat index in the (T, M, K + 2) score order
    (group (a)'s 2 points, then group (b)'s K, per duration and stone), its slot in the search's
    candidate buffer, its duration index and its stone index, so that one lookup replaces the
    index arithmetic of every step. The buffer is the score order itself when the groups are
    fused; apart, it holds group (a), (T, M, 2), then group (b), (M, K), once for all T."""

    def make() -> torch.Tensor:
        flat = torch.arange(nt * m * (k + 2), device=device)
        tm, c = flat // (k + 2), flat % (k + 2)  # tm = t_idx * M + m_idx; c the candidate
        t_idx, m_idx = tm // m, tm % m
        if fuse:
            slot = flat
        else:
            slot = torch.where(c < 2, tm * 2 + c, nt * m * 2 + m_idx * k + (c - 2))
        return torch.stack([slot, t_idx, m_idx])

    return kept(("pick", nt, m, k, fuse, torch.device(device)), make)
