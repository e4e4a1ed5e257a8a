"""The evaluation protocol: rollout metrics on hand-made trajectories, the stratified course
assignment, one set of terminations / courses / commands for every arm, success reachable at every
compute preset, and teacher-stage rows in eval.csv (resumed without duplicates)."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from march.config.cli import load
from march.env.course import eval_cells
from march.evaluation.protocol import episode_metrics, summarise
from march.learn.metrics import EVAL_COLUMNS, EVAL_METRICS, append_row, has_row, truncate_rows
from march.world.courses import CourseCfg, generate_course

DT = 0.02
PRESETS = ("smoke", "cpu", "gpu", "auto")


def _traj(t_len: int, e: int = 1):
    """Zero trajectories of T steps for E envs (everything a test does not set is 0 / False)."""
    return {
        "torque": torch.zeros(t_len, e),
        "ang_vel": torch.zeros(t_len, e, 3),
        "reward": torch.zeros(t_len, e),
        "terminated": torch.zeros(t_len, e, dtype=torch.bool),
        "truncated": torch.zeros(t_len, e, dtype=torch.bool),
        "progress": torch.zeros(t_len, e),
        "goal_distance": torch.zeros(e),
        "dt": DT,
        "reached": torch.zeros(t_len, e, dtype=torch.bool),
    }


# ------------------------------------------------------------------ per-rollout arithmetic


def test_jerk_and_torque_leave_the_reset_out():
    """Episode of 4 live steps ending (fall) at step 4; steps 4.. carry the next episode's
    post-reset state (a huge jump) that must not enter jerk or torque."""
    tr = _traj(7)
    wx = [0.0, 1.0, 4.0, 9.0, 100.0, -50.0, 3.0]
    tr["ang_vel"][:, 0, 0] = torch.tensor(wx)
    tr["torque"][:, 0] = torch.tensor([10.0, 20.0, 30.0, 40.0, 999.0, 999.0, 999.0])
    tr["terminated"][4, 0] = True
    m = episode_metrics(**tr)
    # Live steps 0..3; jerk samples at t = 2, 3: second differences 4-2+0 = 2 and 9-8+1 = 2 on
    # the x axis only, so |.| averaged over 3 axes is 2/3, over dt^2.
    assert m["abs_ang_jerk"].item() == pytest.approx((2.0 / 3.0) / DT**2)
    assert m["abs_torque_nm"].item() == pytest.approx(25.0)
    assert m["episode_steps"].item() == 5


def test_jerk_hand_values_on_all_axes():
    tr = _traj(5)
    w = torch.tensor([[0, 0, 0], [1, -1, 2], [3, 1, 2], [2, 2, 2], [7, 7, 7.0]])
    tr["ang_vel"][:, 0] = w
    tr["truncated"][4, 0] = True
    m = episode_metrics(**tr)
    # t=2: (3-2+0, 1+2+0, 2-4+0) = (1, 3, -2) -> mean |.| 2; t=3: (2-6+1, 2-2-1, 2-4+2) =
    # (-3, -1, 0) -> 4/3. Mean (2 + 4/3) / 2 = 5/3.
    assert m["abs_ang_jerk"].item() == pytest.approx((5.0 / 3.0) / DT**2)


@pytest.mark.parametrize(
    ("reached", "terminated", "truncated", "success"),
    [
        (True, False, True, 1.0),  # the success termination (the env reports it truncated too)
        (True, False, False, 1.0),  # reached, whatever the env's truncated flag
        (True, True, True, 0.0),  # the goal and a fall in one step count as a fall
        (False, False, True, 0.0),  # time-out short of the goal
        (False, True, False, 0.0),  # a fall
    ],
)
def test_success_rule(reached, terminated, truncated, success):
    tr = _traj(6)
    tr["goal_distance"][:] = 3.0
    # Pre-step progress; the episode ends at step 3.
    tr["progress"][:, 0] = torch.tensor([0.0, 1.0, 2.0, 2.9, 0.0, 0.0])
    tr["reached"][3, 0] = reached
    tr["terminated"][3, 0] = terminated
    tr["truncated"][3, 0] = truncated
    m = episode_metrics(**tr)
    assert m["success_rate"].item() == success
    # A success is scored at the goal distance, anything else at its last pre-step progress.
    assert m["distance_m"].item() == pytest.approx(3.0 if success else 2.9)
    assert m["episode_steps"].item() == 4


def _case(t_len: int = 8):
    """One env, goal at 2.0 m, torque t + 1 and reward 2^t at step t, progress 0.5 t (pre-step),
    angular velocity x = t^2 (second difference 2 everywhere: jerk (2/3) / dt^2)."""
    tr = _traj(t_len)
    steps = torch.arange(t_len, dtype=torch.float32)
    tr["goal_distance"][:] = 2.0
    tr["torque"][:, 0] = steps + 1
    tr["reward"][:, 0] = 2.0**steps
    tr["progress"][:, 0] = 0.5 * steps
    tr["ang_vel"][:, 0, 0] = steps**2
    return tr


def test_reach_then_fall_off_is_a_success_measured_up_to_the_goal():
    """The pelvis is over the goal platform after step 4 (success termination), and the same
    robot would have stepped off the far end at step 6: the rollout ended at step 4."""
    tr = _case()
    tr["reached"][4, 0] = True
    tr["truncated"][4, 0] = True
    tr["terminated"][6, 0] = True  # the next episode's business: never looked at
    m = episode_metrics(**tr)
    assert m["success_rate"].item() == 1.0
    assert m["distance_m"].item() == 2.0  # the goal distance
    assert m["episode_steps"].item() == 5
    assert m["reward"].item() == 1 + 2 + 4 + 8 + 16  # steps 0..4
    assert m["abs_torque_nm"].item() == pytest.approx((1 + 2 + 3 + 4) / 4)  # live steps 0..3
    assert m["abs_ang_jerk"].item() == pytest.approx((2.0 / 3.0) / DT**2)  # t = 2, 3


def test_fall_before_reaching_is_a_failure():
    tr = _case()
    tr["terminated"][2, 0] = True  # fell at step 2 (progress 1.0 before it)
    tr["reached"][5, 0] = True  # never happens in one episode: ignored
    m = episode_metrics(**tr)
    assert m["success_rate"].item() == 0.0
    assert m["distance_m"].item() == 1.0
    assert m["reward"].item() == 1 + 2 + 4
    assert m["abs_torque_nm"].item() == pytest.approx((1 + 2) / 2)
    assert math.isnan(m["abs_ang_jerk"].item())  # only 2 live steps


def test_time_out_on_the_stones_is_a_failure():
    tr = _case(4)  # progress 0, 0.5, 1.0, 1.5: the goal (2.0) never reached
    tr["truncated"][3, 0] = True
    m = episode_metrics(**tr)
    assert m["success_rate"].item() == 0.0
    assert m["distance_m"].item() == 1.5
    assert m["reward"].item() == 1 + 2 + 4 + 8
    assert m["abs_torque_nm"].item() == pytest.approx((1 + 2 + 3) / 3)
    assert m["abs_ang_jerk"].item() == pytest.approx((2.0 / 3.0) / DT**2)  # t = 2 only


def test_reach_at_the_last_step_is_a_success():
    """The goal is reached on the time-out step itself (both terminations fire): a success."""
    tr = _case(5)
    tr["reached"][4, 0] = True
    tr["truncated"][4, 0] = True
    m = episode_metrics(**tr)
    assert m["success_rate"].item() == 1.0
    assert m["distance_m"].item() == 2.0
    assert m["reward"].item() == 1 + 2 + 4 + 8 + 16
    assert m["abs_torque_nm"].item() == pytest.approx((1 + 2 + 3 + 4) / 4)
    # Still running at the horizon without a flag: timed out there, no success.
    tr = _case(5)
    m = episode_metrics(**tr)
    assert m["success_rate"].item() == 0.0 and m["distance_m"].item() == 2.0
    assert m["episode_steps"].item() == 5


def test_return_counts_the_final_step_not_the_next_episode():
    tr = _traj(5)
    tr["reward"][:, 0] = torch.tensor([1.0, 2.0, 4.0, 8.0, 16.0])
    tr["terminated"][2, 0] = True
    assert episode_metrics(**tr)["reward"].item() == pytest.approx(7.0)


def test_short_rollouts_are_left_out_and_counted():
    """Envs ending at step 0 (no live step), 2 (2 live steps: torque only), 3 (3: one jerk
    sample) and never (treated as timed out at the last step)."""
    tr = _traj(6, e=4)
    tr["torque"][:] = torch.arange(1.0, 7.0)[:, None]
    tr["ang_vel"][:, :, 1] = torch.tensor([0.0, 0.0, 1.0, 0.0, 0.0, 0.0])[:, None]
    tr["terminated"][0, 0] = True
    tr["terminated"][2, 1] = True
    tr["truncated"][3, 2] = True
    tr["progress"][:, 3] = torch.linspace(0.0, 5.0, 6)
    tr["goal_distance"][:] = 4.0
    m = episode_metrics(**tr)
    assert math.isnan(m["abs_torque_nm"][0]) and math.isnan(m["abs_ang_jerk"][0])
    assert m["abs_torque_nm"][1].item() == pytest.approx(1.5)  # steps 0, 1
    assert math.isnan(m["abs_ang_jerk"][1])
    assert m["abs_torque_nm"][2].item() == pytest.approx(2.0)  # steps 0, 1, 2
    assert m["abs_ang_jerk"][2].item() == pytest.approx((1.0 / 3.0) / DT**2)  # t=2: 1-0+0
    # Never ended: live steps 0..4, the last step is its time-out; no success termination, so
    # no success, and the distance stops at the goal (4.0).
    assert m["abs_torque_nm"][3].item() == pytest.approx(3.0)
    assert m["success_rate"][3].item() == 0.0 and m["distance_m"][3].item() == 4.0
    s = summarise(m)
    assert (s["n_torque"], s["n_jerk"]) == (3, 3 - 1)
    assert s["mean_abs_torque_nm"] == pytest.approx((1.5 + 2.0 + 3.0) / 3)
    assert s["mean_success_rate"] == 0.0  # success counts every rollout


def test_standard_errors_against_hand_values():
    per = {name: torch.tensor([1.0, 2.0, 3.0, 4.0]) for name in EVAL_METRICS}
    per["abs_ang_jerk"] = torch.tensor([2.0, float("nan"), 4.0, float("nan")])
    per["success_rate"] = torch.tensor([1.0, 0.0, 0.0, 0.0])
    s = summarise(per)
    # Sample std of 1..4 = sqrt(5/3); SE = sqrt(5/3) / 2.
    assert s["mean_distance_m"] == pytest.approx(2.5)
    assert s["se_distance_m"] == pytest.approx(math.sqrt(5.0 / 3.0) / 2.0)
    # Two defined jerks 2, 4: std sqrt(2), SE sqrt(2)/sqrt(2) = 1.
    assert s["mean_abs_ang_jerk"] == pytest.approx(3.0) and s["se_abs_ang_jerk"] == pytest.approx(1)
    # Success 1/4: SE = sqrt(p(1-p) n/(n-1)) / sqrt(n) = sqrt(0.25 * 0.75 / 3) = 0.25.
    assert s["se_success_rate"] == pytest.approx(0.25)
    assert s["n_jerk"] == 2 and s["n_torque"] == 4
    one = summarise({name: torch.tensor([2.0]) for name in EVAL_METRICS})
    assert one["mean_reward"] == 2.0 and math.isnan(one["se_reward"])


def _naive(tr) -> dict[str, list[float]]:
    """The metric definitions of march/evaluation/protocol.py written as a plain per-env loop."""
    t_len, e = tr["reward"].shape
    out: dict[str, list[float]] = {k: [] for k in (*EVAL_METRICS, "pelvis_distance_m")}
    for i in range(e):
        done = [
            bool(tr["terminated"][t, i] or tr["truncated"][t, i] or tr["reached"][t, i])
            for t in range(t_len)
        ]
        end = done.index(True) if any(done) else t_len - 1
        fell = bool(tr["terminated"][end, i]) and any(done)
        won = bool(tr["reached"][end, i]) and any(done) and not fell
        tq = [float(tr["torque"][t, i]) for t in range(end)]
        w = tr["ang_vel"][:, i].double()
        jk = [
            float((w[t] - 2 * w[t - 1] + w[t - 2]).abs().mean() / tr["dt"] ** 2)
            for t in range(2, end)
        ]
        goal = float(tr["goal_distance"][i])
        feet = tr.get("foothold")
        feet = tr["progress"] if feet is None else feet
        far = max(float(feet[t, i]) for t in range(end + 1))
        out["distance_m"].append(goal if won else min(far, goal))
        out["pelvis_distance_m"].append(goal if won else min(float(tr["progress"][end, i]), goal))
        out["success_rate"].append(float(won))
        out["abs_torque_nm"].append(sum(tq) / len(tq) if tq else math.nan)
        out["abs_ang_jerk"].append(sum(jk) / len(jk) if jk else math.nan)
        out["reward"].append(float(tr["reward"][: end + 1, i].double().sum()))
        out["reward_per_step"].append(out["reward"][-1] / (end + 1))
        out["torque_success"].append(out["abs_torque_nm"][-1] if won else math.nan)
        out["jerk_success"].append(out["abs_ang_jerk"][-1] if won else math.nan)
    return out


@pytest.mark.parametrize("seed", range(20))
def test_matches_a_plain_loop_on_random_trajectories(seed):
    g = torch.Generator().manual_seed(seed)
    t_len = int(torch.randint(1, 40, (1,), generator=g))
    e = 9
    tr = _traj(t_len, e)
    tr["torque"] = torch.rand(t_len, e, generator=g) * 50
    tr["ang_vel"] = torch.randn(t_len, e, 3, generator=g)
    tr["reward"] = torch.randn(t_len, e, generator=g)
    tr["terminated"] = torch.rand(t_len, e, generator=g) < 0.05
    tr["truncated"] = torch.rand(t_len, e, generator=g) < 0.05
    tr["reached"] = torch.rand(t_len, e, generator=g) < 0.05
    tr["progress"] = torch.rand(t_len, e, generator=g) * 6
    tr["foothold"] = torch.rand(t_len, e, generator=g) * 6
    tr["goal_distance"] = torch.rand(e, generator=g) * 6
    got = episode_metrics(**tr)
    want = _naive(tr)
    for k in (*EVAL_METRICS, "pelvis_distance_m"):
        np.testing.assert_allclose(got[k].numpy(), np.array(want[k]), rtol=1e-9, atol=1e-9)


def test_a_fall_forward_is_not_paid_as_distance():
    """Zero action's topple, as measured in the cpu eval env (docs/evaluation.md): the pelvis
    moves 0.56 m along the course in the last 40 steps while the feet stay within 3 cm; the
    tilt termination ends it. The distance is where the feet got, the pelvis's is kept apart."""
    tr = _traj(70)
    tr["goal_distance"][:] = 3.0
    t = torch.arange(70.0)
    tr["progress"][:, 0] = (0.56 * ((t - 25) / 35).clamp(min=0) ** 2).clamp(max=0.56)
    tr["foothold"] = (0.03 * (t / 60).clamp(max=1))[:, None]
    tr["terminated"][60, 0] = True  # tilt
    m = episode_metrics(**tr)
    assert m["distance_m"].item() == pytest.approx(0.03)
    assert m["pelvis_distance_m"].item() == pytest.approx(0.56)


