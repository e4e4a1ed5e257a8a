"""Footstep planner: safety of the footholds, optimality against a naive plan, infeasibility,
batching and determinism; progress: a planner-only walk over generated courses keeps pace."""

from dataclasses import replace

import numpy as np
import pytest
import torch
from synthetic import grid_course, make_footholds, straight_course

from march.config import EnvCfg
from march.reference.plan_tables import locate_on_stones
from march.reference.planner import PlannerCfg, evaluate_plan, plan_footsteps
from march.world.courses import CourseCfg, generate_course, hardware_course
from march.world.footholds import Footholds, footholds_from_layouts
from march.world.synthetic import synthetic_courses

torch.set_num_threads(1)
CFG = PlannerCfg()


def _plan(footholds, stance_xy, left, command, seed=0, cfg=CFG):
    gen = torch.Generator().manual_seed(seed)
    return plan_footsteps(stance_xy, left, command, footholds, cfg, gen)


def _forward(e, vx=0.6, vy=0.0):
    return torch.tensor([[vx, vy, 0.0]]).expand(e, 3).contiguous()


@pytest.fixture(scope="module")
def courses():
    """Synthetic courses at increasing difficulty, stance on the start platform (left foot)."""
    fh = synthetic_courses([0.0, 0.25, 0.5, 0.75, 1.0, 1.0], seed=3)
    stance = torch.tensor([[0.3, 0.125]]).expand(fh.num_envs, 2).contiguous()
    left = torch.ones(fh.num_envs, dtype=torch.bool)
    return fh, stance, left


def test_plan_shapes_and_alternation(courses):
    fh, stance, left = courses
    plan = _plan(fh, stance, left, _forward(fh.num_envs))
    e, n = fh.num_envs, CFG.num_steps
    assert plan.footholds.shape == (e, n, 3) and plan.durations.shape == (e, n)
    assert plan.cost.shape == (e,) and plan.feasible.shape == (e,)
    # Left stance -> the right foot lands first, then they alternate.
    assert plan.lands_left.tolist() == [[False, True, False, True]] * e
    grid = CFG.duration_grid()
    assert torch.isin(plan.durations, grid).all()


def test_every_foothold_on_a_stone_with_margin(courses):
    fh, stance, left = courses
    plan = _plan(fh, stance, left, _forward(fh.num_envs))
    assert plan.feasible.all()
    assert fh.contains(plan.footholds[..., :2], CFG.stone_margin).all()
    # z is the top of the stone under the foothold.
    d = (plan.footholds[:, :, None, :2] - fh.center[:, None, :, :2]).abs()
    on = (d <= fh.half_size[:, None]).all(-1) & fh.valid[:, None]
    z = (fh.center[:, None, :, 2] * on).sum(-1)
    torch.testing.assert_close(plan.footholds[..., 2], z)
    # Step bounds and lateral limits hold along the whole plan.
    steps = plan.steps()
    assert (steps[..., :2].norm(dim=-1) <= CFG.max_step + 1e-6).all()
    side = torch.where(plan.lands_left, 1.0, -1.0)
    assert (side * steps[..., 1] >= CFG.min_lateral - 1e-6).all()
    assert (side * steps[..., 1] <= CFG.max_lateral + 1e-6).all()


def test_plan_cost_matches_evaluation(courses):
    fh, stance, left = courses
    cmd = _forward(fh.num_envs)
    plan = _plan(fh, stance, left, cmd)
    cost, ok = evaluate_plan(
        stance, plan.footholds[..., :2], plan.durations, plan.lands_left, cmd, fh, CFG
    )
    torch.testing.assert_close(cost, plan.cost, atol=1e-4, rtol=1e-5)
    assert torch.equal(ok, plan.feasible)


