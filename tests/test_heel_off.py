"""The audit's stance-foot contact model ``heel_off`` (march.audit.kinematic_g1, issue 55): the
stance foot's toe edge is held (no slide, roll and yaw held), the foot pitches heel UP only,
about that edge, up to ``IkCfg.heel_pitch_max``; checked against the G1 foot's geometry by hand,
on touchdown poses the flat foot cannot take, and with the audit's judgement and command line.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from march.audit.feasibility import FeasibilityCfg
from march.audit.kinematic_g1 import IkCfg, KinematicG1, foot_sole, with_toe_sites
from march.audit.reach_envelope import EnvelopeCfg, pose_reached, touchdown_reference
from march.env.g1 import g1_mjcf_spec

HELD = (np.array([0.0, 0.125, 0.0]), np.eye(3))
"""The envelope's stance foot: the left foot site at (0, w/2, 0), flat, heading +x."""


@pytest.fixture(scope="module")
def heel_off() -> KinematicG1:
    # pinned (not the tuned defaults): the bound 0.5 rad and a heel cost of 1, at which the
    # hand-checked poses below were measured
    return KinematicG1(IkCfg(stance="heel_off", heel_pitch_max=0.5, heel_cost=1.0))


@pytest.fixture(scope="module")
def flat() -> KinematicG1:
    return KinematicG1()


def foot_points(kin: KinematicG1, offsets: np.ndarray) -> np.ndarray:
    """World positions (n, 3) of points given in the left foot site's frame, last measured
    state."""
    sid = kin.site_ids[0]
    pos, rot = kin.data.site_xpos[sid], kin.data.site_xmat[sid].reshape(3, 3)
    return pos + offsets @ rot.T


def test_the_sole_is_read_from_the_g1_foot_capsules():
    """mjlab's G1 foot: seven capsules of radius 1 cm whose centre lines run from x = -0.094
    (heel) to +0.092 m (toe) in the foot site's frame, 1.2 cm above it; the three middle ones
    end at the toe at y = -0.01, 0, 0.01 and the two beside them (y = +-0.018) 9 mm behind
    (within the 1 cm that counts as the toe edge)."""
    model = g1_mjcf_spec().compile()
    for site in ("left_foot", "right_foot"):
        sole = foot_sole(model, site)
        assert sole.toe_x == pytest.approx(0.092, abs=1e-6)
        assert sole.heel_x == pytest.approx(-0.094, abs=1e-6)
        assert sole.toe_half_width == pytest.approx(0.018, abs=1e-6)
        assert sole.sole_z == pytest.approx(0.012 - 0.010, abs=1e-6)


def test_the_toe_sites_sit_on_the_toe_edge_and_move_no_body():
    """``with_toe_sites`` adds ``<foot>_toe`` at the foot site + R (0.092, 0, 0.002); the
    bodies, the foot sites and the CoM of the same configuration are unchanged (so the flat
    model's numbers are too)."""
    bare = g1_mjcf_spec().compile()
    toes = with_toe_sites(g1_mjcf_spec(), ("left_foot", "right_foot")).compile()
    assert (bare.nq, bare.nv, bare.nbody) == (toes.nq, toes.nv, toes.nbody)
    rng = np.random.default_rng(0)
    q = np.zeros(bare.nq)
    q[3] = 1.0
    q[7:] = rng.uniform(-0.3, 0.3, bare.nq - 7)
    datas = []
    for m in (bare, toes):
        d = mujoco.MjData(m)
        d.qpos[:] = q
        mujoco.mj_forward(m, d)
        datas.append(d)
    a, b = datas
    assert np.array_equal(a.xpos, b.xpos) and np.array_equal(a.subtree_com, b.subtree_com)
    for site in ("left_foot", "right_foot"):
        i, j = bare.site(site).id, toes.site(site).id
        assert np.array_equal(a.site_xpos[i], b.site_xpos[j])
        rot = b.site_xmat[j].reshape(3, 3)
        toe = b.site_xpos[toes.site(f"{site}_toe").id]
        np.testing.assert_allclose(toe, b.site_xpos[j] + rot @ [0.092, 0.0, 0.002], atol=1e-9)


@pytest.mark.parametrize("length", [0.65, 0.7])
def test_heel_off_reaches_a_touchdown_the_flat_foot_cannot_without_sliding_the_toe(
    flat, heel_off, length
):
    """Touchdown of a 0.65 / 0.7 m step at the author's CoM height 0.67 m: with the stance
    foot flat the CoM stays > 3 cm below its reference (com_z missed; the envelope ends at
    0.5 m); with heel_off every output is within tolerance. By hand: the toe edge's two
    corners (0.092, 0.125 +- 0.018, 0.002) stay where they were (< 0.1 mm), the foot turned
    about its own y axis only (its y axis still the world's), by a pitch 0 < p <= 0.5 rad,
    and the heel (x = -0.094) rose by (0.092 + 0.094) sin p above the ground, never below."""
    cfg, judge = EnvelopeCfg(), FeasibilityCfg()
    y = touchdown_reference(length, 0.67, cfg)
    missed = pose_reached(flat, y, cfg, judge)
    assert not missed["reached"] and missed["worst_output"] == "com_z"
    assert missed["com_z_error_m"] < -0.03
    sole = heel_off.soles[0]
    corners = sole.toe_corners()
    np.testing.assert_allclose(corners, [[0.092, -0.018, 0.002], [0.092, 0.018, 0.002]], atol=1e-6)
    reached = pose_reached(heel_off, y, cfg, judge)
    assert reached["reached"], reached
    after = foot_points(heel_off, corners)
    before = HELD[0] + corners  # the held foot: flat at (0, 0.125, 0), heading +x
    assert np.abs(after - before).max() < 1e-4
    rot = heel_off.data.site_xmat[heel_off.site_ids[0]].reshape(3, 3)
    np.testing.assert_allclose(rot[:, 1], [0.0, 1.0, 0.0], atol=1e-5)  # no roll, no yaw
    pitch = math.atan2(rot[0, 2], rot[0, 0])
    assert 0.05 < pitch <= 0.5 + 1e-6
    assert reached["stance_pitch_rad"] == pytest.approx(pitch, abs=1e-9)
    heel = foot_points(heel_off, sole.heel_offset()[None])[0]
    assert heel[2] - 0.002 == pytest.approx(0.186 * math.sin(pitch), abs=2e-4)
    assert reached["heel_lift_m"] == pytest.approx(0.186 * math.sin(pitch), abs=2e-4)
    assert reached["slide_m"] < 1e-4


