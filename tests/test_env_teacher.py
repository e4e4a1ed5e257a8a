"""The teacher env with stage (1) wired in: reference command term, CLF rewards, terminations and
privileged observations, for reward=clf and reward=modelfree (one env per reward, built once)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from march.clf.lyapunov import CLF_OUTPUT_NAMES
from march.config.cli import load
from march.env.build import build_env_cfg, make_env
from march.env.course import CourseRuler
from march.env.observations import NUM_STONES, STONE_FEATURES

ROOT = Path(__file__).resolve().parent.parent
STEPS = 200

# The documented difference between the two reward sets (conf/reward/*.yaml, README).
CLF_ONLY = {"clf", "dclf", "holonomic_pos", "holonomic_vel"}
MODELFREE_ONLY = {
    "track_linear_velocity",
    "track_angular_velocity",
    "forward_progress",
    "alive",
    "upright",
    "feet_edge_distance",
    "foot_slip",
}
SHARED = {"torque": 1.0e-5, "joint_limits": 1.0, "action_rate": 0.01}


def _cfg(reward: str):
    return load(["compute=smoke", f"reward={reward}"])


# ------------------------------------------------------------------ config level (no env)


def test_reward_sets_differ_in_the_documented_terms():
    clf = build_env_cfg(_cfg("clf"), "teacher")
    free = build_env_cfg(_cfg("modelfree"), "teacher")
    ck, fk = set(clf.rewards), set(free.rewards)
    assert ck - fk == CLF_ONLY
    assert fk - ck == MODELFREE_ONLY
    assert ck & fk == set(SHARED)
    for name, weight in SHARED.items():
        assert clf.rewards[name].weight == free.rewards[name].weight == weight
    assert clf.rewards["clf"].weight == 10.0 and clf.rewards["dclf"].weight == 1.0
    assert clf.rewards["holonomic_pos"].weight == 4.0
    assert clf.rewards["holonomic_vel"].weight == 2.0
    # One sign convention: every weight is positive (penalties return values <= 0).
    assert all(t.weight > 0 for t in [*clf.rewards.values(), *free.rewards.values()])
    # Only clf runs the planner: its command, its termination and its observation.
    assert set(clf.commands) - set(free.commands) == {"reference"}
    assert set(clf.terminations) - set(free.terminations) == {"planner_infeasible"}
    assert "foot_too_low" in free.terminations
    for group in ("actor", "critic"):
        ct, ft = set(clf.observations[group].terms), set(free.observations[group].terms)
        assert ct - ft == {"reference"}
        assert "stones" in ft


def _feet_sensor(sensors):
    (feet,) = [s for s in sensors if s.name == "feet_ground_contact"]
    return feet


def test_air_time_is_tracked_only_where_a_term_reads_it():
    """mjlab's G1 task tracks the feet's air time for terms neither arm has; a term that reads
    it (mjlab's own feet_air_time reward, or a user's function naming the timers) keeps the
    tracking, in every purpose's env."""
    from dataclasses import replace

    from mjlab.managers.reward_manager import RewardTermCfg
    from mjlab.tasks.velocity import mdp as vel_mdp
    from mjlab.tasks.velocity.config.g1.env_cfgs import unitree_g1_rough_env_cfg

    from march.env.build import _air_time_if_read

    def reads_timers(env, sensor_name: str = "feet_ground_contact"):
        return env.scene[sensor_name].data.current_air_time.sum(-1)

    mjlab_cfg = unitree_g1_rough_env_cfg()
    assert _feet_sensor(mjlab_cfg.scene.sensors).track_air_time  # what mjlab asks for
    assert _feet_sensor(_air_time_if_read(mjlab_cfg)).track_air_time  # its terms read it
    for reward in ("clf", "modelfree"):
        cfg = load(["compute=smoke", f"reward={reward}"])
        for purpose in ("teacher", "student", "eval"):
            env_cfg = build_env_cfg(cfg, purpose)
            assert not _feet_sensor(env_cfg.scene.sensors).track_air_time, (reward, purpose)
            env_cfg.scene.sensors = tuple(
                replace(s, track_air_time=True) if s.name == "feet_ground_contact" else s
                for s in env_cfg.scene.sensors
            )
            assert not _feet_sensor(_air_time_if_read(env_cfg)).track_air_time
            for func in (vel_mdp.feet_air_time, reads_timers):
                env_cfg.rewards["extra"] = RewardTermCfg(func=func, weight=1.0, params={})
                assert _feet_sensor(_air_time_if_read(env_cfg)).track_air_time, func.__name__


