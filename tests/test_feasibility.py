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


def walk_one_step(kin: KinematicG1, length: float) -> dict:
    trace = WalkTrace()
    held = (np.array([0.0, 0.125, 0.0]), np.eye(3))
    track_step(kin, trace, one_step(length), 0, held, True, ReferenceCfg(), HlipCfg())
    walks = LevelWalks(0, 0.0, "stones", [0.5], [trace], [None])
    p11 = kin.clf.P_blocks_np[:, 0, 0]
    return level_summary(walks, FeasibilityCfg().tolerances(), p11, kin.v_max) | {"trace": trace}


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
    assert long["reach"]["touchdown"] == 0.0
    named = CLF_OUTPUT_NAMES[int(np.argmax(np.abs(td) / tol))]
    assert long["reach"]["misses_by_output"] == {named: 1}
    short = walk_one_step(kin, 0.3)
    assert short["reach"] | {"step_length_m": 0, "step_rise_m": 0} == {
        "touchdown": 1.0,
        "whole_step": 1.0,
        "misses_by_output": {},
        "step_length_m": 0,
        "step_rise_m": 0,
    }
    assert np.abs(short["trace"].touchdown_eta[0]).max() < 5e-3


def test_the_planners_longest_step_keeps_the_com_below_its_reference(kin):
    """The planner's max_step, 0.85 m ahead (0.886 m with the 0.25 m step width): at touchdown
    the HLIP CoM is l/2 = 0.425 m ahead of the stance foot at z0 = 0.67 m, so each hip is about
    sqrt(0.425^2 + 0.125^2 + 0.67^2) ~ 0.80 m from its foot, beyond the leg's ~0.7 m: the CoM
    must sink about 0.1 m. The report names com_z, and the swing foot still lands."""
    step = walk_one_step(kin, 0.85)
    td = np.asarray(step["trace"].touchdown_eta[0])
    assert step["reach"]["misses_by_output"] == {"com_z": 1}
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
        assert s["steps"] == 2 and s["ticks"] > 40
        assert set(s["eta_abs"]["outputs"]) == set(CLF_OUTPUT_NAMES)
        assert 0.0 <= s["reach"]["touchdown"] <= 1.0
    assert out.with_suffix(".png").stat().st_size > 10_000
    table = capsys.readouterr().out
    assert len([r for r in table.splitlines() if r[:5].strip().isdigit()]) == len(levels)


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
