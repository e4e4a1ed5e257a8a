"""Batched footstep planner over stepping stones (paper eq. "planner"), plain torch.

Problem (per env): from the current stance foot p_0, choose N steps l_i and durations dt_i,

    min  sum_i ||v_i - v_D||^2 + c_edge(p_i)  (+ optional w_time (dt_i - T_nom)^2)
                               + c_pace(l_i, dt_i)                     (progress term, below)
    s.t. p_{i+1} = p_i + l_i,  v_i = (l_i - n_i) / dt_i,  p_i on a stone with a margin,
         l_i within the step bounds, feet alternate left/right, lateral limits per foot.

Progress term (decision, docs/decisions.md "Planner progress"). With the paper's cost alone a
step onto a stone farther than v_D * 0.7 s ahead costs more than a step in place: at 0.3 m/s and
a 0.68 m stone pitch, (0.68/0.7 - 0.3)^2 = 0.45 against 0.3^2 = 0.09, so the walk stepped in
place before every far stone and kept pace on 15-21% of the generated courses. Each step now
pays

    c_pace = pace_cost * max(0, rho v_D dt - a) / (rho v_D dt)   while the goal lies ahead,

with a = l . d the step's advance along the course direction d, v_D the command's component
along d, rho = ``pace_fraction`` (0.5). It is zero for every step that keeps pace (a step of
exactly v_D dt, the paper's optimum on open ground, is untouched), and ``pace_cost`` (1000) is
larger than any edge + velocity cost, so a step that keeps pace always wins over one that does
not; among steps that cannot keep pace, the one advancing most wins (a step in place pays the
full pace_cost, a backward step more). It stays below ``infeasible_cost``, so a feasible short
step still beats an infeasible one. "Goal lies ahead" = the stance foot of that step is before
the goal platform (progress < goal_distance); on the goal platform the paper's cost alone
applies (the walk may slow down and stand at its far end). Consequence: on courses whose stones
are farther apart than the command allows, the plan walks faster than commanded rather than
stepping in place (at a 0.3 m/s command the planner-only walk reaches the goal at about
0.45 m/s on the easiest and 0.8 m/s on the hardest level). The plan
carries a stall flag (``Plan.stalled``): some step could not keep pace while the goal lay ahead.

n_i is the nominal lateral offset of the landing foot (+/- step width across the course): the
paper writes v_i = l_i / dt_i; measured raw, the alternating +/- w lateral part of every step would
enter the cost as +/- w/dt and bias every plan toward the slowest timing, so the velocity is
measured between the feet's nominal lines (equivalently, the velocity of the mid-stance point).

Solver: random shooting with R = 16 greedy rollouts. At each step every rollout scores all
discretised durations (7 in [0.45, 0.7] s) times candidate footholds on the M stones nearest to the
nominal foothold; candidates per stone are the nominal foothold clamped into the stone (with the
hard margin, and with margin + edge clearance) plus K random points on it. Rollout 0 is the pure
greedy choice on a deterministic candidate set (a fixed ring of K points instead of random ones),
so a single-rollout planner is plain greedy and more rollouts can only lower the cost; rollouts
1.. draw random points and perturb the step scores with Gumbel noise (= sampling from a softmin
with temperature ``explore_temperature``), which lets them trade a worse step now for a reachable
next stone. The rollout with the lowest noise-free cost wins; a plan is feasible when every step
met every constraint.

Frames: positions and the velocity command are in the world frame. Longitudinal/lateral limits and
the nominal width use the course frame given by ``Footholds.direction`` (+x for generated courses).
The yaw-rate command is ignored for foothold placement (the course is straight and the planner
works in the course frame); the env's command term passes the forward command along the course
direction (march.env.reference_command, "Velocity command, in the course frame").

Randomness: every random draw has a shape independent of the number of envs and is shared by all
envs, so a batched plan equals a per-env loop and a seeded ``torch.Generator`` fixes the plan.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from march.compiled_math import fused
from march.reference.search_inputs import pick_table, planner_draws
from march.reference.step_cost import (
    _EPS,
    XY,
    _step_cost,
    goal_ahead,
    height_ok,
    into,
    pace_floor,
    pace_terms,
    step_terms,
)
from march.world.footholds import Footholds

"""Numerical slack [m] so that clamped footholds pass ``Footholds.contains`` in float32."""


@dataclass
class PlannerCfg:
    """Footstep planner parameters (author values where SPEC.md gives them)."""

    num_steps: int = 4
    """Horizon N: planned steps per replan (paper: 4)."""
    num_rollouts: int = 16
    """Greedy random-shooting rollouts R (paper: 16); rollout 0 is noise-free greedy."""
    duration_range: tuple[float, float] = (0.45, 0.7)
    """Shortest and longest step duration dt [s] (author)."""
    num_durations: int = 7
    """Number of evenly spaced duration candidates in ``duration_range`` (author: 7)."""
    step_width: float = 0.25
    """Nominal lateral distance between the feet [m] (author y_nom); keep equal to HlipCfg."""
    max_step: float = 0.85
    """Upper bound on the horizontal step length ||l|| [m] (author)."""
    min_step_forward: float = -0.25
    """Lower bound on the step component along the course [m] (a short backward step is allowed)."""
    min_lateral: float = 0.08
    """Least lateral distance of the landing foot to its own side of the stance foot [m]."""
    max_lateral: float = 0.45
    """Largest lateral distance of the landing foot from the stance foot [m]."""
    max_step_height: float = 0.3
    """Largest |height change| between stance and landing stone tops [m]."""
    stone_margin: float = 0.04
    """Hard margin: a foothold keeps at least this distance to every stone edge [m]."""
    edge_clearance: float = 0.1
    """Soft margin: footholds closer than this to an edge pay the edge cost [m] (author)."""
    edge_cost: float = 100.0
    """Edge cost weight; c_edge = edge_cost * (max(0, clearance - d_edge) / clearance)^2 (author)."""
    w_velocity: float = 1.0
    """Weight of ||v_i - v_D||^2 [1/(m/s)^2] (paper: 1)."""
    w_time: float = 0.45
    """Step-time regulariser weight on (dt - T_nom)^2 [1/s^2] (author's extra, not in the paper's
    cost; it mostly breaks ties toward the middle duration on open ground). 0 = paper cost."""
    num_candidate_stones: int = 8
    """M: stones per step nearest to the nominal foothold that are searched."""
    samples_per_stone: int = 4
    """K: random footholds drawn uniformly on each searched stone (with the hard margin)."""
    fuse_candidates: bool | None = None
    """Score both candidate groups in one call (fewer, larger ops: kernel launches count on a
    GPU) or apart (smaller tensors: on CPU they stay under torch's intra-op grain size). The
    same plans either way; None: fused on CUDA, apart elsewhere."""
    explore_temperature: float = 0.2
    """Softmin temperature of the randomised rollouts [cost units]; 0 makes all rollouts greedy."""
    infeasible_cost: float = 1.0e4
    """Cost added per violated step; keeps costs finite and ranks least-violating fallbacks."""
    pace_fraction: float = 0.5
    """rho: a step keeps pace when its advance along the course is at least rho * v_D * dt
    (v_D the command's component along the course, dt the step's duration). 0 disables the
    progress term (the paper's cost alone, which steps in place before a far stone). 0.5 leaves
    the velocity term room to average the pace over short and long steps (0.9 made walks on the
    easiest courses 20% faster than commanded) and still rules out steps in place."""
    pace_cost: float = 1.0e3
    """Cost per step of missing the pace entirely: pace_cost * max(0, rho v_D dt - advance) /
    (rho v_D dt), charged only while the goal platform lies ahead of the stance foot. Larger than
    any edge + velocity cost (<= ~110) so a step that keeps pace always beats one that does not,
    smaller than ``infeasible_cost`` so a feasible short step still beats an infeasible one."""

    @property
    def nominal_duration(self) -> float:
        """T_nom: the middle of ``duration_range`` [s] (a candidate when num_durations is odd)."""
        return 0.5 * (self.duration_range[0] + self.duration_range[1])

    def duration_grid(
        self, device: torch.device | str = "cpu", dtype=torch.float32
    ) -> torch.Tensor:
        """(num_durations,) candidate step durations [s]."""
        return torch.linspace(*self.duration_range, self.num_durations, device=device, dtype=dtype)


@dataclass
class Plan:
    """A batch of footstep plans (E envs, N steps)."""

    footholds: torch.Tensor
    """(E, N, 3) planned footholds: xy on a stone and the stone's top height z [m], world frame."""
    durations: torch.Tensor
    """(E, N) duration of each step, touchdown to touchdown [s]."""
    lands_left: torch.Tensor
    """(E, N) bool: True where the left foot lands at that step (steps alternate)."""
    cost: torch.Tensor
    """(E,) plan cost (velocity + edge + time + progress terms, plus ``infeasible_cost`` per
    violation)."""
    feasible: torch.Tensor
    """(E,) bool: every step met every constraint."""
    start: torch.Tensor
    """(E, 3) stance foot the plan starts from (xy as given, z = top of the stone under it) [m]."""
    stalled: torch.Tensor | None = None
    """(E,) bool stall flag: some step advances less than the pace requirement rho v_D dt while
    the goal platform lies ahead (the stones in reach do not allow the commanded pace). None for
    plans not made by :func:`plan_footsteps`."""

    @property
    def num_steps(self) -> int:
        return self.footholds.shape[1]

    def steps(self) -> torch.Tensor:
        """(E, N, 3) step vectors l_i = p_{i+1} - p_i (including the height change)."""
        prev = torch.cat([self.start[:, None], self.footholds[:, :-1]], dim=1)
        return self.footholds - prev


def course_frame(footholds: Footholds) -> tuple[torch.Tensor, torch.Tensor]:
    """(E, 2) unit vectors along and across (to the left of) the course."""
    axis = footholds.direction / footholds.direction.norm(dim=-1, keepdim=True).clamp(min=1e-9)
    return axis, torch.stack([-axis[:, 1], axis[:, 0]], dim=-1)


def locate_on_stones(footholds: Footholds, xy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Signed edge clearance (E, ...) and stone top height (E, ...) of points xy (E, ..., 2).

    The clearance is the largest over the env's stones of min(half_size - |xy - center|): on a stone
    it is the distance to that stone's nearest edge, off every stone it is negative. z is the top
    height of the stone attaining it.
    """
    e = xy.shape[0]
    pts = xy.reshape(e, -1, 1, 2)
    d = (pts - footholds.center[:, None, :, :2]).abs()
    clearance = (footholds.half_size[:, None] - d).min(-1).values  # (E, P, S)
    clearance = clearance.masked_fill(~footholds.valid[:, None], -1e9)
    best, idx = clearance.max(-1)
    z = torch.gather(footholds.center[..., 2], 1, idx)
    return best.reshape(xy.shape[:-1]), z.reshape(xy.shape[:-1])


def evaluate_plan(
    start_xy: torch.Tensor,
    footholds_xy: torch.Tensor,
    durations: torch.Tensor,
    lands_left: torch.Tensor,
    command: torch.Tensor,
    footholds: Footholds,
    cfg: PlannerCfg,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Cost (E,) and feasibility (E,) of a given plan under the planner's cost and constraints.

    start_xy (E, 2), footholds_xy (E, N, 2), durations (E, N), lands_left (E, N), command (E, 3).
    """
    axis, lat = course_frame(footholds)
    clear_start, z_start = locate_on_stones(footholds, start_xy)
    clear, z = locate_on_stones(footholds, footholds_xy)
    prev_xy = torch.cat([start_xy[:, None], footholds_xy[:, :-1]], dim=1)
    prev_z = torch.cat([z_start[:, None], z[:, :-1]], dim=1)
    prev = prev_xy.movedim(-1, 0)  # (2, E, N): the step cost's stacked x-y layout
    ahead = goal_ahead(footholds, prev)
    terms = step_terms(
        durations,
        lands_left,
        command[:, None, :2].movedim(-1, 0),
        axis[:, None].movedim(-1, 0),
        lat[:, None].movedim(-1, 0),
        cfg,
    )
    cost, ok = _step_cost(
        prev,
        footholds_xy.movedim(-1, 0),
        clear,
        height_ok(prev_z, z, cfg),
        terms,
        pace_terms(terms.cmd[0], ahead, cfg),
        cfg,
    )
    return cost.sum(-1), ok.all(-1)


# Rows of :func:`_stone_table` (its first dim), slices where a row pair is read as a (2, ...)
# x-y stack: the centre x, y and z; the lower and upper clamp bounds, each (2 axes, 2 margins);
# the half extents over which group (b)'s points spread; the half sizes of the clearance.
_CENTER_XY, _CZ = slice(0, 2), 2
_LOWER, _UPPER = slice(3, 7), slice(7, 11)
_SPREAD, _HALF = slice(11, 13), slice(13, 15)


def _clearance(center: XY, half: XY, xy: XY) -> torch.Tensor:
    """Edge clearance of points ``xy`` on the stones of centres ``center`` and half sizes
    ``half`` (rows of :func:`_stone_table`, broadcast against the points): negative off the
    stone, -inf on an unusable one."""
    off = (xy - center).abs_()
    inside = into(off, torch.sub, half, off)  # (in place: a fresh temporary of the points' shape)
    return torch.minimum(inside[0], inside[1])


def plan_footsteps(
    stance_xy: torch.Tensor,
    stance_is_left: torch.Tensor,
    command: torch.Tensor,
    footholds: Footholds,
    cfg: PlannerCfg | None = None,
    generator: torch.Generator | None = None,
    compiled: bool = False,
) -> Plan:
    """Plan N footsteps for every env by random shooting with greedy rollouts.

    stance_xy: (E, 2) current stance foot [m], world frame; stance_is_left: (E,) bool;
    command: (E, 3) [vx, vy, yaw_rate] in the world frame [m/s, m/s, rad/s] (yaw rate unused
    here); footholds: the envs' stones. Deterministic for a seeded ``generator``.
    ``compiled``: run the search (everything but the random draws) under ``torch.compile``
    (:func:`march.compiled_math.fused`): the same plans, fused into a few kernels.
    """
    cfg = cfg or PlannerCfg()
    m = min(cfg.num_candidate_stones, footholds.center.shape[1])
    unit, gumbel = planner_draws(cfg, m, generator, stance_xy.device, stance_xy.dtype)
    search = fused(_search) if compiled else _search
    return search(stance_xy, stance_is_left, command, footholds, unit, gumbel, cfg)


def _stone_table(footholds: Footholds, cfg: PlannerCfg) -> torch.Tensor:
    """(15, E, S) what the search reads of each stone, built once per plan so that a step gathers
    its M stones' rows in one op; rows (first dim, so that an x-y pair of rows is a (2, ...)
    stack): centre x, y (``_CENTER_XY``), z (``_CZ``); the lower (``_LOWER``) and upper
    (``_UPPER``) bounds of a foothold clamped into the stone, (2 axes, 2 margins) each (hard:
    with the hard margin, soft: with margin + edge clearance); the half extents with the hard
    margin (``_SPREAD``), over which group (b)'s points spread; the half sizes the clearance is
    measured against (``_HALF``): -inf on a padding entry or a stone too small for the hard
    margin, so that every point on it is off the stones."""
    half = footholds.half_size.movedim(-1, 0)  # (2, E, S)
    hard = half - cfg.stone_margin - _EPS
    usable = footholds.valid & (hard >= 0.0).all(0)
    hard = hard.clamp(min=0.0)
    soft = (half - cfg.stone_margin - cfg.edge_clearance).clamp(min=0.0)
    extent = torch.stack([hard, soft], dim=1)  # (2 axes, 2 margins, E, S)
    center = footholds.center.movedim(-1, 0)  # (3, E, S)
    xy = center[:2, None]
    return torch.cat(
        [
            center,
            (xy - extent).flatten(0, 1),
            (xy + extent).flatten(0, 1),
            hard,
            torch.where(usable, half, float("-inf")),
        ],
        dim=0,
    )


def _search(
    stance_xy: torch.Tensor,
    stance_is_left: torch.Tensor,
    command: torch.Tensor,
    footholds: Footholds,
    unit: torch.Tensor,
    gumbel: torch.Tensor,
    cfg: PlannerCfg,
) -> Plan:
    """The greedy random-shooting search of :func:`plan_footsteps` on given draws (pure).

    Everything that does not depend on the rollouts' stance feet (the command and course frame
    terms, the per-duration costs, the stones' clamp bounds, the scaled noise, the candidate
    buffers) is computed or allocated once before the step loop; the chosen points are stacked
    and the stall flags computed after it. Points are (2, ...) x-y stacks (step_cost.XY)."""
    device, dtype = stance_xy.device, stance_xy.dtype
    e, r, n = stance_xy.shape[0], cfg.num_rollouts, cfg.num_steps
    m = min(cfg.num_candidate_stones, footholds.center.shape[1])
    k = cfg.samples_per_stone
    durations = cfg.duration_grid(device, dtype)
    fuse = cfg.fuse_candidates if cfg.fuse_candidates is not None else device.type == "cuda"
    nt = durations.numel()
    axis, lat = course_frame(footholds)
    not_left = ~stance_is_left
    lands_left = torch.stack([not_left if i % 2 == 0 else stance_is_left for i in range(n)], 1)
    # Broadcast shapes: per env (2, E, 1, 1, 1, 1) x-y stacks against (2, E, R, T, M, C)
    # candidates; the landing side's terms per env and step (2, E, N, 1, 1, 1), read at step i
    # as (2, E, 1, 1, 1, 1).
    v_cmd, axis_, lat_ = (a.T.reshape(2, e, 1, 1, 1, 1) for a in (command[:, :2], axis, lat))
    dur = durations.view(1, 1, nt, 1, 1)
    terms = step_terms(dur, lands_left.view(e, n, 1, 1, 1), v_cmd, axis_, lat_, cfg)
    # Nominal foothold offsets from the stance foot, (2, E, N, T, 1, 1): width offset + v_D dt.
    nom_d = terms.offset * lat_ + v_cmd * dur
    floor, scale_ahead = pace_floor(terms.cmd[0], cfg)
    table = _stone_table(footholds, cfg)
    # The nearest-stone search: padding entries get half sizes of -inf (infinitely far).
    centers = table[_CENTER_XY, :, None]  # (2, E, 1, S)
    halves = torch.where(footholds.valid, footholds.half_size.movedim(-1, 0), float("-inf"))
    halves = halves[:, :, None]
    noise = cfg.explore_temperature * gumbel
    picks = pick_table(nt, m, k, fuse, device)
    # Candidate buffers, rewritten every step (what a step reads of them it gathers first).
    c = k + 2
    if fuse:  # one (T, M, C) group
        cand = torch.empty(2, e, r, nt * m * c, device=device, dtype=dtype)
        full = cand.view(2, e, r, nt, m, c)
        pos_a = full[..., :2]
    else:  # group (a), (T, M, 2), then group (b), (1, M, K): see search_inputs.pick_table
        split = nt * m * 2
        cand = torch.empty(2, e, r, split + m * k, device=device, dtype=dtype)
        ok_buf = torch.empty(e, r, split + m * k, device=device, dtype=torch.bool)
        pos_a = cand[..., :split].view(2, e, r, nt, m, 2)
        pos_b = cand[..., split:].view(2, e, r, 1, m, k)
        ok_a = ok_buf[..., :split].view(e, r, nt, m, 2)
        ok_b = ok_buf[..., split:].view(e, r, 1, m, k)

    _, z0 = locate_on_stones(footholds, stance_xy)
    p = stance_xy.T[:, :, None].expand(2, e, r)  # the rollouts' stance feet
    pz = z0[:, None].expand(e, r)
    points, t_picks, aheads = [p[0], p[1], pz], [], []
    for i in range(n):
        step = terms._replace(
            own_side=terms.own_side[:, :, i : i + 1], nominal=terms.nominal[:, :, i : i + 1]
        )
        # Nominal foothold for each duration, (2, E, R, T, 1): stance + width offset + v_D dt.
        nom = p[:, :, :, None, None] + nom_d[:, :, i : i + 1, :, :, 0]
        # The M stones whose rectangles are nearest to the middle duration's nominal foothold.
        d = ((nom[:, :, :, nt // 2, 0, None] - centers).abs() - halves).clamp(min=0.0)
        d = d * d  # (2, E, R, S)
        near = (d[0] + d[1]).topk(m, dim=-1, largest=False).indices  # (E, R, M)
        rows = table.gather(2, near.view(1, e, r * m).expand(table.shape[0], -1, -1))
        rows = rows.view(-1, e, r, m)
        center, half = (rows[s].view(2, e, r, 1, m, 1) for s in (_CENTER_XY, _HALF))
        # Two candidate groups, scored separately because only the first depends on dt:
        # (a) the nominal foothold clamped into each stone (hard and soft margins), (T, M, 2);
        # (b) random points on each stone, (1, M, K).
        lower, upper = (
            rows[s].view(2, 2, e, r, m).permute(0, 2, 3, 4, 1)[:, :, :, None]
            for s in (_LOWER, _UPPER)
        )  # (2 axes, E, R, 1, M, 2 margins)
        into(pos_a, torch.clamp, nom[..., None], lower, upper)
        spread_b = unit[i][:, None] * rows[_SPREAD].view(2, e, r, m, 1)
        ahead = goal_ahead(footholds, p)  # (E, R): the progress term applies
        scale = scale_ahead * ahead.view(e, r, 1, 1, 1)  # (0 where the goal is behind)
        prev = p.view(2, e, r, 1, 1, 1)
        height = height_ok(pz.view(e, r, 1, 1, 1), rows[_CZ].view(e, r, 1, m, 1), cfg)
        pace = (floor, scale)
        if fuse:
            full[..., 2:].copy_((center.view(2, e, r, m, 1) + spread_b)[:, :, :, None])
            cost, ok = _step_cost(
                prev, full, _clearance(center, half, full), height, step, pace, cfg
            )
            flat_ok = ok.expand_as(cost).reshape(e, r, -1)
        else:
            into(pos_b.view(2, e, r, m, k), torch.add, center.view(2, e, r, m, 1), spread_b)
            clear_a, clear_b = (_clearance(center, half, pos) for pos in (pos_a, pos_b))
            # The costs are joined by cat, not written into a buffer: a where(out=) into the
            # (T, M, 2 + K) interleaved layout runs 2-4 element inner loops, slower on CPU.
            cost_a, _ = _step_cost(prev, pos_a, clear_a, height, step, pace, cfg, ok_a)
            cost_b, _ = _step_cost(prev, pos_b, clear_b, height, step, pace, cfg, ok_b)
            cost, flat_ok = torch.cat([cost_a, cost_b], dim=-1), ok_buf
        # (T, M, C) flattened, C = the 2 + K candidates: group (a) first, then group (b)
        flat_cost = cost.view(e, r, -1)
        pick = (flat_cost + noise[i]).argmin(-1, keepdim=True)  # (E, R, 1)
        chosen = flat_cost.gather(-1, pick)[..., 0]
        slot, t_idx, m_idx = picks[:, pick[..., 0]]  # each (E, R)
        ok = flat_ok.gather(-1, slot[..., None])[..., 0]
        p = cand.gather(-1, slot.view(1, e, r, 1).expand(2, e, r, 1))[..., 0]
        if i == 0:
            total, feasible = chosen, ok
        else:
            total, feasible = total + chosen, feasible & ok
        pz = rows[_CZ].gather(-1, m_idx[..., None])[..., 0]
        points += [p[0], p[1], pz]
        t_picks.append(t_idx)
        aheads.append(ahead)

    path = torch.stack(points, dim=-1).view(e, r, n + 1, 3)  # the stance foot, then the N steps
    t_idx = torch.stack(t_picks, dim=-1)  # (E, R, N)
    # Stall flag: a chosen step falls short of the pace while the goal lies ahead.
    step_xy = (path[..., 1:, :2] - path[..., :-1, :2]) * axis[:, None, None]
    advance = step_xy[..., 0] + step_xy[..., 1]
    need = (floor.view(e, 1) * durations - _EPS).gather(1, t_idx.flatten(1)).view(e, r, n)
    stalled = (torch.stack(aheads, dim=-1) & (advance < need)).any(-1)

    # Best rollout: feasible ones first, then the lowest noise-free cost.
    rank = total.masked_fill(~feasible, float("inf"))
    best = torch.where(feasible.any(-1), rank.argmin(-1), total.argmin(-1))
    env = torch.arange(e, device=device)
    return Plan(
        footholds=path[env, best, 1:],
        durations=durations[t_idx[env, best]],
        lands_left=lands_left,
        cost=total[env, best],
        feasible=feasible[env, best],
        start=torch.cat([stance_xy, z0[:, None]], dim=-1),
        stalled=stalled[env, best],
    )
