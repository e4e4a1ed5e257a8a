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

from march.reference.planner import Plan  # noqa: E402
from march.reference.walk import on_stones, walk_course  # noqa: E402
from march.world.footholds import Footholds  # noqa: E402
from march.world.synthetic import synthetic_courses  # noqa: E402

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