def test_no_placeholders_left_for_the_teacher():
    from march.env.build import PLACEHOLDERS

    assert "reward=clf" not in PLACEHOLDERS and "reference" not in PLACEHOLDERS


# ------------------------------------------------------------------ rollouts on the real env


def _rollout(env, steps: int = STEPS) -> dict:
    """Random actions with resets; per-term extremes of the reward manager's per-step buffers."""
    rm = env.reward_manager
    names = list(rm.active_terms)
    lo = {n: math.inf for n in names}
    hi = {n: -math.inf for n in names}
    finite = {n: True for n in names}
    term = (
        env.command_manager.get_term("reference")
        if "reference" in env.command_manager.active_terms
        else None
    )
    gen = torch.Generator().manual_seed(0)
    n_act = env.action_manager.total_action_dim
    resets = 0
    plans_checked = plans_off = 0
    if term is not None:
        # Random actions land feet only while the robot falls (pelvis tilt 0.58-0.88 rad, no
        # touchdown since issue 55): the tilt condition is lifted so that the replanning at a
        # touchdown is exercised here (tests/test_env_reference.py tests the condition).
        term.cfg.touchdown_max_tilt = math.pi
    env.reset()
    for _ in range(steps):
        action = 0.3 * torch.randn(env.num_envs, n_act, generator=gen)
        _, reward, terminated, truncated, _ = env.step(action)
        assert torch.isfinite(reward).all()
        resets += int((terminated | truncated).sum())
        for j, n in enumerate(names):
            raw = rm.get_term_cfg(n).func(env, **rm.get_term_cfg(n).params)
            finite[n] &= bool(torch.isfinite(raw).all())
            v = rm._step_reward[:, j] / rm.get_term_cfg(n).weight
            lo[n] = min(lo[n], float(v.min()))
            hi[n] = max(hi[n], float(v.max()))
        if term is not None:
            new = term.step_switched & term.plan_feasible
            if new.any():
                ids = new.nonzero().flatten()
                fh = term.footholds.index(ids)
                margin = term.cfg.planner.stone_margin - 1e-3
                on = fh.contains(term.plan_footholds[ids, :, :2], margin=margin)
                plans_checked += on.numel()
                plans_off += int((~on).sum())
    return {
        "names": names,
        "lo": lo,
        "hi": hi,
        "finite": finite,
        "resets": resets,
        "plans_checked": plans_checked,
        "plans_off": plans_off,
    }


@pytest.fixture(scope="module")
def clf_env():
    env = make_env(_cfg("clf"), "teacher")
    yield env
    env.close()


@pytest.fixture(scope="module")
def clf_run(clf_env):
    return _rollout(clf_env)


@pytest.mark.sim
def test_clf_terms_finite_and_in_range(clf_env, clf_run):
    assert clf_run["resets"] > 0  # the rollout crossed episode resets
    assert all(clf_run["finite"].values()), clf_run["finite"]
    lo, hi = clf_run["lo"], clf_run["hi"]
    assert set(clf_run["names"]) == CLF_ONLY | set(SHARED)
    assert math.exp(-1.0) - 1e-6 <= lo["clf"] <= hi["clf"] <= 1.0 + 1e-6
    assert hi["dclf"] <= 0.0
    assert lo["dclf"] < 0.0  # random actions violate the decrease condition somewhere
    clip = clf_env.command_manager.get_term("reference").cfg.clf.dclf_clip
    assert clip is None or lo["dclf"] >= -clip - 1e-6
    for name in ("holonomic_pos", "holonomic_vel"):
        assert 0.0 <= lo[name] <= hi[name] <= 1.0
    for name in SHARED:
        assert hi[name] <= 0.0  # penalties


