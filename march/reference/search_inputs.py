"""What the footstep planner's search reads besides the robot and the stones: the random draws of
one plan and the fixed tables of its score layout (:mod:`march.reference.planner`).

Both are independent of the number of envs (an evaluation draws each env's own instead,
:func:`planner_draws` with ``row_uniform``: its rollouts do not depend on the batch). The draws stay outside ``torch.compile``
(``plan_footsteps`` makes them eagerly, so the generator is not traced and the compiled plans
are the eager ones); the fixed parts (rollout 0's ring, the layout tables) are built once per
configuration and device and kept (:mod:`march.reference.kept`). Plain torch.

Two candidate layouts (one pass each; the planner's module docstring, "Solver"):

- the **stone layout** (M, Q), Q = 2T + K: per searched stone its T x 2 clamped nominal
  footholds (group (a): duration t, hard and soft margin), then its K random points (group (b));
  everything that depends on the landing point only (clearance, the constraints, the edge cost,
  the course-frame step) is computed once per point here, with the stone's rows broadcast;
- the **score layout** (T, M, C), C = 2 + K, flattened to F = T M C: every (duration, point)
  pair, the order of the Gumbel noise and of the argmin (ties go to the first), group (a)'s own
  duration only. One ``index_select`` (:attr:`ScoreLayout.index`) moves the stone layout's rows
  into it; the duration-dependent terms (velocity error, pace, time) are computed there.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch

from march.reference.kept import kept
from march.reference.planner_cfg import EPS, PlannerCfg

RowUniform = Callable[[tuple[int, ...]], torch.Tensor]
"""``draw(shape)``: (E, *shape) uniforms in [0, 1), one stream per env of the batch."""


def _ring(k: int, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    """(2, K) rollout 0's fixed ring of points at half the stone's usable extent."""

    def make() -> torch.Tensor:
        theta = 2.0 * torch.pi * (torch.arange(k, device=device, dtype=dtype) + 0.5) / max(k, 1)
        return 0.5 * torch.stack([torch.cos(theta), torch.sin(theta)])

    return kept(("ring", k, torch.device(device), dtype), make)


def planner_draws(
    cfg: PlannerCfg,
    m: int,
    generator: torch.Generator | RowUniform | None,
    device: torch.device,
    dtype: torch.dtype,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The shared random draws of one plan (shapes independent of E; march.reference.planner): unit
    points (N, 2, R, M, K) in [-1, 1] (rollout 0's a fixed ring) and the scaled Gumbel noise
    ``explore_temperature * g`` (N, R, T * M * (K + 2)) (rollout 0's zero), in the score layout.

    The numbers are those of ``2 rand - 1`` and ``T * -log(-log(rand.clamp(1e-12, 1 - 1e-7)))``
    from the same stream, in fewer ops (``uniform_(-1, 1)`` draws the same variates: 2 u - 1 is
    exact in float32; the temperature times the outer negation is one product by -T)."""
    r, n, k, nt = cfg.num_rollouts, cfg.num_steps, cfg.samples_per_stone, cfg.num_durations
    if generator is not None and not isinstance(generator, torch.Generator):
        return _row_draws(cfg, m, generator, device, dtype)  # each env's own stream
    gen_device = generator.device if generator is not None else device
    unit = torch.empty((n, 2, r, m, k), device=gen_device).uniform_(-1.0, 1.0, generator=generator)
    unit = unit.to(device, dtype)
    # Rollout 0 is deterministic.
    unit[:, :, 0] = _ring(k, device, dtype)[None, :, None, :]
    u = torch.rand((n, r, nt * m * (k + 2)), generator=generator, device=gen_device)
    noise = u.clamp_(1e-12, 1.0 - 1e-7).log_().neg_().log_().mul_(-cfg.explore_temperature)
    noise = noise.to(device, dtype)
    noise[:, 0] = 0.0  # rollout 0 is plain greedy
    return unit, noise


