"""The paper's DR table as mjlab terms (march.env.randomization, march.env.dr_terms).

Fast tests check the term configs and ``describe_dr``; the ``sim`` test builds one real 4-env
mjlab G1 env on CPU (with the chest depth camera) and reads every sampled parameter back from
the simulator.
"""

from __future__ import annotations

import math
import os

import pytest
import torch

os.environ.setdefault(
    "WARP_CACHE_PATH", os.path.join(os.path.dirname(__file__), "..", ".warp_cache")
)

from mjlab.asset_zoo.robots.unitree_g1.g1_constants import G1_ACTUATOR_5020  # noqa: E402
from mjlab.managers.event_manager import RecomputeLevel  # noqa: E402
from mjlab.tasks.velocity.config.g1.env_cfgs import unitree_g1_flat_env_cfg  # noqa: E402

from march.config import DepthCfg, DrCfg  # noqa: E402
from march.env import dr_terms as D  # noqa: E402
from march.env import randomization as R  # noqa: E402

CAM = "depth_cam"
EVENT_ROWS = R.PAPER_ROWS[:13]


# ---------------------------------------------------------------------------------------------
# Fast: configuration only.
# ---------------------------------------------------------------------------------------------


def test_describe_dr_covers_every_paper_row():
    dr = DrCfg()
    rows = R.describe_dr(dr, camera=CAM)
    assert [r["row"] for r in rows] == list(R.PAPER_ROWS)
    assert len(rows) == 15  # 13 event rows + pixel dropout + depth noise
    for r in rows:
        assert set(r) >= {"row", "term", "mode", "range", "units"}
    events = R.paper_dr_events(dr, camera=CAM)
    by_row = {r["row"]: r for r in rows}
    # Every event row names a term that exists, with that term's mode; every term has a row.
    terms = [by_row[name]["term"] for name in EVENT_ROWS]
    assert sorted(terms) == sorted(events)
    for name in EVENT_ROWS:
        r = by_row[name]
        assert r["mode"] == events[r["term"]].mode
    modes = {r["term"]: r["mode"] for r in rows if r["term"]}
    assert [t for t, m in modes.items() if m == "startup"] == [
        "link_mass",
        "base_added_mass",
        "base_com",
    ]
    assert [t for t, m in modes.items() if m == "step"] == ["push_robot"]  # issue 41: sync-free
    assert sum(m == "reset" for m in modes.values()) == 9
    # The paper's numbers are what is printed.
    assert by_row["Friction Coefficients"]["range"] == "U(0.5, 1.25)"
    assert by_row["Link Mass"]["range"] == "U(0.9, 1.2) x default"
    assert by_row["Base Additional Mass"]["range"] == "U(-1, 3)"
    assert by_row["Base Additional Mass"]["units"] == "kg"
    assert by_row["Encoder Bias"]["range"] == "U(-0.015, 0.015)"
    assert "dy U(-0.05, 0.05)" in by_row["Base CoM Offset"]["range"]
    assert by_row["Motor Effort Limits"]["range"] == "U(0.85, 1.1) x default"
    assert by_row["Joint Damping"]["range"] == "U(0.75, 1.25) x default"
    assert by_row["Joint Friction"]["range"] == "U(0, 0.04)"
    assert by_row["Push Perturbation"]["range"].startswith("every U(10, 15) s")
    assert by_row["Control Delay"]["range"] == "U(0, 20)"
    assert "lag 0..4" in by_row["Control Delay"]["note"]
    assert by_row["Depth Camera Rotation (Euler)"]["range"] == (
        "roll U(-2.5, 2.5), pitch U(-3, 3), yaw U(-2.5, 2.5)"
    )
    assert by_row["Depth Camera FOV"]["range"] == "U(-2, 2)"
    # Pixel dropout and depth noise live in the depth pipeline, with DepthCfg's numbers.
    depth = DepthCfg()
    assert by_row["Pixel Dropout"]["mode"] == "depth pipeline"
    assert by_row["Pixel Dropout"]["term"] is None
    assert by_row["Pixel Dropout"]["range"] == f"{depth.dropout:g}" == "0.05"
    assert by_row["Depth Noise"]["range"] == "sigma = 0.1 x depth"