def test_distance_is_the_farthest_point_both_feet_reached():
    """A walker whose feet reached 1.2 m and then stepped back to 1.0 m before falling keeps
    1.2 m; a success is scored at the goal wherever its feet are."""
    tr = _traj(6, e=2)
    tr["goal_distance"][:] = 2.0
    feet = torch.tensor([0.0, 0.5, 1.2, 1.0, 1.0, 9.0])  # step 5: after the end, never read
    tr["foothold"] = torch.stack([feet, 0.5 * feet], -1)
    tr["progress"][:, :] = 1.7
    tr["terminated"][4, 0] = True
    tr["reached"][4, 1] = True
    m = episode_metrics(**tr)
    assert m["distance_m"].tolist() == pytest.approx([1.2, 2.0])
    assert m["pelvis_distance_m"].tolist() == pytest.approx([1.7, 2.0])
    tr["foothold"] = torch.zeros(5, 2)
    with pytest.raises(ValueError, match="foothold"):
        episode_metrics(**tr)


def test_shape_mismatch_is_one_clear_error():
    tr = _traj(4, e=2)
    tr["ang_vel"] = torch.zeros(4, 2)
    with pytest.raises(ValueError, match="ang_vel"):
        episode_metrics(**tr)


# ------------------------------------------------------------------ which courses


