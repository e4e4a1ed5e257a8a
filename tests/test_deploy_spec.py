"""deploy.json as a G1 owner reads it, the out-of-range guard, and the latencies in the loop.

The guard and command checks run on hand-made specs (no simulator). The ``sim`` tests read the
smoke student's bundle: every gain and limit of its ``joints`` table against the compiled
training scene by name (and against the values of mjlab's G1 by hand), one naming scheme
(JSON = ONNX metadata = Unitree), relative paths; the command and depth delays of the runner
against mjlab's delay-buffer semantics, and the command line with delays end to end.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from march.sim2sim.guard import CommandRefused, RangeGuard, check_command

ROOT = Path(__file__).resolve().parent.parent


def toy_spec() -> dict:
    """Two terms: a 2-vector with mean (0, 1), std (0.5, 0) and a 1-vector, eps 0.1."""
    eps = 0.1

    def entry(mean, std):
        return {
            "mean": mean,
            "std": std,
            "lo": [m - 4 * (s + eps) for m, s in zip(mean, std, strict=True)],
            "hi": [m + 4 * (s + eps) for m, s in zip(mean, std, strict=True)],
        }

    return {
        "command_ranges": {
            "lin_vel_x": [0.3, 0.8],
            "lin_vel_y": [0.0, 0.0],
            "ang_vel_z": [-0.2, 0.2],
        },
        "observation": {
            "terms": [
                {"name": "a", "dim": 2, "elements": ["x", "y"]},
                {"name": "b", "dim": 1, "elements": ["q"]},
            ],
            "training_range": {
                "a": entry([0.0, 1.0], [0.5, 0.0]),
                "b": entry([2.0], [1.0]),
                "eps": eps,
                "margin_sigmas": 1.0,
            },
        },
    }


@pytest.mark.parametrize(
    "command,ok",
    [
        ((0.3, 0.0, 0.0), True),
        ((0.8, 0.0, -0.2), True),
        ((0.81, 0.0, 0.0), False),
        ((0.29, 0.0, 0.0), False),
        ((0.5, 0.1, 0.0), False),  # the case: training fixed v_y = 0
        ((0.5, 0.0, 0.25), False),
    ],
)
def test_a_command_outside_the_trained_ranges_is_refused_in_one_line(command, ok):
    if ok:
        check_command(toy_spec(), command)
        return
    with pytest.raises(CommandRefused) as err:
        check_command(toy_spec(), command)
    msg = str(err.value)
    assert "\n" not in msg and "outside the trained range" in msg


def test_guard_flags_past_five_sigma_only():
    """sigma = std + eps: a.x 0.6, a.y 0.1, b 1.1; flagged beyond 4 + 1 sigma from the mean."""
    g = RangeGuard(toy_spec())
    assert g.check(np.array([0.0, 1.0, 2.0])) == []
    assert g.check(np.array([2.99, 1.49, 2.0 - 5.49])) == []  # just inside 5 sigma each
    flags = g.check(np.array([3.01, 1.0, 2.0]))
    assert [(f.term, f.element) for f in flags] == [("a", "x")]
    assert flags[0].sigmas == pytest.approx(3.01 / 0.6)
    assert flags[0].lo == pytest.approx(-2.4) and flags[0].hi == pytest.approx(2.4)
    # v_y-like: std 0, so 0.51 off the mean is 5.1 sigma (the 0.1 m/s lateral command
    # read ~10 sigma with eps 0.01)
    flags = g.check(np.array([0.0, 0.49, 2.0 + 5.6]))
    assert [(f.term, f.element, round(f.sigmas, 2)) for f in flags] == [
        ("a", "y", -5.1),
        ("b", "q", 5.09),
    ]
    assert "a[y] = 0.49 outside training" in flags[0].line(7) and flags[0].line(7).startswith(
        "step 7: "
    )
    assert [f.term for f in g.check(np.array([np.nan, 1.0, 2.0]))] == ["a"]
    with pytest.raises(ValueError, match="size 2"):
        g.check(np.zeros(2))


# ---------------------------------------------------------------------------------------------
# The smoke student's bundle.

G1_BY_HAND = {  # mjlab's G1 (issue 22): kp, kd, torque limit [N m]
    "left_hip_roll_joint": (99.1, 6.31, 139.0),
    "right_knee_joint": (99.1, 6.31, 139.0),
    "left_ankle_pitch_joint": (28.5, 1.81, 50.0),
    "right_wrist_yaw_joint": (16.8, 1.07, 5.0),
}


@pytest.fixture(scope="module")
def spec(bundle) -> dict:
    return json.loads(bundle.with_suffix(".deploy.json").read_text())


@pytest.mark.sim
def test_every_gain_and_limit_matches_the_compiled_model_by_name(spec):
    import mujoco

    from march.config.cli import load
    from march.env.g1 import course_scene
    from march.export.deploy_terms import G1_MOTOR_ORDER
    from march.sim2sim.bundle_schema import G1_JOINT_RANGES

    model, _, _ = course_scene(load([]), "hardware")  # compiled afresh, not the bundle's file
    joints = spec["joints"]
    assert len(joints) == 29
    assert {k for j in joints for k in j} == {
        "name",
        "motor_index",
        "default_pos",
        "action_scale",
        "kp",
        "kd",
        "torque_limit",
        "pos_limits",
    }
    assert sorted(j["motor_index"] for j in joints) == list(range(29))
    for j in joints:
        assert G1_MOTOR_ORDER[j["motor_index"]] == j["name"]  # unitree_sdk2 G1JointIndex
        jid = model.joint("robot/" + j["name"]).id
        (act,) = [
            a
            for a in range(model.nu)
            if model.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT
            and model.actuator_trnid[a, 0] == jid
        ]
        assert model.actuator(act).name == "robot/" + j["name"]
        assert j["kp"] == pytest.approx(float(model.actuator_gainprm[act, 0]), rel=1e-12)
        assert j["kp"] == pytest.approx(-float(model.actuator_biasprm[act, 1]), rel=1e-12)
        assert j["kd"] == pytest.approx(-float(model.actuator_biasprm[act, 2]), rel=1e-12)
        assert [-j["torque_limit"], j["torque_limit"]] == list(model.actuator_forcerange[act])
        assert j["pos_limits"] == list(model.jnt_range[jid])
        # march's own G1 table (what a bundle's pos_limits are held to) is this model's ranges
        assert list(G1_JOINT_RANGES[j["name"]]) == pytest.approx(list(model.jnt_range[jid]))
        assert j["pos_limits"][0] < j["default_pos"] < j["pos_limits"][1]
        assert j["action_scale"] > 0
    by_name = {j["name"]: j for j in joints}
    for name, (kp, kd, tau) in G1_BY_HAND.items():
        j = by_name[name]
        assert (round(j["kp"], 1), round(j["kd"], 2), j["torque_limit"]) == (kp, kd, tau)
    assert spec["joints"][0]["name"] == "left_hip_pitch_joint"  # policy order = motor order
    assert [j["motor_index"] for j in joints] == list(range(29))


@pytest.mark.sim
def test_one_naming_scheme_relative_paths_and_what_a_robot_needs(spec, bundle):
    from march.export.onnx_graph import read_onnx_metadata

    meta = read_onnx_metadata(bundle)
    names = [j["name"] for j in spec["joints"]]
    assert json.loads(meta["action_joint_names"]) == names == spec["action"]["joint_names"]
    assert spec["robot"]["joint_names"] == names
    text = json.dumps(spec)
    assert '"robot/' not in text.replace('"scene_prefix": "robot/"', "")
    for path in (spec["checkpoint"]["teacher_ckpt"], meta["teacher_ckpt"]):
        assert path and not Path(path).is_absolute() and path.endswith("teacher/latest.pt")
    for entry in (spec["onnx"], *spec["courses"].values()):
        name = entry.get("file") or entry["scene"]
        assert "/" not in name and (bundle.parent / name).is_file()
    rates = spec["rates"]
    assert (rates["control_hz"], rates["physics_hz"]) == pytest.approx((50.0, 200.0))
    terms = {t["name"]: t for t in spec["observation"]["terms"]}
    assert list(terms) == [t["name"] for t in spec["observation"]["proprio_terms"]]
    assert (
        "imu_in_pelvis" in terms["base_ang_vel"]["source"]
        and terms["base_ang_vel"]["units"] == "rad/s"
    )
    assert "imu_in_pelvis" in terms["projected_gravity"]["source"]
    assert all("clip" in t and t["frame"] and t["units"] for t in terms.values())
    assert terms["joint_pos"]["elements"] == names
    rng = spec["observation"]["training_range"]
    assert all(len(rng[n]["mean"]) == t["dim"] for n, t in terms.items())
    assert rng["command"]["std"][1] == 0.0  # v_y fixed at 0 in training
    assert spec["command_ranges"]["lin_vel_x"] == [0.3, 0.8]
    assert spec["command_ranges"]["lin_vel_y"] == [0.0, 0.0]
    assert spec["latency"]["control_delay_ms"] == [0.0, 20.0]
    assert spec["latency"]["depth_delay_steps"] == [0, 1]
    cam = spec["depth"]
    k = cam["intrinsics"]
    assert k["fy_px"] == pytest.approx(12 / np.tan(np.radians(55.2 / 2)))
    assert (k["cx_px"], k["cy_px"]) == (16.0, 12.0) and len(cam["from_a_real_camera"]) == 4


@pytest.mark.sim
def test_command_delay_and_depth_delay_follow_mjlabs_buffers(bundle, monkeypatch):
    """Command lag L physics steps: the first L physics steps of an episode hold the default-pose
    target, then every target arrives L steps late. Depth lag 1: each step sees the previous
    step's image, the first step (after the reset) its own."""
    import march.sim2sim.runner as runner
    from march.sim2sim.deploy_bundle import Bundle

    b = Bundle.load(bundle)
    sim = runner.Sim2Sim(b, "hardware")
    applied = []
    real_step = runner.mujoco.mj_step

    def spy(m, d):
        applied.append(d.ctrl[sim.act_ids].copy())
        real_step(m, d)

    monkeypatch.setattr(runner.mujoco, "mj_step", spy)
    lag = 3
    sim.reset(b.cell("hardware", 0.0, 0), -1, runner.Delays(lag, (1, 1)))
    rest = sim.offset.copy()
    images, actions = [], []
    for k in range(3):
        images.append(sim.depth_image())
        feeds = sim.inputs()
        want = images[max(k - 1, 0)]
        np.testing.assert_array_equal(feeds["depth"], want)
        a = np.full(sim.num_actions, 0.1 * (k + 1))
        actions.append(sim.offset + sim.scale * a)
        sim.step(a)
    sent = [rest] * lag + [t for t in actions for _ in range(sim.decimation)]
    np.testing.assert_allclose(np.array(applied), np.array(sent[: len(applied)]), atol=0)
    d = runner.Delays.draw_train(b.spec["latency"], sim.physics_dt, seed=3)
    assert 0 <= d.control_lag <= 4 and d.depth_lag == (0, 1)
    lags = {runner.Delays.draw_train(b.spec["latency"], 0.005, s).control_lag for s in range(60)}
    assert lags == {0, 1, 2, 3, 4}  # round(U(0, 20) ms / 5 ms)