def test_describe_dr_marks_rows_that_are_off():
    no_cam = {r["row"]: r for r in R.describe_dr(DrCfg())}
    for name in EVENT_ROWS[:10]:
        assert no_cam[name]["mode"] != "off"
    for name in EVENT_ROWS[10:]:
        assert no_cam[name]["mode"] == "off" and no_cam[name]["term"] is None
    assert len(R.paper_dr_events(DrCfg())) == 10  # no camera -> no camera terms
    off = R.describe_dr(DrCfg(name="none"), camera=CAM)
    assert len(off) == 15
    assert sum(r["mode"] == "off" for r in off) == 13
    assert all(r["term"] is None for r in off)


def test_dr_none_gives_no_terms_and_no_delay():
    dr = DrCfg(name="none")
    assert R.paper_dr_events(dr) == {}
    assert R.paper_dr_events(dr, camera=CAM) == {}
    cfg = unitree_g1_flat_env_cfg()
    assert set(R.MJLAB_DR_EVENTS) <= set(cfg.events)
    R.apply_dr(cfg, dr)
    assert sorted(cfg.events) == ["reset_base", "reset_robot_joints"]
    assert D.install_control_delay(cfg, dr) == 0
    lags = [a.delay_max_lag for a in cfg.scene.entities["robot"].articulation.actuators]
    assert lags == [0] * 6


def test_paper_terms_carry_the_paper_ranges():
    ev = R.paper_dr_events(DrCfg(), camera=CAM)
    p = {k: v.params for k, v in ev.items()}
    assert p["foot_friction"]["ranges"] == (0.5, 1.25)
    assert p["foot_friction"]["asset_cfg"].geom_names == R.G1_FOOT_GEOMS
    assert len(R.G1_FOOT_GEOMS) == 14
    assert p["link_mass"]["scale_range"] == (0.9, 1.2)
    assert p["base_added_mass"]["mass_range"] == (-1.0, 3.0)
    assert p["base_added_mass"]["asset_cfg"].body_names == ("torso_link",)
    assert p["encoder_bias"]["bias_range"] == (-0.015, 0.015)
    assert p["base_com"]["ranges"] == {0: (-0.025, 0.025), 1: (-0.05, 0.05), 2: (-0.05, 0.05)}
    assert p["base_com"]["operation"] == "add"
    assert p["effort_limits"]["effort_limit_range"] == (0.85, 1.1)
    assert p["joint_damping"]["scale_range"] == (0.75, 1.25)
    assert p["joint_friction"]["ranges"] == (0.0, 0.04)
    assert ev["push_robot"].interval_range_s == (10.0, 15.0)
    assert p["push_robot"]["velocity_range"] == {
        "x": (-1.0, 1.0),
        "y": (-1.0, 1.0),
        "roll": (-0.4, 0.4),
        "pitch": (-0.4, 0.4),
        "yaw": (-0.4, 0.4),
    }
    assert p["control_delay"]["delay_ms"] == (0.0, 20.0)
    assert p["camera_pos"]["ranges"] == {i: (-0.025, 0.025) for i in range(3)}
    assert p["camera_rot"]["roll_range"][1] == pytest.approx(math.radians(2.5))
    assert p["camera_rot"]["pitch_range"][0] == pytest.approx(-math.radians(3.0))
    assert p["camera_rot"]["yaw_range"][1] == pytest.approx(0.0436332, abs=1e-6)
    assert p["camera_fov"]["ranges"] == (-2.0, 2.0)
    # Custom ranges flow through.
    custom = R.paper_dr_events(DrCfg(friction=(0.2, 0.3), control_delay_ms=(0.0, 0.0)))
    assert custom["foot_friction"].params["ranges"] == (0.2, 0.3)
    assert "control_delay" not in custom