@pytest.mark.parametrize(("rows", "cols"), [(10, 8), (4, 3), (3, 5), (1, 1), (6, 6)])
def test_eval_cells_cover_every_cell_and_balance_levels(rows, cols):
    for first in (0, 7, 31):
        lv, col = eval_cells(first, rows * cols, rows, cols)
        cells = set(zip(lv.tolist(), col.tolist(), strict=True))
        assert len(cells) == rows * cols  # every (level, column) exactly once
    for n in range(1, 3 * rows * cols):
        lv, col = eval_cells(0, n, rows, cols)
        per_level = torch.bincount(lv, minlength=rows)
        assert per_level.max() - per_level.min() <= 1
        for r in range(rows):  # each level's rollouts spread over its courses
            per_col = torch.bincount(col[lv == r], minlength=cols)
            assert per_col.max() - per_col.min() <= 1


# ------------------------------------------------------------------ one protocol for every arm


def _eval_cfg(reward: str, curriculum: str):
    from march.env.build import build_env_cfg

    cfg = load(["compute=smoke", f"reward={reward}", f"curriculum={curriculum}"])
    return cfg, build_env_cfg(cfg, "eval")


def _events(env_cfg) -> dict:
    return {k: (v.func, v.mode, repr(v.params)) for k, v in env_cfg.events.items()}


