"""Stepping-stone courses: layout ranges, pairs, hardware course, and the compiled terrain."""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch

from march.world.courses import (
    ROLE_GOAL,
    ROLE_PAIR,
    ROLE_START,
    ROLE_STONE,
    CourseCfg,
    difficulty_ranges,
    flat_course,
    generate_course,
    hardware_course,
)
from march.world.footholds import FootholdTable, footholds_from_layouts

torch.set_num_threads(1)
os.environ.setdefault(
    "WARP_CACHE_PATH", os.path.join(os.path.dirname(__file__), "..", ".warp_cache")
)

CFG = CourseCfg()
DIFFICULTIES = np.linspace(0.0, 1.0, 6)
EPS = 1e-9


def _courses(d: float, n: int = 40, seed: int = 0):
    rng = np.random.default_rng(seed)
    return [generate_course(d, CFG, rng) for _ in range(n)]


def test_difficulty_ranges_interpolate_easy_to_hard():
    r0, r1 = difficulty_ranges(0.0, CFG), difficulty_ranges(1.0, CFG)
    assert r0.stone_size == pytest.approx((0.45, 0.50))
    assert r1.stone_size == pytest.approx((0.25, 0.30))
    assert r0.gap == pytest.approx((0.10, 0.15))
    assert r1.gap == pytest.approx((0.35, 0.45))
    assert (r0.height, r1.height) == pytest.approx((0.0, 0.10))
    assert r1.lateral == pytest.approx((0.10, 0.21))
    mid = difficulty_ranges(0.5, CFG)
    assert mid.stone_size == pytest.approx((0.35, 0.40))
    assert mid.gap == pytest.approx((0.225, 0.30))


@pytest.mark.parametrize("d", DIFFICULTIES)
def test_every_box_inside_the_sub_terrain(d):
    for lay in _courses(d):
        lo = lay.center[:, :2] - lay.half_size
        hi = lay.center[:, :2] + lay.half_size
        assert lo.min() >= -EPS
        assert (hi[:, 0] <= CFG.size[0] + EPS).all() and (hi[:, 1] <= CFG.size[1] + EPS).all()
        assert (lay.top > lay.bottom).all()
        assert lay.bottom == pytest.approx(-1.0)
        assert lay.role[0] == ROLE_START and lay.role[-1] == ROLE_GOAL
        assert lay.center[0, 2] == 0.0 and lay.center[-1, 2] == 0.0
        assert lay.origin == pytest.approx([1.0, 2.0, 0.0])
        assert lay.course_length == pytest.approx(10.75)
        assert lay.goal_distance >= 0.75 + 2.0


@pytest.mark.parametrize("d", DIFFICULTIES)
def test_sizes_gaps_heights_lateral_within_the_level_ranges(d):
    r = difficulty_ranges(d, CFG)
    y_mid = 0.5 * CFG.size[1]
    for lay in _courses(d):
        stones = (lay.role == ROLE_STONE) | (lay.role == ROLE_PAIR)
        size = 2.0 * lay.half_size[stones]
        assert size.min() >= r.stone_size[0] - EPS and size.max() <= r.stone_size[1] + EPS
        gaps = lay.gaps()
        assert len(gaps) == lay.num_steps + 1
        assert gaps.min() >= r.gap[0] - EPS and gaps.max() <= r.gap[1] + EPS
        assert np.abs(lay.top[stones]).max() <= r.height + EPS
        single = lay.role == ROLE_STONE
        off = np.abs(lay.center[single, 1] - y_mid)
        assert off.min() >= r.lateral[0] - EPS and off.max() <= r.lateral[1] + EPS
        # The goal platform absorbs what is left: < one gap + stone + maximal gap beyond minimum.
        goal_len = 2.0 * lay.half_size[-1, 0]
        slack = 2 * r.gap[1] - r.gap[0] + r.stone_size[1]
        assert CFG.goal_length - EPS <= goal_len <= CFG.goal_length + slack
        assert 10 <= lay.num_steps <= 16


