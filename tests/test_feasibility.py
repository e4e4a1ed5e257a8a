"""The reference's kinematic feasibility (march.audit): the G1's whole-body IK reaches what a
real G1 pose defines and names what no pose reaches; its V is march.clf's; the report covers
every curriculum level; inside a live env the kinematic reference measures what the env
measures and walks.
"""

from __future__ import annotations

import json
import math

import mujoco
import numpy as np
import pytest
import torch

from march.audit.feasibility import (
    FeasibilityCfg,
    LevelWalks,
    level_summary,
    output_paths,
    reference_report,
)
from march.audit.ik_walk import WalkTrace, track_step
from march.audit.kinematic_g1 import GROUPS, KinematicG1, rotation_zyx
from march.clf.lyapunov import CLF_OUTPUT_NAMES, ClfModel
from march.config.cli import load
from march.errors import ConfigError
from march.reference.hlip import HlipCfg
from march.reference.trajectory import ReferenceCfg, StepState, angle_mask


@pytest.fixture(scope="module")
def kin() -> KinematicG1:
    return KinematicG1()


def real_pose(kin: KinematicG1, rng: np.random.Generator, left: bool) -> tuple:
    """A G1 configuration inside its joint limits whose stance-foot site is flat at a random
    heading and place on z = 0: joints drawn around the default pose, then the base turned
    and moved so the stance foot lies flat (a pose a G1 can take on one foot)."""
    m = kin.model
    q = kin.default_qpos.copy()
    jid = [m.joint(n).id for n in kin.joint_names]
    lo, hi = m.jnt_range[jid, 0], m.jnt_range[jid, 1]
    q[kin.joint_qpos] = np.clip(q[kin.joint_qpos] + rng.normal(0, 0.12, 29), 0.9 * lo, 0.9 * hi)
    kin.measure(q, None, left)
    sid = kin.site_ids[0 if left else 1]
    site_pos, site_rot = kin.data.site_xpos[sid].copy(), kin.data.site_xmat[sid].reshape(3, 3)
    yaw = rng.uniform(-math.pi, math.pi)
    turn = rotation_zyx(0.0, 0.0, yaw) @ site_rot.T
    base_rot = np.empty(9)
    mujoco.mju_quat2Mat(base_rot, q[3:7])
    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, (turn @ base_rot.reshape(3, 3)).ravel())
    foot = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), 0.0])
    q[0:3] = foot + turn @ (q[0:3] - site_pos)
    q[3:7] = quat
    y, _ = kin.measure(q, None, left)
    assert np.allclose(kin.data.site_xpos[sid], foot, atol=1e-9)
    assert np.allclose(kin.data.site_xmat[sid].reshape(3, 3), rotation_zyx(0, 0, yaw), atol=1e-9)
    return q, y, foot, rotation_zyx(0.0, 0.0, yaw)


@pytest.mark.parametrize("seed", range(6))
def test_a_reference_a_real_g1_pose_defines_is_reached(kin, seed):
    """y_ref measured from a real pose: from the default pose the IK reaches it, every output
    within 2.5 mm / 2.5 mrad (floor ~0 against the 20-30 mm reach tolerances; measured: 0.3 to
    2.0 mm of CoM, the rest below 0.6 mm / mrad: the IK is a local method and settles next to
    the pose's own joint angles, up to 0.045 rad from them; without the polish steps,
    IkCfg.polish = 0, up to 4.4 mm), within the joint limits, V / Vmax < 1e-4."""
    rng = np.random.default_rng(seed)
    left = bool(seed % 2)
    q_true, y_ref, foot, rot = real_pose(kin, rng, left)
    kin.stand(y_ref, left, foot, rot)
    for _ in range(10):  # the same instant held for 0.2 s: positions settle, rates go to 0
        tick = kin.track(y_ref, np.zeros(29), left, foot, rot)
    worst = {g: float(np.abs(tick.eta[lo:hi]).max()) for g, (lo, hi) in GROUPS.items()}
    assert max(worst.values()) < 2.5e-3, worst
    assert tick.v_ratio < 1e-4
    m = kin.model
    jid = [m.joint(n).id for n in kin.joint_names]
    joints = tick.qpos[kin.joint_qpos]
    assert np.all(joints >= m.jnt_range[jid, 0] - 1e-6)
    assert np.all(joints <= m.jnt_range[jid, 1] + 1e-6)