def test_eval_env_is_the_same_for_every_arm():
    from march.env.build import EVAL_TERMINATIONS, build_env_cfg

    arms = {(r, c): _eval_cfg(r, c) for r in ("clf", "modelfree") for c in ("stones", "flat_first")}
    ref_cfg, ref = arms[("modelfree", "stones")]
    vx = ref_cfg.eval.command_vx
    for (reward, curriculum), (cfg, env_cfg) in arms.items():
        what = f"reward={reward} curriculum={curriculum}"
        assert tuple(env_cfg.terminations) == EVAL_TERMINATIONS, what
        assert env_cfg.terminations["time_out"].time_out
        # The success termination is no failure (truncated, not terminated); the falls are.
        assert env_cfg.terminations["goal_reached"].time_out
        non_falls = ("time_out", "goal_reached")
        assert not any(t.time_out for k, t in env_cfg.terminations.items() if k not in non_falls)
        # The same stone courses over every level, whatever the training curriculum.
        gen = env_cfg.scene.terrain.terrain_generator
        assert gen == ref.scene.terrain.terrain_generator, what
        assert env_cfg.scene.terrain.max_init_terrain_level is None
        assert gen.num_rows == cfg.curriculum.num_levels and gen.curriculum
        assert all(s.flat_below == 0.0 for s in gen.sub_terrains.values()), what
        assert env_cfg.curriculum == {}
        # DR as in training, depth corruption as in training, one command, one episode length.
        assert _events(env_cfg) == _events(ref), what
        assert _events(env_cfg) == _events(build_env_cfg(cfg, "student")), what
        assert env_cfg.observations["depth"] == ref.observations["depth"]
        assert env_cfg.observations["depth"].terms["depth"].params["dropout"] > 0
        twist = env_cfg.commands["twist"]
        assert twist.ranges == ref.commands["twist"].ranges, what
        assert twist.ranges.lin_vel_x == (vx, vx)
        assert env_cfg.episode_length_s == cfg.eval.episode_length_s
    # Training keeps the planner's verdict for clf: only evaluation drops it.
    clf_cfg = arms[("clf", "stones")][0]
    assert "planner_infeasible" in build_env_cfg(clf_cfg, "teacher").terminations
    # ... and only evaluation ends an episode at the goal.
    for cfg, _ in arms.values():
        for purpose in ("teacher", "student"):
            assert "goal_reached" not in build_env_cfg(cfg, purpose).terminations