def test_open_ground_tracks_the_command_exactly():
    """On one large platform the optimum is the nominal gait: l = v_D T_nom +/- width."""
    fh = make_footholds([[(0.0, 0.0, 0.1, 3.0, 3.0)]] * 2, [(0.0, 0.0)] * 2)
    stance = torch.tensor([[0.0, 0.125], [0.0, -0.125]])
    left = torch.tensor([True, False])
    cmd = torch.tensor([[0.5, 0.1, 0.0], [0.3, -0.1, 0.2]])
    plan = _plan(fh, stance, left, cmd)
    assert plan.feasible.all()
    assert plan.cost.max() < 1e-8
    torch.testing.assert_close(plan.durations, torch.full((2, 4), CFG.nominal_duration))
    steps = plan.steps()
    t = CFG.nominal_duration
    side = torch.where(plan.lands_left, 1.0, -1.0)
    torch.testing.assert_close(steps[..., 0], cmd[:, None, 0].expand(2, 4) * t)
    torch.testing.assert_close(steps[..., 1], cmd[:, None, 1] * t + side * CFG.step_width)
    torch.testing.assert_close(plan.footholds[..., 2], torch.full((2, 4), 0.1))


def _naive_plan(e, pitch, width, n):
    """Constant steps from a left stance at (0, w/2): right foot first."""
    k = torch.arange(1, n + 1, dtype=torch.float32)
    x = (k * pitch).expand(e, n)
    y = torch.where(k % 2 == 1, -0.5 * width, 0.5 * width).expand(e, n)
    return torch.stack([x, y], dim=-1), torch.full((e, n), CFG.nominal_duration)


def test_cost_no_worse_than_naive_constant_plan():
    vx = 0.5
    pitch, width, n = vx * CFG.nominal_duration, CFG.step_width, CFG.num_steps
    shifts = [
        [0.0] * 6,  # stones exactly under the naive plan: both are optimal (cost 0)
        [0.06, -0.06, 0.05, -0.05, 0.06, 0.0],  # naive footholds near stone edges
        [0.04, 0.04, 0.04, 0.04, 0.04, 0.04],
        [-0.06, 0.03, 0.0, 0.06, -0.02, 0.05],
    ]
    courses = [grid_course(6, pitch, width, 0.22, s) for s in shifts]
    fh = make_footholds(courses, [(0.0, 0.5 * width)] * len(courses))
    e = fh.num_envs
    stance = torch.tensor([[0.0, 0.5 * width]]).expand(e, 2).contiguous()
    left = torch.ones(e, dtype=torch.bool)
    cmd = _forward(e, vx)
    naive_xy, naive_t = _naive_plan(e, pitch, width, n)
    plan = _plan(fh, stance, left, cmd)
    naive_cost, naive_ok = evaluate_plan(stance, naive_xy, naive_t, plan.lands_left, cmd, fh, CFG)
    assert naive_ok.all(), "the naive plan must be feasible for this comparison"
    assert plan.feasible.all()
    assert (plan.cost <= naive_cost + 1e-5).all()
    assert float(plan.cost[0]) == pytest.approx(0.0, abs=1e-6)
    # Where the naive plan steps near edges, the planner finds a clearly better plan.
    assert (plan.cost[1:] < naive_cost[1:] - 1.0).all()


@pytest.mark.parametrize(("gap", "feasible"), [(1.0, False), (0.5, True)])
def test_gap_beyond_max_step_is_infeasible(gap, feasible):
    """Stance on a small stone (too small for both feet) before a gap: beyond the 0.85 m max
    step nothing is reachable; a 0.5 m gap is fine."""
    course = straight_course(4, stone_size=0.14, gap=gap, zigzag=0.06)
    fh = make_footholds([course], [(0.0, 0.0)])
    first = course[1]
    stance = torch.tensor([[first[0], first[1]]])
    plan = _plan(fh, stance, torch.tensor([True]), _forward(1))
    assert bool(plan.feasible[0]) is feasible
    if not feasible:
        assert float(plan.cost[0]) >= CFG.infeasible_cost


def test_batched_equals_per_env_loop(courses):
    fh, stance, left = courses
    left = torch.tensor([True, False, True, False, True, False])
    stance = stance.clone()
    stance[~left, 1] = -0.125
    cmd = torch.tensor(
        [[0.6, 0.0, 0.0], [0.4, 0.1, 0.1], [0.8, -0.1, 0.0], [0.5, 0.0, -0.2], [0.7, 0.05, 0.0]]
        + [[0.3, 0.0, 0.0]]
    )
    batched = _plan(fh, stance, left, cmd, seed=7)
    for i in range(fh.num_envs):
        idx = torch.tensor([i])
        single = _plan(fh.index(idx), stance[idx], left[idx], cmd[idx], seed=7)
        torch.testing.assert_close(single.footholds[0], batched.footholds[i], atol=1e-5, rtol=0)
        torch.testing.assert_close(single.durations[0], batched.durations[i])
        torch.testing.assert_close(single.cost[0], batched.cost[i], atol=1e-5, rtol=1e-6)
        assert bool(single.feasible[0]) == bool(batched.feasible[i])