def one_step(length: float, duration: float = 0.6) -> StepState:
    """A step from standing on the left foot at the origin, the right foot swinging from
    beside it to ``length`` ahead [m] (flat ground, heading +x)."""
    t = torch.tensor
    return StepState(
        stance_pos=t([[0.0, 0.125, 0.0]]),
        stance_is_left=t([True]),
        swing_start=t([[0.0, -0.125, 0.0]]),
        target=t([[length, -0.125, 0.0]]),
        next_target=t([[2 * length, 0.125, 0.0]]),
        duration=t([duration]),
        next_duration=t([duration]),
        yaw0=t([0.0]),
        yaw_rate=t([0.0]),
        axis=t([[1.0, 0.0]]),
        ramp=t([True]),
        ramp_from=t([[0.0, 0.0]]),
    )


def walk_one_step(kin: KinematicG1, length: float, hlip: HlipCfg | None = None) -> dict:
    trace = WalkTrace()
    held = (np.array([0.0, 0.125, 0.0]), np.eye(3))
    track_step(kin, trace, one_step(length), 0, held, True, ReferenceCfg(), hlip or HlipCfg())
    walks = LevelWalks(0, 0.0, "stones", [0.5], [trace], [None])
    p11 = kin.clf.P_blocks_np[:, 0, 0]
    return level_summary(walks, FeasibilityCfg(), p11, kin.v_max) | {"trace": trace}


def test_a_step_longer_than_the_leg_is_not_reached_and_the_report_names_the_output(kin):
    """A step 1.3 m ahead of the stance foot (the G1's leg, hip to sole, is ~0.7 m): the
    swing foot stops more than 10 cm short, no step is reached, and the report names the
    output with the largest |eta| / tolerance at touchdown. A 0.3 m step of the same reference
    is reached within 5 mm (the CoM lags its moving reference by a few millimetres)."""
    tol = FeasibilityCfg().tolerances()
    long = walk_one_step(kin, 1.3)
    td = np.asarray(long["trace"].touchdown_eta[0])
    assert abs(td[CLF_OUTPUT_NAMES.index("swing_x")]) > 0.1
    assert long["eta_abs"]["outputs"]["swing_x"]["p90"] > 0.05
    assert long["reach"]["touchdown_tick_positions"] == 0.0
    assert long["reach"]["whole_step"] == 0.0
    worst = np.asarray(long["trace"].step_max_eta[0]) / tol
    rates = np.asarray(long["trace"].step_max_etadot[0]) / FeasibilityCfg().rate_tolerances()
    named = CLF_OUTPUT_NAMES[int(np.argmax(worst))]
    if rates.max() > worst.max():
        named = CLF_OUTPUT_NAMES[int(np.argmax(rates))] + " rate"
    assert long["reach"]["misses_by_cause"] == {named: 1}
    short = walk_one_step(kin, 0.3)
    assert short["reach"]["touchdown_tick_positions"] == 1.0
    assert short["reach"]["whole_step"] == 1.0
    assert short["reach"]["misses_by_cause"] == {}
    assert np.abs(short["trace"].touchdown_eta[0]).max() < 5e-3
    # the stance foot is held as a hard constraint: it does not slide, even on the long step
    assert short["stance_slide_m"]["max"] < 1e-4 and long["stance_slide_m"]["max"] < 1e-4
    # the rate the walk judges is its error's own finite difference over each tick
    for walked in (short, long):
        eta, etadot = (np.asarray(x) for x in (walked["trace"].eta, walked["trace"].etadot))
        assert np.allclose(etadot[1:], np.diff(eta, axis=0) / kin.cfg.dt, atol=1e-9)


def test_the_planners_longest_step_keeps_the_com_below_its_reference(kin):
    """The planner's max_step, 0.85 m ahead (0.886 m with the 0.25 m step width): at touchdown
    the HLIP CoM is l/2 = 0.425 m ahead of the stance foot at z0 = 0.67 m, so each hip is about
    sqrt(0.425^2 + 0.125^2 + 0.67^2) ~ 0.80 m from its foot, beyond the leg's ~0.7 m: the CoM
    must sink about 0.1 m. At the touchdown tick the worst output is com_z, and the swing foot
    still lands; the step is not reached."""
    step = walk_one_step(kin, 0.85)
    td = np.asarray(step["trace"].touchdown_eta[0])
    assert CLF_OUTPUT_NAMES[int(np.argmax(np.abs(td) / FeasibilityCfg().tolerances()))] == "com_z"
    assert step["reach"]["touchdown_tick_positions"] == 0.0 and step["reach"]["whole_step"] == 0.0
    assert -0.15 < td[CLF_OUTPUT_NAMES.index("com_z")] < -0.05
    assert np.abs(td[6:9]).max() < FeasibilityCfg().tol_swing_pos