@pytest.mark.sim
def test_clf_outputs_and_replanning(clf_env, clf_run):
    term = clf_env.command_manager.get_term("reference")
    e = clf_env.num_envs
    for t in (term.y_ref_pos, term.y_ref_vel, term.y_sim_pos, term.y_sim_vel):
        assert t.shape == (e, len(CLF_OUTPUT_NAMES)) and torch.isfinite(t).all()
    assert term.plan_feasible.shape == (e,) and term.plan_feasible.dtype == torch.bool
    assert term.v.shape == (e,) and torch.isfinite(term.v).all()
    # Touchdowns happened and triggered replans; every feasible new plan lies on stones.
    assert int(term.touchdown_count.sum()) > 0
    assert bool((term.replan_count >= term.touchdown_count + 1).all())
    assert clf_run["plans_checked"] > 0 and clf_run["plans_off"] == 0
    # The term's footholds follow the curriculum's cells (table lookup redone on reset).
    ruler = CourseRuler(clf_env).footholds()
    assert torch.allclose(term.footholds.center, ruler.center)
    # Both CLF terms read the one V of this step.
    v, _, _ = term.clf_state()
    assert v is term.v
    obs = clf_env.observation_manager.compute()
    om = clf_env.observation_manager
    dims = dict(zip(om.active_terms["actor"], om.group_obs_term_dim["actor"], strict=True))
    n = term.cfg.planner.num_steps
    assert dims["reference"] == (2 * len(CLF_OUTPUT_NAMES) + 3 * n + 2,)
    assert dims["stones"] == (NUM_STONES * STONE_FEATURES,)
    assert torch.isfinite(obs["actor"]).all() and torch.isfinite(obs["critic"]).all()


@pytest.mark.sim
def test_planner_infeasible_terminates(clf_env, clf_run):
    term = clf_env.command_manager.get_term("reference")
    ids = torch.tensor([0], device=clf_env.device)
    term.footholds.center[0, :, :2] += 50.0  # every stone far away: no safe foothold
    plan = term.replan(ids)
    assert not bool(plan.feasible[0]) and not bool(term.plan_feasible[0])
    n_act = clf_env.action_manager.total_action_dim
    _, _, terminated, _, _ = clf_env.step(torch.zeros(clf_env.num_envs, n_act))
    assert bool(clf_env.termination_manager.get_term("planner_infeasible")[0])
    assert bool(terminated[0])
    # The reset restored the env's real course and a feasible plan from the start platform.
    assert torch.allclose(term.footholds.center[0], CourseRuler(clf_env).footholds().center[0])
    assert bool(term.plan_feasible[0])


@pytest.fixture(scope="module")
def modelfree_run():
    # Built after the clf tests ran (file order), so only one env is ever being built.
    env = make_env(_cfg("modelfree"), "teacher")
    try:
        # 100 steps: every env falls and resets once (4 resets at seeds 0-1); no touchdown or
        # plan to wait for here (the clf rollout walks STEPS for those)
        run = _rollout(env, steps=100)
        run["commands"] = list(env.command_manager.active_terms)
        run["terminations"] = list(env.termination_manager.active_terms)
        om = env.observation_manager
        run["actor_terms"] = dict(
            zip(om.active_terms["actor"], om.group_obs_term_dim["actor"], strict=True)
        )
    finally:
        env.close()
    return run


@pytest.mark.sim
def test_modelfree_terms_finite(modelfree_run):
    run = modelfree_run
    assert run["resets"] > 0
    assert all(run["finite"].values()), run["finite"]
    assert set(run["names"]) == MODELFREE_ONLY | set(SHARED)
    assert -2.0 <= run["lo"]["feet_edge_distance"] <= run["hi"]["feet_edge_distance"] <= 0.0
    assert "reference" not in run["commands"]
    assert "planner_infeasible" not in run["terminations"]
    assert "foot_too_low" in run["terminations"]
    assert "reference" not in run["actor_terms"]
    assert run["actor_terms"]["stones"] == (NUM_STONES * STONE_FEATURES,)


@pytest.mark.sim
def test_inspect_lists_clf_terms(modelfree_run):
    # After the in-process envs are done (never two env builds at once). In this process: the
    # command itself (``python -m march.inspect compute=smoke > env.json``, clf the default)
    # runs in getting-started's block (tests/test_docs.py), which checks its stdout is JSON;
    # a second process here paid ~8 s of CPU for its imports alone.
    from march.inspect import inspect

    info = json.loads(json.dumps(inspect(load(["reward=clf", "compute=smoke"]))))
    names = [r["name"] for r in info["rewards"]]
    assert "clf" in names and "dclf" in names
    assert "planner_infeasible" in [t["name"] for t in info["terminations"]]
    assert "reward=clf" not in info["placeholders"]