def test_same_seed_same_plan(courses):
    fh, stance, left = courses
    cmd = _forward(fh.num_envs)
    a = _plan(fh, stance, left, cmd, seed=11)
    b = _plan(fh, stance, left, cmd, seed=11)
    assert torch.equal(a.footholds, b.footholds) and torch.equal(a.durations, b.durations)
    assert torch.equal(a.cost, b.cost)


def test_randomised_rollouts_never_lose_to_greedy(courses):
    """Rollout 0 is the plain greedy rollout, so more rollouts can only lower the cost."""
    fh, stance, left = courses
    cmd = _forward(fh.num_envs)
    greedy = _plan(fh, stance, left, cmd, cfg=PlannerCfg(num_rollouts=1))
    shooting = _plan(fh, stance, left, cmd)
    assert (shooting.cost <= greedy.cost + 1e-5).all()


# ---------------------------------------------------------------- progress (issue 10)

EPISODE_S = EnvCfg().episode_length_s
"""The training episode length [s] over which a walk must keep pace."""
LEVELS = [0.0, 0.2, 0.4, 0.6, 0.8, 1.0]
WALK_SEEDS = (0, 1, 2)
IN_PLACE_M = 0.05
"""A step advancing less than this along the course counts as a step in place [m]."""


def _walk_courses() -> tuple[Footholds, list[str]]:
    """Generated courses at every level for several terrain seeds, plus the hardware course."""
    ccfg = CourseCfg()
    layouts, names = [], []
    for seed in WALK_SEEDS:
        rng = np.random.default_rng(seed)
        for d in LEVELS:
            layouts.append(generate_course(d, ccfg, rng))
            names.append(f"difficulty {d:.1f} seed {seed}")
    layouts.append(hardware_course(ccfg))
    names.append("hardware")
    origins = np.stack([lay.origin for lay in layouts]) + np.array([[0.0, 0.0, 0.0]])
    return footholds_from_layouts(layouts, origins), names


def _reachable_ahead(fh: Footholds, stance: torch.Tensor, left: torch.Tensor) -> torch.Tensor:
    """(E,) bool, by brute force: some point on a stone (9 x 9 grid inside the hard margin) is a
    legal next step for the foot that lands (``left`` = the left foot lands) and advances at
    least IN_PLACE_M along the course."""
    g = torch.linspace(-1.0, 1.0, 9)
    gx, gy = torch.meshgrid(g, g, indexing="ij")
    usable = (fh.half_size - CFG.stone_margin).clamp(min=0.0)  # (E, S, 2)
    px = fh.center[..., 0:1] + gx.flatten() * usable[..., 0:1]  # (E, S, 81)
    py = fh.center[..., 1:2] + gy.flatten() * usable[..., 1:2]
    _, z0 = locate_on_stones(fh, stance)
    sx, sy = px - stance[:, 0, None, None], py - stance[:, 1, None, None]
    side = torch.where(left, 1.0, -1.0)[:, None, None]
    ok = (
        fh.valid[..., None]
        & (sx >= IN_PLACE_M)
        & (sx**2 + sy**2 <= CFG.max_step**2)
        & (side * sy >= CFG.min_lateral)
        & (side * sy <= CFG.max_lateral)
        & ((fh.center[..., 2:3] - z0[:, None, None]).abs() <= CFG.max_step_height)
    )
    return ok.flatten(1).any(-1)


