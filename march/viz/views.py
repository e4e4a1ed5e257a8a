"""``python -m march.viz <job>``: pictures of the terrain, the student's depth and footstep plans.

    python -m march.viz terrain [out=terrain.png]   # top views of the courses (cfg.terrain)
    python -m march.viz depth [out=depth.png]       # a real student env: clean vs corrupted depth
    python -m march.viz plan [out=plan.png]         # planner walks on generated courses

Every job composes the same config as ``march.train`` and takes its ``key=value`` overrides
(e.g. ``seed=3``, ``terrain.pair_prob=0.5``, ``depth.dropout=0.2``); it prints the file written.

- ``terrain``: :func:`march.viz.terrain_view.draw_terrain` on ``cfg.terrain`` (difficulties 0, 1/3,
  2/3, 1 and the hardware course; courses drawn with ``seed``). No simulator.
- ``depth``: builds the ``student`` env with 4 envs (on ``compute.device``) spread over the
  curriculum levels 0 .. num_levels-1, steps it a few control steps with zero actions (the robot
  stands at its spawn point on the start platform, looking at the first stones), then draws per
  env: the chest camera's depth normalised only (``march.env.depth.normalize``), the same frame
  through the training corruption (``corrupt`` then ``normalize`` with ``cfg.depth``, seeded),
  and the env's own ``depth`` observation (corrupted and delayed, what the student was fed).
- ``plan``: courses drawn by :func:`march.world.courses.generate_course` at difficulties 0, 1/3, 2/3,
  1 (plus the hardware course), walked with the models only by
  :func:`march.reference.walk.walk_course` (replan at every touchdown, forward command
  ``eval.command_vx``); drawn by :func:`march.viz.plan_view.draw_plans`. No simulator.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

from march.config import MarchConfig
from march.config.cli import fail, run_tool

USAGE = "usage: python -m march.viz terrain|depth|plan [out=<file>.png] [key=value ...]"
DIFFICULTIES = (0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0)
DEPTH_ENVS = 4
DEPTH_STEPS = 5
"""Control steps with zero actions before the depth frame is taken (the delay buffers fill)."""
PLAN_MAX_STEPS = 60
"""Footsteps walk_course may take per course (a 12 m course takes ~30-40 at 0.5 m/s)."""


def _out(cfg: MarchConfig, default: str) -> Path:
    out = Path(cfg.out or default)
    if not out.suffix:
        fail(f"out={out}: give a file name with an image suffix, e.g. out={default}")
    out.parent.mkdir(parents=True, exist_ok=True)
    return out


def terrain(cfg: MarchConfig) -> Path:
    from march.viz.terrain_view import draw_terrain

    out = draw_terrain(cfg.terrain, _out(cfg, "terrain.png"), DIFFICULTIES, seed=cfg.seed)
    print(out)
    return out


def plan(cfg: MarchConfig) -> Path:
    import numpy as np
    import torch

    from march.reference.walk import on_stones, walk_course
    from march.viz.plan_view import draw_plans
    from march.world.courses import generate_course, hardware_course
    from march.world.footholds import footholds_from_layouts

    out = _out(cfg, "plan.png")
    rng = np.random.default_rng(cfg.seed)
    layouts = [generate_course(d, cfg.terrain, rng) for d in DIFFICULTIES]
    layouts.append(hardware_course(cfg.terrain))
    # Each course in its own sub-terrain frame (world = local): origins are the spawn points.
    footholds = footholds_from_layouts(layouts, np.stack([lay.origin for lay in layouts]))
    command = torch.tensor([[cfg.eval.command_vx, 0.0, 0.0]]).expand(len(layouts), 3)
    walked, com = walk_course(footholds, command, max_steps=PLAN_MAX_STEPS, seed=cfg.seed)
    titles = []
    for i, lay in enumerate(layouts):
        feet = walked.footholds[i]
        ok = torch.isfinite(feet[:, 0])
        n = int(ok.sum())
        last = feet[ok][-1:, :2] if n else footholds.start_xy[i : i + 1]
        reached = bool(footholds.index(torch.tensor([i])).progress(last)[0] >= lay.goal_distance)
        name = "hardware course" if lay.kind == "hardware" else f"difficulty {lay.difficulty:.2f}"
        titles.append(
            f"{name}: {n} steps at v_x {cfg.eval.command_vx:g} m/s, "
            f"all on stones (margin) = {on_stones(footholds, walked, i)}, "
            f"reached goal platform = {reached}"
        )
    draw_plans(footholds, walked, com, str(out), titles)
    print(out)
    return out


def depth(cfg: MarchConfig) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import torch

    from march.env.build import make_env
    from march.env.course import foothold_table
    from march.env.depth import corrupt, normalize

    out = _out(cfg, "depth.png")
    torch.manual_seed(cfg.seed)
    c = cfg.curriculum
    c.max_init_level = c.num_levels - 1
    d = cfg.depth
    env = make_env(cfg, "student", num_envs=DEPTH_ENVS)
    try:
        terrain_ = env.scene.terrain
        levels = torch.linspace(0, c.num_levels - 1, DEPTH_ENVS, device=env.device).round().long()
        terrain_.terrain_levels[:] = levels
        terrain_.env_origins[:] = terrain_.terrain_origins[levels, terrain_.terrain_types]
        obs, _ = env.reset()  # no step taken yet: the level curriculum leaves the levels alone
        zero = torch.zeros(env.num_envs, env.action_manager.total_action_dim, device=env.device)
        with torch.no_grad():
            for _ in range(DEPTH_STEPS):
                obs, *_ = env.step(zero)
        raw = env.scene[d.name].data.depth[..., 0].clone()  # (E, H, W) metres, 0 = no return
        gen = torch.Generator(device=raw.device).manual_seed(cfg.seed)
        clean = normalize(raw, d.min_range, d.max_range)
        noisy = normalize(corrupt(raw, d.noise_scale, d.dropout, gen), d.min_range, d.max_range)
        fed = obs["depth"][:, 0]
        table = foothold_table(env)
        lv = terrain_.terrain_levels.cpu()
        ty = terrain_.terrain_types.cpu()
        diff = table.difficulty.cpu()[lv, ty]
        along = (env.scene["robot"].data.root_link_pos_w[:, 0] - env.scene.env_origins[:, 0]).cpu()
    finally:
        env.close()

    cols = (
        ("clean (normalise only)", clean),
        (f"corrupted: noise {d.noise_scale:g}*d, dropout {d.dropout:g}", noisy),
        (f"env obs 'depth' (corrupted, delay {list(d.delay_steps)} steps)", fed),
    )
    e = raw.shape[0]
    fig, axes = plt.subplots(e, len(cols), figsize=(3.4 * len(cols), 2.3 * e + 0.6), squeeze=False)
    im = None
    for i in range(e):
        for j, (name, img) in enumerate(cols):
            ax = axes[i, j]
            im = ax.imshow(img[i].cpu().numpy(), cmap="viridis", vmin=0.0, vmax=1.0)
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(name, fontsize=8)
        axes[i, 0].set_ylabel(
            f"env {i}: level {int(lv[i])}\n(difficulty {float(diff[i]):.2f})", fontsize=8
        )
        far = float((clean[i] >= 1.0).float().mean())
        hit = raw[i][raw[i] > 0]
        span = f"{float(hit.min()):.2f}-{float(hit.max()):.2f} m" if hit.numel() else "no return"
        print(
            f"env {i}: level {int(lv[i])} difficulty {float(diff[i]):.2f}, "
            f"pelvis {float(along[i]):+.2f} m from spawn, raw depth {span}, "
            f"{100 * far:.0f}% at max range (clean)"
        )
    fig.suptitle(
        f"student depth {d.width}x{d.height}, fovy {d.fovy:g} deg, pitch {d.pitch_deg:g} deg; "
        f"0 = {d.min_range:g} m, 1 = {d.max_range:g} m or no return",
        fontsize=9,
    )
    fig.tight_layout(rect=(0, 0, 0.9, 0.97))
    cax = fig.add_axes((0.92, 0.15, 0.015, 0.7))
    fig.colorbar(im, cax=cax).set_label("normalised depth", fontsize=8)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    print(out)
    return out


JOBS = {"terrain": terrain, "depth": depth, "plan": plan}


def main(argv: Sequence[str] | None = None) -> None:
    run_tool(JOBS, argv, usage=USAGE)


if __name__ == "__main__":
    main(sys.argv[1:])
