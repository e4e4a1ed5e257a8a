"""The footstep plan drawn through mjlab's debug visualizer (``python -m march.play``).

One drawing for both of play's outputs: mjlab's browser viewer (viser, ``viewer=viser``) and the
offscreen MuJoCo frames of the MP4. It draws, for the visualised env, from the ``reference``
command term:

- the planned footholds (``plan_footholds``), numbered 1..N in plan order, magenta for the
  left foot and green for the right (the feet alternate; step 1 is the current swing foot's);
- the swing-foot target of the current step (``step.target``): a red post on the stone, and
  an arrow from the swing foot to it;
- the CoM reference of the current step (``reference(tau)`` over the step): an aqua path,
  with the reference CoM at the current ``tau`` as a larger aqua ball;
- the stones the planner considered: the ``num_candidate_stones`` stones nearest each planned
  foothold (the planner searches the M stones nearest each step's nominal foothold), as thin
  translucent crimson slabs on the stones' tops.

Numbers: mjlab's visualizers drop ``label``; the MuJoCo scene's decor geoms carry a text label
MuJoCo renders, and viser gets a scene label per foothold. The drawing copies a few tensors of
one env to the host: it runs only when a viewer or the video asks for a frame, never inside the
env step.
"""

from __future__ import annotations

import types
from typing import Any

import numpy as np
import torch

LEFT_RGBA = (0.9, 0.0, 0.75, 1.0)
"""Planned left-foot footholds: magenta."""
RIGHT_RGBA = (0.0, 0.8, 0.05, 1.0)
"""Planned right-foot footholds: green."""
TARGET_RGBA = (1.0, 0.05, 0.0, 1.0)
"""The current step's swing-foot target post and arrow: red (viser shows it orange-red)."""
COM_RGBA = (0.0, 1.0, 0.8, 1.0)
"""The CoM reference path and ball: aqua."""
STONE_RGBA = (0.55, 0.05, 0.15, 0.55)
"""The considered stones' slabs: translucent crimson (a rose tint on the stones' tops)."""
MARKER_RGBAS = {
    "left foothold": LEFT_RGBA,
    "right foothold": RIGHT_RGBA,
    "swing target": TARGET_RGBA,
    "CoM reference": COM_RGBA,
    "considered stone": STONE_RGBA,
}
"""Every colour the drawing uses. The course's boxes run blue (low) - grey - yellow (high)
(:mod:`march.env.stone_terrain`), so the markers take hues off that axis (magenta, green, red,
aqua, crimson): each is at least 50 CIELAB units from every box colour and from every other
marker, whether a renderer shows the values as sRGB or as linear light (viser does), and a
considered-stone slab tints every box by at least 25 (tests/test_plan_drawing_colours.py;
docs/decisions.md)."""
COM_SAMPLES = 12
"""Points on the drawn CoM reference path of the current step."""
FOOT_RADIUS = 0.045
"""Radius of a planned-foothold ball [m]."""


def considered_stones(
    centers: torch.Tensor, valid: torch.Tensor, footholds: torch.Tensor, m: int
) -> torch.Tensor:
    """(S,) bool: the stones among the ``m`` nearest (in xy) to any of the planned ``footholds``
    (N, 3); ``centers`` (S, 3) and ``valid`` (S,) are one env's stones."""
    d = torch.cdist(footholds[:, :2].float(), centers[:, :2].float())  # (N, S)
    d = torch.where(valid[None], d, torch.full_like(d, float("inf")))
    k = min(m, int(valid.sum()))
    out = torch.zeros_like(valid)
    if k == 0:
        return out
    near = d.topk(k, dim=1, largest=False).indices  # (N, k)
    out[near.flatten()] = True
    return out & valid


