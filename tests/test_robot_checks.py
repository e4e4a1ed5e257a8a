"""What the robot loop reads and sends, checked (march.robot.wire_checks), and the G1's physical
ranges on everything that reaches a motor (march.sim2sim.bundle_schema.check_motor_ranges),
refused by the schema and again by the loop - by hand and over many generated cases."""

from __future__ import annotations

import copy
import re

import numpy as np
import pytest

from march.sim2sim.bundle_schema import SchemaError, check_motor_ranges, check_spec, gain_bounds

pytestmark = pytest.mark.sim


@pytest.fixture(scope="module")
def spec(bundle):
    from march.sim2sim.deploy_bundle import Bundle

    return Bundle.load(bundle).spec


def test_gain_bounds_by_hand():
    # rating / 0.1 rad; max(10, rating x 0.2 s); the rating (mjlab's G1 motors)
    assert gain_bounds("left_knee_joint") == pytest.approx((1390.0, 27.8, 139.0))
    assert gain_bounds("right_hip_pitch_joint") == pytest.approx((880.0, 17.6, 88.0))
    assert gain_bounds("left_ankle_roll_joint") == pytest.approx((500.0, 10.0, 50.0))
    assert gain_bounds("waist_pitch_joint") == pytest.approx((500.0, 10.0, 50.0))
    assert gain_bounds("waist_yaw_joint") == pytest.approx((880.0, 17.6, 88.0))
    assert gain_bounds("left_wrist_pitch_joint") == pytest.approx((50.0, 10.0, 5.0))
    assert gain_bounds("left_wrist_roll_joint") == pytest.approx((250.0, 10.0, 25.0))
    assert gain_bounds("right_elbow_joint") == pytest.approx((250.0, 10.0, 25.0))


def _mutations(spec, rng):
    """(spec with one motor-facing value out of range, the words its line must hold)."""
    n = len(spec["joints"])
    for _ in range(60):
        s = copy.deepcopy(spec)
        i = int(rng.integers(n))
        j = s["joints"][i]
        kp_max, kd_max, rated = gain_bounds(j["name"])
        kind = rng.choice(["kp-", "kp+", "kd-", "kd+", "tau", "tau0", "pose", "scale", "scale0"])
        if kind == "kp-":
            j["kp"] = -float(rng.uniform(1e-3, 1e3))
        elif kind == "kp+":
            j["kp"] = kp_max * float(rng.uniform(1.001, 100))
        elif kind == "kd-":
            j["kd"] = -float(rng.uniform(1e-3, 10))
        elif kind == "kd+":
            j["kd"] = kd_max * float(rng.uniform(1.001, 100))
        elif kind == "tau":
            j["torque_limit"] = rated * float(rng.uniform(1.01, 1e7))
        elif kind == "tau0":
            j["torque_limit"] = -float(rng.uniform(0, 10))
        elif kind == "pose":
            lo, hi = j["pos_limits"]
            j["default_pos"] = (
                hi + float(rng.uniform(1e-3, 1))
                if rng.random() < 0.5
                else (lo - float(rng.uniform(1e-3, 1)))
            )
            s["robot"]["default_joint_pos"][i] = j["default_pos"]
        elif kind == "scale":
            j["action_scale"] = float(rng.uniform(1.01, 50))
            s["action"]["scale"][i] = j["action_scale"]
        else:
            j["action_scale"] = 0.0
            s["action"]["scale"][i] = 0.0
        key = {"kp-": "kp", "kp+": "kp", "kd-": "kd", "kd+": "kd", "tau": "torque_limit",
               "tau0": "torque_limit", "pose": "default_pos", "scale": "action_scale",
               "scale0": "action_scale"}[kind]  # fmt: skip
        yield s, f"joints[{i}].{key}"


def test_motor_ranges_refused_by_the_schema_and_again_by_the_loop(spec):
    from march.robot.wire_checks import BundleRefused, Limits
    from march.sim2sim.motors import motor_table

    check_spec(spec)  # the smoke bundle is inside every range
    slots = motor_table(spec)
    Limits.from_spec(spec, slots)
    rng = np.random.default_rng(0)
    for bad, where in _mutations(spec, rng):
        with pytest.raises(SchemaError) as err:
            check_spec(bad)
        line = str(err.value)
        assert where in line and "\n" not in line, (where, line)
        with pytest.raises(BundleRefused) as err2:
            Limits.from_spec(bad, slots)
        assert where in str(err2.value)
    for name, value in (("kp", -500.0), ("torque_limit", 1e9)):
        bad = copy.deepcopy(spec)
        bad["joints"][3][name] = value
        with pytest.raises(SchemaError, match=re.escape(f"joints[3].{name} = {value:g}")):
            check_motor_ranges(bad)
    bad = copy.deepcopy(spec)
    bad["deploy"]["shutdown"]["damping_kd"] = 12.0  # over the 4010 / 5020 motors' 10
    with pytest.raises(SchemaError, match="damping_kd"):
        check_motor_ranges(bad)


def _lowstate(spec, q=None):
    from march.robot import hg
    from march.sim2sim.motors import motor_table

    slots = motor_table(spec)
    q = np.asarray(spec["robot"]["default_joint_pos"]) if q is None else q
    ls = hg.LowState_(mode_machine=int(spec["deploy"]["mode_machine"]), tick=7)
    for i, s in enumerate(slots):
        ls.motor_state[int(s)].q = float(q[i])
    ls.crc = hg.lowstate_crc(ls)
    return ls, slots