def _sim2sim(*words: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "march.sim2sim", *words],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )


@pytest.mark.sim
def test_cli_with_delays_and_a_refused_command(bundle):
    res = _sim2sim(f"onnx={bundle}", "seconds=0.5", "delays=train", "episodes=2", "seed=4")
    assert res.returncode == 0, res.stderr[-2000:]
    row = json.loads(res.stdout)
    assert row["delays"] == "train" and len(row["episodes"]) == 2
    for ep in row["episodes"]:
        assert ep["control_delay_ms"] in (0.0, 5.0, 10.0, 15.0, 20.0)
        assert ep["depth_delay_steps"] == [0, 1] and "out_of_range" in ep
    assert row["distance_m"] == pytest.approx(np.mean([e["distance_m"] for e in row["episodes"]]))
    res = _sim2sim(f"onnx={bundle}", "seconds=0.2", "control_delay_ms=20", "depth_delay_steps=1")
    assert res.returncode == 0, res.stderr[-2000:]
    row = json.loads(res.stdout)
    assert row["delays"] == {"control_delay_ms": 20.0, "depth_delay_steps": 1}
    assert row["control_lag_physics_steps"] == 4
    res = _sim2sim(f"onnx={bundle}", "vy=0.1")
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2 and len(lines) == 1
    assert "lin_vel_y=0.1 is outside the trained range [0, 0]" in lines[0]