def plan_picture(term: Any, env_idx: int) -> dict[str, np.ndarray]:
    """What is drawn for env ``env_idx``, on the host (world frame, metres)."""
    e = env_idx
    feet_plan = term.plan_footholds[e]  # (N, 3)
    n = feet_plan.shape[0]
    first_left = ~term.stance_is_left[e]  # step 1 lands the swing foot
    lands_left = (torch.arange(n, device=feet_plan.device) % 2 == 0) == first_left
    duration = term.step.duration  # (E,)
    taus = torch.linspace(0.0, 1.0, COM_SAMPLES, device=duration.device)[:, None] * duration
    com_path = torch.stack([term.reference(tau)[0][e, 0:3] for tau in taus])
    com_now = term.reference(term.tau)[0][e, 0:3]
    fh = term.footholds
    considered = considered_stones(
        fh.center[e], fh.valid[e], feet_plan, term.cfg.planner.num_candidate_stones
    )
    feet = term.feet_pos()[e]  # (2, 3) left, right
    swing = feet[1] if bool(term.stance_is_left[e]) else feet[0]
    return {
        "footholds": feet_plan.cpu().numpy(),
        "lands_left": lands_left.cpu().numpy(),
        "target": term.step.target[e].cpu().numpy(),
        "swing_foot": swing.cpu().numpy(),
        "com_path": com_path.cpu().numpy(),
        "com_now": com_now.cpu().numpy(),
        "stone_center": fh.center[e][considered].cpu().numpy(),
        "stone_half": fh.half_size[e][considered].cpu().numpy(),
    }


def _label_last(visualizer: Any, name: str, text: str, pos: np.ndarray) -> None:
    """Give the geom just added a text label (MuJoCo scene) or put a viser label at ``pos``.

    In viser the label is a child of the scene's ``/fixed_bodies`` frame (mjviser moves that
    frame by the scene offset, which follows the robot when the camera tracks it), at ``pos``
    in world coordinates: it moves in the same update as mjlab's debug primitives. Placed at
    ``pos`` plus the scene offset read now, it lagged one scene update behind them, and a label
    could stand beside the next foothold's ball."""
    scn = getattr(visualizer, "_mjv_scene", None)
    if scn is not None and scn.ngeom > 0:
        scn.geoms[scn.ngeom - 1].label = text
        return
    server = getattr(visualizer, "server", None)
    if server is None or not getattr(visualizer, "debug_visualization_enabled", True):
        return
    frame = getattr(visualizer, "fixed_bodies_frame", None)
    if frame is not None:
        parent, at = frame.name, pos
    else:
        parent, at = "", pos + np.asarray(getattr(visualizer, "_scene_offset", np.zeros(3)))
    server.scene.add_label(
        f"{parent}/march_plan/{name}",
        text,
        position=tuple(float(v) for v in at),
        font_screen_scale=1.2,
        anchor="bottom-center",
    )


def draw_picture(pic: dict[str, np.ndarray], visualizer: Any) -> None:
    """Draw one env's plan picture through an mjlab ``DebugVisualizer``."""
    eye = np.eye(3)
    for c, h in zip(pic["stone_center"], pic["stone_half"], strict=True):
        visualizer.add_box(
            np.array([c[0], c[1], c[2] + 0.006]), np.array([h[0], h[1], 0.006]), eye, STONE_RGBA
        )
    path = pic["com_path"]
    for a, b in zip(path[:-1], path[1:], strict=True):
        visualizer.add_cylinder(a, b, 0.008, COM_RGBA)
    visualizer.add_sphere(pic["com_now"], 0.04, COM_RGBA, label="CoM reference")
    target = pic["target"]
    visualizer.add_cylinder(target, target + np.array([0.0, 0.0, 0.25]), 0.012, TARGET_RGBA)
    visualizer.add_arrow(pic["swing_foot"], target + np.array([0.0, 0.0, 0.02]), TARGET_RGBA)
    for j, (p, left) in enumerate(zip(pic["footholds"], pic["lands_left"], strict=True)):
        if not np.isfinite(p).all():
            continue
        center = p + np.array([0.0, 0.0, FOOT_RADIUS * 0.6])
        text = f"{j + 1}{'L' if left else 'R'}"
        visualizer.add_sphere(center, FOOT_RADIUS, LEFT_RGBA if left else RIGHT_RGBA, label=text)
        _label_last(visualizer, f"foothold_{j}", text, center + np.array([0.0, 0.0, 0.06]))


def draw_plan(term: Any, visualizer: Any) -> None:
    """The ``reference`` term's ``_debug_vis_impl``: its plan for the visualised env(s)."""
    with torch.no_grad():
        for e in visualizer.get_env_indices(term.num_envs):
            draw_picture(plan_picture(term, e), visualizer)


def enable_plan_drawing(env: Any) -> Any:
    """Make the env's ``reference`` command term draw its plan in mjlab's debug visualization
    (viewer and offscreen renderer). Returns the term."""
    from march.env.reference_command import reference_term

    term = reference_term(env)
    term.cfg.debug_vis = True
    term._debug_vis_impl = types.MethodType(draw_plan, term)
    return term
