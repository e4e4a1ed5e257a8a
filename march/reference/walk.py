"""Planner-only walks: the footstep planner and the reference, without a robot.

:func:`walk_course` plays the receding-horizon loop the env runs (plan at each touchdown, take
step 0) with ideal touchdowns on the planned footholds, so the planner's behaviour over whole
courses can be measured (tests/test_planner.py, ``python -m march.bench planner``) and drawn
(``python -m march.viz plan``) without a simulator.
"""

from __future__ import annotations

import torch

from march.keyed_random import RowStreams, row_keys
from march.reference.hlip import HlipCfg
from march.reference.planner import Plan, plan_footsteps
from march.reference.planner_cfg import PlannerCfg
from march.reference.trajectory import (
    ReferenceCfg,
    StepState,
    com_state,
    reference_at,
    step_state_from_plan,
)
from march.world.footholds import Footholds


def walk_course(
    footholds: Footholds,
    command: torch.Tensor,
    max_steps: int = 30,
    seed: int = 0,
    planner: PlannerCfg | None = None,
    hlip: HlipCfg | None = None,
    samples_per_step: int = 10,
    keys: torch.Tensor | None = None,
    reference: ReferenceCfg | None = None,
) -> tuple[Plan, torch.Tensor]:
    """Receding-horizon walk with the models only: plan at each touchdown, take step 0.

    ``keys`` (E,) int: each course's identity; the planner then draws from one counter-based
    stream per course keyed by (``seed``, key) (march.keyed_random), so a course walks the same
    alone or in any batch. None: draws shared by the batch from one generator seeded ``seed``.
    ``reference``: the CoM reference (default ``ReferenceCfg()``: continuous, each step carrying
    the previous step's reference CoM state at its ideal touchdown).

    The start stance is the left foot at start_xy + (0.3, w/2) along/across the course. Returns
    the executed steps as a Plan (E, S; entries after an env stops are NaN) and the CoM reference
    path (E, S * samples_per_step, 2). An env stops when the plan turns infeasible or the stance
    foot reaches the goal platform.
    """
    planner = planner or PlannerCfg()
    hlip = hlip or HlipCfg()
    reference = reference or ReferenceCfg()
    e = footholds.num_envs
    source: dict = {"generator": torch.Generator().manual_seed(seed)}
    if keys is not None:
        streams = RowStreams(e, "cpu")
        streams.keys.copy_(row_keys(seed, keys))

        def draw(shape: tuple[int, ...]) -> torch.Tensor:
            return streams.uniform(None, shape, torch.float32, advance=active)

        source = {"row_uniform": draw}
    axis = footholds.direction
    lat = torch.stack([-axis[:, 1], axis[:, 0]], dim=-1)
    stance = footholds.start_xy + 0.3 * axis + 0.5 * planner.step_width * lat
    swing = None  # (E, 3) swing foot at lift-off; starts beside the stance foot
    left = torch.ones(e, dtype=torch.bool)
    active = torch.ones(e, dtype=torch.bool)
    nan = float("nan")
    feet = torch.full((e, max_steps, 3), nan)
    durations = torch.full((e, max_steps), nan)
    sides = torch.zeros(e, max_steps, dtype=torch.bool)
    com = torch.full((e, max_steps * samples_per_step, 2), nan)
    start = None
    zero = torch.zeros(e)
    step: StepState | None = None
    for k in range(max_steps):
        plan = plan_footsteps(stance, left, command, footholds, planner, **source)
        start = plan.start if start is None else start
        active = active & plan.feasible
        if swing is None:
            swing = plan.start.clone()
            swing[:, :2] -= planner.step_width * lat
        # The first step starts from standing: its CoM reference ramps from rest at the feet's
        # midpoint (march.reference.trajectory), as the env's first step does from the measured CoM.
        ramp_from = 0.5 * (plan.start[:, :2] + swing[:, :2]) if k == 0 else None
        # Later steps carry the previous step's reference CoM state at its (ideal) touchdown.
        com_from = None if step is None else com_state(step, step.duration, reference, hlip)
        step = step_state_from_plan(
            plan,
            plan.start,
            swing,
            zero,
            zero,
            axis,
            ramp_from=ramp_from,
            com_from=com_from,
            cfg=reference,
            hlip=hlip,
        )
        for j in range(samples_per_step):
            tau = plan.durations[:, 0] * j / (samples_per_step - 1)
            ref = reference_at(step, tau, reference, hlip, num_upper=0)
            com[active, k * samples_per_step + j] = ref.com_pos[active, :2]
        feet[active, k] = plan.footholds[active, 0]
        durations[active, k] = plan.durations[active, 0]
        sides[:, k] = plan.lands_left[:, 0]
        swing = torch.where(active[:, None], plan.start, swing)
        stance = torch.where(active[:, None], plan.footholds[:, 0, :2], stance)
        left = torch.where(active, plan.lands_left[:, 0], left)
        reached = footholds.progress(stance) >= footholds.goal_distance + 0.3
        active = active & ~reached
        if not active.any():
            break
    walked = Plan(
        footholds=feet,
        durations=durations,
        lands_left=sides,
        cost=torch.zeros(e),
        feasible=~torch.isnan(feet[..., 0]).all(-1),
        start=start,
    )
    return walked, com


def on_stones(footholds: Footholds, plan: Plan, i: int) -> bool:
    """Every executed foothold of env ``i`` lies on a stone with the planner's margin."""
    feet = plan.footholds[i : i + 1, :, :2]
    ok = torch.isfinite(feet[..., 0])
    one = footholds.index(torch.tensor([i]))
    inside = one.contains(feet.nan_to_num(), PlannerCfg().stone_margin)
    return bool(inside[ok].all()) and bool(ok.any())
