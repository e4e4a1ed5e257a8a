"""Top-view drawings of footstep plans and CoM references (matplotlib Agg; no simulator import)."""

from __future__ import annotations

from collections.abc import Sequence

import matplotlib

matplotlib.use("Agg")

import matplotlib.patheffects as pe  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402
from matplotlib.colors import Normalize  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402

from march.bench.planner_speed import synthetic_courses  # noqa: E402
from march.reference.hlip import HlipCfg  # noqa: E402
from march.reference.planner import Plan, PlannerCfg, plan_footsteps  # noqa: E402
from march.reference.trajectory import ReferenceCfg, reference_at, step_state_from_plan  # noqa: E402
from march.world.footholds import Footholds  # noqa: E402

LEFT_COLOR, RIGHT_COLOR = "tab:blue", "tab:red"


def draw_plans(
    footholds: Footholds,
    plans: Plan,
    com_paths: torch.Tensor | Sequence[torch.Tensor] | None,
    path: str,
    titles: Sequence[str] | None = None,
) -> None:
    """One top-view panel per env: stones coloured by top height, the plan's footholds numbered
    and coloured by foot (blue left, red right; non-finite entries are skipped), the start stance
    foot as a black cross, and the CoM reference path (P, 2) per env as a line. Writes ``path``."""
    fh = footholds.to("cpu")
    e = fh.num_envs
    z = fh.center[..., 2][fh.valid]
    norm = Normalize(float(z.min()) - 1e-3, float(z.max()) + 1e-3)
    cmap = plt.get_cmap("viridis")
    # Panel width from the courses' aspect ratio (equal axes), so a panel fills its row.
    lo = (fh.center[..., :2] - fh.half_size)[fh.valid]
    hi = (fh.center[..., :2] + fh.half_size)[fh.valid]
    span = (hi.max(0).values - lo.min(0).values).clamp(min=0.5)
    width = min(18.0, max(8.0, 2.0 * float(span[0] / span[1]) + 1.0))  # titles fit
    fig, axes = plt.subplots(
        e, 1, figsize=(width, 2.0 * e + 0.6), squeeze=False, layout="constrained"
    )
    for i, ax in enumerate(axes[:, 0]):
        for s in torch.nonzero(fh.valid[i])[:, 0].tolist():
            (cx, cy, cz), (hx, hy) = fh.center[i, s].tolist(), fh.half_size[i, s].tolist()
            ax.add_patch(
                Rectangle(
                    (cx - hx, cy - hy),
                    2 * hx,
                    2 * hy,
                    facecolor=cmap(norm(cz)),
                    edgecolor="k",
                    lw=0.5,
                )
            )
        if com_paths is not None:
            com = torch.as_tensor(com_paths[i]).cpu()
            ax.plot(com[:, 0], com[:, 1], color="orange", lw=1.5)
        start = plans.start[i].cpu()
        ax.plot(start[0], start[1], "kx", ms=8, mew=2)
        feet = plans.footholds[i].cpu()
        left = plans.lands_left[i].cpu()
        for j in range(feet.shape[0]):
            if not torch.isfinite(feet[j]).all():
                continue
            color = LEFT_COLOR if bool(left[j]) else RIGHT_COLOR
            ax.plot(feet[j, 0], feet[j, 1], "o", color=color, ms=5, mec="white", mew=0.8)
            ax.annotate(
                str(j + 1),
                (float(feet[j, 0]), float(feet[j, 1])),
                fontsize=8,
                fontweight="bold",
                xytext=(3, 3),
                textcoords="offset points",
                color=color,
                path_effects=[pe.withStroke(linewidth=2, foreground="white")],
            )
        ax.set_aspect("equal")
        ax.autoscale_view()
        ax.set_ylabel("y [m]")
        ax.set_title(titles[i] if titles else f"env {i}", fontsize=9)
    handles = [
        Line2D([], [], marker="o", ls="", color=LEFT_COLOR, label="left foot"),
        Line2D([], [], marker="o", ls="", color=RIGHT_COLOR, label="right foot"),
        Line2D([], [], marker="x", ls="", color="k", mew=2, label="start stance"),
        Line2D([], [], color="orange", label="CoM reference"),
    ]
    axes[0, 0].legend(handles=handles, loc="upper right", fontsize=7, ncol=4)
    axes[-1, 0].set_xlabel("x [m] (course direction)")
    fig.colorbar(
        plt.cm.ScalarMappable(norm=norm, cmap=cmap),
        ax=axes[:, 0].tolist(),
        label="stone top z [m]",
        location="bottom",  # below the panels: clear of the long panel titles
        shrink=0.5,
        aspect=40,
    )
    fig.savefig(path, dpi=110)
    plt.close(fig)


def walk_course(
    footholds: Footholds,
    command: torch.Tensor,
    max_steps: int = 30,
    seed: int = 0,
    planner: PlannerCfg | None = None,
    hlip: HlipCfg | None = None,
    samples_per_step: int = 10,
) -> tuple[Plan, torch.Tensor]:
    """Receding-horizon walk with the models only: plan at each touchdown, take step 0.

    The start stance is the left foot at start_xy + (0.3, w/2) along/across the course. Returns
    the executed steps as a Plan (E, S; entries after an env stops are NaN) and the CoM reference
    path (E, S * samples_per_step, 2). An env stops when the plan turns infeasible or the stance
    foot reaches the goal platform.
    """
    planner = planner or PlannerCfg()
    hlip = hlip or HlipCfg()
    gen = torch.Generator().manual_seed(seed)
    e = footholds.num_envs
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
    for k in range(max_steps):
        plan = plan_footsteps(stance, left, command, footholds, planner, gen)
        start = plan.start if start is None else start
        active = active & plan.feasible
        if swing is None:
            swing = plan.start.clone()
            swing[:, :2] -= planner.step_width * lat
        # The first step starts from standing: its CoM reference ramps from rest at the feet's
        # midpoint (march.reference.trajectory), as the env's first step does from the measured CoM.
        ramp_from = 0.5 * (plan.start[:, :2] + swing[:, :2]) if k == 0 else None
        step = step_state_from_plan(plan, plan.start, swing, zero, zero, axis, ramp_from=ramp_from)
        for j in range(samples_per_step):
            tau = plan.durations[:, 0] * j / (samples_per_step - 1)
            ref = reference_at(step, tau, ReferenceCfg(), hlip, num_upper=0)
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


def demo_plan_figure(path: str, seed: int = 0) -> Plan:
    """Synthetic courses at difficulties 0, 1/3, 2/3, 1 walked by the planner; drawn to ``path``."""
    difficulties = [0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0]
    footholds = synthetic_courses(difficulties, seed=seed)
    command = torch.tensor([[0.6, 0.0, 0.0]]).expand(len(difficulties), 3)
    walked, com = walk_course(footholds, command, seed=seed)
    titles = [
        f"difficulty {d:.2f}: {int(torch.isfinite(walked.footholds[i, :, 0]).sum())} steps, "
        f"all on stones (margin) = "
        f"{bool(on_stones(footholds, walked, i))}"
        for i, d in enumerate(difficulties)
    ]
    draw_plans(footholds, walked, com, path, titles)
    return walked


def on_stones(footholds: Footholds, plan: Plan, i: int) -> bool:
    feet = plan.footholds[i : i + 1, :, :2]
    ok = torch.isfinite(feet[..., 0])
    one = footholds.index(torch.tensor([i]))
    inside = one.contains(feet.nan_to_num(), PlannerCfg().stone_margin)
    return bool(inside[ok].all()) and bool(ok.any())
