"""The simulated G1's motor wiring, and the bundle's motor table read against it (numpy only).

A real G1 has motor slots, not joint names: ``LowCmd_.motor_cmd[i]`` and
``LowState_.motor_state[i]`` of Unitree's ``hg`` messages (35 slots, 29 used by the 29-DoF G1).
The simulated robot here is wired like the real one: :data:`G1_MOTOR_WIRING` says which MuJoCo
joint (and the position actuator driving it) sits behind each slot - what Unitree's
``unitree_mujoco`` does with the MJCF's actuator order. It is written here from unitree_sdk2's
``G1JointIndex``, on purpose apart from the bundle's own table (``deploy.json`` ``joints[i]
.motor_index``, written by ``march.export``): the loops (:class:`march.sim2sim.runner.Sim2Sim`,
``march.robot``) map policy joint ``i`` to slot ``motor_index[i]`` and never look a joint up by
name, so a wrong table in a bundle shows in simulation as it would on the robot.
"""

from __future__ import annotations

from typing import Any

import numpy as np

NUM_MOTOR_SLOTS = 35
"""Slots in an ``hg`` LowCmd_ / LowState_ (``motor_cmd[35]``, ``motor_state[35]``)."""

G1_MOTOR_WIRING = (
    "left_hip_pitch_joint",
    "left_hip_roll_joint",
    "left_hip_yaw_joint",
    "left_knee_joint",
    "left_ankle_pitch_joint",
    "left_ankle_roll_joint",
    "right_hip_pitch_joint",
    "right_hip_roll_joint",
    "right_hip_yaw_joint",
    "right_knee_joint",
    "right_ankle_pitch_joint",
    "right_ankle_roll_joint",
    "waist_yaw_joint",
    "waist_roll_joint",
    "waist_pitch_joint",
    "left_shoulder_pitch_joint",
    "left_shoulder_roll_joint",
    "left_shoulder_yaw_joint",
    "left_elbow_joint",
    "left_wrist_roll_joint",
    "left_wrist_pitch_joint",
    "left_wrist_yaw_joint",
    "right_shoulder_pitch_joint",
    "right_shoulder_roll_joint",
    "right_shoulder_yaw_joint",
    "right_elbow_joint",
    "right_wrist_roll_joint",
    "right_wrist_pitch_joint",
    "right_wrist_yaw_joint",
)
"""Motor slot -> joint of the 29-DoF G1 (unitree_sdk2 ``G1JointIndex``, ankles in the default
pitch/roll mode); slots 29..34 are unused on this robot."""


class MotorTableError(ValueError):
    """The bundle's motor table is not a usable map from policy joints to motor slots."""


def motor_table(spec: dict[str, Any]) -> np.ndarray:
    """``deploy.json``'s ``joints[i].motor_index`` (policy order) as an int array, checked: one
    distinct slot in [0, 35) per policy joint, joints in the policy's order."""
    joints = spec["joints"]
    names = [j["name"] for j in joints]
    if names != list(spec["robot"]["joint_names"]):
        raise MotorTableError("joints[].name is not robot.joint_names (the policy's order)")
    idx = np.array([j["motor_index"] for j in joints], dtype=np.int64)
    if ((idx < 0) | (idx >= NUM_MOTOR_SLOTS)).any():
        raise MotorTableError(f"a motor_index outside [0, {NUM_MOTOR_SLOTS})")
    if len(set(idx.tolist())) != len(idx):
        raise MotorTableError("two policy joints share a motor_index")
    return idx


class MotorBus:
    """The simulated robot's motors: slot -> MuJoCo joint (qpos / qvel address) and actuator."""

    def __init__(self, model: Any, prefix: str, wiring: tuple[str, ...] = G1_MOTOR_WIRING) -> None:
        import mujoco

        n = len(wiring)
        self.num_motors = n
        self.qadr = np.zeros(n, dtype=np.int64)
        self.vadr = np.zeros(n, dtype=np.int64)
        self.act = np.zeros(n, dtype=np.int64)
        drives = {
            int(model.actuator_trnid[a, 0]): a
            for a in range(model.nu)
            if model.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT
        }
        for s, name in enumerate(wiring):
            j = model.joint(prefix + name).id
            self.qadr[s] = model.jnt_qposadr[j]
            self.vadr[s] = model.jnt_dofadr[j]
            if j not in drives:
                raise MotorTableError(f"no actuator drives {name} (motor slot {s})")
            self.act[s] = drives[j]

    def q(self, data: Any) -> np.ndarray:
        """Joint positions of every wired slot (slot order)."""
        return data.qpos[self.qadr].copy()

    def dq(self, data: Any) -> np.ndarray:
        return data.qvel[self.vadr].copy()
