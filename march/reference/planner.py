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

Evaluation (issue 41: ~53 ops per planned step, 284 per call with the draws and tables, was 503 /
358): one pass per term over both candidate groups. What depends on the landing point only
(clearance, the constraints, the edge cost, the step in the course frame) is computed once per
point in the stone layout (M, 2T + K), with the stone's rows broadcast; one gather moves those
rows into the score layout (T, M, 2 + K) of the noise and the argmin, where the terms that
depend on the duration are added; the six constraints are rows of one buffer tested against
their bounds in one comparison, and one gather reads a rollout's choice (duration, cost,
feasibility, point, its stone's height, its advance). Every float is the one
:func:`march.reference.step_cost.score_steps` computes (the same ops on the same values; the
search tests a >= b as -a <= -b and reads -clearance, negations being exact), so the plans are
the old ones bit for bit (:func:`evaluate_plan` still scores with ``score_steps``).

Frames: positions and the velocity command are in the world frame. Longitudinal/lateral limits and
the nominal width use the course frame given by ``Footholds.direction`` (+x for generated courses).
The yaw-rate command is ignored for foothold placement (the course is straight and the planner
works in the course frame); the env's command term passes the forward command along the course
direction (march.env.reference_command, "Velocity command, in the course frame").

Randomness: draws shared by all envs (shapes independent of E: a batched plan equals a per-env
loop; a seeded ``torch.Generator`` fixes the plan), or each env's own (``row_uniform``, evaluation).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from march.compiled_math import fused
from march.reference.plan_tables import (
    CENTER_XY,
    CZ,
    DIR,
    FRAME,
    GOAL,
    HALF,
    HALVES,
    LOWER,
    SPREAD,
    START,
    UPPER,
    PlanTables,
    course_frame,
    locate_on_stones,
    pad_stones,
    plan_tables,
    stance_z,
)
from march.reference.planner_cfg import EPS, PlannerCfg
from march.reference.search_inputs import RowUniform, planner_draws, score_layout
from march.reference.step_cost import (
    XY,
    goal_ahead,
    height_ok,
    into,
    pace_terms,
    score_steps,
    step_terms,
)
from march.world.footholds import Footholds


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
    cost, ok = score_steps(
        prev,
        footholds_xy.movedim(-1, 0),
        clear,
        height_ok(prev_z, z, cfg),
        terms,
        pace_terms(terms.cmd[0], ahead, cfg),
        cfg,
    )
    return cost.sum(-1), ok.all(-1)


def plan_footsteps(
    stance_xy: torch.Tensor,
    stance_is_left: torch.Tensor,
    command: torch.Tensor,
    footholds: Footholds | PlanTables,
    cfg: PlannerCfg | None = None,
    generator: torch.Generator | None = None,
    compiled: bool = False,
    row_uniform: RowUniform | None = None,
) -> Plan:
    """Plan N footsteps for every env by random shooting with greedy rollouts.

    stance_xy: (E, 2) current stance foot [m], world frame; stance_is_left: (E,) bool;
    command: (E, 2 or 3) [vx, vy(, yaw_rate)] in the world frame [m/s, m/s, rad/s] (yaw rate
    unused here); footholds: the envs' stones, or their :func:`plan_tables`. Deterministic for
    a seeded ``generator``. ``compiled``: run the search (everything but the random draws)
    under ``torch.compile`` (:func:`march.compiled_math.fused`): the same plans, fused into a
    few kernels. ``row_uniform``: each env's own draws (an evaluation; search_inputs).
    """
    cfg = cfg or PlannerCfg()
    args = (stance_xy, stance_is_left, command, footholds, cfg, row_uniform or generator, compiled)
    threads = torch.get_num_threads()
    if stance_xy.device.type != "cpu" or threads == 1:
        return _plan(*args)
    # On CPU the planner runs on one thread: its ops (an 8-env batch: 18k-340k elements) pass
    # torch's intra-op grain size (32k) and the random draws fork too; each would start an
    # OpenMP region, which stalls on a busy machine (2 threads, loaded 2 cores, 16 envs: median
    # 20-40 ms per call against 8 ms on one thread; the draws alone 9.5 ms against 0.09). The
    # same plans on any thread count (no float sums; the generator's stream is serial).
    torch.set_num_threads(1)
    try:
        return _plan(*args)
    finally:
        torch.set_num_threads(threads)


