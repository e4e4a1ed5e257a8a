"""The kinematic reference as a behaviour inside a live march env (the reward audit's
"reference").

:class:`KinematicReference` poses mjlab's G1 by whole-body IK (:class:`KinematicG1`) for each
env's current reference, read from the env's ``reference`` command term
(:mod:`march.env.reference_command`): every control step, :meth:`KinematicReference.act`
solves for y_ref at ``tau + step_dt`` (the instant the env's V of this step is evaluated
against, :meth:`ReferenceCommand.clf_state`), WRITES that pose into the simulator (root pose and
velocity, joint positions and velocities: the finite difference over the step) and returns the
joint-position action that targets it. ``env.step(action)`` then integrates one control step
from the placed pose, so the rewards, the touchdown detection and the planner see the kinematic
trajectory plus one step (0.02 s) of physics under the PD targets.

The stance foot is held where the sim's stance foot stood when its step began (the env's own
anchor, read again at every replan: touchdown, timeout restart, reset), and each env's IK starts
from the sim's state at its episode start.

What it can tell: the reward the env's terms give a robot that tracks every output as well as
the G1's kinematics allow (the CLF terms' ceiling, V's floor in the env's own bookkeeping:
touchdowns from real contacts, replans, the V history), and whether the reward ranks that above
standing. What it cannot: it ignores dynamics. The pose is written, not reached by torques: no
balance (zero-moment point, friction), no torque or joint-velocity limits, no contact forces
before the write, domain randomization of masses and pushes only act within one step; the IK
uses the nominal masses (with randomized link masses the env's measured CoM differs by a few
millimetres). A good score here is necessary, not sufficient, for a policy to earn it.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from march.audit.kinematic_g1 import IkCfg, KinematicG1
from march.env.reference_command import reference_term


class KinematicReference:
    """``KinematicReference(env)``; ``act(env)`` each control step (module docstring)."""

    def __init__(self, env: Any, ik: IkCfg | None = None, action_term: str | None = None):
        self.term = reference_term(env)
        self.robot = self.term.robot
        self.kin = KinematicG1(ik or IkCfg(dt=float(env.step_dt)), clf=self.term.cfg.clf)
        names = list(self.robot.joint_names)
        if sorted(names) != sorted(self.kin.joint_names):
            raise ValueError(f"the env's robot joints {names} are not the G1's")
        m = self.kin.model
        self.env_q = np.array([m.joint(n).qposadr[0] for n in names])
        """The env's joint order -> the kinematic model's qpos columns."""
        self.env_v = np.array([m.joint(n).dofadr[0] for n in names])
        manager = env.action_manager
        term = manager.get_term(action_term or manager.active_terms[0])
        if term.action_dim != len(names):
            raise ValueError(f"action term has {term.action_dim} targets, the G1 {len(names)}")
        self.action = term
        self.num_envs = int(env.num_envs)
        self.qpos: list[np.ndarray | None] = [None] * self.num_envs
        self.held: list[tuple[np.ndarray, np.ndarray] | None] = [None] * self.num_envs
        self.replans = np.full(self.num_envs, -1)
        self.last_v_ratio = np.zeros(self.num_envs)
        """V / Vmax of each env's pose against its y_ref, as the IK measured it."""
        self.last_y = np.zeros((self.num_envs, 29))
        """(E, 29) the outputs of the poses the last :meth:`act` placed, as the IK measured
        them (and their rates: ``last_ydot``)."""
        self.last_ydot = np.zeros((self.num_envs, 29))

    def _sim_state(self) -> tuple[np.ndarray, np.ndarray]:
        """(E, nq) and (E, nv) the robot's state in the kinematic model's layout."""
        idx = self.robot.indexing
        qpos, qvel = self.robot.data.data.qpos, self.robot.data.data.qvel
        q = np.zeros((self.num_envs, self.kin.model.nq))
        v = np.zeros((self.num_envs, self.kin.model.nv))
        q[:, 0:7] = qpos[:, idx.free_joint_q_adr].cpu().double().numpy()
        q[:, self.env_q] = qpos[:, idx.joint_q_adr].cpu().double().numpy()
        v[:, 0:6] = qvel[:, idx.free_joint_v_adr].cpu().double().numpy()
        v[:, self.env_v] = qvel[:, idx.joint_v_adr].cpu().double().numpy()
        return q, v

    def place(self, env: Any, qpos: np.ndarray, qvel: np.ndarray) -> None:
        """Write (E, nq) configurations and (E, nv) velocities of the kinematic model into
        the sim (root and joints; MuJoCo's free-joint convention on both sides) and forward
        it, so every derived quantity (sites, CoM, contacts) is the written state's."""
        idx = self.robot.indexing
        sim = self.robot.data.data
        dev, dtype = sim.qpos.device, sim.qpos.dtype
        rows = torch.arange(self.num_envs, device=dev)[:, None]
        sim.qpos[rows, idx.free_joint_q_adr] = torch.as_tensor(
            qpos[:, 0:7], dtype=dtype, device=dev
        )
        sim.qpos[rows, idx.joint_q_adr] = torch.as_tensor(
            qpos[:, self.env_q], dtype=dtype, device=dev
        )
        sim.qvel[rows, idx.free_joint_v_adr] = torch.as_tensor(
            qvel[:, 0:6], dtype=dtype, device=dev
        )
        sim.qvel[rows, idx.joint_v_adr] = torch.as_tensor(
            qvel[:, self.env_v], dtype=dtype, device=dev
        )
        env.sim.forward()

    def _stance_pose(self, i: int, left: bool) -> tuple[np.ndarray, np.ndarray]:
        """The sim's stance-foot site pose of env ``i`` (position, rotation)."""
        q, _ = self._sim_state()
        kin = self.kin
        kin.measure(q[i], None, left)
        sid = kin.site_ids[0 if left else 1]
        return kin.data.site_xpos[sid].copy(), kin.data.site_xmat[sid].reshape(3, 3).copy()

    def act(self, env: Any) -> torch.Tensor:
        """Solve every env's IK for its y_ref at tau + step_dt, place the robot there and
        return the (E, action_dim) joint-position action that targets the pose."""
        term = self.term
        ref_pos, ref_vel = term.reference(term.tau + float(env.step_dt))
        ref_pos, ref_vel = ref_pos.cpu().double().numpy(), ref_vel.cpu().double().numpy()
        left = term.stance_is_left.cpu().numpy()
        replans = term.replan_count.cpu().numpy()
        fresh = (env.episode_length_buf == 0).cpu().numpy()
        sim_q, _ = self._sim_state()
        qpos = np.zeros_like(sim_q)
        qvel = np.zeros((self.num_envs, self.kin.model.nv))
        for i in range(self.num_envs):
            if self.qpos[i] is None or fresh[i]:
                self.qpos[i] = sim_q[i]
            if replans[i] != self.replans[i] or self.held[i] is None or fresh[i]:
                self.held[i] = self._stance_pose(i, bool(left[i]))
                self.replans[i] = replans[i]
            self.kin.reset(self.qpos[i])
            tick = self.kin.track(ref_pos[i], ref_vel[i], bool(left[i]), *self.held[i])
            qpos[i], qvel[i] = tick.qpos, self.kin.data.qvel.copy()
            self.qpos[i] = tick.qpos
            self.last_v_ratio[i] = tick.v_ratio
            self.last_y[i], self.last_ydot[i] = tick.y, tick.ydot
        self.place(env, qpos, qvel)
        joints = torch.as_tensor(qpos[:, self.env_q], dtype=torch.float32, device=env.device)
        return (joints - self.action.offset) / self.action.scale
