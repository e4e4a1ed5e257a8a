"""The lean step's equivalences (issue 11): what the step computes more cheaply is what it
computed before.

- The height scan from the course boxes (``march.env.observations.terrain_height_scan``) equals
  mjlab's ``terrain_scan`` ray-cast sensor + ``height_scan`` observation, ray by ray, in a real
  env stepped with random actions on every curriculum level.
- A term shared within one observation compute (``march.env.step_cache.shared``) gives the
  value a direct call gives; outside a manager's compute nothing is cached.
"""

from __future__ import annotations

import math

import pytest
import torch

from march.config.cli import load
from march.env.observations import (
    SCAN_MAX_DISTANCE,
    scan_offsets,
    stones_ahead,
    terrain_height_scan,
)


def test_scan_offsets_are_mjlabs_g1_grid():
    off = scan_offsets()
    assert off.shape == (17 * 11, 2)
    # GridPatternCfg: x runs fastest ("xy" meshgrid), from -0.8 to 0.8 and -0.5 to 0.5
    assert off[0].tolist() == pytest.approx([-0.8, -0.5])
    assert off[1].tolist() == pytest.approx([-0.7, -0.5])
    assert off[-1].tolist() == pytest.approx([0.8, 0.5])


@pytest.fixture(scope="module")
def scan_env():
    from mjlab.envs import ManagerBasedRlEnv
    from mjlab.tasks.velocity.config.g1.env_cfgs import unitree_g1_rough_env_cfg

    from march.env.build import build_env_cfg

    cfg = load(
        ["compute=smoke", "reward=modelfree", "compute.num_envs=16", "curriculum.max_init_level=9"]
    )
    env_cfg = build_env_cfg(cfg, "teacher")
    assert all(s.name != "terrain_scan" for s in env_cfg.scene.sensors)  # not ray cast any more
    sensor = next(s for s in unitree_g1_rough_env_cfg().scene.sensors if s.name == "terrain_scan")
    env_cfg.scene.sensors = tuple(env_cfg.scene.sensors) + (sensor,)
    env = ManagerBasedRlEnv(cfg=env_cfg, device="cpu")
    yield env
    env.close()


@pytest.mark.sim
def test_height_scan_from_boxes_equals_the_ray_cast_sensor(scan_env):
    from mjlab.envs import mdp as envs_mdp

    env = scan_env
    gen = torch.Generator().manual_seed(1)
    shape = (env.num_envs, env.action_manager.total_action_dim)
    env.reset()
    levels = set(env.scene.terrain.terrain_levels.tolist())
    assert len(levels) >= 4  # several difficulties (stone heights) in the comparison
    worst, rays, misses, pit, ties = 0.0, 0, 0, 0, 0
    with torch.no_grad():
        for _ in range(60):
            env.step(2 * torch.rand(shape, generator=gen) - 1)
            ours = terrain_height_scan(env)
            ray = envs_mdp.height_scan(env, "terrain_scan")
            assert ours.shape == ray.shape
            diff = (ours - ray).abs()
            # A point exactly on a box edge (float32 ties) may count as on or off the box.
            ties += int((diff > 1e-4).sum())
            worst = max(worst, float(diff[diff <= 1e-4].max()))
            rays += ray.numel()
            misses += int((ray == SCAN_MAX_DISTANCE).sum())
            pit += int((ray > 0.9).sum())  # the pit lies 0.25 m below the platform top
    assert rays == 60 * env.num_envs * 187
    assert pit > 0  # some points saw the pit floor between stones
    assert worst < 1e-5, f"largest |analytic - ray cast| = {worst:.3g} m"
    assert ties <= 1e-4 * rays, f"{ties} of {rays} points disagree"


@pytest.mark.sim
def test_shared_terms_equal_direct_calls(scan_env, monkeypatch):
    import march.env.observations as O

    env = scan_env
    env.reset()
    calls = []
    inner = O._stones_ahead
    monkeypatch.setattr(O, "_stones_ahead", lambda e, k: calls.append(k) or inner(e, k))
    obs = env.observation_manager.compute(update_history=True)
    # the actor and the critic group both observe the stones: one computation
    assert len(calls) == 1
    k = O.NUM_STONES * O.STONE_FEATURES
    actor, critic = obs["actor"], obs["critic"]
    direct = stones_ahead(env)
    assert len(calls) == 2  # outside a manager's compute: computed afresh
    assert torch.equal(actor[:, -k:], direct) or any(
        torch.equal(actor[:, i : i + k], direct) for i in range(actor.shape[1] - k + 1)
    )
    assert any(torch.equal(critic[:, i : i + k], direct) for i in range(critic.shape[1] - k + 1))


@pytest.mark.sim
def test_site_state_equals_mjlabs_site_properties(scan_env):
    from mjlab.utils.lab_api.math import quat_from_matrix

    from march.env.step_cache import site_pos, site_state, site_xmat

    env = scan_env
    gen = torch.Generator().manual_seed(2)
    shape = (env.num_envs, env.action_manager.total_action_dim)
    robot = env.scene["robot"]
    names = ("left_foot", "right_foot")
    local, _ = robot.find_sites(names, preserve_order=True)
    with torch.no_grad():
        for _ in range(5):
            env.step(2 * torch.rand(shape, generator=gen) - 1)
            pos, lin, ang = site_state(env, names)
            d = robot.data
            assert torch.allclose(pos, d.site_pos_w[:, local], atol=1e-6)
            assert torch.allclose(site_pos(env, names), d.site_pos_w[:, local], atol=1e-6)
            assert torch.allclose(lin, d.site_lin_vel_w[:, local], atol=1e-5)
            assert torch.allclose(ang, d.site_ang_vel_w[:, local], atol=1e-6)
            quat = quat_from_matrix(site_xmat(env, names))
            assert torch.allclose(quat, d.site_quat_w[:, local], atol=1e-6)
            assert float(lin.abs().max()) > 0.0  # the robot moves: a real comparison


@pytest.mark.sim
def test_root_frame_equals_mjlabs_root_position_and_heading(scan_env):
    """Issue 41: the root position and heading the observation terms share (read from xpos and
    the root's rotation matrix) equal mjlab's root_link_pos_w and heading_w (through the
    quaternion) within float32 rounding, over random-action steps of robots that turn and fall."""
    from march.env.step_cache import root_frame

    env = scan_env
    gen = torch.Generator().manual_seed(3)
    shape = (env.num_envs, env.action_manager.total_action_dim)
    data = env.scene["robot"].data
    spread = 0.0
    with torch.no_grad():
        for _ in range(20):
            env.step(2 * torch.rand(shape, generator=gen) - 1)
            pos, heading = root_frame(env)
            assert torch.equal(pos, data.root_link_pos_w)
            diff = torch.remainder(heading - data.heading_w + math.pi, 2 * math.pi) - math.pi
            assert float(diff.abs().max()) < 1e-5
            spread = max(spread, float(heading.max() - heading.min()))
    assert spread > 0.1  # headings differ: a real comparison