def _plan(
    stance_xy: torch.Tensor,
    stance_is_left: torch.Tensor,
    command: torch.Tensor,
    footholds: Footholds | PlanTables,
    cfg: PlannerCfg,
    source: torch.Generator | RowUniform | None,
    compiled: bool,
) -> Plan:
    """:func:`plan_footsteps` on the current thread count (``source``: generator or per env)."""
    tables = footholds if isinstance(footholds, PlanTables) else plan_tables(footholds, cfg)
    # Every plan searches M stones (padding entries where a batch has fewer): the draws' shape,
    # and so each env's numbers, never depend on the stone count its batch was padded to.
    tables = pad_stones(tables, cfg.num_candidate_stones)
    m = cfg.num_candidate_stones
    unit, noise = planner_draws(cfg, m, source, stance_xy.device, stance_xy.dtype)
    search = fused(_search) if compiled else _search
    return search(stance_xy, stance_is_left, command, tables, unit, noise, cfg)


# Rows of the stone-layout buffer G (all moved into the score layout's rows _F_MOVED by one
# gather; _G_PEN is ok - 1: 0.0 feasible, -1.0 not), of the constraint buffer W (one row per
# constraint, met where within ScoreLayout.limits) and of the score-layout buffer F (the first
# _F_PICK rows are what a rollout's choice reads, in one gather).
_G_PEN, _G_XY, _G_Z, _G_D, _G_EDGE, _G_ROWS = 0, slice(1, 3), 3, slice(4, 7), 7, 8
_W_NEGCLEAR, _W_SQ, _W_OWN, _W_DZ, _W_ROWS = 0, 1, slice(2, 5), 5, 6
_F_DT, _F_COST, _F_PEN, _F_XY, _F_Z, _F_ALONG, _F_D, _F_EDGE = (
    0,
    1,
    2,
    slice(3, 5),
    5,
    6,
    slice(6, 9),
    9,
)
_F_MOVED, _F_PICK, _F_ROWS = slice(2, 10), 7, 10