def _row_draws(
    cfg: PlannerCfg, m: int, row_uniform: RowUniform, device: torch.device, dtype: torch.dtype
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`planner_draws` with draws of each env's own (``row_uniform(shape)``: (E, *shape)
    uniforms in [0, 1), an evaluation's streams keyed by rollout, march.env.rollout_draws):
    unit points (N, 2, E, R, M, K) and noise (N, E, R, F), the same transforms of the
    uniforms; the search reads the E axis where the shared draws broadcast."""
    r, n, k, nt = cfg.num_rollouts, cfg.num_steps, cfg.samples_per_stone, cfg.num_durations
    unit = row_uniform((n, 2, r, m, k)).to(device, dtype).mul_(2.0).sub_(1.0)
    unit = unit.permute(1, 2, 0, 3, 4, 5)  # (N, 2, E, R, M, K)
    unit[:, :, :, 0] = _ring(k, device, dtype)[None, :, None, None, :]
    u = row_uniform((n, r, nt * m * (k + 2))).to(device)
    noise = u.clamp_(1e-12, 1.0 - 1e-7).log_().neg_().log_().mul_(-cfg.explore_temperature)
    noise = noise.to(dtype).permute(1, 0, 2, 3)  # (N, E, R, F)
    noise[:, :, 0] = 0.0
    return unit, noise


class ScoreLayout(NamedTuple):
    """The fixed tables of the two candidate layouts (module docstring), kept per configuration."""

    durations: torch.Tensor
    """(T,) the duration grid [s]."""
    index: torch.Tensor
    """(F,) int64: for each score-layout slot (t, m, c), its flat index in the stone layout
    (m, q): q = 2 t + c for group (a) (c < 2), 2 T + c - 2 for group (b)."""
    duration: torch.Tensor
    """(F,) the slot's duration [s]."""
    c_time: torch.Tensor
    """(F,) the slot's time cost w_time (dt - T_nom)^2 (the same float ops as
    :func:`march.reference.step_cost.step_terms`)."""
    limits: torch.Tensor
    """(6, 1, 1, 1, 1) the bounds the stone layout's constraint rows must not exceed (the
    planner's ``_W_*`` rows): -(margin - 2 eps), max_step^2, -min_lateral, -min_step_forward,
    max_lateral, max_step_height (a row above its bound violates a constraint)."""
    sides: torch.Tensor
    """(2, 7, N) per landing sequence (0: the right foot stands, so the left lands first; 1: the
    left foot stands) and step: the nominal offsets subtracted from the course-frame step
    (along 0, across side * width, along 0), the constraint signs (-side, -1, side) and
    lands_left (1.0 / 0.0); side = +1 where the left foot lands."""


def score_layout(cfg: PlannerCfg, m: int, device: torch.device, dtype: torch.dtype) -> ScoreLayout:
    """The kept :class:`ScoreLayout` of ``cfg`` with M = ``m`` searched stones."""
    nt, k, n = cfg.num_durations, cfg.samples_per_stone, cfg.num_steps
    key = (
        "layout",
        nt,
        m,
        k,
        n,
        cfg.duration_range,
        cfg.w_time,
        cfg.stone_margin,
        cfg.max_step,
        cfg.min_lateral,
        cfg.min_step_forward,
        cfg.max_lateral,
        cfg.max_step_height,
        cfg.step_width,
        torch.device(device),
        dtype,
    )

    def make() -> ScoreLayout:
        durations = cfg.duration_grid(device, dtype)
        c_time = cfg.w_time * (durations - cfg.nominal_duration) ** 2
        q = 2 * nt + k
        flat = torch.arange(nt * m * (k + 2), device=device)
        tm, c = flat // (k + 2), flat % (k + 2)  # tm = t * M + m; c the candidate
        t_idx, m_idx = tm // m, tm % m
        index = m_idx * q + torch.where(c < 2, t_idx * 2 + c, 2 * nt + c - 2)
        bounds = (
            -(cfg.stone_margin - 2 * EPS),
            cfg.max_step**2,
            -cfg.min_lateral,
            -cfg.min_step_forward,
            cfg.max_lateral,
            cfg.max_step_height,
        )
        limits = torch.stack([torch.full((), b, device=device, dtype=dtype) for b in bounds])
        # side of the first landing foot: +1 (left) when the right foot stands, then alternating
        alt = 1.0 - 2.0 * (torch.arange(n, device=device) % 2).to(dtype)
        width = torch.full((), cfg.step_width, device=device, dtype=dtype)
        zero = torch.zeros(n, device=device, dtype=dtype)

        def rows(side: torch.Tensor) -> torch.Tensor:
            return torch.stack(
                [zero, side * width, zero, -side, zero - 1.0, side, (side > 0).to(dtype)]
            )

        return ScoreLayout(
            durations=durations,
            index=index,
            duration=durations[t_idx],
            c_time=c_time[t_idx],
            limits=limits.view(6, 1, 1, 1, 1),
            sides=torch.stack([rows(alt), rows(-alt)]),
        )

    return kept(key, make)