def test_the_heel_lift_is_bounded_by_the_option():
    """A 0.85 m step at 0.67 m wants more heel lift than 0.2 rad: with the bound 0.2 the pitch
    stops at 0.2 (and the step is missed); with 0.5 it goes past 0.2."""
    cfg, judge = EnvelopeCfg(), FeasibilityCfg()
    y = touchdown_reference(0.85, 0.67, cfg)
    low = KinematicG1(IkCfg(stance="heel_off", heel_pitch_max=0.2, heel_cost=1.0))
    low = pose_reached(low, y, cfg, judge)
    assert low["stance_pitch_rad"] == pytest.approx(0.2, abs=2e-3) and not low["reached"]
    high = KinematicG1(IkCfg(stance="heel_off", heel_pitch_max=0.5, heel_cost=1.0))
    high = pose_reached(high, y, cfg, judge)
    assert high["stance_pitch_rad"] > 0.25


def test_the_foot_never_pitches_toe_up_into_the_ground(heel_off):
    """A reference that pulls the pelvis and CoM back and down over the stance heel (the CoM
    12 cm behind the foot, 0.55 m high): a foot free to turn either way about its toe edge
    would pitch toe up (the heel into the ground). With heel_off the pitch stays >= 0 and
    the heel on or above the ground at every tick, the toe edge held."""
    cfg = EnvelopeCfg()
    y = touchdown_reference(0.4, 0.67, cfg)
    y[0], y[2] = -0.12, 0.55
    heel_off.stand(y, True, *HELD)
    for _ in range(10):
        tick = heel_off.track(y, np.zeros(29), True, *HELD)
        assert tick.stance_pitch >= -1e-6 and tick.heel_lift >= -1e-4
        assert tick.slide < 1e-4


def test_a_heel_in_the_ground_or_a_sliding_toe_is_not_reached_by_hand():
    """judge_steps on hand-built steps otherwise within every tolerance: the heel 2 mm in the
    ground (missed: heel_sink), 0.5 mm (reached: within max_heel_sink 1 mm), the toe edge slid
    1.5 cm (missed: slide), the heel lifted 8 cm (reached: a lift is allowed)."""
    from march.audit.feasibility import CAUSES, judge_steps

    opts = FeasibilityCfg()
    tol, rate_tol = opts.tolerances(), opts.rate_tolerances()
    n = 4
    arrays = {
        "step_max_eta": np.tile(0.5 * tol, (n, 1)),
        "step_max_etadot": np.tile(0.5 * rate_tol, (n, 1)),
        "touchdown_eta": np.tile(0.5 * tol, (n, 1)),
        "slide": np.array([0.0, 0.0, 0.015, 0.0]),
        "real_touchdown": np.ones(n),
        "heel_low": np.array([-0.002, -0.0005, 0.0, 0.08]),
    }
    judged = judge_steps(arrays, opts)
    assert judged["reached"].tolist() == [False, True, False, True]
    assert [CAUSES[c] for c in judged["cause"][[0, 2]]] == ["heel_sink", "slide"]


@pytest.mark.parametrize(
    ("arg", "message"),
    [
        ("audit.stance=tiptoe", "audit.stance='tiptoe': choose one of flat, heel_off, heel_toe"),
        ("audit.heel_flat_by=0", "audit.heel_flat_by=0.0: give a share of the step in (0, 1]"),
        ("audit.heel_pitch_max=-0.1", "audit.heel_pitch_max=-0.1: give a pitch in (0, 1] rad"),
        ("audit.heel_pitch_max=abc", "audit.heel_pitch_max=abc: give a float"),
        ("audit.tol_com=0.1", "audit.tol_com: unknown audit option"),
        ("audit.film=maybe", "audit.film=maybe: give true or false"),
        ("audit.stance=flat audit.stance=heel_off", "audit.stance is given twice"),
    ],
)
def test_a_bad_audit_option_is_one_line_and_exit_2(capsys, arg, message):
    from march.audit.audit_command import main

    with pytest.raises(SystemExit) as stop:
        main(["reference", "compute=smoke", *arg.split()])
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err


def test_the_stance_option_is_for_the_kinematic_audits_only(capsys):
    from march.audit.audit_command import main, split_audit_options

    with pytest.raises(SystemExit) as stop:
        main(["rewards", "audit.stance=heel_off"])
    assert stop.value.code == 2
    assert "applies to reference and envelope" in capsys.readouterr().err
    rest, options = split_audit_options(
        ["envelope", "compute=smoke", "audit.stance=heel_off", "audit.heel_pitch_max=0.4"]
    )
    assert rest == ["envelope", "compute=smoke"]
    assert options.ik == {"stance": "heel_off", "heel_pitch_max": 0.4}
