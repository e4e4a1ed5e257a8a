"""The G1 action's joint groups (march.env.joint_groups) and the teacher's initial action std per
group (teacher.init_std x init_std_<group>, issue 56): derived from mjlab's joint names in
action order, and set on rsl-rl's actor so that the first rollout is drawn with it."""

from __future__ import annotations

import math

import pytest
import torch

from march.config import ConfigError
from march.config.cli import load
from march.env.joint_groups import (
    G1_GROUP_SIZES,
    JOINT_GROUPS,
    group_index,
    group_means,
    group_of,
    joint_groups,
    per_joint,
)


def test_mjlab_g1_joints_fall_into_legs_waist_arms():
    from march.env.g1 import g1_joint_names

    names = g1_joint_names()
    groups = joint_groups(names)
    assert {g: len(ix) for g, ix in groups.items()} == G1_GROUP_SIZES
    assert sorted(i for ix in groups.values() for i in ix) == list(range(len(names)))
    # by what the names say, not by the patterns' own wording
    for i, n in enumerate(names):
        side = n.split("_")[0]
        if "waist" in n:
            assert i in groups["waist"]
        elif any(k in n for k in ("shoulder", "elbow", "wrist")):
            assert i in groups["arms"] and side in ("left", "right")
        else:
            assert i in groups["legs"] and any(k in n for k in ("hip", "knee", "ankle"))


def test_a_name_in_no_group_or_two_is_refused():
    with pytest.raises(ValueError, match="exactly one"):
        group_of("neck_yaw_joint")
    with pytest.raises(ValueError, match="exactly one"):
        group_of("waist_hip_pitch_joint")  # waist and legs both match


def test_group_means_against_a_hand_sum():
    names = ["l_hip_x", "waist_y", "l_elbow_z", "r_knee_x", "r_wrist_q", "r_shoulder_p"]
    idx = group_index(names)
    x = torch.tensor([[1.0, 2.0, 3.0, 5.0, 7.0, 11.0], [0.0, 1.0, 0.0, 1.0, 0.0, 1.0]])
    got = group_means(x, idx)
    want = torch.tensor([[(1 + 5) / 2, 2.0, (3 + 7 + 11) / 3], [0.5, 1.0, 1 / 3]])
    torch.testing.assert_close(got, want)
    assert per_joint(names, {"legs": 1.0, "waist": 0.5, "arms": 0.25}).tolist() == [
        1.0, 0.5, 0.25, 1.0, 0.25, 0.25,
    ]  # fmt: skip


def test_group_init_std_config():
    t = load([]).teacher
    assert t.group_init_std == {"legs": 1.0, "waist": 1.0, "arms": 1.0}  # the paper's
    t = load(["teacher.init_std=0.8", "teacher.init_std_arms=0.25"]).teacher
    assert t.group_init_std == pytest.approx({"legs": 0.8, "waist": 0.8, "arms": 0.2})
    for g in JOINT_GROUPS:
        with pytest.raises(ConfigError, match=f"init_std_{g}"):
            load([f"teacher.init_std_{g}=0"])


@pytest.mark.sim
def test_the_teacher_actor_starts_with_the_std_of_each_joints_group(tmp_path):
    """A real smoke env and rsl-rl's PPO: every action's std is its group's, in the env's
    action order, and the first rollout's stored distributions carry it."""
    from march.env.build import make_env
    from march.env.g1 import g1_joint_names
    from march.env.joint_groups import action_joint_names
    from march.learn.metrics import MetricsLog
    from march.learn.stage_runner import EpisodeStats
    from march.learn.teacher import TeacherRunner

    cfg = load(
        [
            "compute=smoke",
            "compute.num_envs=4",
            "teacher.init_std_waist=0.5",
            "teacher.init_std_arms=0.25",
        ]
    )
    env = make_env(cfg, "teacher")
    log = MetricsLog(tmp_path, cfg.logger, "t")
    try:
        names = action_joint_names(env)
        assert names == g1_joint_names()  # mjlab's G1 order is the action order
        runner = TeacherRunner(env, cfg, tmp_path, log)
        std = runner.alg.actor.distribution.std_param.detach()
        want = {"legs": 1.0, "waist": 0.5, "arms": 0.25}
        for i, n in enumerate(names):
            assert math.isclose(float(std[i]), want[group_of(n)]), n
        runner.start()
        runner.collect(EpisodeStats(env.num_envs, runner.device))
        stored_std = runner.alg.storage.distribution_params[1]  # (T, E, A) of the rollout
        assert torch.allclose(stored_std, std.expand_as(stored_std))
    finally:
        log.close()
        env.close()