def _walk(fh: Footholds, vx: float, seed: int = 0, cfg: PlannerCfg | None = None):
    """Receding-horizon walk with the planner alone: take each plan's first step as if the foot
    landed exactly there, replan from it, repeat (the feet alternate) until EPISODE_S is over.

    Returns (kept pace or reached the goal (E,), progress at the end (E,), in-place steps taken
    while the goal lay ahead and a stone was reachable (E,), steps taken (E,))."""
    e = fh.num_envs
    lat = torch.stack([-fh.direction[:, 1], fh.direction[:, 0]], dim=-1)
    stance = fh.start_xy + 0.5 * CFG.step_width * lat  # left foot at the spawn point
    left = torch.ones(e, dtype=torch.bool)
    cmd = torch.tensor([[vx, 0.0, 0.0]]).expand(e, 3).contiguous()
    t = torch.zeros(e)
    done = torch.zeros(e, dtype=torch.bool)
    reached = torch.zeros(e, dtype=torch.bool)
    bad_in_place = torch.zeros(e, dtype=torch.long)
    steps = torch.zeros(e, dtype=torch.long)
    while not done.all():
        plan = _plan(fh, stance, left, cmd, seed=seed + int(steps.max()), cfg=cfg or CFG)
        land = plan.footholds[:, 0, :2]
        done = done | (t + plan.durations[:, 0] > EPISODE_S)  # this step would end after time-out
        ahead = fh.progress(stance) < fh.goal_distance
        advance = ((land - stance) * fh.direction).sum(-1)
        lands_left = plan.lands_left[:, 0]
        stuck = (advance < IN_PLACE_M) & ahead & ~done
        if stuck.any():
            stuck &= _reachable_ahead(fh, stance, lands_left)
        bad_in_place += stuck.long()
        stance = torch.where(done[:, None], stance, land)
        left = torch.where(done, left, lands_left)
        t = torch.where(done, t, t + plan.durations[:, 0])
        steps += (~done).long()
        reached |= fh.progress(stance) >= fh.goal_distance
    progress = fh.progress(stance)
    kept = reached | (progress >= 0.8 * vx * EPISODE_S)
    return kept, progress, bad_in_place, steps


@pytest.fixture(scope="module")
def walk_courses():
    return _walk_courses()


@pytest.mark.parametrize("vx", [0.3, 0.55, 0.8])
def test_walk_keeps_pace_on_every_course(walk_courses, vx):
    """Command extremes and middle, every level, several terrain seeds and the hardware course:
    the planner-only walk keeps pace (>= 80% of v t in the episode) or reaches the goal, and it
    never steps in place while the goal lies ahead and a stone ahead is reachable."""
    fh, names = walk_courses
    kept, progress, bad_in_place, steps = _walk(fh, vx)
    lagging = [
        f"{n}: {float(p):.2f} m" for n, p, k in zip(names, progress, kept, strict=True) if not k
    ]
    assert not lagging, f"vx={vx}: fell behind {0.8 * vx * EPISODE_S:.1f} m on {lagging}"
    stuck = [f"{n}: {int(b)}" for n, b in zip(names, bad_in_place, strict=True) if b]
    assert not stuck, f"vx={vx}: stepped in place before a reachable stone on {stuck}"
    assert (steps > 5).all()


def test_paper_cost_alone_steps_in_place_before_a_far_stone():
    """Stance on a stone, the next stone 0.68 m ahead, v_D = 0.3 m/s. Paper cost: in place
    (0 - 0.3)^2 = 0.09 < onto the stone (0.68/0.7 - 0.3)^2 = 0.45, so it steps in place; with the
    progress term the in-place step pays pace_cost and the plan steps onto the stone."""
    # Stones 0.28 m long and 0.5 m wide: both feet fit side by side without edge cost.
    rects = [(0.0, 0.0, 0.0, 0.6, 0.6)]
    rects += [(0.8 + 0.68 * k, 0.0, 0.0, 0.14, 0.25) for k in range(5)]
    rects += [(0.8 + 0.68 * 4 + 0.8, 0.0, 0.0, 0.6, 0.6)]
    fh = make_footholds([rects, rects], [(0.0, 0.0)] * 2)
    stance = torch.tensor([[0.8, 0.125]] * 2)  # left foot on the first stone
    left = torch.ones(2, dtype=torch.bool)
    cmd = _forward(2, 0.3)
    paper = _plan(fh, stance, left, cmd, cfg=replace(CFG, pace_fraction=0.0))
    ours = _plan(fh, stance, left, cmd)
    assert float((paper.footholds[0, 0, 0] - 0.8).abs()) < IN_PLACE_M
    assert (ours.footholds[:, 0, 0] > 1.3).all()
    assert ((ours.steps()[..., 0]) > IN_PLACE_M).all()
    assert ours.feasible.all() and paper.feasible.all()
    assert not bool(ours.stalled[0])