@pytest.mark.sim
def test_g1_stands_on_the_start_platform(clf_env):
    """Spawned on the start platform, the G1 neither falls through it nor sticks in a stone:
    over the first 0.3 s with zero actions the feet rest on the platform top and the pelvis stays
    at standing height."""
    env = clf_env
    env.reset()
    robot = env.scene["robot"]
    feet = [robot.site_names.index(s) for s in ("left_foot", "right_foot")]
    top = env.scene.env_origins[:, 2]
    for _ in range(15):
        _, _, terminated, _, _ = env.step(
            torch.zeros(env.num_envs, env.action_manager.total_action_dim)
        )
        assert not terminated.any()
        foot_z = robot.data.site_pos_w[:, feet, 2] - top[:, None]
        assert foot_z.min() > -0.01, foot_z  # not sunk into the platform
        assert foot_z.max() < 0.05, foot_z  # resting on it, not stuck above
        pelvis = robot.data.root_link_pos_w[:, 2] - top
        assert (pelvis > 0.6).all() and (pelvis < 0.85).all(), pelvis


def _served_per_step(env, capacity: int, steps: int) -> dict[str, list[int]]:
    """Zero-action steps from a reset with the reference term's planner batch set to
    ``capacity``: per step, the touchdowns + timeouts served, the ones waiting, the resets."""
    from march.env.build import reseed_env

    term = env.command_manager.get_term("reference")
    saved = term.queue.capacity
    term.queue.capacity = capacity
    try:
        # The same start whatever ran before on this module's env (a random test order): the
        # planner's generator and torch seeded, queued replans dropped, every env reset.
        reseed_env(env, 0)
        torch.manual_seed(0)
        env.reset()
        zeros = torch.zeros(env.num_envs, env.action_manager.total_action_dim)
        served, waiting, resets = [], [], []
        before = int((term.touchdown_count + term.forced_count).sum())
        deferred0 = int(term.queue.deferred_count.sum())
        for _ in range(steps):
            _, _, terminated, truncated, _ = env.step(zeros)
            now = int((term.touchdown_count + term.forced_count).sum())
            served.append(now - before)
            before = now
            waiting.append(int(term.queue.waiting().sum()))
            resets.append(int((terminated | truncated).sum()))
        return {
            "served": served,
            "waiting": waiting,
            "resets": resets,
            "deferred": int(term.queue.deferred_count.sum()) - deferred0,
        }
    finally:
        term.queue.capacity = saved


@pytest.mark.sim
def test_replans_beyond_the_planner_batch_wait_and_are_served(clf_env):
    """Issue 11: touchdowns and timeouts are planned in a fixed-size batch per step. Standing
    with zero actions, the swing foot never leaves the ground, so every env's first step ends
    as a touchdown at 0.6 x its planned duration (0.27-0.42 s), several envs in the same step.
    With a batch of one env at most one is served per step and the others wait, flagged, for a
    later step (each waiting env-step is counted once); with a batch of every env nothing waits
    and the same bursts are served at once."""
    steps = 70  # 1.4 s: past every first timeout
    small = _served_per_step(clf_env, capacity=1, steps=steps)
    assert max(small["served"]) == 1
    assert small["deferred"] > 0 and max(small["waiting"]) >= 1
    # Every waiting event is served one per step: the queue shrinks by exactly the served one
    # unless new events arrive, and the deferred env-steps are the queue's sum over the steps.
    assert small["deferred"] == sum(small["waiting"])
    assert sum(small["served"]) >= clf_env.num_envs - sum(small["resets"])
    full = _served_per_step(clf_env, capacity=clf_env.num_envs, steps=steps)
    assert full["deferred"] == 0 and max(full["waiting"]) == 0
    assert max(full["served"]) > 1  # the same burst, served at once


def test_planner_batch_size_per_update():
    """1/8 of the envs, at least 8, never more than there are (hand-computed)."""
    from march.env.reference_command import ReferenceCommandCfg

    cfg = ReferenceCommandCfg()
    sizes = {e: cfg.capacity(e) for e in (1, 4, 8, 64, 65, 100, 4096)}
    assert sizes == {1: 1, 4: 4, 8: 8, 64: 8, 65: 9, 100: 13, 4096: 512}
    for bad in ({"replan_capacity_fraction": 0.0}, {"replan_capacity_min": 0}):
        with pytest.raises(ValueError, match="replan_capacity"):
            ReferenceCommandCfg(**bad)
