"""Whole-body inverse kinematics of mjlab's G1 for the CLF reference outputs (mink), and the
outputs the solved pose achieves, measured as the env measures them.

:class:`KinematicG1` loads mjlab's G1 MJCF as it is (:func:`march.env.g1.g1_mjcf_spec`) into a
``mink.Configuration`` and, once per control tick (``IkCfg.dt`` = 0.02 s, the env's step),
poses the robot for the reference y_ref of that instant, warm-started from the previous tick:

- **the stance foot**: its site held at its touchdown pose (flat, the course heading) as a
  HARD equality constraint of every QP step (``IkCfg.stance_hard``, mink's ``constraints``: the
  floating base's six free coordinates always satisfy it, so the QP stays feasible under the
  joint limits); the foot's remaining slide, the linearisation's residual, is measured every
  tick (:attr:`Tick.slide`) and a step whose stance foot slid more than 1 cm is not reached
  (:mod:`march.audit.feasibility`). ``stance_hard=False`` restores the soft task of cost
  ``IkCfg.stance_cost``, which slid up to 16 cm at the hardest level (issue 55).
- **tasks**: the whole-body
  CoM (mink's ``ComTask`` reads ``subtree_com`` of the root body, the point the env's y_sim
  reads); the pelvis orientation (a ``FrameTask`` on the pelvis body, orientation only); the
  swing-foot site pose; the 17 upper-body joints (a ``PostureTask``, target default + y_ref); a
  small posture regulariser on the legs (``IkCfg.leg_posture_cost``) so the null space does
  not drift.
- **costs**: output i weighs sqrt(P_i,11) (``march.clf.lyapunov``'s CARE solution): mink's
  objective is sum cost^2 |error|^2, so the IK minimises the position part of V,
  1/2 sum_i P_i,11 eta_i^2, on the linearised problem: the pose whose V is the floor.
- **limits**: ``mink.ConfigurationLimit`` (the MJCF's joint ranges); ``IkCfg.iterations`` QP
  steps per tick (daqp), stopped early once a step moves no joint by more than ``step_tol``.

After solving, :meth:`KinematicG1.track` MEASURES the outputs of the solved pose with the
env's own maths (:func:`march.env.clf_outputs.outputs_from_state` on MuJoCo's ``subtree_com``,
``cvel``, ``xipos``, ``xmat``, the foot sites and the joints, as :func:`measured_outputs` feeds
it), with the velocity the finite difference of the configuration over the tick,
qvel = (q_k minus q_(k-1)) / dt (``mj_differentiatePos``), and returns eta, etadot and V / Vmax
(:class:`march.clf.lyapunov.ClfModel`, the env's CLF config).

What it ignores: dynamics (no contact forces, no zero-moment point, no torque limits), joint
velocity limits, self-collision and collisions with the stones; see docs/audit.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import mink
import mujoco
import numpy as np
import torch

from march.clf.lyapunov import UPPER_BODY_JOINTS, ClfCfg, ClfModel
from march.env.clf_outputs import outputs_from_state
from march.env.g1 import g1_default_pose, g1_mjcf_spec
from march.env.reference_command import ReferenceCommandCfg

GROUPS: dict[str, tuple[int, int]] = {
    "com": (0, 3),
    "pelvis": (3, 6),
    "swing_pos": (6, 9),
    "swing_ori": (9, 12),
    "upper": (12, 29),
}
"""Output groups: [start, stop) columns of the 29 outputs (``CLF_OUTPUT_NAMES`` order)."""
ANGLES = np.zeros(29, dtype=bool)
ANGLES[3:6] = ANGLES[9:12] = True
"""Columns whose errors are wrapped angles (``march.reference.trajectory.ANGLE_OUTPUTS``)."""


@dataclass
class IkCfg:
    """The whole-body IK of :class:`KinematicG1`."""

    dt: float = 0.02
    """Control tick [s] (the env's step: 0.005 s x decimation 4); also the finite-difference
    step of the measured output rates."""
    iterations: int = 4
    """QP steps per tick at most (each a full linearised step toward the targets)."""
    step_tol: float = 1e-4
    """Stop a tick's iterations once a step moves no coordinate by more than this [rad or m]."""
    solver: str = "daqp"
    """qpsolvers backend."""
    damping: float = 1e-4
    """Levenberg-Marquardt damping on every task (keeps steps bounded near singularities)."""
    stance_hard: bool = True
    """Hold the stance-foot site as an equality constraint of every QP step (module
    docstring); False: a soft task of cost ``stance_cost``."""
    stance_tol: float = 1e-5
    """With ``stance_hard``, the stance-foot error (position [m], orientation [rad]) each
    tick's solve ends below, by up to ``stance_iterations`` Gauss-Newton steps on the
    constraint alone (:meth:`KinematicG1.solve`)."""
    stance_iterations: int = 10
    """At most this many of those steps per tick."""
    stance_cost: float = 300.0
    """Cost of the stance-foot pose when soft (position [1/m] and orientation [1/rad]): > 10x
    every output's sqrt(P_11) (the largest, swing_z, is 25.8); it still let the foot slide up
    to 16 cm where the CoM could not be reached otherwise (issue 55)."""
    leg_posture_cost: float = 0.3
    """Cost pulling the 12 leg joints toward the default pose [1/rad]: a regulariser of the
    IK's null space, small against the outputs' costs. It keeps the knees bent away from the
    stretched-leg singularity: at 0.05 the walks' IK drifted there (saturated ticks 1.6% ->
    8.8%, swing-foot height at touchdown p90 4.6 -> 11 cm on the same four courses). Its
    pull biases exactly reachable poses (up to 4.4 mm of CoM in tests/test_feasibility.py),
    which the ``polish`` steps remove."""
    polish: int = 2
    """QP steps per tick after the main ones with the legs' posture target moved to the pose
    just found: the regulariser then only damps, so an exactly reachable reference is reached
    without its bias, while the main steps keep the knees bent (0: no polish)."""
    limit_gain: float = 0.95
    """``mink.ConfigurationLimit`` gain: the share of the distance to a joint limit a step
    may cover."""


def rotation_zyx(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll) (the outputs' ZYX Euler convention), (3, 3)."""
    cr, sr, cp, sp = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
    cy, sy = np.cos(yaw), np.sin(yaw)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def pose(rotation: np.ndarray, position: np.ndarray) -> mink.SE3:
    return mink.SE3.from_rotation_and_translation(mink.SO3.from_matrix(rotation), position)


def wrap(angle: np.ndarray) -> np.ndarray:
    """Angles wrapped to [-pi, pi) (``march.reference.trajectory.wrap_to_pi``)."""
    return np.remainder(angle + np.pi, 2.0 * np.pi) - np.pi


def tracking_error(y: np.ndarray, y_ref: np.ndarray) -> np.ndarray:
    """eta = y - y_ref with the angle columns wrapped (..., 29)."""
    diff = np.asarray(y, dtype=np.float64) - y_ref
    return np.where(ANGLES, wrap(diff), diff)


@dataclass
class Tick:
    """One control tick of the kinematic G1."""

    qpos: np.ndarray
    """(nq,) the solved configuration (free joint: position, quaternion wxyz; then joints)."""
    y: np.ndarray
    """(29,) measured outputs of ``qpos``."""
    ydot: np.ndarray
    """(29,) their rates (finite difference of the configuration over the tick)."""
    eta: np.ndarray
    """(29,) y - y_ref (angles wrapped)."""
    etadot: np.ndarray
    """(29,) ydot - ydot_ref."""
    v: float
    """V = 1/2 x^T P x of (eta, etadot)."""
    v_ratio: float
    """V / Vmax."""
    slide: float = 0.0
    """How far the stance-foot site is from its held position [m] (0 up to the constraint's
    linearisation residual when ``IkCfg.stance_hard``)."""


class KinematicG1:
    """mjlab's G1 as a kinematic chain: whole-body IK toward y_ref and the outputs it reaches
    (module docstring)."""

    def __init__(
        self,
        cfg: IkCfg | None = None,
        clf: ClfCfg | None = None,
        model: mujoco.MjModel | None = None,
        command: ReferenceCommandCfg | None = None,
    ) -> None:
        self.cfg = cfg or IkCfg()
        command = command or ReferenceCommandCfg()
        self.model = model if model is not None else g1_mjcf_spec().compile()
        m = self.model
        self.configuration = mink.Configuration(m)
        self.data = mujoco.MjData(m)
        """Scratch state for measuring (positions and finite-difference velocities)."""
        self.clf = ClfModel(clf or command.clf, dtype=torch.float64)
        self.v_max = float(self.clf.v_max)
        default, root = g1_default_pose()
        self.joint_names = list(default)
        """The actuated joints in mjlab's order (= the env's joint and action order)."""
        self.joint_qpos = np.array([m.joint(n).qposadr[0] for n in self.joint_names])
        self.joint_dof = np.array([m.joint(n).dofadr[0] for n in self.joint_names])
        self.default_qpos = np.zeros(m.nq)
        self.default_qpos[0:3] = root
        self.default_qpos[3] = 1.0
        self.default_qpos[self.joint_qpos] = list(default.values())
        self.upper_qpos = np.array([m.joint(n).qposadr[0] for n in UPPER_BODY_JOINTS])
        self.upper_dof = np.array([m.joint(n).dofadr[0] for n in UPPER_BODY_JOINTS])
        self.default_upper = self.default_qpos[self.upper_qpos].copy()
        self.foot_sites = tuple(command.foot_sites)
        self.site_ids = np.array([m.site(s).id for s in self.foot_sites])
        self.site_bodies = m.site_bodyid[self.site_ids]
        self.root_body = int(m.body("pelvis").id)
        self.output_cost = np.sqrt(self.clf.P_blocks_np[:, 0, 0])
        """(29,) sqrt(P_i,11): each output's IK cost (module docstring)."""
        c = self.output_cost
        self.feet = [
            mink.FrameTask(s, "site", position_cost=1.0, orientation_cost=1.0)
            for s in self.foot_sites
        ]
        self.pelvis = mink.FrameTask("pelvis", "body", position_cost=0.0, orientation_cost=c[3:6])
        self.com = mink.ComTask(cost=c[0:3])
        posture_cost = np.zeros(m.nv)
        legs = [n for n in self.joint_names if n not in UPPER_BODY_JOINTS]
        posture_cost[[m.joint(n).dofadr[0] for n in legs]] = self.cfg.leg_posture_cost
        self.leg_qpos = np.array([m.joint(n).qposadr[0] for n in legs])
        posture_cost[self.upper_dof] = c[12:]
        self.posture = mink.PostureTask(m, cost=posture_cost)
        self.limits = [mink.ConfigurationLimit(m, gain=self.cfg.limit_gain)]
        self.reset(self.default_qpos)

    @property
    def qpos(self) -> np.ndarray:
        return self.configuration.q.copy()

    def reset(self, qpos: np.ndarray) -> None:
        """Start from ``qpos`` (the next solve warm-starts here)."""
        self.configuration.update(np.asarray(qpos, dtype=np.float64).copy())

    def set_targets(
        self,
        y_ref: np.ndarray,
        stance_is_left: bool,
        stance_pos: np.ndarray,
        stance_rot: np.ndarray,
    ) -> None:
        """The tasks' targets for reference outputs ``y_ref`` (29,), with the stance-foot site
        held at ``stance_pos`` (3,) with rotation ``stance_rot`` (3, 3)."""
        c, stance_cost = self.output_cost, self.cfg.stance_cost
        stance, swing = self._feet(stance_is_left)
        stance.set_position_cost(stance_cost)
        stance.set_orientation_cost(stance_cost)
        stance.set_target(pose(np.asarray(stance_rot), np.asarray(stance_pos)))
        swing.set_position_cost(c[6:9])
        swing.set_orientation_cost(c[9:12])
        swing.set_target(pose(rotation_zyx(*y_ref[9:12]), np.asarray(y_ref[6:9])))
        self.pelvis.set_target(pose(rotation_zyx(*y_ref[3:6]), np.zeros(3)))
        self.com.set_target(np.asarray(y_ref[0:3], dtype=np.float64))
        target = self.default_qpos.copy()
        target[self.upper_qpos] += y_ref[12:29]
        self.posture.set_target(target)

    def solve(
        self,
        y_ref: np.ndarray,
        stance_is_left: bool,
        stance_pos: np.ndarray,
        stance_rot: np.ndarray,
        iterations: int | None = None,
    ) -> np.ndarray:
        """The configuration (nq,) whose outputs come nearest ``y_ref`` (module docstring),
        from the current one; ``iterations`` overrides ``IkCfg.iterations``."""
        self.set_targets(
            np.asarray(y_ref, dtype=np.float64), stance_is_left, stance_pos, stance_rot
        )
        cfg = self.cfg
        stance, swing = self._feet(stance_is_left)
        if cfg.stance_hard:
            tasks, constraints = [swing, self.pelvis, self.com, self.posture], [stance]
        else:
            tasks, constraints = [*self.feet, self.pelvis, self.com, self.posture], []
        self._iterate(tasks, constraints, cfg.iterations if iterations is None else iterations)
        if cfg.polish:
            # Bias-free finish: the legs' posture target becomes the pose just found, so the
            # regulariser only damps the step and no longer pulls the outputs off their
            # targets (module docstring, IkCfg.polish).
            target = self.posture.target_q.copy()
            legs = self.leg_qpos
            target[legs] = self.configuration.q[legs]
            self.posture.set_target(target)
            self._iterate(tasks, constraints, cfg.polish)
        if cfg.stance_hard:
            self._restore_stance(stance)
        return self.qpos

    def _restore_stance(self, stance: mink.FrameTask) -> None:
        """Gauss-Newton steps on the stance-foot constraint alone (the least joint motion
        that satisfies its linearisation) until its error is below ``IkCfg.stance_tol``: the
        last QP step's linearisation leaves a residual of up to 2 cm where a leg is nearly
        stretched (measured on a 0.5 m step), which a hard constraint must not keep."""
        cfg = self.cfg
        for _ in range(cfg.stance_iterations):
            if np.abs(stance.compute_error(self.configuration)).max() < cfg.stance_tol:
                return
            vel = mink.solve_ik(
                self.configuration,
                [],
                cfg.dt,
                cfg.solver,
                damping=cfg.damping,
                limits=self.limits,
                constraints=[stance],
            )
            self.configuration.integrate_inplace(vel, cfg.dt)

    def _feet(self, stance_is_left: bool) -> tuple[mink.FrameTask, mink.FrameTask]:
        """The (stance, swing) foot tasks."""
        return (self.feet[0], self.feet[1]) if stance_is_left else (self.feet[1], self.feet[0])

    def _iterate(self, tasks: list, constraints: list, iterations: int) -> None:
        cfg = self.cfg
        for _ in range(iterations):
            vel = mink.solve_ik(
                self.configuration,
                tasks,
                cfg.dt,
                cfg.solver,
                damping=cfg.damping,
                limits=self.limits,
                constraints=constraints or None,
            )
            self.configuration.integrate_inplace(vel, cfg.dt)
            if np.abs(vel).max() * cfg.dt < cfg.step_tol:
                break

    def measure(
        self, qpos: np.ndarray, qpos_before: np.ndarray | None, stance_is_left: bool
    ) -> tuple[np.ndarray, np.ndarray]:
        """(29,) outputs and rates of ``qpos``, the rates by the finite difference from
        ``qpos_before`` over ``IkCfg.dt`` (zero without it), with the env's maths."""
        m, d = self.model, self.data
        d.qpos[:] = qpos
        if qpos_before is None:
            d.qvel[:] = 0.0
        else:
            mujoco.mj_differentiatePos(m, d.qvel, self.cfg.dt, np.asarray(qpos_before), d.qpos)
        mujoco.mj_forward(m, d)
        return self.outputs_of_data(d, stance_is_left)

    def outputs_of_data(
        self, d: mujoco.MjData, stance_is_left: bool
    ) -> tuple[np.ndarray, np.ndarray]:
        """The env's y_sim and its rates (:func:`march.env.clf_outputs.outputs_from_state`)
        of a forwarded MuJoCo state of this model, (29,) each: the same arrays
        :func:`march.env.clf_outputs.measured_outputs` and ``march.env.step_cache.site_state``
        read in the env (the root subtree CoM, the bodies' ``cvel`` / ``xipos`` and masses,
        the pelvis ``xmat`` and angular velocity, the foot sites' pose and velocity about
        the subtree CoM, the upper-body joints against their defaults)."""
        m = self.model
        root = self.root_body

        def t(a: object) -> torch.Tensor:
            return torch.as_tensor(np.array(a, dtype=np.float64))[None]

        pos = d.site_xpos[self.site_ids]
        cvel = d.cvel[self.site_bodies]
        ang = cvel[:, 0:3]
        lin = cvel[:, 3:6] - np.cross(ang, d.subtree_com[root] - pos)
        mats = d.site_xmat[self.site_ids].reshape(2, 3, 3)
        mass = m.body_mass[1:]  # the robot's bodies: every body but the world
        y, ydot = outputs_from_state(
            t(d.subtree_com[root]),
            (t(d.cvel[1:]), t(d.xipos[1:])),
            (t(mass), t([mass.sum()])),
            (t(d.xmat[root].reshape(3, 3)), t(d.cvel[root, 0:3])),
            (t(pos), t(lin), t(ang), t(mats)),
            torch.tensor([bool(stance_is_left)]),
            (t(d.qpos[self.upper_qpos]), t(self.default_upper), t(d.qvel[self.upper_dof])),
            torch.arange(len(UPPER_BODY_JOINTS)),
        )
        return y[0].numpy(), ydot[0].numpy()

    def value(self, eta: np.ndarray, etadot: np.ndarray) -> np.ndarray:
        """V (...,) of eta, etadot (..., 29) by :meth:`march.clf.lyapunov.ClfModel.value`."""
        e = torch.as_tensor(np.asarray(eta, dtype=np.float64)).reshape(-1, 29)
        ed = torch.as_tensor(np.asarray(etadot, dtype=np.float64)).reshape(-1, 29)
        return self.clf.value(e, ed).numpy().reshape(np.shape(eta)[:-1])

    def track(
        self,
        y_ref: np.ndarray,
        ydot_ref: np.ndarray,
        stance_is_left: bool,
        stance_pos: np.ndarray,
        stance_rot: np.ndarray,
        iterations: int | None = None,
    ) -> Tick:
        """One control tick: solve toward ``y_ref``, measure, and the errors and V / Vmax."""
        before = self.qpos
        q = self.solve(y_ref, stance_is_left, stance_pos, stance_rot, iterations)
        y, ydot = self.measure(q, before, stance_is_left)
        eta = tracking_error(y, np.asarray(y_ref))
        etadot = ydot - np.asarray(ydot_ref)
        v = float(self.value(eta, etadot))
        slide = self.slide(stance_is_left, stance_pos)
        return Tick(q, y, ydot, eta, etadot, v, v / self.v_max, slide)

    def slide(self, stance_is_left: bool, stance_pos: np.ndarray) -> float:
        """Distance [m] of the stance-foot site in the last measured state (``self.data``)
        from its held position ``stance_pos``."""
        sid = self.site_ids[0 if stance_is_left else 1]
        return float(np.linalg.norm(self.data.site_xpos[sid] - np.asarray(stance_pos)))

    def stand(
        self,
        y_ref: np.ndarray,
        stance_is_left: bool,
        stance_pos: np.ndarray,
        stance_rot: np.ndarray,
    ) -> np.ndarray:
        """Place the default pose over the feet and solve to convergence (up to 100 QP
        steps) for ``y_ref``: the pose a walk starts from."""
        q = self.default_qpos.copy()
        # The default pose's feet sit 0.039 m ahead of the pelvis and 0.1185 m beside it.
        mid = 0.5 * (np.asarray(stance_pos)[:2] + np.asarray(y_ref[6:8]))
        yaw = float(np.arctan2(stance_rot[1][0], stance_rot[0][0]))
        c, s = np.cos(yaw), np.sin(yaw)
        q[0:2] = mid - 0.039 * np.array([c, s])
        q[2] += float(stance_pos[2])
        q[3:7] = [np.cos(0.5 * yaw), 0.0, 0.0, np.sin(0.5 * yaw)]
        self.reset(q)
        return self.solve(y_ref, stance_is_left, stance_pos, stance_rot, iterations=100)
