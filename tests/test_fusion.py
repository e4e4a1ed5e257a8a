"""compute.compile_math (march.fusion): compiled maths agrees with the eager path, and the op
counter sees a compiled call's kernels instead of losing them.

The agreement tests compile the planner search (~2-4 min on 2 CPU cores), the step reference,
the measured CLF outputs and the height scan: they are marked slow (``make test-all``)."""

from __future__ import annotations

import pytest
import torch

from march.bench.ops import OpCounter
from march.fusion import fused

torch.set_num_threads(1)


def _chain(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    a = x * 2.0 + y  # 2 ops
    b = a.sin() * a.cos()  # 3 ops
    return (b - x).abs().sum(-1) + torch.where(b > 0, a, b).amax(-1)  # 7 ops


def test_the_counter_counts_a_compiled_call_as_its_kernels():
    """12 eager ops; the same maths compiled is counted as the kernels it launches: at least one
    (a counter that lost compiled calls would count 0) and fewer than the eager ops."""
    g = torch.Generator().manual_seed(0)
    x, y = torch.randn(16, 40, generator=g), torch.randn(16, 40, generator=g)
    eager = OpCounter()
    with eager:
        want = _chain(x, y)
    assert eager.total == 12, dict(eager.counts)
    fn = fused(_chain)
    got = fn(x, y)  # compiles
    assert torch.allclose(got, want, atol=1e-5, rtol=0.0)
    compiled = OpCounter()
    with compiled:
        again = fn(x, y)
    assert torch.allclose(again, want, atol=1e-5, rtol=0.0)
    assert 1 <= compiled.total < eager.total, dict(compiled.counts)
    assert compiled.counts["fused_kernel"] >= 1
    # Config floats are graph constants: no per-call tensors built on the host.
    assert "lift_fresh" not in compiled.counts, dict(compiled.counts)


@pytest.mark.slow
def test_compiled_planner_makes_the_eager_plans():
    """plan_footsteps(compiled=True) equals the eager planner over random courses, stances,
    commands and batch sizes (one compile, dynamic batch): footholds within 1e-5 m, the same
    durations, feasibility and stall flags (measured: identical)."""
    from march.reference.planner import PlannerCfg, plan_footsteps
    from march.world.synthetic import synthetic_courses

    for seed, e in enumerate((12, 7, 30, 12)):
        g = torch.Generator().manual_seed(seed)
        fh = synthetic_courses(torch.rand(e, generator=g).tolist(), seed=seed)
        stance = torch.stack(
            [3.0 * torch.rand(e, generator=g) - 0.2, 0.3 * (torch.rand(e, generator=g) - 0.5)], -1
        )
        left = torch.rand(e, generator=g) > 0.5
        cmd = torch.zeros(e, 3)
        cmd[:, 0] = 0.2 + 0.7 * torch.rand(e, generator=g)
        plans = [
            plan_footsteps(
                stance, left, cmd, fh, PlannerCfg(), torch.Generator().manual_seed(seed), compiled=c
            )
            for c in (False, True)
        ]
        assert torch.allclose(plans[0].footholds, plans[1].footholds, atol=1e-5, rtol=0.0)
        assert torch.allclose(plans[0].cost, plans[1].cost, atol=1e-3, rtol=1e-5)
        for name in ("durations", "feasible", "stalled"):
            assert torch.equal(getattr(plans[0], name), getattr(plans[1], name)), name


@pytest.mark.slow
def test_compiled_outputs_and_height_scan_equal_the_eager_maths():
    """outputs_from_state and scan_heights compiled equal eager within 1e-5 on random states
    (quaternions, rotation matrices, stance masks; pelvis positions over random boxes)."""
    from march.env.clf_outputs import outputs_from_state
    from march.env.observations import scan_heights

    for e in (8, 21):
        g = torch.Generator().manual_seed(e)

        def r(*shape, g=g):
            return torch.rand(*shape, generator=g)

        quat = torch.nn.functional.normalize(r(e, 4) - 0.5, dim=-1)
        mat = torch.linalg.qr(r(e, 2, 3, 3) - 0.5)[0]
        mat = mat * torch.linalg.det(mat)[..., None, None].sign()  # proper rotations
        args = (
            r(e, 3),
            r(e, 30, 3),
            (r(1, 30), r(1, 1) + 30.0),
            quat,
            r(e, 3),
            (r(e, 2, 3), r(e, 2, 3), r(e, 2, 3), mat),
            r(e) > 0.5,
            (r(e, 29), r(e, 29), r(e, 29)),
            torch.arange(3, 17),
        )
        for got, want in zip(
            fused(outputs_from_state)(*args), outputs_from_state(*args), strict=True
        ):
            assert torch.allclose(got, want, atol=1e-5, rtol=0.0)
        # Height scan: 4 cells of 6 boxes, random pelvis poses among them.
        k, cells = 6, 4
        center = torch.cat([4.0 * r(cells, k, 2), 0.3 * r(cells, k, 1)], -1)
        half = 0.1 + 0.4 * r(cells, k, 2)
        valid = r(cells, k) > 0.2
        lo = (center[..., 0] - half[..., 0]).masked_fill(~valid, float("inf"))
        hi = (center[..., 0] + half[..., 0]).masked_fill(~valid, -float("inf"))
        extent = torch.stack([lo, hi], -1)
        packed = torch.cat([center, half, valid[..., None].float()], -1).reshape(-1, 6)
        base = torch.cat([4.0 * r(e, 2), 0.5 + 0.5 * r(e, 1)], -1)
        yaw = 6.28 * r(e)
        offsets = torch.stack(
            torch.meshgrid(
                torch.linspace(-0.8, 0.8, 17), torch.linspace(-0.5, 0.5, 11), indexing="ij"
            ),
            -1,
        )
        args = (
            base,
            yaw,
            torch.randint(0, 2, (e,), generator=g),
            torch.randint(0, 2, (e,), generator=g),
            2,
            (extent, packed, 4),
            offsets.reshape(-1, 2),
            5.0,
        )
        got, want = fused(scan_heights)(*args), scan_heights(*args)
        assert (want < 5.0).any() and (want == 5.0).any()  # both hits and misses are tested
        assert torch.allclose(got, want, atol=1e-5, rtol=0.0)


@pytest.mark.parametrize("fuse", [False, True])
def test_the_planner_search_traces_into_one_graph(fuse):
    """torch.compile of the planner's search must not fall apart: a graph break (dynamo refuses,
    e.g., an ``out=`` into a view) leaves the ops between breaks eager and ~480 launches per call
    instead of ~20. Traced with dynamo only (no inductor compile: seconds)."""
    import numpy as np
    import torch._dynamo as dynamo

    from march.reference import planner
    from march.reference.search_inputs import planner_draws
    from march.world.courses import CourseCfg, generate_course
    from march.world.footholds import footholds_from_layouts

    rng = np.random.default_rng(0)
    e = 6
    fh = footholds_from_layouts(
        [generate_course(float(d), CourseCfg(), rng) for d in np.linspace(0, 1, e)],
        np.zeros((e, 3)),
    )
    left = torch.arange(e) % 2 == 0
    cmd = torch.zeros(e, 3)
    cmd[:, 0] = 0.5
    cfg = planner.PlannerCfg(fuse_candidates=fuse)
    m = min(cfg.num_candidate_stones, fh.center.shape[1])
    unit, gumbel = planner_draws(cfg, m, torch.Generator().manual_seed(0), "cpu", torch.float32)
    with torch.no_grad():
        ex = dynamo.explain(planner._search)(fh.start_xy, left, cmd, fh, unit, gumbel, cfg)
    assert ex.graph_break_count == 0, [r.reason[:200] for r in ex.break_reasons]
    assert ex.graph_count == 1
