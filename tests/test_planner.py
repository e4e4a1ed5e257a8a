"""Footstep planner: safety of the footholds, optimality against a naive plan, infeasibility,
batching and determinism."""

import pytest
import torch
from synthetic import grid_course, make_footholds, straight_course

from march.bench_planner import synthetic_courses
from march.planner import PlannerCfg, evaluate_plan, plan_footsteps

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
