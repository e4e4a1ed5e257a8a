"""Commands in the course frame (issue 10): the twist command both reward arms share, the
reference command's heading and its start from standing."""

from __future__ import annotations

import math

import pytest
import torch

from march.config import ConfigError, EnvCfg
from march.config.cli import load
from march.env.build import COURSE_HEADING, build_env_cfg, make_env


def _twist(reward: str, purpose: str, *overrides: str):
    cfg = load(["compute=smoke", f"reward={reward}", *overrides])
    return cfg, build_env_cfg(cfg, purpose).commands["twist"]


@pytest.mark.parametrize("purpose", ["teacher", "student", "eval"])
def test_both_arms_share_one_course_frame_command(purpose):
    """The same twist command for clf and modelfree: one forward speed per episode, no lateral
    command by default, the yaw rate from a heading controller toward the course heading."""
    cfg, clf = _twist("clf", purpose)
    _, free = _twist("modelfree", purpose)
    assert clf == free
    assert clf.heading_command and clf.rel_heading_envs == 1.0
    assert clf.ranges.heading == (COURSE_HEADING, COURSE_HEADING) == (0.0, 0.0)
    assert clf.heading_control_stiffness == cfg.env.command_heading_stiffness == 0.5
    assert clf.ranges.ang_vel_z == tuple(cfg.env.command_yaw_rate)
    assert clf.ranges.lin_vel_y == (0.0, 0.0)
    assert clf.rel_standing_envs == clf.rel_world_envs == clf.rel_forward_envs == 0.0
    assert clf.init_velocity_prob == 0.0
    assert clf.resampling_time_range[0] > 1e6  # never resampled within an episode
    if purpose == "eval":
        assert clf.ranges.lin_vel_x == (cfg.eval.command_vx, cfg.eval.command_vx)
    else:
        assert clf.ranges.lin_vel_x == tuple(cfg.env.command_vx)


def test_eval_command_override_is_kept():
    _, twist = _twist("clf", "eval", "eval.command_vx=0.45")
    assert twist.ranges.lin_vel_x == (0.45, 0.45)


def test_yaw_rate_bounds_must_allow_facing_the_course():
    with pytest.raises(ConfigError, match="must contain 0"):
        EnvCfg(command_yaw_rate=(0.1, 0.2))
    with pytest.raises(ConfigError, match="command_heading_stiffness"):
        EnvCfg(command_heading_stiffness=-1.0)


@pytest.mark.sim
def test_env_commands_follow_the_course_and_the_first_step_starts_at_rest():
    """A real clf teacher env: the yaw command steers to the course heading, the lateral command
    is 0, the yaw references hold the course heading, the first plan advances along the course,
    and the first step's CoM reference starts at the measured CoM with zero velocity."""
    cfg = load(["compute=smoke", "reward=clf"])
    env = make_env(cfg, "teacher", num_envs=4)
    try:
        env.reset()
        zero = torch.zeros(env.num_envs, env.action_manager.total_action_dim)
        env.step(zero)  # the reference term plans in the command update after the reset
        term = env.command_manager.get_term("reference")
        twist = env.command_manager.get_term("twist")
        heading = env.scene["robot"].data.heading_w
        cmd = twist.command
        lo, hi = cfg.env.command_yaw_rate
        k = cfg.env.command_heading_stiffness
        expect = (k * torch.atan2(torch.sin(-heading), torch.cos(-heading))).clamp(lo, hi)
        torch.testing.assert_close(cmd[:, 2], expect, atol=1e-5, rtol=0)
        assert (cmd[:, 1] == 0).all()
        assert ((cmd[:, 0] >= cfg.env.command_vx[0]) & (cmd[:, 0] <= cfg.env.command_vx[1])).all()
        # The first step of the episode ramps from rest at the CoM measured when it was planned.
        assert term.step.ramp.all() and (term.touchdown_count == 0).all()
        com0 = env.sim.data.subtree_com[:, term._root_body, :2]
        pos0, vel0 = term.reference(torch.zeros(env.num_envs))
        torch.testing.assert_close(pos0[:, :2], term.step.ramp_from)
        assert vel0[:, :2].abs().max() < 1e-6
        assert (term.step.ramp_from - com0).norm(dim=-1).max() < 0.02  # standing still
        assert term.y_ref_vel[:, :2].norm(dim=-1).max() < 0.1  # one control step later
        # Yaw references: the course heading, not an integrated yaw rate.
        assert (term.step.yaw0 == COURSE_HEADING).all() and (term.step.yaw_rate == 0).all()
        assert term.y_ref_pos[:, 5].abs().max() < 1e-6 and term.y_ref_pos[:, 11].abs().max() < 1e-6
        # The plan walks along the course (+x).
        start = term.step.stance_pos[:, 0]
        assert (term.plan_footholds[:, -1, 0] > start + 0.3).all()
        # Some steps later the CoM reference has picked up speed along the course.
        for _ in range(10):
            env.step(zero)
        assert math.isfinite(float(term.y_ref_vel[:, 0].mean()))
        assert (term.y_ref_vel[:, 0] > 0.0).any()
    finally:
        env.close()