def test_v_is_march_clf_v_of_the_same_eta(kin):
    """The tick's V against the closed-form CARE of a double integrator (P12 = sqrt(q r),
    P22 = sqrt(r (q_v + 2 P12)), P11 = P12 P22 / r) and against the env's path
    (ClfModel.value_of_outputs with wrapped angles); Vmax = lambda_max(P) eta_max^2."""
    rng = np.random.default_rng(3)
    q_true, y_ref, foot, rot = real_pose(kin, rng, True)
    y_ref = y_ref + rng.normal(0, 0.05, 29)  # not exactly reachable: eta != 0
    ydot_ref = rng.normal(0, 0.3, 29)
    kin.stand(y_ref, True, foot, rot)
    tick = kin.track(y_ref, ydot_ref, True, foot, rot)
    cfg = kin.clf.cfg
    v_hand = 0.0
    for o, e, ed in zip(cfg.outputs, tick.eta, tick.etadot, strict=True):
        p12 = math.sqrt(o.q_pos * o.r)
        p22 = math.sqrt(o.r * (o.q_vel + 2 * p12))
        p11 = p12 * p22 / o.r
        v_hand += 0.5 * (p11 * e * e + 2 * p12 * e * ed + p22 * ed * ed)
    assert tick.v == pytest.approx(v_hand, rel=1e-9)
    env_path = ClfModel(cfg, dtype=torch.float64).value_of_outputs(
        torch.as_tensor(tick.y)[None],
        torch.as_tensor(tick.ydot)[None],
        torch.as_tensor(y_ref)[None],
        torch.as_tensor(ydot_ref)[None],
        angle_mask(17),
    )
    assert tick.v == pytest.approx(float(env_path[0]), rel=1e-9)
    lam = float(np.linalg.eigvalsh(kin.clf.P_np)[-1])
    assert tick.v_ratio == pytest.approx(tick.v / (lam * cfg.eta_max**2), rel=1e-9)


@pytest.mark.parametrize("seed", range(4))
def test_the_walks_rate_is_the_errors_own_and_unbiased_where_the_pose_follows(kin, seed):
    """A real motion: from a real one-foot pose, the 17 upper-body joints swing as
    A sin(w t) (base and legs still, so every instant is a real pose; y_ref measured from it).
    The IK follows it; the rate the walk judges, the error's finite difference
    (``eta_before``), stays near 0 (< 15 % of the bias below), while the configuration's
    backward difference against the reference's rate at the tick's end is off by the
    hand-derived A (sin(w t) - sin(w (t - dt))) / dt - A w cos(w t), about (dt/2) A w^2
    sin(w t): a follower the old rate called late."""
    rng = np.random.default_rng(10 + seed)
    left = bool(seed % 2)
    q0, _, foot, rot = real_pose(kin, rng, left)
    amp, w = rng.uniform(0.1, 0.25, 17), rng.uniform(6.0, 12.0, 17)
    dt = kin.cfg.dt
    upper = slice(*GROUPS["upper"])

    def y_of(t: float) -> np.ndarray:
        q = q0.copy()
        q[kin.upper_qpos] = kin.default_upper + amp * np.sin(w * t)
        return kin.measure(q, None, left)[0]

    kin.stand(y_of(0.0), left, foot, rot)
    for _ in range(5):  # settle on the motion's start
        eta = kin.track(y_of(0.0), np.zeros(29), left, foot, rot).eta
    old_bias, new_rate, hand = [], [], []
    for k in range(1, 16):
        t = k * dt
        ydot_ref = np.zeros(29)
        ydot_ref[upper] = amp * w * np.cos(w * t)
        saved = kin.qpos.copy()
        old = kin.track(y_of(t), ydot_ref, left, foot, rot)
        kin.reset(saved)  # the same tick again, judged by the error's own rate
        new = kin.track(y_of(t), ydot_ref, left, foot, rot, eta_before=eta)
        eta = new.eta
        old_bias.append(old.etadot[upper])
        new_rate.append(new.etadot[upper])
        hand.append(amp * (np.sin(w * t) - np.sin(w * (t - dt))) / dt - amp * w * np.cos(w * t))
    old_bias, new_rate, hand = map(np.asarray, (old_bias, new_rate, hand))
    scale = np.abs(hand).max()
    assert np.abs(old_bias - hand).max() < 0.1 * scale, (np.abs(old_bias - hand).max(), scale)
    assert np.abs(new_rate).max() < 0.15 * scale, (np.abs(new_rate).max(), scale)