def _rects(table) -> set[tuple[float, ...]]:
    """Every course of a foothold table as the set of its stone rectangles (top-face centre
    relative to the spawn point, half sizes; in micrometres), one frozen set per course."""
    courses = set()
    for row in table.layouts:
        for lay in row:
            rel = lay.center - lay.origin
            boxes = np.concatenate([rel, lay.half_size], axis=1)
            courses.add(frozenset(tuple(np.round(b * 1e6).astype(int).tolist()) for b in boxes))
    return courses


@pytest.mark.parametrize("preset", ("smoke", "cpu"))
def test_eval_courses_are_held_out_and_the_same_for_every_arm(preset):
    """At the default seeds no evaluation course equals a training course of either curriculum
    (compared as stone rectangles), and the clf / modelfree arms of both curricula evaluate on
    identical foothold tables."""
    from march.env.build import build_env_cfg
    from march.env.stone_terrain import foothold_table

    tables, training = {}, set()
    for reward in ("clf", "modelfree"):
        for curriculum in ("stones", "flat_first"):
            cfg = load([f"compute={preset}", f"reward={reward}", f"curriculum={curriculum}"])
            assert cfg.eval.terrain_seed != cfg.curriculum.terrain_seed
            train_gen = build_env_cfg(cfg, "teacher").scene.terrain.terrain_generator
            eval_gen = build_env_cfg(cfg, "eval").scene.terrain.terrain_generator
            assert eval_gen.seed == cfg.eval.terrain_seed
            training |= {c for c in _rects(foothold_table(train_gen)) if len(c) > 1}
            tables[(reward, curriculum)] = foothold_table(eval_gen)
    ref = tables[("clf", "stones")]
    held_out = _rects(ref)
    assert len(held_out) == ref.shape[0] * ref.shape[1]  # every eval course is different
    assert not held_out & training
    for key, table in tables.items():
        for name in ("center", "half_size", "valid", "goal_distance", "origins", "direction"):
            assert torch.equal(getattr(table, name), getattr(ref, name)), (key, name)


def test_progress_is_measured_in_the_course_frame():
    """A course laid out along +x and the same course rotated by 0.7 rad about its spawn point
    (stones, direction and the walker's positions rotated alike) give the same progress, the
    same goal verdict and the same clipping at both ends."""
    from march.env.course import course_progress
    from march.world.footholds import FootholdTable

    course = CourseCfg(size=(6.0, 4.0))
    lay = generate_course(0.5, course, np.random.default_rng(3))
    origin = np.array([[[10.0, -2.0, 0.3]]])
    straight = FootholdTable.from_layouts([[lay]], origin)
    a = 0.7
    rot = torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    turned = FootholdTable.from_layouts([[lay]], origin)
    turned.center[..., :2] = turned.center[..., :2] @ rot.T
    turned.direction = straight.direction @ rot.T
    # A walker along the course and sideways: before the start, on it, past its end.
    along = torch.tensor([-0.5, 0.0, 0.8, 1.7, lay.goal_distance, lay.course_length + 1.0])
    side = torch.tensor([0.1, -0.3, 0.2, 0.0, 0.4, -0.2])
    rel = torch.stack([along, side], -1)
    o = torch.as_tensor(origin[0], dtype=torch.float32).expand(len(along), 3)
    zeros = torch.zeros(len(along), dtype=torch.long)
    pos_straight = torch.cat([o[:, :2] + rel, o[:, 2:]], -1)
    pos_turned = torch.cat([o[:, :2] + rel @ rot.T, o[:, 2:]], -1)
    p0 = course_progress(straight, zeros, zeros, o, pos_straight)
    p1 = course_progress(turned, zeros, zeros, o, pos_turned)
    want = along.clamp(0.0, lay.course_length)
    torch.testing.assert_close(p0, want)
    torch.testing.assert_close(p1, want, atol=1e-5, rtol=0)
    goal = straight.goal_distance[0, 0]
    assert torch.equal(p0 >= goal, p1 >= goal - 1e-6)
    # The rotated course's own footholds say the same (the frame the planner plans in).
    fh = turned.for_envs(zeros, zeros, o)
    torch.testing.assert_close(fh.progress(pos_turned[:, :2]), want, atol=1e-5, rtol=0)
    # Measured along world x instead, the rotated course would read short:
    assert float(((pos_turned[3, :2] - o[3, :2]) * torch.tensor([1.0, 0.0])).sum()) < 1.5