def test_zigzag_alternates_sides_at_the_hardest_level():
    y_mid = 0.5 * CFG.size[1]
    for lay in _courses(1.0, n=20, seed=1):
        side = {
            int(s): np.sign(lay.center[lay.step == s, 1][0] - y_mid)
            for s in np.unique(lay.step[lay.role == ROLE_STONE])
        }
        steps = sorted(side)
        for a, b in zip(steps[:-1], steps[1:], strict=True):
            # Consecutive steps alternate sides (a pair in between counts as one toggle).
            assert side[a] * side[b] == (-1.0) ** (b - a)


def test_pairs_appear_near_the_configured_rate():
    steps = pairs = 0
    for lay in _courses(0.5, n=300, seed=2):
        steps += lay.num_steps
        pairs += lay.num_pairs
        for s in np.unique(lay.step[lay.role == ROLE_PAIR]):
            a, b = np.flatnonzero(lay.step == s)
            assert lay.center[a, 0] == lay.center[b, 0]  # side by side: same x extent
            assert lay.half_size[a, 0] == lay.half_size[b, 0]
            lateral_gap = abs(lay.center[a, 1] - lay.center[b, 1]) - (
                lay.half_size[a, 1] + lay.half_size[b, 1]
            )
            assert CFG.pair_gap[0] - EPS <= lateral_gap <= CFG.pair_gap[1] + EPS
    rate = pairs / steps
    assert steps > 3000
    assert abs(rate - CFG.pair_prob) < 0.03, rate


def test_pair_probability_zero_gives_no_pairs():
    cfg = CourseCfg(pair_prob=0.0)
    rng = np.random.default_rng(0)
    assert sum(generate_course(0.7, cfg, rng).num_pairs for _ in range(50)) == 0


def test_hardware_course_has_four_stones_alternating_sides():
    lay = hardware_course(CFG)
    assert list(lay.role) == [ROLE_START] + [ROLE_STONE] * 4 + [ROLE_GOAL]
    y = lay.center[1:5, 1] - 0.5 * CFG.size[1]
    assert y == pytest.approx([0.12, -0.12, 0.12, -0.12])
    assert np.all(np.sign(y[:-1]) != np.sign(y[1:]))
    assert lay.gaps() == pytest.approx([0.25, 0.30, 0.25, 0.30, 0.25])
    assert 2.0 * lay.half_size[1:5] == pytest.approx(np.full((4, 2), 0.30))
    assert lay.top == pytest.approx(np.zeros(6))
    assert lay.goal_distance == pytest.approx(0.75 + 1.35 + 1.2)


def test_flat_course_is_one_platform_with_a_stone_course_goal():
    lay = flat_course(CFG)
    assert lay.num_boxes == 1
    assert 2.0 * lay.half_size[0] == pytest.approx(CFG.size)
    assert lay.goal_distance == pytest.approx(10.75 - 1.5)
    assert lay.course_length == pytest.approx(10.75)


def test_footholds_from_layouts_world_frame_and_padding():
    lays = [hardware_course(CFG), generate_course(1.0, CFG, np.random.default_rng(0))]
    origins = torch.tensor([[10.0, -3.0, 0.0], [-5.0, 4.0, 0.0]])
    fh = footholds_from_layouts(lays, origins)
    s = max(lay.num_boxes for lay in lays)
    assert fh.center.shape == (2, s, 3) and fh.half_size.shape == (2, s, 2)
    assert fh.valid.sum(1).tolist() == [6, lays[1].num_boxes]
    expect = torch.tensor(lays[0].center - lays[0].origin, dtype=torch.float32) + origins[0]
    assert torch.allclose(fh.center[0, :6], expect)
    assert fh.start_xy.tolist() == [[10.0, -3.0], [-5.0, 4.0]]
    assert fh.direction.tolist() == [[1.0, 0.0], [1.0, 0.0]]
    # A point on the first hardware stone is a foothold, the gap before it is not.
    stone = fh.center[0, 1, :2]
    gap = torch.tensor([fh.center[0, 0, 0] + 0.75 + 0.1, fh.center[0, 0, 1]])
    pts = torch.stack([stone, gap])[None].expand(2, 2, 2).clone()
    pts[1] = pts[0] - origins[0, :2] + origins[1, :2]
    inside = fh.contains(pts)
    assert inside[0].tolist() == [True, False]
    assert fh.goal_distance[0].item() == pytest.approx(lays[0].goal_distance)
    assert fh.progress(fh.start_xy + torch.tensor([100.0, 0.0])).tolist() == pytest.approx(
        [lays[0].course_length, lays[1].course_length]
    )