def _strict_json(path) -> dict:
    def refuse(name: str) -> None:
        raise ValueError(f"non-strict JSON constant {name}")

    return json.loads(path.read_text(), parse_constant=refuse)


@pytest.mark.parametrize("curriculum", ["stones", "flat_first"])
def test_the_report_covers_every_curriculum_level(tmp_path, capsys, curriculum):
    cfg = load(["compute=smoke", f"curriculum={curriculum}"])
    out = tmp_path / "ref.json"
    options = FeasibilityCfg(courses_per_level=1, max_steps=2, film=False)
    returned = reference_report(cfg, str(out), options)
    report = _strict_json(out)
    assert report == json.loads(json.dumps(returned))
    levels = report["levels"]
    assert [s["level"] for s in levels] == list(range(cfg.curriculum.num_levels))
    flat = cfg.curriculum.flat_levels if curriculum == "flat_first" else 0
    assert [s["kind"] for s in levels] == ["flat"] * flat + ["stones"] * (len(levels) - flat)
    assert levels[-1]["difficulty"] == 1.0
    for s in levels:
        # two steps, or one that ended the walk without a real touchdown (a step down the
        # kinematic G1's swing foot cannot reach with the CoM z0 above the higher stone)
        assert s["steps"] == 2 or s["walk_ends"] == {"no_touchdown": 1}, s["walk_ends"]
        assert s["ticks"] > 20 * s["steps"]
        assert set(s["eta_abs"]["outputs"]) == set(CLF_OUTPUT_NAMES)
        assert 0.0 <= s["reach"]["whole_step"] <= s["reach"]["touchdown_tick_positions"] <= 1
        assert s["jump_at_touchdown"]["touchdowns"] == s["steps"] - 1  # one between two steps
        assert sum(b["steps"] for b in s["reach"]["by_step_length"]) == s["steps"]
        reach = s["reach"]
        assert reach["reached_steps"] == round(reach["whole_step"] * s["steps"])
        lo, hi = reach["whole_step_ci95"]
        assert lo <= reach["whole_step"] <= hi and hi - lo > 0.3  # 1-2 steps: a wide interval
    assert out.with_suffix(".png").stat().st_size > 10_000
    table = capsys.readouterr().out
    # three tables (floors and reach, jumps, step lengths), one row per level each
    assert len([r for r in table.splitlines() if r[:5].strip().isdigit()]) == 3 * len(levels)
    total = sum(s["reach"]["reached_steps"] for s in levels)
    assert f"all levels: {total} of {sum(s['steps'] for s in levels)} steps reached" in table


def test_an_output_path_without_json_is_one_clear_error():
    with pytest.raises(ConfigError, match="give a .json file name"):
        output_paths("report.png")
    with pytest.raises(ConfigError, match="courses_per_level"):
        FeasibilityCfg(courses_per_level=0)


@pytest.fixture(scope="module")
def live_env():
    from march.env.build import make_env

    env = make_env(load(["compute=smoke", "reward=clf", "dr=none"]), "teacher", num_envs=2)
    env.reset()
    yield env
    env.close()


@pytest.mark.sim
def test_the_kinematic_reference_measures_what_the_env_measures_and_walks(live_env):
    """Inside a live env (DR off: nominal masses on both sides): after ``act`` places the
    robot, the env's own y_sim and rates (``ReferenceCommand.measured``) equal the IK's
    measurement of the same state to float32 rounding; the action targets the placed joints;
    over 60 steps (1.2 s) each env touches down at least once (real contacts), none falls, and
    the env's V / Vmax stays far below standing's 0.70 (issue 50)."""
    import mujoco

    from march.audit.kinematic_reference import KinematicReference
    from march.env.reference_command import reference_term

    env = live_env
    term = reference_term(env)
    ref = KinematicReference(env)
    kin = ref.kin
    ratios = []
    for k in range(60):
        action = ref.act(env)
        if k % 20 == 5:
            y_env, ydot_env = (x.cpu().double().numpy() for x in term.measured())
            # what the IK measured on the pose it solved, before the write
            assert np.abs(ref.last_y - y_env).max() < 5e-5
            assert np.abs(ref.last_ydot - ydot_env).max() < 5e-4
            q, v = ref._sim_state()
            for i in range(env.num_envs):  # and the same maths on the state read back
                kin.data.qpos[:], kin.data.qvel[:] = q[i], v[i]
                mujoco.mj_forward(kin.model, kin.data)
                y, ydot = kin.outputs_of_data(kin.data, bool(term.stance_is_left[i]))
                assert np.abs(y - y_env[i]).max() < 5e-5
                assert np.abs(ydot - ydot_env[i]).max() < 5e-4
            joints = term.robot.data.joint_pos
            targets = action * ref.action.scale + ref.action.offset
            assert torch.allclose(targets, joints, atol=1e-5)
        env.step(action)
        ratios.append((term.v / term.clf.v_max).cpu().numpy())
    assert (term.touchdown_count >= 1).all()
    assert (env.episode_length_buf == 60).all()  # no termination, no reset
    assert np.median(np.asarray(ratios)) < 0.3


