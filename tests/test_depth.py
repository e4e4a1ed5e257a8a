"""Depth post-processing: invalid pixels, dropout, noise, delay, and the camera config."""

from __future__ import annotations

import math

import pytest
import torch

from march.env.depth import (
    DepthCfg,
    DepthDelay,
    DepthPipeline,
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


def test_delay_returns_the_frame_from_k_steps_ago():
    buf = DepthDelay(4, (2, 3), delay_steps=(0, 3))
    buf.set_delay(torch.tensor([0, 1, 2, 3]))
    for t in range(10):
        buf.push(torch.full((4, 2, 3), float(t)))
    out = buf.get()
    assert out[:, 0, 0].tolist() == [9.0, 8.0, 7.0, 6.0]
    # Reset fills an env's history with its current frame: no stale frames from the last episode.
    buf.reset(torch.tensor([3]), torch.full((1, 2, 3), -1.0))
    buf.set_delay(3, torch.tensor([3]))
    buf.push(torch.full((4, 2, 3), 10.0))
    assert buf.get()[:, 0, 0].tolist() == [10.0, 9.0, 8.0, -1.0]
    for t in (11, 12):
        buf.push(torch.full((4, 2, 3), float(t)))
    assert buf.get()[:, 0, 0].tolist() == [12.0, 11.0, 10.0, -1.0]
    buf.push(torch.full((4, 2, 3), 13.0))
    assert buf.get()[3, 0, 0].item() == 10.0


def test_delay_sampled_per_env_within_range():
    g = torch.Generator().manual_seed(0)
    buf = DepthDelay(1000, (1,), delay_steps=(1, 3), generator=g)
    buf.sample_delay()
    counts = torch.bincount(buf.delay, minlength=4).tolist()
    assert counts[0] == 0 and min(counts[1:]) > 250
    with pytest.raises(ValueError):
        buf.set_delay(4)


def test_pipeline_eval_mode_is_clean_and_shaped():
    cfg = DepthCfg()
    raw = torch.full((3, 24, 32, 1), 1.55)
    raw[0, 5, 7, 0] = 0.0
    pipe = DepthPipeline(cfg, 3, train=False)
    out = pipe.step(raw)
    assert out.shape == (3, 1, 24, 32)
    assert out[0, 0, 5, 7].item() == 1.0
    assert out[1].unique().tolist() == pytest.approx([0.5])
    train = DepthPipeline(cfg, 3, train=True, generator=torch.Generator().manual_seed(0))
    assert set(train.delay.delay.tolist()) <= {0, 1}
    noisy = train.step(raw)
    assert noisy.min().item() >= 0.0 and noisy.max().item() <= 1.0
    assert (noisy != out).float().mean().item() > 0.9


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