def test_install_control_delay_copies_actuators():
    cfg = unitree_g1_flat_env_cfg()
    assert cfg.sim.mujoco.timestep == 0.005
    assert D.install_control_delay(cfg, DrCfg()) == 4  # 20 ms / 5 ms
    acts = cfg.scene.entities["robot"].articulation.actuators
    assert [a.delay_max_lag for a in acts] == [4] * 6
    assert [a.delay_min_lag for a in acts] == [0] * 6
    assert [a.delay_hold_prob for a in acts] == [1.0] * 6
    # mjlab's module-level G1 actuator configs are untouched.
    assert G1_ACTUATOR_5020.delay_max_lag == 0
    assert unitree_g1_flat_env_cfg().scene.entities["robot"].articulation.actuators[0] is (
        G1_ACTUATOR_5020
    )
    cfg.sim.mujoco.timestep = 0.002
    assert D.max_delay_steps(DrCfg(), cfg.sim.mujoco.timestep) == 10


# ---------------------------------------------------------------------------------------------
# Sim: one real 4-env G1 env on CPU.
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def env():
    torch.set_num_threads(1)
    torch.manual_seed(0)
    from mjlab.envs import ManagerBasedRlEnv
    from mjlab.sensor import CameraSensorCfg

    cfg = unitree_g1_flat_env_cfg()
    cfg.scene.num_envs = 4
    cfg.seed = 0
    cam = CameraSensorCfg(
        name=CAM,
        parent_body="robot/torso_link",
        pos=(0.1, 0.0, 0.35),
        fovy=55.2,
        width=32,
        height=24,
        data_types=("depth",),
        use_textures=False,
        enabled_geom_groups=(0,),
    )
    cfg.scene.sensors = (cfg.scene.sensors or ()) + (cam,)
    R.apply_dr(cfg, DrCfg(), camera=CAM)
    e = ManagerBasedRlEnv(cfg=cfg, device="cpu")
    e.reset()
    yield e
    e.close()


def _default(env, field):
    return env.sim.get_default_field(field)


def _varies(x: torch.Tensor) -> bool:
    """Not all envs drew the same value (x: (E, ...))."""
    return bool((x - x[:1]).abs().max() > 1e-6)