def test_progress_term_hand_values():
    """evaluate_plan on open ground: a step of v dt costs 0; a step in place costs
    v^2 (velocity) + pace_cost (it misses all of rho v dt); a step of half of rho v dt costs
    (rho v / 2 - v)^2 + pace_cost / 2. Past the goal platform's start the term is off."""
    fh = make_footholds([[(1.0, 0.0, 0.0, 4.0, 3.0), (6.0, 0.0, 0.0, 1.0, 1.0)]], [(-2.0, 0.0)])
    v, t, rho = 0.4, CFG.nominal_duration, CFG.pace_fraction
    cmd = torch.tensor([[v, 0.0, 0.0]])
    start = torch.tensor([[0.0, 0.125]])

    def cost(advance: float, x0: float = 0.0) -> float:
        s = start + torch.tensor([[x0, 0.0]])
        feet = torch.tensor([[[x0 + advance, -0.125]]])
        c, ok = evaluate_plan(s, feet, torch.tensor([[t]]), torch.tensor([[False]]), cmd, fh, CFG)
        assert bool(ok[0])
        return float(c[0])

    assert cost(v * t) == pytest.approx(0.0, abs=1e-6)
    assert cost(0.0) == pytest.approx(v**2 + CFG.pace_cost, rel=1e-5)
    half = 0.5 * rho * v * t
    assert cost(half) == pytest.approx((half / t - v) ** 2 + 0.5 * CFG.pace_cost, rel=1e-5)
    # The goal platform begins at x = 5 (goal_distance 7 m from start_xy (-2, 0)): from a stance
    # on it (x = 5.5) a step in place pays the velocity term only.
    assert float(fh.goal_distance[0]) == pytest.approx(7.0)
    assert cost(0.0, x0=5.5) == pytest.approx(v**2, rel=1e-5)
    assert cost(0.0, x0=4.5) == pytest.approx(v**2 + CFG.pace_cost, rel=1e-5)


def test_short_of_pace_steps_as_far_as_it_can_and_flags_a_stall():
    """One stone 0.2-0.4 m ahead, then nothing within a step before the goal 3 m on: the plan
    steps onto the stone rather than in place, and raises the stall flag (its later steps cannot
    keep pace). On open ground nothing stalls."""
    rects = [(0.0, 0.0, 0.0, 0.2, 0.4), (0.4, -0.1, 0.0, 0.1, 0.15), (3.5, 0.0, 0.0, 0.6, 0.6)]
    fh = make_footholds([rects], [(0.0, 0.0)])
    stance = torch.tensor([[0.1, 0.05]])
    plan = _plan(fh, stance, torch.tensor([True]), _forward(1, 0.8))
    assert float(plan.footholds[0, 0, 0]) > 0.3
    assert bool(plan.stalled[0])
    open_ground = make_footholds([[(0.0, 0.0, 0.0, 3.0, 3.0)]], [(-2.0, 0.0)])
    plan = _plan(open_ground, torch.tensor([[0.0, 0.125]]), torch.tensor([True]), _forward(1))
    assert not bool(plan.stalled[0])