DELAY_CTRL_TOL_RAD = 1e-5
"""Largest |ctrl_env - ctrl_loop| over every physics step of the same action sequence: the two
differ only by float32 rounding of the targets (measured 2026-12-04: 5.9e-8 rad); one physics
step more or less of command lag: the change of target between two actions (2.3e-1 rad)."""
DELAY_DEPTH_MAD_TOL = 1e-4
"""Mean |depth_env - depth_loop| of the fed image on the env's states: measured 9.3e-8 (2026-12-04);
the wrong depth lag 1.6e-2."""


@pytest.mark.sim
def test_delays_match_the_mjlab_env_with_the_same_delays(bundle, smoke_run, monkeypatch):
    """The mjlab eval env with training's delay mechanisms fixed at 20 ms (lag 4 physics steps,
    march.env.dr_terms) and a depth lag of 1 step runs the ONNX student for 25 control steps;
    the loop with Delays(4, (1, 1)) then (a) replays the env's actions from the same start, and
    the position targets each physics step sends to the actuators are compared, and (b) is put
    in the env's state at every step, and the depth image it feeds is compared. An off-by-one
    command lag or a missing depth delay in the loop breaks the agreement.

    Why not the joint positions in closed loop (what this test compared before 2026-12-04): with
    the same actions, mujoco_warp (float32) and MuJoCo (float64) diverged by 2e-2 rad within
    0.1 s when a foot's contact set changed (capsule-box contacts 28 -> 15), as much as a wrong
    lag gives, so the joints could not tell the lag; the targets and the images can."""
    from dataclasses import replace

    import mujoco
    import torch
    from mjlab.envs import ManagerBasedRlEnv
    from mjlab.managers.event_manager import EventTermCfg
    from mjlab.managers.scene_entity_config import SceneEntityCfg
    from smoke_student import hardware_eval_cfg

    from march.env.dr_terms import install_control_delay, sample_control_delay
    from march.sim2sim.deploy_bundle import Bundle
    from march.sim2sim.runner import Delays, Sim2Sim, policy_session

    cfg, env_cfg = hardware_eval_cfg(smoke_run)
    ms = (20.0, 20.0)
    install_control_delay(env_cfg, replace(cfg.dr, control_delay_ms=ms))
    env_cfg.events["control_delay"] = EventTermCfg(
        func=sample_control_delay,
        mode="reset",
        params={"asset_cfg": SceneEntityCfg("robot"), "delay_ms": ms},
    )
    term = env_cfg.observations["depth"].terms["depth"]
    term.delay_min_lag = term.delay_max_lag = 1
    env = ManagerBasedRlEnv(cfg=env_cfg, device="cpu")
    b = Bundle.load(bundle)
    cell = b.cell("hardware", 0.0, 0)
    session = policy_session(b.onnx_path)
    obs, _ = env.reset()
    data = env.sim.data
    env_ctrl = []  # the actuators' command of every physics step (after mjlab's delay buffer)
    physics_step = env.sim.step

    def recorded_step(*args, **kwargs):
        env_ctrl.append(data.ctrl[0].cpu().numpy().astype(np.float64))
        return physics_step(*args, **kwargs)

    env.sim.step = recorded_step
    states = [(data.qpos[0].cpu().numpy().copy(), data.qvel[0].cpu().numpy().copy())]
    env_depth, env_act = [], []
    for _ in range(25):
        feeds = {
            "proprio_hist": obs["student"].numpy(),
            "command": env.command_manager.get_command("twist").numpy(),
            "depth": obs["depth"].numpy(),
        }
        env_depth.append(obs["depth"][0].numpy().copy())
        action = session.run(["actions"], feeds)[0]
        env_act.append(action[0].astype(np.float64))
        obs, _, terminated, truncated, _ = env.step(torch.as_tensor(action))
        assert not bool(terminated | truncated)
        states.append((data.qpos[0].cpu().numpy().copy(), data.qvel[0].cpu().numpy().copy()))
    env_names = [env.sim.mj_model.actuator(i).name.split("/")[-1] for i in range(len(env_ctrl[0]))]
    env.close()
    assert len(env_ctrl) == 25 * 4

    def targets_error(lag: int) -> float:
        """(a): the loop replays the env's actions; max |target difference| per physics step."""
        sim = Sim2Sim(b, "hardware")
        sim.data.qpos[:], sim.data.qvel[:] = states[0]
        sim.start(cell, Delays(lag, (1, 1)))
        names = [sim.model.actuator(int(j)).name.split("/")[-1] for j in sim.act_ids]
        cols = [env_names.index(n) for n in names]
        loop_ctrl = []
        stepper = mujoco.mj_step

        def recorded(m, d):
            loop_ctrl.append(d.ctrl[sim.act_ids].copy())
            stepper(m, d)

        with monkeypatch.context() as patch:
            patch.setattr(mujoco, "mj_step", recorded)
            for action in env_act:
                sim.step(action)
        return float(np.abs(np.array(loop_ctrl) - np.array(env_ctrl)[:, cols]).max())

    def depth_mad(depth_lag: int) -> float:
        """(b): the loop in the env's state of every step; the largest mean |image difference|."""
        sim = Sim2Sim(b, "hardware")
        mad = 0.0
        for k in range(25):
            sim.data.qpos[:], sim.data.qvel[:] = states[k]
            if k == 0:
                sim.start(cell, Delays(4, (depth_lag, depth_lag)))
            else:
                sim.observe()
            image = sim.inputs()["depth"][0]
            mad = max(mad, float(np.abs(image - env_depth[k]).mean()))
        return mad

    ctrl, mad = targets_error(4), depth_mad(1)
    early, late, undelayed = targets_error(3), targets_error(5), depth_mad(0)
    print(
        f"\nwith delays 20 ms / 1 step: targets {ctrl:.2e} rad, depth MAD {mad:.2e}; lag 3: "
        f"{early:.2e}, lag 5: {late:.2e}, depth lag 0: {undelayed:.2e}"
    )
    assert ctrl < DELAY_CTRL_TOL_RAD and mad < DELAY_DEPTH_MAD_TOL
    assert early > 100 * DELAY_CTRL_TOL_RAD  # one physics step too early
    assert late > 100 * DELAY_CTRL_TOL_RAD  # one physics step too late
    assert undelayed > DELAY_DEPTH_MAD_TOL  # the depth delay left out