@pytest.mark.sim
def test_sampled_model_parameters_lie_in_the_paper_ranges(env):
    m = env.sim.model
    robot = env.scene["robot"]
    ix = robot.indexing
    eps = 1e-5

    # Event manager: modes as documented.
    active = env.event_manager.active_terms
    assert active["startup"] == ["link_mass", "base_added_mass", "base_com"]
    assert active["step"] == ["push_robot"] and "interval" not in active  # issue 41
    assert set(active["reset"]) >= {"reset_base", "reset_robot_joints", "control_delay"}

    # Friction: U(0.5, 1.25), one value per env shared by the 14 foot geoms, tangential only.
    local, names = robot.find_geoms(R.G1_FOOT_GEOMS, preserve_order=True)
    assert len(names) == 14
    foot = ix.geom_ids[local].long()
    mu = m.geom_friction[:, foot]
    assert float(mu[..., 0].min()) >= 0.5 - eps and float(mu[..., 0].max()) <= 1.25 + eps
    assert torch.allclose(mu[..., 0], mu[:, :1, 0].expand_as(mu[..., 0]))
    assert _varies(mu[:, 0, 0])
    assert torch.allclose(
        mu[..., 1:], _default(env, "geom_friction")[foot, 1:].expand_as(mu[..., 1:])
    )

    # Link mass x U(0.9, 1.2) with inertia alike; torso: that plus U(-1, 3) kg.
    bodies = ix.body_ids.long()
    torso_local = robot.find_bodies("torso_link")[0][0]
    m0 = _default(env, "body_mass")[bodies]
    i0 = _default(env, "body_inertia")[bodies]
    mass = m.body_mass[:, bodies]
    inertia_ratio = m.body_inertia[:, bodies] / i0
    s = inertia_ratio.mean(-1)
    assert torch.allclose(inertia_ratio, s.unsqueeze(-1).expand_as(inertia_ratio), rtol=1e-5)
    assert float(s.min()) >= 0.9 - eps and float(s.max()) <= 1.2 + eps
    others = [i for i in range(len(bodies)) if i != torso_local]
    assert torch.allclose(mass[:, others] / m0[others], s[:, others], rtol=1e-5)
    assert _varies(s) and float(s.std()) > 0.03  # U(0.9,1.2) has std 0.087
    added = mass[:, torso_local] - m0[torso_local] * s[:, torso_local]
    assert float(added.min()) >= -1.0 - 1e-4 and float(added.max()) <= 3.0 + 1e-4
    assert _varies(added)

    # Base CoM offset on torso_link only: dx +-0.025, dy/dz +-0.05 m.
    ipos0 = _default(env, "body_ipos")[bodies]
    dcom = m.body_ipos[:, bodies] - ipos0
    half = torch.tensor([0.025, 0.05, 0.05])
    assert bool((dcom[:, torso_local].abs() <= half + 1e-6).all())
    assert _varies(dcom[:, torso_local])
    assert float(dcom[:, others].abs().max()) < 1e-6

    # Encoder bias U(-0.015, 0.015) rad per joint.
    bias = robot.data.encoder_bias
    assert bias.shape == (4, robot.num_joints) == (4, 29)
    assert float(bias.abs().max()) <= 0.015 + 1e-7 and _varies(bias)

    # Effort limits x U(0.85, 1.1) per actuator, symmetric.
    ctrl = torch.cat([a.global_ctrl_ids for a in robot.actuators]).long()
    fr0 = _default(env, "actuator_forcerange")[ctrl]
    fr = m.actuator_forcerange[:, ctrl]
    ratio = fr[..., 1] / fr0[:, 1]
    assert float(ratio.min()) >= 0.85 - eps and float(ratio.max()) <= 1.1 + eps
    assert torch.allclose(fr[..., 0], -fr[..., 1]) and _varies(ratio)

    # Joint damping x U(0.75, 1.25): PD kd per joint; kp untouched; passive damping 0 stays 0.
    bp0 = _default(env, "actuator_biasprm")[ctrl]
    kd_ratio = m.actuator_biasprm[:, ctrl, 2] / bp0[:, 2]
    assert float(kd_ratio.min()) >= 0.75 - eps and float(kd_ratio.max()) <= 1.25 + eps
    assert _varies(kd_ratio) and float(kd_ratio.std()) > 0.05
    assert torch.allclose(m.actuator_biasprm[:, ctrl, 1], bp0[:, 1].expand(4, -1))
    assert torch.allclose(
        m.actuator_gainprm[:, ctrl, 0], _default(env, "actuator_gainprm")[ctrl, 0].expand(4, -1)
    )
    dofs = ix.joint_v_adr.long()
    assert float(m.dof_damping[:, dofs].abs().max()) == 0.0

    # Joint friction U(0, 0.04) on the 29 joints; the free joint's 6 dofs stay frictionless.
    fl = m.dof_frictionloss[:, dofs]
    assert float(fl.min()) >= 0.0 and float(fl.max()) <= 0.04 + 1e-7 and _varies(fl)
    assert float(fl.mean()) == pytest.approx(0.02, abs=0.006)
    assert float(m.dof_frictionloss[:, ix.free_joint_v_adr.long()].abs().max()) == 0.0

    # Camera: +-2.5 cm per axis, roll/pitch/yaw within +-2.5/3/2.5 deg, FOV +-2 deg.
    from mjlab.utils.lab_api.math import euler_xyz_from_quat, quat_conjugate, quat_mul

    cam = int(ix.cam_ids[robot.find_cameras(CAM)[0][0]])
    dpos = m.cam_pos[:, cam] - _default(env, "cam_pos")[cam]
    assert float(dpos.abs().max()) <= 0.025 + 1e-6 and _varies(dpos)
    q0 = _default(env, "cam_quat")[cam].expand(4, 4)
    rel = quat_mul(m.cam_quat[:, cam], quat_conjugate(q0))
    roll, pitch, yaw = (torch.atan2(torch.sin(a), torch.cos(a)) for a in euler_xyz_from_quat(rel))
    assert float(roll.abs().max()) <= math.radians(2.5) + 1e-4
    assert float(pitch.abs().max()) <= math.radians(3.0) + 1e-4
    assert float(yaw.abs().max()) <= math.radians(2.5) + 1e-4
    assert _varies(pitch)
    dfov = m.cam_fovy[:, cam] - _default(env, "cam_fovy")[cam]
    assert float(dfov.abs().max()) <= 2.0 + 1e-5 and _varies(dfov)
    assert float(_default(env, "cam_fovy")[cam]) == pytest.approx(55.2, abs=1e-4)
    # The per-world mount reaches the camera pose the renderer reads (torso frame).
    d = env.sim.data
    torso = int(ix.body_ids[torso_local])
    rot = d.xmat[:, torso].reshape(4, 3, 3)
    in_torso = torch.einsum("eji,ej->ei", rot, d.cam_xpos[:, cam] - d.xpos[:, torso])
    assert torch.allclose(in_torso, m.cam_pos[:, cam], atol=1e-4)