def _search(
    stance_xy: torch.Tensor,
    stance_is_left: torch.Tensor,
    command: torch.Tensor,
    footholds: Footholds | PlanTables,
    unit: torch.Tensor,
    noise: torch.Tensor,
    cfg: PlannerCfg,
) -> Plan:
    """The greedy random-shooting search of :func:`plan_footsteps` on given draws (pure).

    Everything that does not depend on the rollouts' stance feet (the command and course frame
    terms, the stones' clamp bounds, the layout tables, the buffers) is computed or allocated
    once before the step loop; a step computes each term in one op over both candidate groups
    (the stone layout for what depends on the point only, then the score layout: module
    docstring of :mod:`march.reference.search_inputs`); the chosen points, costs and stall
    flags are read after it. Points are (2, ...) x-y stacks (step_cost.XY).

    The numbers are those of :func:`march.reference.step_cost.score_steps` bit for bit: the
    same float ops on the same values, where a constraint a >= b is tested as -a > -b
    (violated) and the edge cost reads -clearance (negations are exact)."""
    tables = footholds if isinstance(footholds, PlanTables) else plan_tables(footholds, cfg)
    device, dtype = stance_xy.device, stance_xy.dtype
    e, r, n = stance_xy.shape[0], cfg.num_rollouts, cfg.num_steps
    st = tables.stones
    m = min(cfg.num_candidate_stones, st.shape[2])
    k, nt = cfg.samples_per_stone, cfg.num_durations
    q, f = 2 * nt + k, nt * m * (k + 2)
    lay = score_layout(cfg, m, device, dtype)
    frame = tables.course[FRAME].view(2, 4, e)  # [j]: (lat_j, axis_j, lat_j, axis_j)
    # Per env and step: nominal offsets (3), constraint signs (3), lands_left (1).
    sides = torch.where(stance_is_left[None, :, None], lay.sides[1, :, None], lay.sides[0, :, None])
    lands_left = sides[6] > 0.5  # (E, N)
    # The command along and across the course and the pace floor: (3, E) = (along, across,
    # floor), subtracted from the velocity rows (along, across, along) in one op.
    v_cmd = command[:, :2].T  # (2, E) world
    # One allocation for every buffer of the search (views below); under torch.compile each in
    # its own shape (a flat base's views, symbolic sizes, made the compile take tens of minutes).
    shapes = [(3, e), (_G_ROWS, e, r, m, q), (_W_ROWS, e, r, m, q), (_F_ROWS, e, r, f)]
    shapes.append((n * _F_PICK + 2, e, r))
    if torch.compiler.is_compiling():
        bufs = [torch.empty(shape, device=device, dtype=dtype) for shape in shapes]
    else:
        sizes = [math.prod(shape) for shape in shapes]
        flat = torch.empty(sum(sizes), device=device, dtype=dtype).split(sizes)
        bufs = [b.view(shape) for b, shape in zip(flat, shapes, strict=True)]
    cmd, gbuf, wbuf, fbuf, record = bufs
    into(cmd[0:2], torch.add, v_cmd[0] * frame[0, 1:3], v_cmd[1] * frame[1, 1:3])
    into(cmd[2], torch.mul, cmd[0].clamp(min=0.0), cfg.pace_fraction)
    floor = cmd[2]
    # -scale of pace_floor (the same product, negated: exact); times the goal test per step.
    neg_scale = ((-cfg.pace_cost) / floor.clamp(min=1e-6)) * (floor > 1e-6)
    # Nominal foothold offsets from the stance foot, (2, E, N, T): width offset + v_D dt.
    lat = tables.course[0:5:4]  # (2, E)
    nom_d = (
        sides[1][None, :, :, None] * lat[:, :, None, None] + v_cmd[:, :, None, None] * lay.durations
    )
    centers = st[CENTER_XY, :, None]  # (2, E, 1, S)
    halves = st[HALVES, :, None]
    start = tables.course[START].view(2, e, 1)
    direction = tables.course[DIR].view(2, e, 1)
    goal = tables.course[GOAL].view(e, 1)

    fbuf[_F_DT].copy_(lay.duration)
    # What each step chose, (N, 7, E, R) (the _F_PICK rows), then the summed (cost, violations)
    # of each rollout (2, E, R): the best rollout's are read in one gather.
    chosen_rows, total = record[:-2].view(n, _F_PICK, e, r), record[-2:]
    pos = gbuf[_G_XY]  # (2, E, R, M, Q)
    pos_a = pos[..., : 2 * nt].view(2, e, r, m, nt, 2)
    pos_b = pos[..., 2 * nt :]
    moved = gbuf.view(_G_ROWS, e, r, m * q)

    z0 = stance_z(tables, stance_xy)
    p = stance_xy.T[:, :, None].expand(2, e, r)  # the rollouts' stance feet
    pz = z0[:, None].expand(e, r)
    aheads = []
    for i in range(n):
        # Nominal foothold for each duration, (2, E, R, T): stance + width offset + v_D dt.
        nom = p[..., None] + nom_d[:, :, None, i]
        # The M stones whose rectangles are nearest to the middle duration's nominal foothold.
        d = ((nom[..., nt // 2, None] - centers).abs() - halves).clamp(min=0.0)
        d = d * d  # (2, E, R, S)
        near = (d[0] + d[1]).topk(m, dim=-1, largest=False).indices  # (E, R, M)
        rows = st.gather(2, near.view(1, e, r * m).expand(st.shape[0], -1, -1))
        rows = rows.view(-1, e, r, m, 1)
        center, half = rows[CENTER_XY], rows[HALF]  # (2, E, R, M, 1)
        # (a) the nominal foothold clamped into each stone (hard and soft margins), (M, T, 2);
        # (b) random points on each stone, (M, K): draws shared (2, R, M, K) or per env (2, E, ...)
        lower, upper = (
            rows[s].view(2, 2, e, r, m).permute(1, 2, 3, 4, 0)[:, :, :, :, None]
            for s in (LOWER, UPPER)
        )  # (2 axes, E, R, M, 1, 2 margins)
        into(pos_a, torch.clamp, nom[:, :, :, None, :, None], lower, upper)
        unit_i = unit[i] if unit.dim() == 6 else unit[i][:, None]
        into(pos_b, torch.add, center, unit_i * rows[SPREAD])
        gbuf[_G_Z].copy_(rows[CZ].expand(e, r, m, q))
        # What depends on the point only, (E, R, M, Q) per row.
        off = (pos - center).abs_().sub_(half)  # -(half - |xy - c|): minus the clearance
        into(wbuf[_W_NEGCLEAR], torch.maximum, off[0], off[1])
        step = pos - p.view(2, e, r, 1, 1)
        course = (step[0] * frame[0].view(4, e, 1, 1, 1)).add_(
            step[1] * frame[1].view(4, e, 1, 1, 1)
        )
        into(wbuf[_W_OWN], torch.mul, course[0:3], sides[3:6, :, i].view(3, e, 1, 1, 1))
        sq = step.mul_(step)
        into(wbuf[_W_SQ], torch.add, sq[0], sq[1])
        into(wbuf[_W_DZ], torch.sub, gbuf[_G_Z], pz.view(e, r, 1, 1)).abs_()
        # Feasible where every row is within its bound: a NaN fails (not x <= b), as in
        # score_steps's >= tests. The row holds ok - 1: 0.0 feasible, -1.0 infeasible.
        ok = (wbuf <= lay.limits).view(torch.uint8).amin(0)
        into(gbuf[_G_PEN], torch.add, ok, -1.0)
        edge = wbuf[_W_NEGCLEAR].add(cfg.edge_clearance).div_(cfg.edge_clearance).clamp_(0.0, 1.0)
        into(gbuf[_G_EDGE], torch.mul, edge.pow_(2), cfg.edge_cost)
        into(gbuf[_G_D], torch.sub, course[1:4], sides[0:3, :, i].view(3, e, 1, 1, 1))
        # The score layout (T, M, C): the velocity error, pace and time terms per duration.
        # (a gather with the index broadcast: index_select on the last dim is ~8x slower on CPU)
        into(fbuf[_F_MOVED], torch.gather, moved, -1, lay.index.expand(_G_ROWS, e, r, f))
        err = fbuf[_F_D].div(lay.duration).sub_(cmd.view(3, e, 1, 1))  # v - (cmd, floor)
        sq_err = err[0:2].pow_(2)
        c_vel = sq_err[0] + sq_err[1]
        if cfg.w_velocity != 1.0:  # (the paper's weight 1 is exact without the op)
            c_vel = c_vel.mul_(cfg.w_velocity)
        ahead = _ahead(p, start, direction, goal)  # (E, R): the progress term applies
        aheads.append(ahead)
        c_pace = err[2].clamp_(max=0.0).mul_((neg_scale[:, None] * ahead)[..., None])
        cost = c_vel.add_(fbuf[_F_EDGE]).add_(lay.c_time).add_(c_pace)
        # + infeasible_cost where infeasible: cost + (-c) * (ok - 1), exactly cost + 0 or + c
        into(fbuf[_F_COST], torch.add, cost, fbuf[_F_PEN], alpha=-cfg.infeasible_cost)
        pick = (fbuf[_F_COST] + noise[i]).argmin(-1, keepdim=True)  # (E, R, 1)
        into(
            chosen_rows[i, ..., None],
            torch.gather,
            fbuf[:_F_PICK],
            -1,
            pick.view(1, e, r, 1).expand(_F_PICK, e, r, 1),
        )  # (dt, cost, violated, x, y, z, advance) of the chosen candidate
        if i == 1:
            into(
                total,
                torch.add,
                chosen_rows[0, _F_COST : _F_PEN + 1],
                chosen_rows[1, _F_COST : _F_PEN + 1],
            )
        elif i > 1:
            total.add_(chosen_rows[i, _F_COST : _F_PEN + 1])
        p, pz = chosen_rows[i, _F_XY], chosen_rows[i, _F_Z]
    if n == 1:
        total.copy_(chosen_rows[0, _F_COST : _F_PEN + 1])

    # Stall flag: a chosen step falls short of the pace while the goal lies ahead.
    need = floor[:, None] * chosen_rows[:, _F_DT] - EPS
    stalled = (torch.stack(aheads) & (chosen_rows[:, _F_ALONG] < need)).any(0)
    # Best rollout: feasible ones first, then the lowest noise-free cost.
    feasible = total[1] == 0.0
    rank = torch.where(feasible, total[0], float("inf"))
    best = torch.where(feasible.any(-1, keepdim=True), rank, total[0]).argmin(-1, keepdim=True)
    won = record.gather(-1, best.view(1, e, 1).expand(record.shape[0], e, 1))[..., 0]
    total = won[-2:]  # (cost, violations) of the best rollout, (2, E)
    won = won[:-2].view(n, _F_PICK, e)  # its steps
    return Plan(
        footholds=won[:, _F_XY.start : _F_Z + 1].permute(2, 0, 1),
        durations=won[:, _F_DT].T,
        lands_left=lands_left,
        cost=total[0],
        feasible=total[1] == 0.0,
        start=torch.cat([stance_xy, z0[:, None]], dim=-1),
        stalled=stalled.gather(-1, best)[:, 0],
    )


def _ahead(p: XY, start: torch.Tensor, direction: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
    """(E, R) bool: the points ``p`` (2, E, R) lie before the goal platform along the course
    (:func:`march.reference.step_cost.goal_ahead`, the same ops on table rows)."""
    rel = (p - start) * direction
    return rel[0] + rel[1] < goal