def test_masked_rows_write_equals_a_masked_update_over_random_batches():
    """MaskedRows (one index_put per tensor, the rows not applied sent to a spare row) against
    the plain gather + where + index_put, over random batches, masks, shapes and dtypes."""
    from types import SimpleNamespace

    from march.env.masked_rows import MaskedRows

    g = torch.Generator().manual_seed(5)
    for trial in range(40):
        e = int(torch.randint(1, 20, (1,), generator=g))
        state = SimpleNamespace(
            a=torch.randn(e, generator=g),
            b=torch.randn(e, 3, 2, generator=g),
            c=torch.rand(e, generator=g) > 0.5,
            d=torch.randint(0, 9, (e,), generator=g),
        )
        want = {k: v.clone() for k, v in vars(state).items()}
        rows = MaskedRows(e, {k: (state, k) for k in want})
        for _ in range(3):
            n = int(torch.randint(0, e + 1, (1,), generator=g))
            ids = torch.randperm(e, generator=g)[:n]
            apply = torch.rand(n, generator=g) > 0.4
            values = {
                "a": torch.randn(n, generator=g),
                "b": torch.randn(n, 3, 2, generator=g),
                "c": torch.rand(n, generator=g) > 0.5,
                "d": torch.randint(0, 9, (n,), generator=g).to(torch.int32),  # cast on write
            }
            rows.write(ids, apply, values)
            for k, v in values.items():
                keep = apply.view(-1, *([1] * (v.dim() - 1)))
                want[k][ids] = torch.where(keep, v.to(want[k].dtype), want[k][ids])
            for k in want:
                got = getattr(state, k)
                assert got.shape == want[k].shape and torch.equal(got, want[k]), (trial, k)


def test_masked_rows_write_is_one_index_put_per_dtype():
    """Issue 41: the tensors of one dtype share one buffer (the owners' attributes are views of
    it), so a write of the reference term's 19 tensors is a where, one cat and one index_put
    per dtype (float, bool): 5 ops, not 20."""
    from types import SimpleNamespace

    from march.bench.ops import OpCounter
    from march.env.masked_rows import MaskedRows

    e, n = 8, 3
    floats = {f"f{i}": torch.randn(e, *(() if i % 2 else (4, 3))) for i in range(14)}
    bools = {f"b{i}": torch.rand(e) > 0.5 for i in range(5)}
    state = SimpleNamespace(**floats, **bools)
    rows = MaskedRows(e, {k: (state, k) for k in vars(state)})
    assert state.f0.shape == (e, 4, 3) and state.b0.dtype == torch.bool
    values = {k: torch.zeros(n, *v.shape[1:], dtype=v.dtype) for k, v in vars(state).items()}
    ids, apply = torch.tensor([1, 4, 6]), torch.tensor([True, False, True])
    with torch.inference_mode():  # as in the teacher's rollouts (plus one detach_ per buffer
        rows.write(ids, apply, values)  # on its first write there, which this one makes)
        with OpCounter() as ops:
            rows.write(ids, apply, values)
    assert ops.total == 5, ops.counts
    assert float(state.f0[1].abs().sum()) == 0.0 and float(state.f0[4].abs().sum()) > 0.0
    state.f1 += 1.0  # an in-place update through the owner's view lands in the buffer
    assert torch.equal(rows.storage["f1"][:e], state.f1)