@pytest.mark.sim
def test_reset_resamples_per_episode_and_masses_do_not_accumulate(env):
    m = env.sim.model
    robot = env.scene["robot"]
    bodies = robot.indexing.body_ids.long()
    torso = robot.find_bodies("torso_link")[0][0]
    dofs = robot.indexing.joint_v_adr.long()
    mass_before = m.body_mass[:, bodies].clone()
    fl_before = m.dof_frictionloss[:, dofs].clone()
    bias_before = robot.data.encoder_bias.clone()

    env.reset(env_ids=torch.tensor([0, 1]))
    fl = m.dof_frictionloss[:, dofs]
    bias = robot.data.encoder_bias
    # Reset-mode terms re-draw for the reset envs only; startup terms keep their draw.
    assert bool((fl[:2] != fl_before[:2]).any()) and torch.equal(fl[2:], fl_before[2:])
    assert bool((bias[:2] != bias_before[:2]).any()) and torch.equal(bias[2:], bias_before[2:])
    assert torch.equal(m.body_mass[:, bodies], mass_before)

    # Link mass and base added mass commute: redrawing the link factor keeps the added kg.
    i0 = _default(env, "body_inertia")[bodies]
    m0 = _default(env, "body_mass")[bodies]

    def added():
        s = (m.body_inertia[:, bodies] / i0).mean(-1)
        return m.body_mass[:, bodies] - m0 * s

    added_before = added()
    link_cfg = env.event_manager.get_term_cfg("link_mass").params["asset_cfg"]
    D.scale_link_mass(env, None, (0.9, 1.2), link_cfg)
    env.sim.recompute_constants(RecomputeLevel.set_const)
    assert torch.allclose(added(), added_before, atol=1e-4)
    assert float(added()[:, torso].abs().min()) > 0.0
    others = [i for i in range(len(bodies)) if i != torso]
    assert float(added()[:, others].abs().max()) < 1e-4


@pytest.mark.sim
def test_push_adds_a_velocity_within_the_paper_ranges(env):
    robot = env.scene["robot"]
    term = env.event_manager.get_term_cfg("push_robot")
    assert term.interval_range_s == (10.0, 15.0)
    env.sim.forward()
    before = robot.data.root_link_vel_w.clone()
    term.func(env, torch.arange(4), **term.params)
    env.sim.forward()
    delta = robot.data.root_link_vel_w - before
    assert float(delta[:, :2].abs().max()) <= 1.0 + 1e-4 and _varies(delta[:, :2])
    assert float(delta[:, 2].abs().max()) < 1e-4
    assert float(delta[:, 3:].abs().max()) <= 0.4 + 1e-4 and _varies(delta[:, 3:])
    env.reset()