def test_the_same_seed_walks_the_same_ticks(kin):
    """Seeded: two walks of the same courses, command and seed give the same numbers."""
    from march.audit.ik_walk import ik_walks
    from march.world.courses import CourseCfg, generate_course
    from march.world.footholds import footholds_from_layouts

    layouts = [generate_course(0.7, CourseCfg(size=(6.0, 4.0)), np.random.default_rng(5))]
    footholds = footholds_from_layouts(layouts, np.stack([lay.origin for lay in layouts]))
    command = torch.tensor([[0.6, 0.0]])
    first, second = (ik_walks(kin, footholds, command, max_steps=3, seed=7)[0] for _ in range(2))
    a, b = first.arrays(), second.arrays()
    assert a["eta"].shape[0] > 60
    for key in ("eta", "etadot", "v_ratio", "touchdown_eta", "step_length"):
        assert np.array_equal(a[key], b[key]), key


def hand_trace(ends: list[np.ndarray], starts: list[np.ndarray]) -> WalkTrace:
    """A walk trace with only the reference at each step's two ends, built by hand."""
    trace = WalkTrace()
    trace.ref_end, trace.ref_start = list(ends), list(starts)
    return trace


def test_the_jump_column_reads_a_hand_built_reference_with_known_jumps():
    """Three steps whose reference jumps by hand-chosen amounts at the two touchdowns: com_x
    by 0.1 then 0.3 m, com_vx by 0.5 m/s then 0, pelvis yaw across the +-pi wrap (3.1 ->
    -3.1: a jump of 2 pi - 6.2 = 0.0832 rad, not 6.2), swing_x by the step; a one-step walk
    adds no touchdown. The column's p50 / p90 / max are the hand quantiles of those jumps."""
    from march.audit.feasibility import jump_summary, touchdown_jumps

    def ref(com_x=0.0, com_vx=0.0, yaw=0.0, swing_x=0.0) -> np.ndarray:
        r = np.zeros(58)
        r[0], r[29], r[5], r[6] = com_x, com_vx, yaw, swing_x
        return r

    walk = hand_trace(
        ends=[ref(1.0, 0.7, 3.1, 0.5), ref(2.0, 0.7, 3.1, 1.0), ref(3.0)],
        starts=[ref(), ref(1.1, 1.2, -3.1, 0.0), ref(2.3, 0.7, 3.1, 0.5)],
    )
    alone = hand_trace(ends=[ref(9.0)], starts=[ref(-9.0)])
    jumps = touchdown_jumps([walk, alone])
    assert jumps.shape == (2, 58)
    s = jump_summary(jumps)
    assert s["touchdowns"] == 2
    com_x = s["position"]["com_x"]
    assert com_x["median"] == pytest.approx(0.2)
    assert com_x["p90"] == pytest.approx(0.1 + 0.9 * 0.2)
    assert com_x["max"] == pytest.approx(0.3)
    assert s["rate"]["com_x"]["max"] == pytest.approx(0.5)
    assert s["rate"]["com_x"]["median"] == pytest.approx(0.25)
    assert s["position"]["pelvis_yaw"]["max"] == pytest.approx(2 * math.pi - 6.2)
    assert s["position"]["swing_x"]["median"] == pytest.approx(0.5)  # 0 - 0.5 and 0.5 - 1
    assert s["position_group_norm"]["com"]["max"] == pytest.approx(0.3)
    assert s["position"]["com_y"]["max"] == 0.0