def test_table_for_envs_indexes_levels_and_types():
    rng = np.random.default_rng(0)
    grid = [[generate_course(r / 2, CFG, rng) for _ in range(3)] for r in range(3)]
    origins = torch.randn(3, 3, 3)
    table = FootholdTable.from_layouts(grid, origins)
    levels, types = torch.tensor([0, 2, 1, 2]), torch.tensor([1, 0, 2, 2])
    fh = table.for_envs(levels, types, origins[levels, types])
    for e in range(4):
        lay = grid[int(levels[e])][int(types[e])]
        n = lay.num_boxes
        want = (
            torch.tensor(lay.center - lay.origin, dtype=torch.float32)
            + origins[levels[e], types[e]]
        )
        assert torch.allclose(fh.center[e, :n], want, atol=1e-6)
        assert int(fh.valid[e].sum()) == n
        assert fh.course_length[e].item() == pytest.approx(lay.course_length)


# --- through mjlab's TerrainGenerator ---------------------------------------------------------


def _compile(gen_cfg):
    import mujoco
    from mjlab.terrains import TerrainGenerator

    gen = TerrainGenerator(gen_cfg)
    spec = mujoco.MjSpec()
    gen.compile(spec)
    return gen, spec.compile()


def test_foothold_table_matches_compiled_terrain_geoms():
    import copy

    from march.env.stone_terrain import foothold_table, max_model_mismatch, terrain_generator_cfg

    gen_cfg = terrain_generator_cfg("stones", num_rows=4, num_cols=3, seed=7)
    table = foothold_table(gen_cfg)  # regenerated on a scratch spec
    gen, model = _compile(copy.deepcopy(gen_cfg))  # what the env would compile
    assert table.shape[:2] == (4, 3)
    assert torch.allclose(table.origins, torch.as_tensor(gen.terrain_origins, dtype=torch.float32))
    assert table.difficulty[:, 0].tolist() == pytest.approx([0.0, 1 / 3, 2 / 3, 1.0])
    world = table.world_center().numpy()
    n_checked = 0
    for r in range(4):
        for c in range(3):
            lay = table.layouts[r][c]
            for k in np.flatnonzero(table.valid[r, c].numpy()):
                g = model.geom(f"{lay.name}_{k:02d}")
                assert model.geom_type[g.id] == 6  # mjGEOM_BOX
                top = g.pos + np.array([0.0, 0.0, g.size[2]])
                assert top == pytest.approx(world[r, c, k], abs=1e-4)
                assert g.size[:2] == pytest.approx(table.half_size[r, c, k].numpy(), abs=1e-6)
                assert g.pos[2] - g.size[2] == pytest.approx(-CFG.pit_depth, abs=1e-6)
                n_checked += 1
            # Spawn origin on the start platform, at its top.
            start = world[r, c, 0]
            assert start == pytest.approx(gen.terrain_origins[r, c], abs=1e-4)
    assert n_checked == int(table.valid.sum()) > 4 * 3 * 12
    assert max_model_mismatch(table, model) < 1e-4
    # Each level's stones lie in that level's size range.
    for r in range(4):
        lo, hi = difficulty_ranges(r / 3, CFG).stone_size
        sizes = np.concatenate([2 * table.layouts[r][c].half_size[1:-1] for c in range(3)])
        assert lo - 1e-6 <= sizes.min() and sizes.max() <= hi + 1e-6


