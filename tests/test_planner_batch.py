"""Plans that do not depend on the batch (issue 55): a course walked alone and among 29 others,
with the planner's draws keyed per course (march.keyed_random), gives the same plan, step for
step; the stone padding of the batch shapes nothing."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from march.keyed_random import RowStreams, row_keys
from march.reference.planner import PlannerCfg, plan_footsteps
from march.reference.walk import walk_course
from march.world.courses import CourseCfg, generate_course, hardware_course
from march.world.footholds import footholds_from_layouts

torch.set_num_threads(1)
SEED = 11


def _courses():
    """30 generated courses at every difficulty (the hardware course among them: 6 stones, fewer
    than the planner's 8 searched, so the batch pads it more than any other)."""
    ccfg = CourseCfg()
    rng = np.random.default_rng(5)
    layouts = [generate_course(d, ccfg, rng) for d in np.linspace(0.0, 1.0, 29)]
    layouts.insert(7, hardware_course(ccfg))
    origins = np.stack([lay.origin for lay in layouts])
    return layouts, origins


def _command(e: int) -> torch.Tensor:
    return torch.tensor([[0.5, 0.0, 0.0]]).expand(e, 3).contiguous()


def test_a_course_walks_the_same_alone_and_in_a_batch_of_30():
    layouts, origins = _courses()
    batch = footholds_from_layouts(layouts, origins)
    keys = torch.arange(len(layouts))
    together, com_together = walk_course(
        batch, _command(len(layouts)), max_steps=12, seed=SEED, keys=keys
    )
    for i in (0, 7, 18, 29):
        alone_fh = footholds_from_layouts([layouts[i]], origins[i : i + 1])
        assert alone_fh.center.shape[1] <= batch.center.shape[1]
        alone, com_alone = walk_course(
            alone_fh, _command(1), max_steps=12, seed=SEED, keys=keys[i : i + 1]
        )
        same = torch.equal(
            alone.footholds[0].nan_to_num(9.0), together.footholds[i].nan_to_num(9.0)
        )
        assert same, i
        assert torch.equal(
            alone.durations[0].nan_to_num(9.0), together.durations[i].nan_to_num(9.0)
        )
        assert torch.equal(com_alone[0].nan_to_num(9.0), com_together[i].nan_to_num(9.0))
    assert torch.isfinite(together.footholds[:, :3]).all()  # every course walked some steps


@pytest.mark.parametrize("searched", [8, 20])
def test_a_plan_is_the_same_alone_and_in_a_batch_whatever_the_row(searched):
    """One plan of each course, keyed by course: alone (its own stone count), in the batch, and
    in the batch reversed (another row, another padding neighbour). With 20 searched stones
    every course alone has fewer stones than the batch's padded 20 (13-20 each)."""
    layouts, origins = _courses()
    e = len(layouts)
    batch = footholds_from_layouts(layouts, origins)
    stance = batch.start_xy + torch.tensor([0.3, 0.125])
    left = torch.ones(e, dtype=torch.bool)
    cfg = PlannerCfg(num_candidate_stones=searched)

    def plan(fh, rows):
        streams = RowStreams(len(rows), "cpu")
        streams.keys.copy_(row_keys(SEED, rows))
        return plan_footsteps(
            stance[rows],
            left[rows],
            _command(len(rows)),
            fh,
            cfg,
            row_uniform=lambda shape: streams.uniform(None, shape),
        )

    rows = torch.arange(e)
    together = plan(batch, rows)
    flipped = plan(batch.index(rows.flip(0)), rows.flip(0))
    assert torch.equal(together.footholds, flipped.footholds.flip(0))
    for i in range(e):
        alone = plan(footholds_from_layouts([layouts[i]], origins[i : i + 1]), rows[i : i + 1])
        assert torch.equal(alone.footholds[0], together.footholds[i]), i
        assert torch.equal(alone.durations[0], together.durations[i]), i
