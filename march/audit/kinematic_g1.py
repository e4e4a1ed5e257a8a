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
- **the stance-foot contact model** (``IkCfg.stance``, issue 55): ``flat`` (the default) holds
  the whole pose of the foot site as above. ``heel_off`` holds the foot's TOE EDGE instead:
  a site on the sole's front edge (the foremost ends of the foot's collision capsules,
  :func:`foot_sole`) held in position, roll and yaw as the same hard equality constraint
  (:class:`ToeEdgeTask`: mink's ``FrameTask`` with the local pitch row dropped), while the
  foot may pitch heel UP about that edge, 0 <= pitch <= ``IkCfg.heel_pitch_max``
  (:class:`PitchLimit`, an inequality of every QP step: never toe-up, never the heel into
  the ground); a small cost (``IkCfg.heel_cost``) keeps the foot flat unless lifting the heel
  brings the outputs nearer. A real G1, like a human, lifts its rear heel in late stance; the
  CLF reference says nothing about the stance foot's orientation, so a policy may do it.
  Each tick measures the toe edge's slide (its two corners against their held positions),
  the heel's lift above its held height and the pitch (:class:`Tick`).
  ``heel_toe`` (issue 55, with ``reference.swing_heel_strike``) is ``heel_off`` for a foot that
  landed toe up after a heel strike: from touchdown its HEEL EDGE (``<foot>_heel``) is held the
  same way (position, roll and yaw; :class:`ToeEdgeTask` on the heel site) at the flat pose
  the foot comes down to (:func:`march.audit.ik_walk.heel_landing`), and its toe-up pitch about
  that edge is bounded tick by tick by the landed pitch shrinking to 0 at ``heel_flat_by`` of
  the step (:class:`PitchLimit`: never toe into the stone), with the heel cost pulling it
  flat; from then on the flat foot's toe edge is held as with ``heel_off``. Each heel-phase
  tick measures the heel edge's slide.
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
(:class:`march.clf.lyapunov.ClfModel`, the env's CLF config). Given the previous tick's error
(``eta_before``, as the reference walk gives it), etadot is the error's own finite difference
over the tick instead: the pose's rate and the reference's over the same interval.

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
from march.errors import ConfigError

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


STANCE_MODELS = ("flat", "heel_off", "heel_toe")
"""``IkCfg.stance`` values (module docstring)."""


@dataclass
class IkCfg:
    """The whole-body IK of :class:`KinematicG1`."""

    stance: str = "flat"
    """The stance foot's contact model (module docstring): ``flat`` (default; the foot site's
    whole pose held), ``heel_off`` (its toe edge held, the heel free to lift) or ``heel_toe``
    (a foot that landed toe up held on its heel edge while the toe comes down, flat by
    ``heel_flat_by`` of the step, then as ``heel_off``)."""
    heel_pitch_max: float = 0.7
    """``heel_off``: the largest heel-up pitch of the stance foot about its toe edge [rad]
    (0.7 rad, 40 deg, lifts the heel 12 cm: a human's foot leaves the ground at push-off
    pitched further than this; the G1's own ankle range, -0.87..+0.52 rad, bounds what the
    IK can use of it). Measured (docs/audit.md): at 0.5 rad the heel sat at the bound on the
    long step-downs of the hardest level (level 9 reached 52.9 % at 0.5, 70.6 % at 0.7; all
    levels 87.6 -> 89.5 %, the same option set)."""
    heel_cost: float = 0.3
    """``heel_off``: cost of the stance foot's heel-up pitch [1/rad], a regulariser like
    ``leg_posture_cost`` (0.3): well below the outputs' costs (2-26), so the heel lifts where
    the flat foot leaves an output error and stays down where it does not matter; the
    ``polish`` steps move its target to the pitch just found, as they do the legs' posture.
    Measured on the reference audit (docs/audit.md): with ``reference.swing_pitch_carry`` the
    heel lifts 4-5 cm on most steps at 0.3 and reach is highest; without the carry a lifted
    heel leaves the next swing off its flat lift-off pitch and a cost of 3 (heel within a
    few mm) is best."""
    heel_flat_by: float = 0.3
    """``heel_toe``: the share of the step [-] by which a foot that landed toe up is flat: its
    toe-up pitch about the held heel edge is bounded by the landed pitch times
    (1 - tick / ceil(heel_flat_by n)) over the step's n ticks (:class:`PitchLimit`), then the
    toe edge of the flat foot is held as with ``heel_off``. A human's forefoot is down by
    about 15 % of the gait cycle, 25-30 % of a single-support step."""
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

    def __post_init__(self) -> None:
        if self.stance not in STANCE_MODELS:
            raise ConfigError(
                f"audit.stance={self.stance!r}: choose one of {', '.join(STANCE_MODELS)}"
            )
        if not (isinstance(self.heel_pitch_max, (int, float)) and 0 < self.heel_pitch_max <= 1):
            raise ConfigError(
                f"audit.heel_pitch_max={self.heel_pitch_max}: give a pitch in (0, 1] rad"
            )
        if not (isinstance(self.heel_cost, (int, float)) and self.heel_cost >= 0):
            raise ConfigError(f"audit.heel_cost={self.heel_cost}: give a cost >= 0")
        if not (isinstance(self.heel_flat_by, (int, float)) and 0 < self.heel_flat_by <= 1):
            raise ConfigError(
                f"audit.heel_flat_by={self.heel_flat_by}: give a share of the step in (0, 1]"
            )


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
    """(29,) ydot - ydot_ref, or the error's finite difference over the tick
    (:meth:`KinematicG1.track`'s ``eta_before``)."""
    v: float
    """V = 1/2 x^T P x of (eta, etadot)."""
    v_ratio: float
    """V / Vmax."""
    slide: float = 0.0
    """How far the stance foot's held contact is from its held position [m]: ``flat`` the
    foot site, ``heel_off`` the farther of the toe edge's two corners (``heel_toe``'s heel
    phase: of the heel edge's; 0 up to the constraint's linearisation residual when
    ``IkCfg.stance_hard``)."""
    heel_lift: float = 0.0
    """Height of the stance foot's heel (the sole's rear end) above where it was held [m]:
    0 flat, > 0 lifted (``heel_off``), < 0 in the ground."""
    stance_pitch: float = 0.0
    """The stance foot's pitch against its held orientation about its own y axis [rad],
    positive heel up (``heel_off``: 0..``IkCfg.heel_pitch_max``; ``heel_toe``'s heel phase:
    negative, toe up)."""


@dataclass(frozen=True)
class FootSole:
    """Where a G1 foot's sole is, in its foot site's frame (x forward, z up) [m]."""

    toe_x: float
    """x of the toe edge: the foremost end of the foot's collision capsules."""
    heel_x: float
    """x of the heel: the rearmost end."""
    toe_half_width: float
    """Half the toe edge's width: |y| of the capsule ends within 1 cm of the toe edge."""
    heel_half_width: float
    """Half the heel edge's width: |y| of the capsule ends within 1 cm of the heel."""
    sole_z: float
    """z of the sole: the capsules' lowest points."""

    def toe_offset(self) -> np.ndarray:
        """(3,) the toe edge's midpoint (the heel-off pivot)."""
        return np.array([self.toe_x, 0.0, self.sole_z])

    def toe_corners(self) -> np.ndarray:
        """(2, 3) the toe edge's two ends (the contact points a heel-off must not slide)."""
        w = self.toe_half_width
        return np.array([[self.toe_x, -w, self.sole_z], [self.toe_x, w, self.sole_z]])

    def heel_offset(self) -> np.ndarray:
        """(3,) the heel's midpoint on the sole (the heel-strike pivot)."""
        return np.array([self.heel_x, 0.0, self.sole_z])

    def heel_corners(self) -> np.ndarray:
        """(2, 3) the heel edge's two ends (the contact points a heel strike must not slide)."""
        w = self.heel_half_width
        return np.array([[self.heel_x, -w, self.sole_z], [self.heel_x, w, self.sole_z]])


def foot_sole(model: mujoco.MjModel, site: str) -> FootSole:
    """The sole of the foot carrying ``site``, read from the capsules (MuJoCo geom type 3)
    of the site's body: mjlab's G1 foot has seven, radius 1 cm, their ends from x = -0.094 to
    +0.092 m in the site's frame, their lowest points 2 mm above the site."""
    sid = model.site(site).id
    body = model.site_bodyid[sid]
    site_rot = np.empty(9)
    mujoco.mju_quat2Mat(site_rot, model.site_quat[sid])
    site_rot = site_rot.reshape(3, 3)
    ends, radii = [], []
    for g in np.flatnonzero(model.geom_bodyid == body):
        if model.geom_type[g] != mujoco.mjtGeom.mjGEOM_CAPSULE:
            continue
        rot = np.empty(9)
        mujoco.mju_quat2Mat(rot, model.geom_quat[g])
        axis = rot.reshape(3, 3)[:, 2] * model.geom_size[g][1]
        for sign in (1.0, -1.0):
            end = model.geom_pos[g] + sign * axis
            ends.append(site_rot.T @ (end - model.site_pos[sid]))
            radii.append(model.geom_size[g][0])
    if not ends:
        raise ConfigError(f"audit.stance=heel_off: the body of site {site!r} has no capsules")
    pts, r = np.array(ends), np.array(radii)
    toe_x, heel_x = float(pts[:, 0].max()), float(pts[:, 0].min())
    front = pts[:, 0] >= toe_x - 0.01
    back = pts[:, 0] <= heel_x + 0.01
    return FootSole(
        toe_x=toe_x,
        heel_x=heel_x,
        toe_half_width=float(np.abs(pts[front, 1]).max()),
        heel_half_width=float(np.abs(pts[back, 1]).max()),
        sole_z=float((pts[:, 2] - r).min()),
    )


def with_toe_sites(spec: mujoco.MjSpec, foot_sites: tuple[str, ...]) -> mujoco.MjSpec:
    """``spec`` with a site ``<foot>_toe`` at each foot's toe-edge midpoint (the heel-off
    pivot, :func:`foot_sole`) and ``<foot>_heel`` at its heel-edge midpoint (the heel-strike
    pivot), oriented as the foot site; adding sites moves no body."""
    model = spec.compile()
    for name in foot_sites:
        sid = model.site(name).id
        rot = np.empty(9)
        mujoco.mju_quat2Mat(rot, model.site_quat[sid])
        sole = foot_sole(model, name)
        body = spec.body(model.body(model.site_bodyid[sid]).name)
        for suffix, at in (("toe", sole.toe_offset()), ("heel", sole.heel_offset())):
            body.add_site(
                name=f"{name}_{suffix}",
                pos=(model.site_pos[sid] + rot.reshape(3, 3) @ at).tolist(),
                quat=model.site_quat[sid].tolist(),
            )
    return spec


PITCH_ROW = 4
"""The row of a mink ``FrameTask`` error (translation 0-2, rotation 3-5, in the frame's own
axes) that is the rotation about the frame's y axis: the foot's pitch."""


class ToeEdgeTask(mink.FrameTask):
    """The stance foot's toe edge held (``heel_off``): a ``FrameTask`` on the toe site whose
    error and Jacobian keep the position rows and the rotation about the foot's own x (roll)
    and z (yaw) and drop the rotation about its y (pitch), so as an equality constraint it
    leaves the foot free to pitch about the toe edge and nothing else (the error's rotation
    part is log(R_foot^T R_held), which is (0, -pitch, 0) exactly when the foot is the held
    one turned about its own y axis). As a soft task its pitch cost is 0."""

    ROWS = np.array([0, 1, 2, 3, 5])

    def compute_error(self, configuration: mink.Configuration) -> np.ndarray:
        return super().compute_error(configuration)[self.ROWS]

    def compute_jacobian(self, configuration: mink.Configuration) -> np.ndarray:
        return super().compute_jacobian(configuration)[self.ROWS]

    def pitch(self, configuration: mink.Configuration) -> tuple[float, np.ndarray]:
        """The foot's pitch against its held orientation [rad] (positive heel up) and its
        Jacobian (nv,): minus the full error's pitch row."""
        error = mink.FrameTask.compute_error(self, configuration)
        jac = mink.FrameTask.compute_jacobian(self, configuration)
        return -float(error[PITCH_ROW]), -jac[PITCH_ROW]


class PitchLimit(mink.Limit):
    """``low`` <= the stance foot's pitch about its held edge <= ``high`` [rad] as an
    inequality of the QP step (linearised: pitch + J dq within the bounds; the pitch positive
    heel up, :meth:`ToeEdgeTask.pitch`); the floating base can always turn the foot back, so
    the QP stays feasible. ``heel_off`` on the toe edge: 0..``IkCfg.heel_pitch_max`` (the heel
    only lifts, never into the ground, and the toe never lifts); ``heel_toe``'s heel phase on
    the heel edge: -bound..0 (the toe up no more than a bound set per tick, shrinking to 0 as
    the foot comes down flat, and never into the ground)."""

    def __init__(self, task: ToeEdgeTask, low: float, high: float) -> None:
        self.task, self.low, self.high = task, low, high

    def compute_qp_inequalities(
        self, configuration: mink.Configuration, dt: float
    ) -> mink.limits.limit.Constraint:
        pitch, jac = self.task.pitch(configuration)
        g = np.stack([-jac, jac])  # low - (pitch + J dq) <= 0 and pitch + J dq - high <= 0
        h = np.array([pitch - self.low, self.high - pitch])
        return mink.limits.limit.Constraint(G=g, h=h)


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
        self.foot_sites = tuple(command.foot_sites)
        if model is None:
            model = with_toe_sites(g1_mjcf_spec(), self.foot_sites).compile()
        self.model = model
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
        self.soles = [foot_sole(m, s) for s in self.foot_sites]
        """Each foot's sole in its site's frame (:func:`foot_sole`)."""
        self.toes: list[ToeEdgeTask] = []
        self.heel_limits: list[PitchLimit] = []
        self.heel_tasks: list[mink.FrameTask] = []
        self.heels: list[ToeEdgeTask] = []
        """``heel_toe``: each foot's heel edge as held on landing toe up."""
        self.toe_up_limits: list[PitchLimit] = []
        self.toe_up_tasks: list[mink.FrameTask] = []
        if self.cfg.stance in ("heel_off", "heel_toe"):
            toe_sites = [f"{s}_toe" for s in self.foot_sites]
            heel_sites = [f"{s}_heel" for s in self.foot_sites]
            missing = [
                s
                for s in toe_sites + heel_sites
                if mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, s) < 0
            ]
            if missing:
                raise ConfigError(
                    f"audit.stance={self.cfg.stance} needs the sole sites {missing}"
                    " (with_toe_sites)"
                )
            self.toes = [ToeEdgeTask(s, "site", 1.0, [1.0, 0.0, 1.0]) for s in toe_sites]
            self.heel_limits = [PitchLimit(t, 0.0, self.cfg.heel_pitch_max) for t in self.toes]
            self.heel_tasks = [
                mink.FrameTask(s, "site", 0.0, [0.0, self.cfg.heel_cost, 0.0]) for s in toe_sites
            ]
        if self.cfg.stance == "heel_toe":
            self.heels = [ToeEdgeTask(s, "site", 1.0, [1.0, 0.0, 1.0]) for s in heel_sites]
            self.toe_up_limits = [PitchLimit(h, 0.0, 0.0) for h in self.heels]
            self.toe_up_tasks = [
                mink.FrameTask(s, "site", 0.0, [0.0, self.cfg.heel_cost, 0.0]) for s in heel_sites
            ]
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
        toe_up: float | None = None,
    ) -> None:
        """The tasks' targets for reference outputs ``y_ref`` (29,), with the stance-foot site
        held at ``stance_pos`` (3,) with rotation ``stance_rot`` (3, 3) (``toe_up``: the heel
        phase of ``heel_toe``, the held pose's heel edge held and its toe up by at most this
        [rad]; :meth:`solve`)."""
        c, stance_cost = self.output_cost, self.cfg.stance_cost
        stance, swing = self._feet(stance_is_left)
        stance.set_position_cost(stance_cost)
        stance.set_orientation_cost(stance_cost)
        held = pose(np.asarray(stance_rot), np.asarray(stance_pos))
        stance.set_target(held)
        i = 0 if stance_is_left else 1

        def hold_edge(edge: ToeEdgeTask, pitch_task: mink.FrameTask, at: np.ndarray) -> None:
            # the edge at ``at`` (the sole's point in the site frame) of the held pose
            held_edge = pose(np.asarray(stance_rot), np.asarray(stance_pos) + stance_rot @ at)
            edge.set_position_cost(stance_cost)
            edge.set_orientation_cost([stance_cost, 0.0, stance_cost])
            edge.set_target(held_edge)
            pitch_task.set_target(held_edge)

        if self.toes:
            hold_edge(self.toes[i], self.heel_tasks[i], self.soles[i].toe_offset())
        if toe_up is not None:
            hold_edge(self.heels[i], self.toe_up_tasks[i], self.soles[i].heel_offset())
            self.toe_up_limits[i].low = -float(toe_up)
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
        toe_up: float | None = None,
    ) -> np.ndarray:
        """The configuration (nq,) whose outputs come nearest ``y_ref`` (module docstring),
        from the current one; ``iterations`` overrides ``IkCfg.iterations``. ``toe_up``
        (``heel_toe`` only): the heel phase, the heel edge of the held (flat) pose held and the
        foot's toe-up pitch about it in [0, toe_up] [rad]; None: as ``heel_off``."""
        if toe_up is not None and not self.heels:
            raise ValueError("toe_up needs IkCfg.stance='heel_toe'")
        self.set_targets(
            np.asarray(y_ref, dtype=np.float64), stance_is_left, stance_pos, stance_rot, toe_up
        )
        cfg = self.cfg
        stance, swing = self._feet(stance_is_left)
        limits = self.limits
        extra: list = []
        if self.toes:  # heel_off: the toe edge held, the heel free to lift (module docstring)
            i = 0 if stance_is_left else 1
            stance, limits = self.toes[i], [*self.limits, self.heel_limits[i]]
            extra = [self.heel_tasks[i]]
        if toe_up is not None:  # heel_toe's heel phase: the heel edge held, the toe coming down
            i = 0 if stance_is_left else 1
            stance, limits = self.heels[i], [*self.limits, self.toe_up_limits[i]]
            extra = [self.toe_up_tasks[i]]
        if cfg.stance_hard:
            tasks, constraints = [swing, self.pelvis, self.com, self.posture, *extra], [stance]
        else:
            tasks, constraints = [stance, swing, self.pelvis, self.com, self.posture, *extra], []
        steps = cfg.iterations if iterations is None else iterations
        self._iterate(tasks, constraints, steps, limits)
        if cfg.polish:
            # Bias-free finish: the legs' posture target becomes the pose just found, so the
            # regulariser only damps the step and no longer pulls the outputs off their
            # targets (module docstring, IkCfg.polish); the heel's likewise.
            target = self.posture.target_q.copy()
            legs = self.leg_qpos
            target[legs] = self.configuration.q[legs]
            self.posture.set_target(target)
            for task in extra:
                task.set_target_from_configuration(self.configuration)
            self._iterate(tasks, constraints, cfg.polish, limits)
        if cfg.stance_hard:
            self._restore_stance(stance, limits)
        return self.qpos

    def _restore_stance(self, stance: mink.FrameTask, limits: list) -> None:
        """Gauss-Newton steps on the stance-foot constraint alone (the least joint motion
        that satisfies its linearisation) until its error is below ``IkCfg.stance_tol``: the
        last QP step's linearisation leaves a residual of up to 2 cm where a leg is nearly
        stretched (measured on a 0.5 m step), which a hard constraint must not keep."""
        cfg = self.cfg
        for _ in range(cfg.stance_iterations):
            error = np.abs(stance.compute_error(self.configuration)).max()
            if stance in self.heels:  # the toe above the ground too
                error = max(error, stance.pitch(self.configuration)[0])
            elif isinstance(stance, ToeEdgeTask):  # the heel above the ground too
                error = max(error, -stance.pitch(self.configuration)[0])
            if error < cfg.stance_tol:
                return
            vel = mink.solve_ik(
                self.configuration,
                [],
                cfg.dt,
                cfg.solver,
                damping=cfg.damping,
                limits=limits,
                constraints=[stance],
            )
            self.configuration.integrate_inplace(vel, cfg.dt)

    def _feet(self, stance_is_left: bool) -> tuple[mink.FrameTask, mink.FrameTask]:
        """The (stance, swing) foot tasks."""
        return (self.feet[0], self.feet[1]) if stance_is_left else (self.feet[1], self.feet[0])

    def _iterate(self, tasks: list, constraints: list, iterations: int, limits: list) -> None:
        cfg = self.cfg
        for _ in range(iterations):
            vel = mink.solve_ik(
                self.configuration,
                tasks,
                cfg.dt,
                cfg.solver,
                damping=cfg.damping,
                limits=limits,
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
        eta_before: np.ndarray | None = None,
        toe_up: float | None = None,
    ) -> Tick:
        """One control tick: solve toward ``y_ref``, measure, and the errors and V / Vmax.

        ``eta_before``: the error at the previous tick, measured with this tick's stance
        labels. Given, etadot is the error's own finite difference over the tick,
        (eta - eta_before) / dt, which compares the pose's rate with the reference's over the
        same interval (both to O(dt^2)); ``ydot_ref`` is then unused. Without it, etadot is
        ydot - ydot_ref: the configuration's backward difference mapped at the tick's end
        against the reference's rate at that instant, off by about dt/2 times the outputs'
        acceleration even when the pose follows the reference exactly. ``toe_up``: the heel
        phase of ``heel_toe`` (:meth:`solve`)."""
        before = self.qpos
        q = self.solve(y_ref, stance_is_left, stance_pos, stance_rot, iterations, toe_up)
        y, ydot = self.measure(q, before, stance_is_left)
        eta = tracking_error(y, np.asarray(y_ref))
        if eta_before is None:
            etadot = ydot - np.asarray(ydot_ref)
        else:
            etadot = (eta - np.asarray(eta_before)) / self.cfg.dt
        v = float(self.value(eta, etadot))
        slide, heel, pitch = self.contact(
            stance_is_left, stance_pos, stance_rot, toe_up is not None
        )
        return Tick(q, y, ydot, eta, etadot, v, v / self.v_max, slide, heel, pitch)

    def slide(self, stance_is_left: bool, stance_pos: np.ndarray) -> float:
        """Distance [m] of the stance-foot site in the last measured state (``self.data``)
        from its held position ``stance_pos``."""
        sid = self.site_ids[0 if stance_is_left else 1]
        return float(np.linalg.norm(self.data.site_xpos[sid] - np.asarray(stance_pos)))

    def contact(
        self,
        stance_is_left: bool,
        stance_pos: np.ndarray,
        stance_rot: np.ndarray,
        on_heel: bool = False,
    ) -> tuple[float, float, float]:
        """The stance foot in the last measured state against its held pose (``stance_pos``,
        ``stance_rot``): (slide [m], heel lift [m], pitch [rad]) as :class:`Tick` defines
        them (``flat``: the site's slide; ``heel_off``: the toe edge's corners'; ``on_heel``,
        ``heel_toe``'s heel phase: the heel edge's corners', the pitch negative toe up)."""
        i = 0 if stance_is_left else 1
        sid, sole = self.site_ids[i], self.soles[i]
        pos, rot = self.data.site_xpos[sid], self.data.site_xmat[sid].reshape(3, 3)
        held_pos, held_rot = np.asarray(stance_pos), np.asarray(stance_rot)
        if self.toes:
            corners = sole.heel_corners() if on_heel else sole.toe_corners()
            now, held = pos + corners @ rot.T, held_pos + corners @ held_rot.T
            slide = float(np.linalg.norm(now - held, axis=1).max())
        else:
            slide = float(np.linalg.norm(pos - held_pos))
        heel = sole.heel_offset()
        lift = float((pos + rot @ heel)[2] - (held_pos + held_rot @ heel)[2])
        turn = held_rot.T @ rot  # the held foot turned about its own y by the pitch
        pitch = float(np.arctan2(turn[0, 2], turn[0, 0]))
        return slide, lift, pitch

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
