"""Student depth image: camera config on the G1 torso and post-processing in plain torch.

Pipeline, per control step (all tensors (E, H, W) in metres until the last step):

1. ``raw``: MuJoCo Warp's planar depth (distance along the optical axis); rays that hit nothing
   read 0, exactly like an invalid D435 pixel.
2. ``corrupt`` (training only): Gaussian noise sigma = noise_scale * depth on valid pixels, then
   pixel dropout - a dropped pixel is set to 0, i.e. *invalid*, the value the real camera gives
   for a pixel it cannot match; step 4 turns it into max range like any other invalid pixel, so
   the deployed robot runs the very same ``normalize`` on the D435 stream.
3. ``DepthDelay``: the frame from k control steps ago, k per env (sampled at reset).
4. ``normalize``: invalid (<= 0 or non-finite) -> max range, clip to [min_range, max_range],
   map linearly to [0, 1] (0 = min_range, 1 = max range or nothing seen).

Randomness comes from an optional ``torch.Generator`` (on the tensors' device) or torch's
global RNG, which march seeds from the run's ``seed``.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

import torch

from march.config import DepthCfg

if TYPE_CHECKING:
    from mjlab.sensor import CameraSensorCfg

TORSO_BODY = "robot/torso_link"
"""The G1 torso body in mjlab's scene (entity "robot", body "torso_link" of the G1 MJCF)."""


def camera_quat(pitch_deg: float) -> tuple[float, float, float, float]:
    """(w, x, y, z) of a MuJoCo camera looking along its parent's +x, pitched down by pitch_deg.

    A MuJoCo camera looks along its local -z with +y up. Looking along +x with +z up means the
    camera axes (x, y, z) = (-y, +z, -x) of the parent, a quarter turn about x then about z:
    q0 = (0.5, 0.5, -0.5, -0.5). Pitching down is a rotation by +pitch about the parent's +y
    (it takes +x to (cos, 0, -sin)): q = q_y(pitch) * q0.
    """
    h = 0.5 * math.radians(pitch_deg)
    a = (math.cos(h), 0.0, math.sin(h), 0.0)
    b = (0.5, 0.5, -0.5, -0.5)
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return (
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
    )


def depth_camera_cfg(cfg: DepthCfg, parent_body: str = TORSO_BODY) -> CameraSensorCfg:
    """mjlab camera sensor creating a depth camera on the G1 torso (add it to
    ``env_cfg.scene.sensors``; read ``env.scene[cfg.name].data.depth``, (E, H, W, 1) metres)."""
    from mjlab.sensor import CameraSensorCfg

    return CameraSensorCfg(
        name=cfg.name,
        parent_body=parent_body,
        pos=tuple(cfg.pos),
        quat=camera_quat(cfg.pitch_deg),
        fovy=cfg.fovy,
        width=cfg.width,
        height=cfg.height,
        data_types=("depth",),
        use_textures=False,
        enabled_geom_groups=tuple(cfg.geom_groups),
    )


def normalize(depth: torch.Tensor, min_range: float, max_range: float) -> torch.Tensor:
    """Invalid (<= 0, NaN, inf) -> max_range, clip to [min_range, max_range], map to [0, 1]."""
    invalid = ~torch.isfinite(depth) | (depth <= 0.0)
    d = torch.where(invalid, torch.full_like(depth, max_range), depth)
    d = d.clamp(min_range, max_range)
    return (d - min_range) / (max_range - min_range)


def corrupt(
    depth: torch.Tensor,
    noise_scale: float,
    dropout: float,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Depth [m] with noise N(0, (noise_scale * depth)^2) on valid pixels and a fraction
    ``dropout`` of pixels set to 0 (invalid). Invalid input pixels stay 0."""
    valid = depth > 0.0
    out = depth
    if noise_scale > 0.0:
        noise = torch.randn(
            depth.shape, generator=generator, device=depth.device, dtype=depth.dtype
        )
        # A valid pixel stays valid: noise beyond -depth (a 10-sigma event) clamps to 1 mm.
        out = torch.where(valid, (depth + noise_scale * depth * noise).clamp(min=1e-3), depth)
    if dropout > 0.0:
        drop = torch.rand(depth.shape, generator=generator, device=depth.device) < dropout
        out = torch.where(drop, torch.zeros_like(out), out)
    return out


@contextmanager
def camera_paused(env) -> Iterator[None]:
    """Skip the depth render (mjlab's ``Simulation.sense``) of ``env`` inside the block.

    For rollouts of a policy that does not see the depth image (the privileged teacher on the
    evaluation env, whose scene carries the student's camera): the render was a quarter of a
    4-env CPU evaluation step and buys nothing there. Physics, rewards, terminations and every
    random draw are untouched, so the rollout's numbers are exactly those with the render on
    (tests/test_eval_repeat.py); only the env's depth observation holds a stale frame, which
    the teacher never reads. mjlab 1.6.0's ``sense()`` does nothing without a sensor context
    (also on a GPU, where it would launch the captured sense graph); a context that also serves
    ray-cast sensors is left alone, as their readings may be observed.
    """
    sim = env.unwrapped.sim  # (mjlab: ``unwrapped`` is the env itself, or a wrapper's env)
    ctx = sim._sensor_context
    if ctx is None or ctx.has_raycasts:
        yield
        return
    sim._sensor_context = None
    try:
        yield
    finally:
        sim._sensor_context = ctx