# ------------------------------------------------------------------ success is reachable


def _generated_goal_max(course: CourseCfg, seeds: int = 6) -> float:
    """Largest goal distance over courses drawn at 11 difficulties x ``seeds`` x 10 draws."""
    worst = 0.0
    for seed in range(seeds):
        rng = np.random.default_rng(seed)
        for d in np.linspace(0.0, 1.0, 11):
            for _ in range(10):
                worst = max(worst, generate_course(float(d), course, rng).goal_distance)
    return worst


@pytest.mark.parametrize("preset", PRESETS)
def test_goal_reachable_with_a_quarter_of_the_episode_to_spare(preset):
    from march.env.stone_terrain import foothold_table, terrain_generator_cfg

    cfg = load([f"compute={preset}"])
    course, c = cfg.terrain, cfg.curriculum
    goal_max = course.goal_distance_max
    # The bound is the generator's worst case: no generated course exceeds it, the flat layout
    # (flat_first) sits on it, and drawn courses come within one gap of it.
    assert _generated_goal_max(course) <= goal_max + 1e-9
    assert _generated_goal_max(course) >= goal_max - course.gap_hard[1]
    seeds = {"stones": c.terrain_seed, "flat_first": c.terrain_seed, "eval": cfg.eval.terrain_seed}
    for kind, seed in seeds.items():
        gen = "stones" if kind == "eval" else kind
        table = foothold_table(
            terrain_generator_cfg(
                gen, course, num_rows=c.num_levels, num_cols=c.num_cols, seed=seed
            )
        )
        assert float(table.goal_distance.max()) <= goal_max + 1e-5, kind
        # The success termination fires on the goal platform: it has room along the course.
        assert float((table.course_length - table.goal_distance).min()) >= course.goal_length - 1e-5
    # Evaluation (the held-out courses): walking at the evaluation command, the pelvis is over
    # the farthest goal platform (the success termination) with at least 25% of the episode to
    # spare; the rollout ends there, so walking on can no longer turn it into a failure.
    t_goal = goal_max / cfg.eval.command_vx
    assert t_goal <= 0.75 * cfg.eval.episode_length_s, (preset, t_goal)
    # Training: promotion (progress >= promote_fraction x goal distance within an episode) is
    # possible on the farthest course at the middle of the training forward-command range.
    v_mid = 0.5 * (cfg.env.command_vx[0] + cfg.env.command_vx[1])
    t_promote = c.promote_fraction * goal_max / v_mid
    assert t_promote <= cfg.env.episode_length_s, (preset, t_promote)
    lo, hi = cfg.env.command_vx
    assert lo <= cfg.eval.command_vx <= hi


def test_eval_command_outside_the_training_range_is_one_clear_error():
    from march.config import ConfigError

    with pytest.raises(ConfigError, match="eval.command_vx=0.9"):
        load(["compute=smoke", "eval.command_vx=0.9"])


# ------------------------------------------------------------------ eval.csv rows and resume


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def test_eval_columns_keep_the_names_figures_read():
    for col in ("stage", "iteration", "env_steps", "n_rollouts"):
        assert col in EVAL_COLUMNS
    for m in ("distance_m", "success_rate", "abs_torque_nm", "abs_ang_jerk", "reward"):
        assert f"mean_{m}" in EVAL_COLUMNS and f"se_{m}" in EVAL_COLUMNS
    for m in ("reward_per_step", "torque_success", "jerk_success"):
        assert f"mean_{m}" in EVAL_COLUMNS and f"se_{m}" in EVAL_COLUMNS
    assert EVAL_COLUMNS[-5:] == (
        "n_torque",
        "n_jerk",
        "n_torque_success",
        "n_jerk_success",
        "deferred_replans",
    )


