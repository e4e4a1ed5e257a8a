"""The measured CLF outputs y_sim of the robot in the mjlab env, and the stance foot's state.

:func:`measured_outputs` reads the 29 outputs the CLF tracks (``CLF_OUTPUT_NAMES`` order) and
their rates from the simulator state; :func:`stance_foot_state` the stance foot's site position
and velocities for the holonomic terms. Plain functions of the env, the robot entity, the foot
site names, the body masses and the stance mask, called by the ``reference`` command term
(``march.env.reference_command``); :func:`reference_in_base_frame` builds its base-relative observation.

Decisions (``march.env.reference_command`` lists the others)
- **CoM.** Whole-body CoM: ``subtree_com`` of the robot's root body (MuJoCo's mass-weighted CoM of
  all robot bodies, domain-randomised masses included); its velocity is the mass-weighted mean of
  the bodies' CoM velocities (``body_com_lin_vel_w``), with the per-world body masses.
- **Outputs** (``CLF_OUTPUT_NAMES`` order, 29): CoM x/y/z (world), pelvis roll/pitch/yaw (ZYX Euler
  of the root link) and their Euler-angle rates, swing-foot site position/velocity (world) and its
  roll/pitch/yaw with Euler rates, 17 upper-body joints relative to their defaults. The swing-foot
  site is at sole level on the G1 (z ~ 1.5 mm standing), so ``ReferenceCfg.foot_height_offset``
  is 0.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from mjlab.utils.lab_api.math import euler_xyz_from_quat

from march.compiled_math import maybe_fused
from march.env.step_cache import constant, site_state, site_xmat
from march.reference.trajectory import wrap_to_pi

if TYPE_CHECKING:
    from mjlab.entity import Entity
    from mjlab.envs import ManagerBasedRlEnv


def euler_rates(euler: torch.Tensor, omega_b: torch.Tensor) -> torch.Tensor:
    """ZYX Euler-angle rates (roll, pitch, yaw)-dot (E, 3) from the body-frame angular velocity.

    R = Rz(yaw) Ry(pitch) Rx(roll) (``euler_xyz_from_quat``'s convention); cos(pitch) is kept
    away from 0 (the tilt termination ends episodes long before the singularity).
    """
    roll, pitch = euler[:, 0], euler[:, 1]
    p, q, r = omega_b.unbind(-1)
    sr, cr = torch.sin(roll), torch.cos(roll)
    cp = torch.cos(pitch)
    cp = torch.where(cp.abs() < 0.1, torch.full_like(cp, 0.1), cp)
    tp = torch.sin(pitch) / cp
    a = q * sr + r * cr
    return torch.stack([p + a * tp, q * cr - r * sr, a / cp], dim=-1)


def euler_zyx(quat: torch.Tensor) -> torch.Tensor:
    """(E, 3) ZYX Euler angles (roll, pitch, yaw) of (E, 4) quaternions (mjlab's
    ``euler_xyz_from_quat``; the step reads them from rotation matrices:
    :func:`euler_from_matrix`)."""
    return torch.stack(euler_xyz_from_quat(quat), dim=-1)


def euler_from_matrix(mat: torch.Tensor) -> torch.Tensor:
    """(..., 3) ZYX Euler angles (roll, pitch, yaw) of (..., 3, 3) rotation matrices
    R = Rz(yaw) Ry(pitch) Rx(roll): roll = atan2(R32, R33), pitch = asin(-R31) (clamped to
    [-1, 1]), yaw = atan2(R21, R11). The same angles as :func:`euler_zyx` of the matrix's
    quaternion (its atan2 / asin arguments are these entries written in the quaternion), within
    float32 rounding, without the quaternion."""
    r = mat.flatten(-2)  # row-major: R32 = r[7], R33 = r[8], R21 = r[3], R11 = r[0], R31 = r[6]
    roll = torch.atan2(r[..., 7:8], r[..., 8:9])
    yaw = torch.atan2(r[..., 3:4], r[..., 0:1])
    pitch = torch.asin((-r[..., 6:7]).clamp(-1.0, 1.0))
    return torch.cat([roll, pitch, yaw], dim=-1)


def euler_rates_of(euler: torch.Tensor, omega_b: torch.Tensor) -> torch.Tensor:
    """:func:`euler_rates` for any leading shape (..., 3). cos(pitch) >= 0 for pitch in
    [-pi/2, pi/2] (asin's range; -4e-8 at pi/2 in float32), so its floor at 0.1 is a clamp."""
    sines, cosines = torch.sin(euler[..., 0:2]), torch.cos(euler[..., 0:2])
    sr, sp = sines[..., 0], sines[..., 1]
    cr = cosines[..., 0]
    cp = cosines[..., 1].clamp(min=0.1)
    p, q, r = omega_b.unbind(-1)
    a = q * sr + r * cr
    return torch.stack([p + a * (sp / cp), q * cr - r * sr, a / cp], dim=-1)


def yaw_rotate(vec: torch.Tensor, yaw: torch.Tensor) -> torch.Tensor:
    """Rotate the xy part of (E, ..., 2|3) vectors by -yaw (world -> yaw-aligned base frame)."""
    c, s = torch.cos(yaw), torch.sin(yaw)
    while c.dim() < vec.dim():
        c, s = c[..., None], s[..., None]
    x, y = vec[..., 0:1], vec[..., 1:2]
    return torch.cat([c * x + s * y, -s * x + c * y, vec[..., 2:]], dim=-1)  # one op, no copies


def reference_in_base_frame(
    reference: tuple[torch.Tensor, torch.Tensor],
    footholds: torch.Tensor,
    phase: tuple[torch.Tensor, torch.Tensor],
    base: tuple[torch.Tensor, torch.Tensor],
) -> torch.Tensor:
    """The privileged reference observation, relative to the base (yaw-aligned pelvis frame),
    from the y_ref positions and velocities ``reference`` (E, 29) each, the plan's ``footholds``
    (E, N, 3), ``phase`` = (tau, step duration) (E,) each and ``base`` = the pelvis position
    (E, 3) and heading (E,).

    Layout (E, 29 + 29 + 3N + 2): y_ref positions, y_ref velocities, the N planned footholds
    (dx, dy, dz from the pelvis), then tau / duration and duration [s]. Position-like outputs
    (CoM, swing foot) are taken relative to the pelvis and rotated by -heading, their velocities
    rotated by -heading; the pelvis and swing-foot yaw references are given relative to the
    heading (wrapped); roll, pitch and joints as they are.

    One rotation for every vector turned into the base frame: the CoM and swing-foot positions
    and the N footholds relative to the base, then the CoM and swing-foot velocities (five
    rotations and their copies before: ~75 more ops a step)."""
    (pos, vel), (tau, duration), (base, yaw) = reference, phase, base
    e, n = footholds.shape[:2]

    def com_and_swing(y: torch.Tensor) -> torch.Tensor:  # (E, 2, 3): columns 0:3 and 6:9 (a view)
        return y[:, 0:9].reshape(e, 3, 3)[:, 0::2]

    vectors = torch.cat([com_and_swing(pos), footholds, com_and_swing(vel)], dim=1)
    vectors[:, : n + 2] -= base[:, None]  # the points relative to the base, not the rates
    turned = yaw_rotate(vectors, yaw)
    yaws = wrap_to_pi(pos[:, 5:12:6] - yaw[:, None])  # pelvis and swing-foot yaw (a view)
    return torch.cat(
        [
            turned[:, 0],  # com_xyz
            pos[:, 3:5],
            yaws[:, 0:1],  # pelvis_yaw
            turned[:, 1],  # swing_xyz
            pos[:, 9:11],
            yaws[:, 1:2],  # swing_yaw
            pos[:, 12:],
            turned[:, n + 2],  # com velocity
            vel[:, 3:6],
            turned[:, n + 3],  # swing-foot velocity
            vel[:, 9:],
            turned[:, 2 : n + 2].flatten(1),  # footholds
            (tau / duration).clamp(max=2.0)[:, None],
            duration[:, None],
        ],
        dim=-1,
    )


def body_masses(
    env: ManagerBasedRlEnv, body_ids: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """(W|1, B) masses of the robot bodies ``body_ids`` (per world when the model has them per
    world) and their (W|1, 1) sums, copied from the model."""
    mass = env.sim.model.body_mass
    mass = mass[:, body_ids] if mass.dim() == 2 else mass[body_ids][None]
    return mass.clone(), mass.sum(1, keepdim=True)


def measured_outputs(
    env: ManagerBasedRlEnv,
    robot: Entity,
    foot_sites: tuple[str, str],
    entity_name: str,
    root_body: int,
    upper_ids: torch.Tensor,
    masses: tuple[torch.Tensor, torch.Tensor],
    stance_is_left: torch.Tensor,
    compiled: bool = False,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(E, 29) measured outputs y_sim (positions) and their rates (module docstring).

    ``robot`` is the robot entity (``entity_name`` in the scene), ``foot_sites`` its left and
    right foot sites, ``root_body`` its root body id, ``upper_ids`` the upper-body joints
    (``UPPER_BODY_JOINTS`` order), ``masses`` from :func:`body_masses` and ``stance_is_left``
    (E,) the stance mask (the swing foot is the other one); ``compiled``: the maths
    (:func:`outputs_from_state`) under ``torch.compile`` (``compute.compile_math``).

    Read straight from MuJoCo's arrays: the bodies' ``cvel`` and ``xipos`` (what mjlab's
    ``body_com_lin_vel_w`` converts), the pelvis's ``xmat`` and world angular velocity (its
    ``root_link_quat_w`` / ``root_link_ang_vel_b``, without the quaternion), the foot sites'
    state once per reward compute (:func:`march.env.step_cache.site_state`, shared with the
    holonomic terms)."""
    data = robot.data
    sim = data.data
    names = tuple(foot_sites)
    bodies = body_rows(env, robot)
    pos, lin, ang = site_state(env, names, entity_name)
    outputs = maybe_fused(outputs_from_state, compiled)
    return outputs(
        sim.subtree_com[:, root_body],
        (sim.cvel[:, bodies], sim.xipos[:, bodies]),
        masses,
        (sim.xmat[:, root_body].reshape(-1, 3, 3), sim.cvel[:, root_body, 0:3]),
        (pos, lin, ang, site_xmat(env, names, entity_name)),
        stance_is_left,
        (data.joint_pos, data.default_joint_pos, data.joint_vel),
        upper_ids,
    )


def body_rows(env: ManagerBasedRlEnv, robot: Entity) -> slice | torch.Tensor:
    """The robot's body ids as a slice when they are consecutive (a view, no gather), else
    as a kept index tensor."""

    def make() -> slice | torch.Tensor:
        ids = [int(i) for i in torch.as_tensor(robot.indexing.body_ids).tolist()]
        if ids == list(range(ids[0], ids[0] + len(ids))):
            return slice(ids[0], ids[0] + len(ids))
        return torch.tensor(ids, dtype=torch.long, device=env.device)

    return constant(env, ("body_rows", id(robot)), make)


def outputs_from_state(
    com: torch.Tensor,
    bodies: tuple[torch.Tensor, torch.Tensor],
    masses: tuple[torch.Tensor, torch.Tensor],
    root: tuple[torch.Tensor, torch.Tensor],
    feet: tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor],
    stance_is_left: torch.Tensor,
    joints: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    upper_ids: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The maths of :func:`measured_outputs` on the state read from the sim (pure torch):
    ``com`` (E, 3) root subtree CoM, ``bodies`` = the robot bodies' ``cvel`` (E, B, 6) and CoM
    positions (E, B, 3), ``masses`` (W|1, B) and their sums, ``root`` = the pelvis's rotation
    matrix (E, 3, 3) and world angular velocity (E, 3), ``feet`` = position, linear and angular
    velocity (E, 2, 3) and rotation matrix (E, 2, 3, 3) of the two foot sites, the stance mask
    and ``joints`` = joint positions, default positions and velocities (E, J).

    The pelvis and the swing foot go through one stacked pass: body-frame rates R^T w and ZYX
    Euler angles read from the matrices (:func:`euler_from_matrix`), then their Euler rates."""
    cvel, xipos = bodies
    mass, mass_sum = masses
    # mjlab's body_com_lin_vel_w: cvel's linear part moved from the subtree CoM to each body CoM
    lin_b = cvel[..., 3:6] - torch.cross(cvel[..., 0:3], com[:, None] - xipos, dim=-1)
    com_vel = (lin_b * mass[..., None]).sum(1) / mass_sum
    pos, lin, ang, mat = feet
    pick = (~stance_is_left)[:, None]  # the swing foot is the other one
    swing_pos = torch.where(pick, pos[:, 0], pos[:, 1])
    swing_vel = torch.where(pick, lin[:, 0], lin[:, 1])
    root_mat, root_omega = root
    mats = torch.stack([root_mat, torch.where(pick[..., None], mat[:, 0], mat[:, 1])], dim=1)
    omega_w = torch.stack([root_omega, torch.where(pick, ang[:, 0], ang[:, 1])], dim=1)
    omega_b = (omega_w[..., None, :] @ mats)[..., 0, :]  # R^T w, (E, 2, 3)
    angles = euler_from_matrix(mats)
    rates = euler_rates_of(angles, omega_b)
    joint_pos, default_pos, joint_vel = joints
    upper = (joint_pos - default_pos)[:, upper_ids]
    upper_vel = joint_vel[:, upper_ids]
    pos = torch.cat([com, angles[:, 0], swing_pos, angles[:, 1], upper], dim=-1)
    vel = torch.cat([com_vel, rates[:, 0], swing_vel, rates[:, 1], upper_vel], dim=-1)
    return pos, vel


def stance_foot_state(
    env: ManagerBasedRlEnv,
    foot_sites: tuple[str, str],
    entity_name: str,
    stance_is_left: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Stance foot site position (E, 3), linear velocity (E, 3) and angular velocity (E, 3)."""
    pos, lin, ang = site_state(env, tuple(foot_sites), entity_name)
    left = stance_is_left[:, None]
    return (
        torch.where(left, pos[:, 0], pos[:, 1]),
        torch.where(left, lin[:, 0], lin[:, 1]),
        torch.where(left, ang[:, 0], ang[:, 1]),
    )