def test_the_bundles_motor_table_is_the_simulated_robots_wiring():
    """Two tables written apart (the export's claim, the simulated robot's wiring) agree."""
    from march.export.deploy_terms import G1_MOTOR_ORDER
    from march.sim2sim.motors import G1_MOTOR_WIRING

    assert G1_MOTOR_ORDER == G1_MOTOR_WIRING
    assert len(set(G1_MOTOR_WIRING)) == 29


@pytest.mark.sim
def test_onnx_metadata_carries_the_joint_table_as_mjlab_does(spec, bundle):
    from march.export.onnx_graph import read_onnx_metadata

    meta = read_onnx_metadata(bundle)
    joints = spec["joints"]
    assert meta["joint_names"].split(",") == [j["name"] for j in joints]
    kp = [float(v) for v in meta["joint_stiffness"].split(",")]
    kd = [float(v) for v in meta["joint_damping"].split(",")]
    np.testing.assert_allclose(kp, [j["kp"] for j in joints], rtol=1e-8)
    np.testing.assert_allclose(kd, [j["kd"] for j in joints], rtol=1e-8)
    assert [int(v) for v in meta["motor_index"].split(",")] == [j["motor_index"] for j in joints]
    assert json.loads(meta["joint_table"]) == joints


@pytest.mark.sim
def test_command_frame_is_the_body_frame_training_tracks(spec):
    terms = {t["name"]: t for t in spec["observation"]["terms"]}
    frame = terms["command"]["frame"]
    assert "body" in frame and "root_link_lin_vel_b" in frame and "course frame" not in frame
    assert "body" in spec["command_ranges"]["meaning"]
    assert "course frame" not in json.dumps(spec)
    d = spec["deploy"]
    assert (d["msg_type"], d["lowcmd_topic"], d["lowstate_topic"]) == (
        "hg",
        "rt/lowcmd",
        "rt/lowstate",
    )
    assert d["heading_reference"] == "imu_yaw" and d["measured_latency_ms"] > 0
    assert len(d["joint_vel_limits"]) == 29 and min(d["joint_vel_limits"]) == 20.0


@pytest.mark.sim
def test_delays_measured_is_the_exports_latency_rounded_up(spec):
    import math

    from march.sim2sim.runner import Delays

    ms = spec["deploy"]["measured_latency_ms"]
    d = Delays.measured(spec)
    assert d.control_lag == math.ceil(ms / 5.0 - 1e-9) and d.depth_lag == (0, 0)
    assert (
        Delays.measured(
            {**spec, "deploy": {**spec["deploy"], "measured_latency_ms": 10.0}}
        ).control_lag
        == 2
    )
    assert (
        Delays.measured(
            {**spec, "deploy": {**spec["deploy"], "measured_latency_ms": 10.5}}
        ).control_lag
        == 3
    )