def test_resume_truncation_keeps_other_stages(tmp_path):
    path = tmp_path / "eval.csv"
    for stage, it in [("teacher", 1), ("teacher", 2), ("teacher", 3), ("student", 1)]:
        append_row(path, EVAL_COLUMNS, {"stage": stage, "iteration": it, "n_torque": 4})
    truncate_rows(path, "teacher", 2)
    assert [(r["stage"], r["iteration"]) for r in _rows(path)] == [
        ("teacher", "1"),
        ("teacher", "2"),
        ("student", "1"),
    ]
    assert has_row(path, "teacher", 2) and not has_row(path, "teacher", 3)
    assert not has_row(tmp_path / "missing.csv", "teacher", 1)


@pytest.mark.sim
def test_teacher_rows_during_training_and_resume_without_duplicates(tmp_path):
    """stage=teacher on the real env: eval rows at every teacher.eval_interval iteration and at
    the end; a second run in the same directory resumes without repeating a row."""
    from march.train import run_pipeline

    def run(iterations: int) -> list[dict[str, str]]:
        cfg = load(
            [
                "compute=smoke",
                "stage=teacher",
                f"teacher.max_iterations={iterations}",
                "teacher.eval_interval=2",
                "eval.num_rollouts=6",  # more rollouts than the 4 eval envs: two waves
                "eval.episode_length_s=0.5",  # 25-step waves: the rows, not the walking, count
            ]
        )
        run_pipeline(cfg, tmp_path)
        return _rows(tmp_path / "eval.csv")

    first = run(1)
    assert [(r["stage"], r["iteration"]) for r in first] == [("teacher", "1")]
    rows = run(3)
    assert [(r["stage"], int(r["iteration"])) for r in rows] == [
        ("teacher", 1),
        ("teacher", 2),
        ("teacher", 3),
    ]
    metrics = [r for r in _rows(tmp_path / "metrics.csv") if r["stage"] == "teacher"]
    steps = {int(r["iteration"]): r["env_steps"] for r in metrics}
    for r in rows:
        assert r["env_steps"] == steps[int(r["iteration"])]
        assert int(r["n_rollouts"]) == 6
        assert 0 <= int(r["n_jerk"]) <= int(r["n_torque"]) <= 6
        assert 0.0 <= float(r["mean_success_rate"]) <= 1.0
        assert float(r["mean_distance_m"]) >= 0.0


@pytest.mark.sim
def test_real_env_rollouts_on_stratified_cells_leave_training_rng_alone(tmp_path, monkeypatch):
    """The smoke eval env with zero actions (the G1 holds its default pose and tips over within
    a couple of seconds): 6 rollouts on 4 envs take two waves on the next course cells, every
    rollout ends by a fall inside the episode, and the caller's random state is untouched. The
    per-rollout metrics checked are the ones march's evaluation itself rolled (read on their way
    to the summary): its standing floor, once per env and rollout count, and each policy row."""
    import march.evaluation.protocol as protocol
    from march.env.build import make_env
    from march.evaluation.protocol import evaluate
    from march.evaluation.summary import eval_line, format_summary

    rolled: list[dict[str, torch.Tensor]] = []
    real_rollouts = protocol.sharded_rollouts  # all waves of one call, in rollout order

    def recorded(*args, **kwargs):
        rolled.append(real_rollouts(*args, **kwargs))
        return rolled[-1]

    monkeypatch.setattr(protocol, "sharded_rollouts", recorded)
    cfg = load(["compute=smoke"])
    env = make_env(cfg, "eval")
    try:
        n_act = env.action_manager.total_action_dim

        def still(obs):
            return torch.zeros(env.num_envs, n_act)

        torch.manual_seed(123)
        state = torch.get_rng_state()
        # march's evaluation of the zero action: it scores ~0 (its feet stay put while the
        # pelvis topples forward), and the row carries the standing floor: the same numbers
        row = evaluate(env, still, 6, tmp_path, "teacher", 0, 0, sees_depth=False)
        assert torch.equal(torch.get_rng_state(), state)
        terrain = env.scene.terrain
        lv, col = eval_cells(4, 4, *terrain.terrain_origins.shape[:2])  # 4 envs: the 2nd wave
        assert terrain.terrain_levels.tolist() == lv.tolist()
        assert terrain.terrain_types.tolist() == col.tolist()
        horizon = int(env.max_episode_length)
        again = evaluate(env, still, 6, tmp_path, "teacher", 1, 0, sees_depth=False)
    finally:
        env.close()
    assert len(rolled) == 3  # the floor, then the policy twice: the floor is not rolled again
    per = rolled[1]  # the first evaluation's policy rollouts: the floor's, value for value
    torch.testing.assert_close(per, rolled[0], rtol=0, atol=0, equal_nan=True)
    assert row["floor_distance_m"] == row["mean_distance_m"] == again["floor_distance_m"]
    assert row["floor_se_distance_m"] == row["se_distance_m"]
    assert row["floor_reward"] == row["mean_reward"]
    assert ("floor_clf/v_p50" in row) == ("clf/v_p50" in row)
    if "clf/v_p50" in row:  # the floor's CLF samples are its own, not added to the policy's
        assert row["floor_clf/v_p50"] == row["clf/v_p50"]
    assert f"standing floor {row['floor_distance_m']:.3g} m" in eval_line(row)
    assert "standing floor" in format_summary(row)
    assert [r["floor_distance_m"] for r in _rows(tmp_path / "eval.csv")] == [
        f"{row['floor_distance_m']:.6g}"
    ] * 2
    assert per["distance_m"].max() < 0.1, per["distance_m"]  # the feet barely move
    assert per["pelvis_distance_m"].mean() > 0.3, per["pelvis_distance_m"]  # the topple
    for k in (*EVAL_METRICS, "episode_steps"):
        assert per[k].shape == (6,), k
    steps = per["episode_steps"]
    assert ((steps >= 3) & (steps < horizon)).all(), steps  # fell, long enough for jerk
    assert torch.isfinite(per["abs_torque_nm"]).all() and torch.isfinite(per["abs_ang_jerk"]).all()
    assert (per["abs_torque_nm"] > 0).all()
    assert (per["success_rate"] == 0).all()  # a fall is never a success
    assert ((per["distance_m"] >= 0) & (per["distance_m"] <= cfg.terrain.size[0])).all()


