"""The sync-free twist command and push event (issue 41) against mjlab's own terms: the same
numbers where the random draws are the same, the same rule and ranges where they are not."""

from __future__ import annotations

import dataclasses

import pytest
import torch

pytestmark = pytest.mark.sim


@pytest.fixture(scope="module")
def env():
    from march.config.cli import load
    from march.env.build import make_env

    cfg = load(["compute=smoke", "reward=modelfree", "dr=paper", "compute.num_envs=64"])
    env = make_env(cfg, "teacher")
    env.reset()
    yield env
    env.close()


def _pair(env, **changes):
    """mjlab's ``UniformVelocityCommand`` and march's sync-free one on the same env and config
    (``changes``: config fields to set on both, e.g. standing / world / forward shares)."""
    from mjlab.tasks.velocity.mdp import UniformVelocityCommandCfg
    from mjlab.tasks.velocity.mdp.velocity_command import UniformVelocityCommand

    from march.env.velocity_command import SyncFreeVelocityCommand, sync_free

    twist = env.command_manager.get_term("twist")
    assert isinstance(twist, SyncFreeVelocityCommand)
    cfg = dataclasses.replace(twist.cfg, **changes)
    base = UniformVelocityCommandCfg(
        **{f.name: getattr(cfg, f.name) for f in dataclasses.fields(cfg) if f.init}
    )
    return UniformVelocityCommand(base, env), SyncFreeVelocityCommand(sync_free(base), env)


def _wide():
    from mjlab.tasks.velocity.mdp import UniformVelocityCommandCfg

    ranges = UniformVelocityCommandCfg.Ranges(
        lin_vel_x=(-1.0, 1.0), lin_vel_y=(-0.5, 0.5), ang_vel_z=(-1.0, 1.0), heading=(-3.0, 3.0)
    )
    return {"ranges": ranges}


WIDE = _wide()
"""Every command component drawn from a non-empty range (march's own keep vy and heading 0)."""
STATE = ("vel_command_b", "vel_command_w", "heading_target", "is_heading_env")
MASKS = ("is_standing_env", "is_world_env", "is_forward_env")


def _same(a, b, names=STATE + MASKS):
    for name in names:
        assert torch.equal(getattr(a, name), getattr(b, name)), name


@pytest.mark.parametrize(
    "shares",
    [
        {},  # march's own config: heading envs only
        {"rel_standing_envs": 0.3, "rel_world_envs": 0.4, "rel_forward_envs": 0.5, **WIDE},
        {"rel_heading_envs": 0.5, "rel_world_envs": 1.0, "rel_standing_envs": 0.0, **WIDE},
    ],
)
def test_the_sync_free_twist_command_computes_mjlabs_numbers(env, shares):
    """Reset draws (a host-sized id batch) and the per-step update equal mjlab's bit for bit,
    over many random resets and robot headings."""
    mj, ours = _pair(env, **shares)
    gen = torch.Generator().manual_seed(5)
    for _ in range(20):
        ids = torch.randperm(env.num_envs, generator=gen)[
            : int(torch.randint(1, 64, (1,), generator=gen))
        ]
        seed = int(torch.randint(0, 2**31, (1,), generator=gen))
        torch.manual_seed(seed)
        mj._resample_command(ids)
        torch.manual_seed(seed)
        ours._resample_command(ids)
        _same(mj, ours)
        mj._update_command(None)
        ours._update_command(None)
        _same(mj, ours)
        assert torch.equal(mj.heading_error, ours.heading_error)
    if shares:  # the masks took both values: every branch ran
        mixed = [m for m in (*MASKS, "is_heading_env") if 0 < int(getattr(ours, m).sum()) < 64]
        assert mixed


def test_a_due_command_is_resampled_from_the_same_ranges(env):
    """With a short resampling time the due envs (and only they) draw new commands, uniform in
    the configured ranges; the others keep theirs; the timers restart in the range."""
    _, ours = _pair(env, resampling_time_range=(0.05, 0.05))
    assert not ours._never_due
    ours.time_left.fill_(1.0)
    ours.time_left[:10] = 0.01
    before = ours.vel_command_b.clone()
    ours.compute(0.02)
    changed = (ours.vel_command_b != before).any(-1)
    assert changed[:10].all() and not changed[10:].any()
    assert torch.allclose(ours.time_left[:10], torch.full((10,), 0.05))
    assert torch.allclose(ours.time_left[10:], torch.full((54,), 0.98))
    lo, hi = ours.cfg.ranges.lin_vel_x
    assert ((ours.vel_command_b[:10, 0] >= lo) & (ours.vel_command_b[:10, 0] <= hi)).all()
    assert ours.command_counter[:10].min() >= 1


def test_the_push_keeps_mjlabs_timer_rule_and_arithmetic(env):
    """Due envs (timer below 1e-6 s after the step) get mjlab's push arithmetic; the others keep
    their root velocity bit for bit; due timers restart in [10, 15] s, others count down."""
    from mjlab.utils.lab_api.math import quat_apply_inverse

    term = env.event_manager.get_term_cfg("push_robot")
    assert term.mode == "step" and term.interval_range_s == (10.0, 15.0)
    push = term.func
    robot = env.scene["robot"]
    env.sim.forward()
    push.time_left[:] = 5.0
    push.time_left[::4] = 0.5 * env.step_dt  # 16 envs fall due this step
    qvel0 = robot.data.data.qvel.clone()
    vel_w = robot.data.root_link_vel_w.clone()
    torch.manual_seed(3)
    push(env, None, **term.params)
    due = torch.zeros(env.num_envs, dtype=torch.bool)
    due[::4] = True
    qvel = robot.data.data.qvel
    adr = robot.data.indexing.free_joint_v_adr
    assert torch.equal(qvel[~due], qvel0[~due])
    # mjlab's push on the same offsets: the draw order is timers, then offsets
    torch.manual_seed(3)
    torch.rand(env.num_envs)
    offset = push.lo + push.span * torch.rand(env.num_envs, 6)
    want = vel_w + offset
    quat = robot.data.data.qpos[:, robot.data.indexing.free_joint_q_adr[3:7]]
    want = torch.cat([want[:, :3], quat_apply_inverse(quat, want[:, 3:])], -1)
    assert torch.equal(qvel[due][:, adr], want[due])
    d = offset[due]
    assert d[:, :2].abs().max() <= 1.0 and d[:, 2].abs().max() == 0.0
    assert d[:, 3:].abs().max() <= 0.4
    assert ((push.time_left[due] >= 10.0) & (push.time_left[due] <= 15.0)).all()
    assert torch.allclose(push.time_left[~due], torch.full((48,), 5.0 - env.step_dt))
    push.reset(torch.arange(4))
    assert ((push.time_left[:4] >= 10.0) & (push.time_left[:4] <= 15.0)).all()
    env.reset()