def _plain_search(stance_xy, stance_is_left, command, fh, cfg, generator):
    """The search of march.reference.planner written the plain way: per step and rollout, the
    candidates listed in the score order (duration, stone, [hard clamp, soft clamp, K random
    points]) and scored by step_cost.score_steps against locate-on-the-stone clearances, on the
    planner's own draws. The planner's fused layouts must give the same floats, bit for bit."""
    from march.reference.plan_tables import course_frame
    from march.reference.planner_cfg import EPS
    from march.reference.search_inputs import planner_draws
    from march.reference.step_cost import goal_ahead, pace_terms, score_steps, step_terms

    e, r, n = stance_xy.shape[0], cfg.num_rollouts, cfg.num_steps
    m = min(cfg.num_candidate_stones, fh.center.shape[1])
    k, nt = cfg.samples_per_stone, cfg.num_durations
    unit, noise = planner_draws(cfg, m, generator, stance_xy.device, stance_xy.dtype)
    dur = cfg.duration_grid()
    axis, lat = course_frame(fh)
    _, z0 = locate_on_stones(fh, stance_xy)
    lands = torch.stack([~stance_is_left if i % 2 == 0 else stance_is_left for i in range(n)], 1)
    half = fh.half_size.movedim(-1, 0)  # (2, E, S)
    hard = half - cfg.stone_margin - EPS
    usable = fh.valid & (hard >= 0.0).all(0)
    hard, soft = hard.clamp(min=0.0), (half - cfg.stone_margin - cfg.edge_clearance).clamp(min=0.0)
    halves = torch.where(fh.valid, half, float("-inf"))
    clear_half = torch.where(usable, half, float("-inf"))
    cxy = fh.center[..., :2].movedim(-1, 0)  # (2, E, S)
    p = stance_xy.T[:, :, None].expand(2, e, r).clone()
    pz = z0[:, None].expand(e, r).clone()
    total = torch.zeros(e, r)
    feasible = torch.ones(e, r, dtype=torch.bool)
    stalled = torch.zeros(e, r, dtype=torch.bool)
    path = torch.zeros(e, r, n, 3)
    t_of = torch.zeros(e, r, n, dtype=torch.long)
    for i in range(n):
        # per env and rollout: (2, E, R, T) nominal footholds, the M nearest stones
        side = lands[:, i].float() * 2.0 - 1.0  # +1 where the left foot lands
        offset = side * cfg.step_width
        nom_d = (offset[:, None] * lat.T[:, :, None])[..., None] + command[:, :2].T[
            ..., None, None
        ] * dur
        nom = p[..., None] + nom_d  # (2, E, R, T): stance + (width offset + v_D dt)
        mid = nom[..., nt // 2]  # (2, E, R)
        d = ((mid[..., None] - cxy[:, :, None]).abs() - halves[:, :, None]).clamp(min=0.0)
        near = (d[0] * d[0] + d[1] * d[1]).topk(m, dim=-1, largest=False).indices  # (E, R, M)

        def pick(t, near=near):  # (2, E, R, M) rows of the nearest stones
            return t[:, torch.arange(e)[:, None, None], near]

        c, h, ch = pick(cxy), pick(hard), pick(clear_half)
        s_ = pick(soft)
        z = fh.center[..., 2][torch.arange(e)[:, None, None], near]  # (E, R, M)
        # candidates (2, E, R, T, M, C) in the score order
        nomx = nom[:, :, :, :, None]  # (2, E, R, T, 1)
        cand_a = [
            torch.minimum(torch.maximum(nomx, (c - ext)[:, :, :, None]), (c + ext)[:, :, :, None])
            for ext in (h, s_)
        ]
        pts = unit[i][:, None] * h[..., None] + c[..., None]  # (2, E, R, M, K)
        cand_b = pts[:, :, :, None].expand(2, e, r, nt, m, k)
        cand = torch.cat([cand_a[0][..., None], cand_a[1][..., None], cand_b], dim=-1)
        off = (cand - c[:, :, :, None, :, None]).abs()
        inside = ch[:, :, :, None, :, None] - off
        clearance = torch.minimum(inside[0], inside[1])
        height = (z[:, :, None, :, None] - pz[:, :, None, None, None]).abs() <= cfg.max_step_height
        frame = [a.T.reshape(2, e, 1, 1, 1, 1) for a in (axis, lat)]
        v_cmd = command[:, :2].T.reshape(2, e, 1, 1, 1, 1)
        terms = step_terms(
            dur.view(1, 1, nt, 1, 1), lands[:, i].view(e, 1, 1, 1, 1), v_cmd, *frame, cfg
        )
        ahead = goal_ahead(fh, p).view(e, r, 1, 1, 1)
        pace = pace_terms(terms.cmd[0], ahead, cfg)
        prev = p.view(2, e, r, 1, 1, 1)
        cost, ok = score_steps(prev, cand, clearance, height, terms, pace, cfg)
        flat = cost.reshape(e, r, -1)
        choice = (flat + noise[i]).argmin(-1)  # (E, R)
        t_idx = choice // (m * (k + 2))
        m_idx = (choice // (k + 2)) % m
        ok = ok.expand_as(cost).reshape(e, r, -1).gather(-1, choice[..., None])[..., 0]
        new = cand.reshape(2, e, r, -1).gather(-1, choice.expand(2, e, r)[..., None])[..., 0]
        advance = ((new - p) * axis.T[:, :, None]).unbind(0)
        need = cfg.pace_fraction * terms.cmd[0].reshape(e, 1).clamp(min=0.0) * dur[t_idx] - EPS
        stalled |= goal_ahead(fh, p) & (advance[0] + advance[1] < need)
        total = (
            total + flat.gather(-1, choice[..., None])[..., 0]
            if i
            else flat.gather(-1, choice[..., None])[..., 0]
        )
        feasible &= ok
        p = new
        pz = z.gather(-1, m_idx[..., None])[..., 0]
        path[:, :, i] = torch.stack([p[0], p[1], pz], -1)
        t_of[:, :, i] = t_idx
    rank = total.masked_fill(~feasible, float("inf"))
    best = torch.where(feasible.any(-1), rank.argmin(-1), total.argmin(-1))
    env = torch.arange(e)
    return {
        "footholds": path[env, best],
        "durations": dur[t_of[env, best]],
        "cost": total[env, best],
        "feasible": feasible[env, best],
        "stalled": stalled[env, best],
    }


def test_the_search_equals_the_plain_search_bit_for_bit():
    """The planner's fused layouts (issue 41: one pass per term over both candidate groups, the
    constraints as rows tested at once, one gather per choice) compute every float as the plain
    per-candidate search does (_plain_search): torch.equal on every plan field over random
    courses (rotated too), stances, commands, batch sizes and cfg variants."""
    for seed in range(8):
        g = torch.Generator().manual_seed(seed)
        e = (12, 5, 20, 1)[seed % 4]
        fh = synthetic_courses(torch.rand(e, generator=g).tolist(), seed=seed)
        if seed % 2:
            ang = (torch.rand(e, generator=g) - 0.5) * 5.0
            fh.direction = torch.stack([torch.cos(ang), torch.sin(ang)], -1) * 1.5
        stance = torch.stack(
            [3.0 * torch.rand(e, generator=g) - 0.2, 0.3 * (torch.rand(e, generator=g) - 0.5)], -1
        )
        left = torch.rand(e, generator=g) > 0.5
        cmd = torch.zeros(e, 3)
        cmd[:, 0] = -0.2 + 1.1 * torch.rand(e, generator=g)
        cmd[:, 1] = 0.2 * (torch.rand(e, generator=g) - 0.5)
        cfg = PlannerCfg()
        if seed % 3 == 2:
            cfg = replace(cfg, w_velocity=1.5, num_rollouts=5, samples_per_stone=3, num_durations=4)
        got = _plan(fh, stance, left, cmd, seed=seed, cfg=cfg)
        want = _plain_search(stance, left, cmd, fh, cfg, torch.Generator().manual_seed(seed))
        for name, value in want.items():
            assert torch.equal(getattr(got, name), value), (seed, name)


def test_the_cpu_planner_runs_on_one_thread_and_restores_the_count(courses, monkeypatch):
    """On CPU plan_footsteps runs the draws and the search on one thread (its ops pass torch's
    intra-op grain size; OpenMP regions stall on a busy machine) and gives the thread count
    back; the plans are those of a one-thread process."""
    from march.reference import planner

    fh, stance, left = courses
    seen = []
    search = planner._search

    def recording(*args):
        seen.append(torch.get_num_threads())
        return search(*args)

    one = _plan(fh, stance, left, _forward(fh.num_envs))
    monkeypatch.setattr(planner, "_search", recording)
    torch.set_num_threads(2)
    try:
        two = _plan(fh, stance, left, _forward(fh.num_envs))
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(1)
    assert seen == [1]
    for name in ("footholds", "durations", "cost", "feasible", "stalled"):
        assert torch.equal(getattr(one, name), getattr(two, name)), name