def test_lowstate_faults_by_hand(spec):
    from march.robot import hg
    from march.robot.wire_checks import Limits, lowstate_fault

    ls, slots = _lowstate(spec)
    lim = Limits.from_spec(spec, slots)
    assert lowstate_fault(ls, lim) is None
    knee = int(slots[3])
    hi = spec["joints"][3]["pos_limits"][1]
    vel = spec["deploy"]["joint_vel_limits"][3]

    def mutated(fn, recrc=True):
        m = copy.deepcopy(ls)
        fn(m)
        if recrc:
            m.crc = hg.lowstate_crc(m)
        return lowstate_fault(m, lim)

    bad_crc = copy.deepcopy(ls)
    bad_crc.crc ^= 0x55
    assert "CRC" in lowstate_fault(bad_crc, lim)
    assert "CRC" in mutated(lambda m: setattr(m.motor_state[knee], "q", 1.0), recrc=False)
    assert "not finite" in mutated(lambda m: setattr(m.motor_state[knee], "q", float("nan")))
    assert "not finite" in mutated(lambda m: setattr(m.motor_state[knee], "dq", float("inf")))
    assert "past its limit" in mutated(lambda m: setattr(m.motor_state[knee], "q", hi + 0.3))
    assert mutated(lambda m: setattr(m.motor_state[knee], "q", hi + 0.05)) is None  # margin
    assert "over" in mutated(lambda m: setattr(m.motor_state[knee], "dq", vel * 1.01))
    assert mutated(lambda m: setattr(m.motor_state[knee], "dq", vel * 0.99)) is None
    assert "quaternion" in mutated(lambda m: setattr(m.imu_state, "quaternion", [0, 0, 0, 0]))
    nan_gyro = [0.0, float("nan"), 0.0]
    assert "IMU" in mutated(lambda m: setattr(m.imu_state, "gyroscope", nan_gyro))
    # an unused slot's reading does not matter
    assert mutated(lambda m: setattr(m.motor_state[33], "q", float("nan"))) is None


def test_the_last_check_before_publish(spec):
    from march.robot import hg
    from march.robot.wire_checks import Limits, command_fault, damping_lowcmd
    from march.sim2sim.motors import motor_table

    slots = motor_table(spec)
    lim = Limits.from_spec(spec, slots)
    kp = np.array([j["kp"] for j in spec["joints"]])

    def cmd(q=None, gains=kp, state_slot=None):
        msg = hg.LowCmd_(mode_machine=lim.mode_machine)
        q = np.asarray(spec["robot"]["default_joint_pos"]) if q is None else q
        for i, s in enumerate(slots):
            m = msg.motor_cmd[int(s)]
            m.mode, m.q, m.kp, m.kd = 1, float(q[i]), float(gains[i]), 1.0
        msg.crc = hg.lowcmd_crc(msg)
        return msg

    ok = cmd()
    for state in ("ramp", "hold", "policy"):
        assert command_fault(ok, state, lim) is None
    for state in ("zero_torque", "damping", "done"):
        assert "kp" in command_fault(ok, state, lim)  # gains outside ramp / hold / policy
    assert command_fault(damping_lowcmd(lim, 8.0, 0), "damping", lim) is None
    assert command_fault(damping_lowcmd(lim, 8.0, 0), "zero_torque", lim) is None
    q = np.asarray(spec["robot"]["default_joint_pos"]).copy()
    q[5] = np.nan
    assert "not finite" in command_fault(cmd(q), "policy", lim)
    big = kp.copy()
    big[3] = 1e4
    assert "outside the motor's range" in command_fault(cmd(gains=big), "hold", lim)
    neg = kp.copy()
    neg[0] = -500.0
    assert "outside the motor's range" in command_fault(cmd(gains=neg), "hold", lim)
    stray = cmd()
    stray.motor_cmd[33].mode = 1
    stray.crc = hg.lowcmd_crc(stray)
    assert "unused slot" in command_fault(stray, "hold", lim)
    wrong = cmd()
    wrong.crc ^= 1
    assert "CRC" in command_fault(wrong, "hold", lim)


def test_malformed_and_mostly_invalid_depth():
    from march.robot.dds import DepthImage_
    from march.robot.wire_checks import depth_image, depth_invalid_flag

    img, why = depth_image(DepthImage_(1, 24, 32, [1.0] * 10), 24, 32)
    assert img is None and "24x32 with 10 values" in why
    img, why = depth_image(DepthImage_(1, 24, 31, [1.0] * 24 * 31), 24, 32)
    assert img is None and "malformed" in why
    img, why = depth_image(DepthImage_(1, 24, 32, [float("inf")] + [1.0] * 767), 24, 32)
    assert img is None and "inf" in why
    img, why = depth_image(DepthImage_(1, 24, 32, [1.0] * 768), 24, 32)
    assert why is None and img.shape == (24, 32)
    rng = np.random.default_rng(1)
    for frac in (0.0, 0.1, 0.3, 0.49, 0.52, 0.7, 0.9, 1.0):
        image = np.full(24 * 32, 1.2)
        bad = rng.choice(24 * 32, int(round(frac * 24 * 32)), replace=False)
        image[bad[: len(bad) // 2]] = np.nan
        image[bad[len(bad) // 2 :]] = 0.0
        flag = depth_invalid_flag(image.reshape(24, 32))
        assert (flag is not None) == (len(bad) / 768 > 0.5), (frac, flag)
    assert "90%" in depth_invalid_flag(np.where(np.arange(768) < 691, np.nan, 1.0).reshape(24, 32))