def test_an_older_eval_csv_gets_the_new_columns(tmp_path):
    path = tmp_path / "eval.csv"
    old = EVAL_COLUMNS[:-5]  # written before the count columns existed
    append_row(path, old, {"stage": "student", "iteration": 1, "mean_distance_m": 1.5})
    append_row(path, EVAL_COLUMNS, {"stage": "student", "iteration": 2, "n_torque": 3})
    rows = _rows(path)
    assert list(rows[0]) == list(EVAL_COLUMNS)
    assert (rows[0]["mean_distance_m"], rows[0]["n_torque"]) == ("1.5", "")
    assert (rows[1]["iteration"], rows[1]["n_torque"]) == ("2", "3")


# ------------------------------------------------------------------ strict JSON (issue 49)


def test_summary_json_is_strict_with_the_count_beside_each_null(tmp_path):
    """No successful rollout and a single rollout: the undefined means and SEs are null and
    ``null_because`` names the count; the file loads with a parser that refuses NaN."""
    from march import strict_json
    from march.evaluation.summary import write_summary

    per = {name: torch.tensor([1.5]) for name in EVAL_METRICS}
    per["torque_success"] = per["jerk_success"] = torch.tensor([float("nan")])
    row = {"stage": "student", "iteration": 1, "env_steps": 8, "n_rollouts": 1, **summarise(per)}
    assert math.isnan(row["mean_torque_success"]) and math.isnan(row["se_distance_m"])
    path = write_summary(row, tmp_path, {"wall_s": float("inf")})
    text = path.read_text()
    assert "NaN" not in text and "Infinity" not in text
    data = strict_json.loads(text)
    assert data["mean_torque_success"] is None and data["n_torque_success"] == 0
    assert data["wall_s"] is None and data["mean_distance_m"] == 1.5
    assert data["null_because"]["mean_torque_success"] == "n_torque_success = 0 (a mean needs 1)"
    assert data["null_because"]["se_distance_m"] == "n_rollouts = 1 (a standard error needs 2)"
    assert "mean_distance_m" not in data["null_because"]
    with pytest.raises(ValueError, match="not strict JSON: NaN"):
        strict_json.loads('{"x": NaN}')
    with pytest.raises(TypeError):
        strict_json.dumps({"x": object()})  # not JSON at all: still an error, never a guess
    assert strict_json.dumps({"a": np.float32("nan"), "b": (1.0, np.float64(2.5))}) == (
        '{"a": null, "b": [1.0, 2.5]}'
    )


def test_every_json_file_a_smoke_run_writes_is_strict(smoke_run, bundle):
    """``python -m march.train compute=smoke`` and its export: every JSON file loads with a
    parser that refuses NaN and Infinity (JavaScript's, Go's, serde_json's behaviour)."""
    from march import strict_json

    files = sorted(smoke_run.rglob("*.json")) + sorted(bundle.parent.glob("*.json"))
    names = {p.name for p in files}
    assert {"summary.json", "status.json"} <= names
    assert any(n.endswith(".deploy.json") for n in names)
    for path in files:
        strict_json.loads(path.read_text())  # raises on NaN / Infinity
    summary = strict_json.loads((smoke_run / "summary.json").read_text())
    for key, why in summary.get("null_because", {}).items():
        assert summary[key] is None and why.split(" = ")[0] in summary
    print(f"{len(files)} JSON files strict: {', '.join(sorted(names))}")