@pytest.mark.sim
def test_control_delay_lags_and_delayed_targets(env):
    robot = env.scene["robot"]
    # Lag distribution: round(U(0, 20) ms / 5 ms) -> {0..4} with {1/8, 1/4, 1/4, 1/4, 1/8}.
    params = env.event_manager.get_term_cfg("control_delay").params
    draws = []
    for _ in range(250):
        D.sample_control_delay(env, None, **params)
        draws.append(D.control_delay_lags(env))
    lags = torch.cat(draws)
    freq = torch.bincount(lags, minlength=5).float() / lags.numel()
    assert lags.numel() == 1000 and int(lags.min()) == 0 and int(lags.max()) == 4
    assert freq.tolist() == pytest.approx([0.125, 0.25, 0.25, 0.25, 0.125], abs=0.05)

    env.reset()
    # After reset the target is seeded with the zero-action command (default pose - bias).
    seed = robot.data.default_joint_pos - robot.data.encoder_bias
    assert torch.allclose(robot.data.joint_pos_target, seed)
    assert int(D.control_delay_lags(env).max()) <= 4

    # Known lags 0, 1, 2, 4 physics steps: substep k of the first control step still applies
    # the seed where k < lag, the new action's target where k >= lag.
    lag = torch.tensor([0, 1, 2, 4])
    for act in robot.actuators:
        act.set_lags(lag)
    am = env.action_manager
    am.process_action(torch.full((4, am.total_action_dim), 0.5))
    term = am.get_term("joint_pos")
    jid = term.target_ids.long()
    target = seed.clone()
    target[:, jid] = term._processed_actions - robot.data.encoder_bias[:, jid]
    assert float((target - seed).abs().min()) > 1e-3
    for k in range(env.cfg.decimation):
        am.apply_action()
        env.scene.write_data_to_sim()
        for act in robot.actuators:
            ctrl = env.sim.data.ctrl[:, act.global_ctrl_ids.long()]
            j = act.target_ids.long()
            for i in range(4):
                want = seed[i, j] if k < int(lag[i]) else target[i, j]
                assert torch.allclose(ctrl[i], want, atol=1e-6), (k, i)
        env.sim.step()
        env.scene.update(dt=env.physics_dt)
    env.reset()


def test_gather_delay_equals_mjlabs_delay_buffer():
    """Issue 41: march's command delay (one gather per physics step) returns exactly what
    mjlab's DelayBuffer with per-episode lags (hold_prob 1) returns, step by step, through
    random appends, partial resets (repeated with the same ids, as a fused group's actuators
    do), lag changes and backfills; a read is one op and an append one op."""
    from mjlab.utils.buffers.delay_buffer import DelayBuffer

    from march.bench.ops import OpCounter
    from march.env.command_delay import GatherDelay

    for seed in range(6):
        g = torch.Generator().manual_seed(seed)
        e, max_lag = 7, 1 + seed % 4
        ref = DelayBuffer(0, max_lag, e, "cpu", hold_prob=1.0, update_period=0)
        ours = GatherDelay.from_buffer(DelayBuffer(0, max_lag, e, "cpu", hold_prob=1.0))
        for step in range(60):
            if step % 7 == 3:
                ids = torch.randperm(e, generator=g)[: int(torch.randint(1, e, (1,), generator=g))]
                for buf in (ref, ours):
                    buf.reset(ids)
                    buf.reset(ids)
            if step % 7 == 4 or step == 0:
                ids = torch.randperm(e, generator=g)[:4]
                lags = torch.randint(0, max_lag + 2, (4,), generator=g)
                for buf in (ref, ours):
                    buf.set_lags(lags, ids)
            frame = torch.rand(e, 3, 2, generator=g)
            with OpCounter() as ops:
                ours.append(frame)
                got = ours.compute()
            ref.append(frame)
            want = ref.compute()
            assert torch.equal(got, want), (seed, step)
            assert torch.equal(ours.current_lags, ref.current_lags)
            if step % 7 not in (3, 4) and step % 11 != 6 and step > 1:
                assert ops.total == 2, ops.counts  # (after a reset: + a where and a fill)
            if step % 11 == 5:
                ids = torch.tensor([1, 4])
                back = torch.rand(e, 3, 2, generator=g)
                ref.reset(ids), ours.reset(ids)
                ref.backfill(back, ids), ours.backfill(back, ids)
                assert torch.equal(ours.peek(), ref.peek())
