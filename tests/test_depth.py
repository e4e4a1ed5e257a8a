"""Depth post-processing: invalid pixels, dropout, noise, delay, and the camera config."""

from __future__ import annotations

import math

import pytest
import torch

from march.env.depth import (
    DepthCfg,
    camera_quat,
    corrupt,
    normalize,
)

torch.set_num_threads(1)


def test_normalize_maps_misses_to_max_range_and_clips():
    d = torch.tensor([0.0, -1.0, float("nan"), float("inf"), 0.05, 1.55, 3.0, 10.0])
    out = normalize(d, 0.1, 3.0)
    assert out.tolist() == pytest.approx([1.0, 1.0, 1.0, 1.0, 0.0, 0.5, 1.0, 1.0])


def test_dropout_fraction_near_five_percent():
    g = torch.Generator().manual_seed(0)
    img = torch.full((256, 24, 32), 2.0)
    out = corrupt(img, noise_scale=0.0, dropout=0.05, generator=g)
    dropped = (out == 0.0).float().mean().item()
    assert abs(dropped - 0.05) < 0.003  # n = 196608 pixels, binomial sd 0.0005
    assert ((out == 2.0) | (out == 0.0)).all()
    # Dropped pixels read as max range after normalisation.
    norm = normalize(out, 0.1, 3.0)
    assert (norm[out == 0.0] == 1.0).all()
    assert norm[out == 2.0].unique().tolist() == pytest.approx([(2.0 - 0.1) / 2.9])


@pytest.mark.parametrize("depth", [0.5, 2.0])
def test_noise_std_is_a_tenth_of_depth(depth):
    g = torch.Generator().manual_seed(1)
    img = torch.full((128, 24, 32), depth)
    img[:, 0, 0] = 0.0  # a missed ray stays invalid
    out = corrupt(img, noise_scale=0.1, dropout=0.0, generator=g)
    assert (out[:, 0, 0] == 0.0).all()
    vals = out[:, 1:, :]
    assert vals.mean().item() == pytest.approx(depth, rel=0.005)
    assert vals.std().item() == pytest.approx(0.1 * depth, rel=0.02)


def test_corruption_is_reproducible_with_a_generator():
    img = torch.rand(4, 24, 32) * 3
    a = corrupt(img, 0.1, 0.05, torch.Generator().manual_seed(5))
    b = corrupt(img, 0.1, 0.05, torch.Generator().manual_seed(5))
    c = corrupt(img, 0.1, 0.05, torch.Generator().manual_seed(6))
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_depth_delay_is_wired_as_configured():
    """The student's depth term is delayed by mjlab's observation delay buffer with
    cfg.depth.delay_steps; evaluation without corruption has neither delay nor corruption."""
    from march.config.cli import load
    from march.env.build import build_env_cfg

    cfg = load(["compute=smoke"])
    term = build_env_cfg(cfg, "student").observations["depth"].terms["depth"]
    assert (term.delay_min_lag, term.delay_max_lag) == tuple(cfg.depth.delay_steps) == (0, 1)
    assert term.params["noise_scale"] == 0.1 and term.params["dropout"] == 0.05
    clean_cfg = load(["compute=smoke", "eval.corruption=false"])
    clean = build_env_cfg(clean_cfg, "eval").observations["depth"].terms["depth"]
    assert (clean.delay_min_lag, clean.delay_max_lag) == (0, 0)
    assert clean.params["noise_scale"] == 0.0 and clean.params["dropout"] == 0.0


def test_delay_returns_the_frame_from_k_steps_ago():
    from mjlab.utils.buffers.delay_buffer import DelayBuffer

    buf = DelayBuffer(min_lag=2, max_lag=2, batch_size=3)
    for t in range(6):
        buf.append(torch.full((3, 1, 2, 2), float(t)))
        out = buf.compute()
    assert out[:, 0, 0, 0].tolist() == [3.0, 3.0, 3.0]  # frame T - 2 at T = 5


def test_camera_looks_forward_and_down():
    pitch = 47.6
    w, x, y, z = camera_quat(pitch)
    assert w * w + x * x + y * y + z * z == pytest.approx(1.0)
    # Rotate the camera's optical axis (-z) into the parent frame: R @ (0, 0, -1) = -R[:, 2].
    axis = [-(2 * (x * z + w * y)), -(2 * (y * z - w * x)), -(1 - 2 * (x * x + y * y))]
    p = math.radians(pitch)
    assert axis == pytest.approx([math.cos(p), 0.0, -math.sin(p)], abs=1e-9)


def test_depth_camera_cfg_on_the_g1_torso():
    from march.env.depth import depth_camera_cfg

    cfg = DepthCfg()
    cam = depth_camera_cfg(cfg)
    assert cam.parent_body == "robot/torso_link"
    assert (cam.width, cam.height, cam.fovy) == (32, 24, 55.2)
    assert cam.data_types == ("depth",)
    assert cam.quat == pytest.approx(camera_quat(47.6))
    assert cam.pos == pytest.approx((0.0576, 0.0175, 0.42))
