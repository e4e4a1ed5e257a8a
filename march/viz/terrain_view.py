"""Top view of stepping-stone courses at several difficulty levels (matplotlib, no simulator).

``python -m march.viz.terrain_view [out.png]`` draws the default courses; ``draw_terrain`` is the API.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import Normalize  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402

from march.world.courses import (  # noqa: E402
    ROLE_GOAL,
    ROLE_PAIR,
    ROLE_START,
    CourseCfg,
    CourseLayout,
    difficulty_ranges,
    generate_course,
    hardware_course,
)


def _title(lay: CourseLayout, cfg: CourseCfg) -> str:
    if lay.kind == "hardware":
        return "hardware course: 4 stones alternating left/right"
    r = difficulty_ranges(lay.difficulty, cfg)
    return (
        f"difficulty {lay.difficulty:.2f}: {lay.num_steps} steps, {lay.num_pairs} pairs\n"
        f"stone {100 * r.stone_size[0]:.0f}-{100 * r.stone_size[1]:.0f} cm, "
        f"gap {100 * r.gap[0]:.0f}-{100 * r.gap[1]:.0f} cm, "
        f"height +/-{100 * r.height:.0f} cm, zig-zag {100 * r.lateral[0]:.0f}-"
        f"{100 * r.lateral[1]:.0f} cm"
    )


def draw_terrain(
    cfg: CourseCfg,
    path: str | Path,
    difficulties: Sequence[float] = (0.0, 0.33, 0.66, 1.0),
    seed: int = 0,
    hardware: bool = True,
) -> Path:
    """Write a PNG with one top view per difficulty (and the hardware course); returns the path.

    Boxes are coloured by top height (shared colour bar, platforms at 0 m); stones of a
    side-by-side pair have a red outline; the spawn point is a black cross and the goal line
    (``goal_distance``) dashed.
    """
    rng = np.random.default_rng(seed)
    layouts = [generate_course(float(d), cfg, rng) for d in difficulties]
    if hardware:
        layouts.append(hardware_course(cfg))
    h = max(cfg.height_hard, cfg.height_easy, 1e-3)
    norm = Normalize(-h, h)
    cmap = plt.get_cmap("viridis")
    sx, sy = cfg.size
    fig, axes = plt.subplots(
        len(layouts), 1, figsize=(9.0, 0.4 + 2.75 * len(layouts) * sy / 4.0), squeeze=False
    )
    for ax, lay in zip(axes[:, 0], layouts, strict=True):
        ax.add_patch(Rectangle((0, 0), sx, sy, color="0.15", zorder=0))
        for k in range(lay.num_boxes):
            (cx, cy, top), (hx, hy) = lay.center[k], lay.half_size[k]
            role = lay.role[k]
            pair = role == ROLE_PAIR
            ax.add_patch(
                Rectangle(
                    (cx - hx, cy - hy),
                    2 * hx,
                    2 * hy,
                    facecolor=cmap(norm(top)),
                    edgecolor="red" if pair else "white",
                    linewidth=1.6 if pair else 0.5,
                    zorder=2,
                )
            )
            if role in (ROLE_START, ROLE_GOAL):
                ax.text(
                    cx,
                    cy + hy - 0.25,
                    "start" if role == ROLE_START else "goal",
                    ha="center",
                    va="top",
                    fontsize=8,
                    color="white",
                    zorder=3,
                )
        ox, oy = lay.origin[:2]
        ax.plot([ox], [oy], "kx", ms=7, mew=2, zorder=4)
        gx = ox + lay.goal_distance
        ax.plot([gx, gx], [0, sy], "w--", lw=0.8, zorder=3)
        ax.set_xlim(0, sx)
        ax.set_ylim(0, sy)
        ax.set_aspect("equal")
        ax.set_title(_title(lay, cfg), fontsize=9, loc="left")
        ax.set_ylabel("y [m]", fontsize=8)
        ax.tick_params(labelsize=7)
    axes[-1, 0].set_xlabel(
        "x along the course [m]  (red outline: side-by-side pair; "
        "x: spawn; dashed: goal platform starts)",
        fontsize=8,
    )
    fig.tight_layout(rect=(0, 0, 0.9, 1))
    box = axes[0, 0].get_position()
    cax = fig.add_axes((box.x1 + 0.02, 0.15, 0.015, 0.7))
    sm = plt.cm.ScalarMappable(norm=norm, cmap=cmap)
    fig.colorbar(sm, cax=cax).set_label("top height rel. to platforms [m]", fontsize=8)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