def course_frame_feet(kin: KinematicG1, qpos: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """(2,) lateral coordinate (left of the course axis) of the left and right foot sites."""
    kin.measure(qpos, None, True)
    lat = np.array([-axis[1], axis[0], 0.0])
    return np.array([kin.data.site_xpos[s] @ lat for s in kin.site_ids])


def test_the_legs_never_cross_in_an_ik_walk(kin):
    """On flat ground, the left foot stays left of the right foot by at least 0.15 m (the
    step width is 0.25 m) at every tick of a 4-step walk, and the first step's swing foot
    starts on its own side, 0.25 m from the stance foot. A walk whose swing foot starts on
    the stance side (legs crossed) fails both."""
    from march.audit.ik_walk import ik_walks
    from march.world.courses import CourseCfg, flat_course
    from march.world.footholds import footholds_from_layouts

    layouts = [flat_course(CourseCfg(size=(6.0, 4.0)))]
    footholds = footholds_from_layouts(layouts, np.stack([lay.origin for lay in layouts]))
    axis = footholds.direction[0].double().numpy()
    trace = ik_walks(kin, footholds, torch.tensor([[0.5, 0.0]]), max_steps=4, keep_qpos=True)[0]
    assert len(trace.step_length) == 4 and len(trace.qpos) > 80
    gaps = np.array([np.subtract(*course_frame_feet(kin, q, axis)) for q in trace.qpos])
    assert gaps.min() > 0.15, gaps.min()
    lat = np.array([-axis[1], axis[0]])
    swing_start = trace.y_ref[0][6:8]  # the right foot, the left one stands
    assert (swing_start - footholds.start_xy[0].double().numpy()) @ lat == pytest.approx(
        0.5 * 0.25 - 0.25, abs=0.02
    )


def test_a_swing_foot_that_never_lifts_is_no_touchdown(kin):
    """A reference whose swing foot slides along the ground (apex clearance 0) is tracked
    within every tolerance, but the foot never leaves the ground: the step is no real
    touchdown, not reached, and the report says so; the same step with the 10 cm apex is a
    real touchdown and reached."""
    trace = WalkTrace()
    held = (np.array([0.0, 0.125, 0.0]), np.eye(3))
    _, _, real = track_step(
        kin, trace, one_step(0.3), 0, held, True, ReferenceCfg(swing_height=0.0), HlipCfg()
    )
    assert not real and trace.real_touchdown == [False] and trace.lifted[0] < 0.005
    walks = LevelWalks(0, 0.0, "flat", [0.5], [trace], [None])
    p11 = kin.clf.P_blocks_np[:, 0, 0]
    s = level_summary(walks, FeasibilityCfg(), p11, kin.v_max)
    assert s["no_touchdown_steps"] == 1
    assert s["reach"]["whole_step"] == 0.0 and s["reach"]["touchdown_tick_positions"] == 1.0
    assert s["reach"]["misses_by_cause"] == {"no_touchdown": 1}
    lifted = walk_one_step(kin, 0.3)
    assert lifted["trace"].real_touchdown == [True] and lifted["no_touchdown_steps"] == 0
    assert lifted["trace"].lifted[0] == pytest.approx(0.10, abs=0.01)


def test_a_soft_stance_foot_that_slides_does_not_count_as_reached():
    """The soft stance task (cost 300) lets the stance foot slide about 2 cm on a 0.5 m step
    where the swing leg stretches; the audit reports it and does not count the step, while the
    hard constraint holds the foot within 0.1 mm."""
    from march.audit.kinematic_g1 import IkCfg

    soft = walk_one_step(KinematicG1(IkCfg(stance_hard=False)), 0.5)
    assert soft["stance_slide_m"]["max"] > FeasibilityCfg().max_slide
    assert soft["reach"]["whole_step"] == 0.0
    hard = walk_one_step(KinematicG1(), 0.5)
    assert hard["stance_slide_m"]["max"] < 1e-4


def test_the_reach_envelope_finds_the_longest_step_and_lowers_with_height(kin):
    """At the author's CoM height 0.67 m a 0.9 m step's touchdown pose misses on com_z (the
    hips are ~0.8 m from the feet, the leg ~0.7 m: the CoM stays below its reference), and so
    does a 0.6 m step; with the CoM at 0.62 m the 0.6 m step is reached. The envelope's
    longest step is the longest reached length of the grid."""
    from march.audit.reach_envelope import (
        EnvelopeCfg,
        longest_reached,
        pose_reached,
        touchdown_reference,
    )

    cfg, judge = EnvelopeCfg(), FeasibilityCfg()
    y = touchdown_reference(0.9, 0.67, cfg)
    assert y[0] == pytest.approx(0.45, abs=0.02)  # the HLIP orbit: l / 2 ahead at touchdown
    assert y[2] == pytest.approx(0.67) and y[6] == pytest.approx(0.9)
    high = pose_reached(kin, y, cfg, judge)
    assert not high["reached"] and high["worst_output"] == "com_z"
    assert high["com_z_error_m"] < -0.05 and high["slide_m"] < 1e-4
    mid = pose_reached(kin, touchdown_reference(0.6, 0.67, cfg), cfg, judge)
    assert not mid["reached"] and mid["worst_output"] == "com_z" and mid["com_z_error_m"] < 0
    low = pose_reached(kin, touchdown_reference(0.6, 0.62, cfg), cfg, judge)
    assert low["reached"]
    lengths = np.array([0.4, 0.5, 0.6, 0.7])
    assert longest_reached(lengths, [True, True, False, False]) == 0.5
    assert longest_reached(lengths, [False, True, False, True]) == 0.7
    assert longest_reached(lengths, [False] * 4) is None


def test_a_step_is_judged_over_every_tick_rates_slide_and_touchdown_by_hand():
    """judge_steps on hand-built steps, each with one fault: within every tolerance (reached);
    CoM x 3.1 cm off at some tick but within tolerance at touchdown (missed, although the old
    touchdown-tick criterion passes it); the swing-z rate at 0.21 m/s against 0.2 (missed on
    the rate); the stance foot slid 1.5 cm (missed: slide); no real touchdown (missed). A
    slide of 0.9 cm alone is reached."""
    from march.audit.feasibility import CAUSES, judge_steps

    opts = FeasibilityCfg()
    tol, rate_tol = opts.tolerances(), opts.rate_tolerances()
    n = 6
    arrays = {
        "step_max_eta": np.tile(0.5 * tol, (n, 1)),
        "step_max_etadot": np.tile(0.5 * rate_tol, (n, 1)),
        "touchdown_eta": np.tile(0.5 * tol, (n, 1)),
        "slide": np.zeros(n),
        "real_touchdown": np.ones(n),
    }
    arrays["step_max_eta"][1, 0] = 0.031
    arrays["step_max_etadot"][2, CLF_OUTPUT_NAMES.index("swing_z")] = 0.21
    arrays["slide"][3] = 0.015
    arrays["real_touchdown"][4] = 0.0
    arrays["slide"][5] = 0.009
    judged = judge_steps(arrays, opts)
    assert judged["reached"].tolist() == [True, False, False, False, False, True]
    assert judged["at_touchdown"].tolist() == [True] * n
    causes = [CAUSES[c] for c in judged["cause"][1:5]]
    assert causes == ["com_x", "swing_z rate", "slide", "no_touchdown"]


def test_the_audit_reads_the_reference_config_the_env_is_built_from():
    """reference_command_cfg is build_env_cfg's ``reference`` command for the run's overrides
    (its planner seed is the run's seed), also for an arm whose reward does not need the
    reference (modelfree): so every reference option a run can take reaches the audit."""
    from march.audit.feasibility import reference_command_cfg
    from march.env.build import build_env_cfg

    cfg = load(["compute=smoke", "seed=5"])
    audited = reference_command_cfg(cfg)
    assert audited == build_env_cfg(cfg, "teacher", num_envs=1).commands["reference"]
    assert audited.planner_seed == 5
    modelfree = reference_command_cfg(load(["compute=smoke", "reward=modelfree"]))
    assert modelfree.planner == audited.planner and modelfree.hlip == audited.hlip


def hand_planned_walk(
    kin: KinematicG1, lengths: tuple[float, ...], reference: ReferenceCfg, monkeypatch
) -> WalkTrace:
    """The audit's own walk (``ik_walks``) on flat ground with the planner's step 0 replaced by
    hand-chosen steps: ``lengths`` [m] ahead along +x, 0.25 m across, 0.4 s each (20 ticks
    exactly: the touchdown tick is at tau = T, no timing term). Each plan starts where the
    kinematic G1's foot landed, as the walk's plans do."""
    from march.audit import ik_walk
    from march.reference.planner import plan_footsteps as real_planner
    from march.world.courses import CourseCfg, flat_course
    from march.world.footholds import footholds_from_layouts

    steps = iter(lengths)

    def by_hand(stance, left, command, footholds, cfg, gen):
        plan = real_planner(stance, left, command, footholds, cfg, gen)
        length = next(steps)
        across = torch.where(left, -0.25, 0.25)  # the landing foot's side of the stance foot
        first = plan.start + torch.stack([torch.full_like(across, length), across, 0 * across], -1)
        second = first + torch.stack([torch.full_like(across, length), -across, 0 * across], -1)
        plan.footholds = torch.stack([first, second], dim=1)
        plan.durations = torch.full((len(left), 2), 0.4)
        plan.lands_left = torch.stack([~left, left], dim=1)
        plan.feasible = torch.ones_like(left)
        return plan

    monkeypatch.setattr(ik_walk, "plan_footsteps", by_hand)
    layouts = [flat_course(CourseCfg(size=(6.0, 4.0)))]
    footholds = footholds_from_layouts(layouts, np.stack([lay.origin for lay in layouts]))
    command = torch.tensor([[0.8, 0.0]])
    trace = ik_walk.ik_walks(kin, footholds, command, len(lengths), reference=reference)[0]
    assert trace.real_touchdown == [True] * len(lengths)
    # the step's horizontal length: l along the course, 0.25 m across
    assert trace.step_length == pytest.approx([math.hypot(x, 0.25) for x in lengths], abs=1e-3)
    return trace


def test_the_walk_carries_the_com_reference_across_a_touchdown_as_the_env_does(kin, monkeypatch):
    """A hand-planned two-step walk, 0.45 m then 0.25 m. With the continuous reference (the
    default) the audit's jump column reads ~0 for the CoM, position and velocity. With
    ``com_anchoring=stance`` each step's HLIP orbit restarts at -l_new/2 behind the new stance
    foot after the old one ended l_old/2 ahead of the old foot: a jump of (l_old - l_new)/2 =
    0.1 m (plus the landing offset of the kinematic G1's foot, < 5 mm here) and, by the
    period-1 orbit's symmetry (v(0) = v- = lam coth(lam T / 2) l / 2), a velocity jump of
    lam coth(lam T / 2) (l_old - l_new) / 2 exactly (the orbit's velocity depends on the step
    vector alone)."""
    from march.audit.feasibility import jump_summary, touchdown_jumps

    hlip = HlipCfg()
    com_x, com_vx = CLF_OUTPUT_NAMES.index("com_x"), 29 + CLF_OUTPUT_NAMES.index("com_x")
    continuous = hand_planned_walk(kin, (0.45, 0.25), ReferenceCfg(), monkeypatch)
    jumps = touchdown_jumps([continuous])
    assert jumps.shape == (1, 58)
    summary = jump_summary(jumps)
    assert summary["position_group_norm"]["com"]["max"] < 1e-4
    assert summary["rate_group_norm"]["com"]["max"] < 1e-3
    stance = hand_planned_walk(kin, (0.45, 0.25), ReferenceCfg(com_anchoring="stance"), monkeypatch)
    jump = touchdown_jumps([stance])[0]
    assert jump[com_x] == pytest.approx(0.1, abs=0.005)
    lam, half_t = hlip.lam, 0.5 * 0.4
    assert jump[com_vx] == pytest.approx(lam / math.tanh(lam * half_t) * 0.1, rel=1e-3)


def test_the_walk_lowers_the_com_with_the_step_length_when_asked(kin, monkeypatch):
    """``com_height=step``: a 0.7 m step ends with its CoM reference at
    0.67 - 0.35 (0.7 - 0.5) = 0.60 m, the 0.3 m step after it back at 0.67 m, carried across
    the touchdown without a jump; ``fixed`` walks both at 0.67 m."""
    from march.audit.feasibility import touchdown_jumps

    com_z = CLF_OUTPUT_NAMES.index("com_z")
    lowered = hand_planned_walk(kin, (0.7, 0.3), ReferenceCfg(com_height="step"), monkeypatch)
    ends = np.asarray(lowered.ref_end)[:, com_z]
    assert ends == pytest.approx([0.60, 0.67], abs=1e-5)
    assert np.abs(touchdown_jumps([lowered])[0][[0, 1, 2, 29, 30, 31]]).max() < 1e-4
    fixed = hand_planned_walk(kin, (0.7, 0.3), ReferenceCfg(), monkeypatch)
    assert np.asarray(fixed.ref_end)[:, com_z] == pytest.approx([0.67, 0.67], abs=1e-5)