def test_foothold_table_is_deterministic_and_flat_first_levels():
    from march.env.stone_terrain import foothold_table, terrain_generator_cfg

    a = foothold_table(terrain_generator_cfg("stones", num_rows=3, num_cols=2, seed=1))
    b = foothold_table(terrain_generator_cfg("stones", num_rows=3, num_cols=2, seed=1))
    c = foothold_table(terrain_generator_cfg("stones", num_rows=3, num_cols=2, seed=2))
    assert torch.equal(a.center, b.center) and torch.equal(a.valid, b.valid)
    assert not (a.center.shape == c.center.shape and torch.equal(a.center, c.center))

    ff = foothold_table(
        terrain_generator_cfg("flat_first", num_rows=5, num_cols=2, seed=0, flat_levels=2)
    )
    n_boxes = ff.valid.sum(-1)
    assert n_boxes[:2].tolist() == [[1, 1], [1, 1]]  # levels 0, 1: flat ground
    assert (n_boxes[2:] > 10).all()  # levels 2..4: stones at difficulty 0, 0.5, 1
    lay = ff.layouts[2][0]
    assert 2 * lay.half_size[1:-1].min() >= 0.45 - 1e-6  # easiest stones

    hw = foothold_table(terrain_generator_cfg("hardware"))
    assert hw.shape == (1, 1, 6)


def test_terrain_entity_envs_get_their_cells_footholds_after_level_changes():
    from mjlab.terrains import TerrainEntity

    from march.env.stone_terrain import (
        max_model_mismatch,
        terrain_entity_cfg,
        terrain_foothold_table,
    )

    cfg = terrain_entity_cfg("stones", num_rows=4, num_cols=3, seed=5, max_init_terrain_level=None)
    cfg.num_envs = 16
    terrain = TerrainEntity(cfg, device="cpu")
    table = terrain_foothold_table(terrain)
    assert max_model_mismatch(table, terrain.spec.compile()) < 1e-4
    for _ in range(2):  # before and after a curriculum move
        lv, ty = terrain.terrain_levels, terrain.terrain_types
        fh = table.for_envs(lv, ty, terrain.env_origins)
        assert torch.allclose(fh.center[:, 0], terrain.env_origins, atol=1e-5)  # on the start
        want = table.world_center()[lv, ty]
        assert torch.allclose(fh.center, want, atol=1e-5)
        assert fh.valid.sum(1).tolist() == table.valid[lv, ty].sum(1).tolist()
        up = torch.ones(16, dtype=torch.bool)
        terrain.update_env_origins(torch.arange(16), up, ~up)


@pytest.mark.parametrize(
    "cfg",
    [
        CFG,
        CourseCfg(size=(6.0, 4.0)),
        CourseCfg(size=(3.5, 4.0), start_length=1.0, goal_length=1.0),
        CourseCfg(size=(3.0, 4.0), start_length=1.0, goal_length=1.2),  # no stone ever fits
        CourseCfg(max_stones=2),  # the stone cap binds
        CourseCfg(gap_easy=(0.5, 0.6), gap_hard=(0.2, 0.3)),  # the easy gaps are the larger
    ],
)
def test_goal_distance_max_bounds_every_generated_course(cfg):
    # Hand value for the default 12 m cell: goal platform from 12 - 0.25 - 1.5 = 10.25 at the
    # latest, spawn at 0.25 + 0.75 = 1.0.
    if cfg is CFG:
        assert CFG.goal_distance_max == pytest.approx(9.25)
    worst = 0.0
    for seed in range(4):
        rng = np.random.default_rng(seed)
        for d in DIFFICULTIES:
            for _ in range(25):
                lay = generate_course(float(d), cfg, rng)
                assert lay.goal_distance <= cfg.goal_distance_max + 1e-9
                assert lay.origin[0] == pytest.approx(cfg.spawn_x)
                worst = max(worst, lay.goal_distance)
    largest_gap = max(cfg.gap_easy[1], cfg.gap_hard[1])
    if cfg.max_stones >= 20:  # tight unless the stone cap binds: within one largest gap
        assert worst >= cfg.goal_distance_max - largest_gap - 1e-9
    goal_x0_latest = cfg.size[0] - cfg.end_margin - cfg.goal_length
    if goal_x0_latest >= cfg.end_margin + cfg.start_length + largest_gap:
        assert flat_course(cfg).goal_distance == pytest.approx(cfg.goal_distance_max)
