"""The paper's domain-randomization table (appendix, tab:domain_randomization) as mjlab terms.

``paper_dr_events(dr, robot, camera)`` returns one mjlab ``EventTermCfg`` per row of the table,
with the ranges of :class:`march.config.DrCfg`; ``describe_dr(dr, camera)`` lists the same rows
for ``march.inspect``; ``apply_dr`` does all of it to a mjlab env config at once, including
``install_control_delay``, which switches on the actuator command buffer that the
``control_delay`` event needs. The event functions mjlab has no exact counterpart for (the
``:func:`` entries below) live in :mod:`march.env.dr_terms`.

Row -> mechanism (all per env; G1 names from mjlab's G1 velocity task):

==========================  =====================================================  =========
paper row                   mjlab mechanism                                        mode
==========================  =====================================================  =========
friction U(0.5, 1.25)       ``dr.geom_friction`` abs, tangential axis, one value   reset
                            shared by the 14 foot collision geoms (they carry
                            contact priority 1, so their friction is the contact's)
link mass x U(0.9, 1.2)     :func:`scale_link_mass`: mass *and* inertia of every   startup
                            robot body times one draw per body (uniform density:
                            a heavier link is a denser link); COM unchanged
base added mass U(-1, 3)    :func:`add_base_mass`: point mass at the torso_link    startup
                            COM (mass only, inertia untouched)
encoder bias U(+-0.015)     ``dr.encoder_bias`` per joint                          reset
base CoM offset             ``dr.body_com_offset`` add on torso_link body_ipos     startup
effort limits x U(.85,1.1)  ``dr.effort_limits`` scale, per actuator               reset
                            (``actuator_forcerange``)
joint damping x U(.75,1.25) :func:`scale_joint_damping`: passive ``dof_damping``   reset
                            and the position actuator's derivative gain (kd,
                            ``actuator_biasprm[2]``) times one draw per joint. The
                            G1 MJCF has dof_damping = 0, so kd is the only joint
                            damping there is; scaling 0 alone would do nothing
joint friction U(0, 0.04)   ``dr.joint_friction`` abs (``dof_frictionloss``) [N m]  reset
push every 10-15 s          :class:`interval_push` (``push_by_setting_velocity``'s step
                            push, mjlab's interval timers, without a host sync): x, y
                            +-1 m/s; roll, pitch, yaw +-0.4 rad/s (added to the root
                            velocity)
control delay U(0, 20) ms   :func:`sample_control_delay` sets the per-env lag of   reset
                            mjlab's actuator command delay buffer (physics-step
                            resolution, see ``march.env.dr_terms``)
camera translation +-2.5cm  ``dr.cam_pos`` add, per axis, parent (torso) frame     reset
camera rotation             ``dr.cam_quat``: roll +-2.5, pitch +-3, yaw +-2.5 deg  reset
                            composed on the nominal mount (torso-frame RPY)
camera FOV +-2 deg          ``dr.cam_fovy`` add                                    reset
pixel dropout, depth noise  not events: ``march.env.build.depth_image``            per step
==========================  =====================================================  =========

Startup vs reset. The paper samples per episode where it is cheap. Every term above that needs no
derived-constant recomputation is sampled at every reset. Link mass, base added mass and base CoM
change ``body_mass`` / ``body_inertia`` / ``body_ipos`` and so require mjwarp's ``set_const``
(forward kinematics + mass-matrix work over *all* worlds) each time they fire; with thousands of
envs some env resets at almost every control step, so per-episode sampling would run set_const
nearly every step. These three are sampled once per env at startup (as mjlab's own G1 task does
for ``base_com``): with 4096 envs that is 4096 independent robots.

Pure configuration; the simulator is only touched when mjlab calls the event functions.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

from mjlab.envs.mdp import dr as mjdr
from mjlab.managers.event_manager import EventTermCfg
from mjlab.managers.scene_entity_config import SceneEntityCfg

from march.config import DepthCfg, DrCfg
from march.env.dr_terms import (
    add_base_mass,
    install_control_delay,
    max_delay_steps,
    sample_control_delay,
    scale_joint_damping,
    scale_link_mass,
)
from march.env.push_event import interval_push

if TYPE_CHECKING:
    from mjlab.envs import ManagerBasedRlEnvCfg

G1_FOOT_GEOMS: tuple[str, ...] = tuple(
    f"{side}_foot{i}_collision" for side in ("left", "right") for i in range(1, 8)
)
"""The G1 foot collision geoms (as in mjlab's G1 velocity task)."""
BASE_BODY = "torso_link"
"""The body the paper's "base" rows act on (mjlab's G1 task uses it for ``base_com``)."""

MJLAB_DR_EVENTS: tuple[str, ...] = ("foot_friction", "encoder_bias", "base_com", "push_robot")
"""mjlab's G1 velocity-task DR/perturbation events; :func:`paper_dr_events` reuses these names,
so ``cfg.events.update(paper_dr_events(...))`` replaces them; with dr=none drop them."""

# Event term names, one per paper row (the four above are reused on purpose).
T_FRICTION = "foot_friction"
T_LINK_MASS = "link_mass"
T_BASE_MASS = "base_added_mass"
T_ENCODER = "encoder_bias"
T_BASE_COM = "base_com"
T_EFFORT = "effort_limits"
T_DAMPING = "joint_damping"
T_JOINT_FRICTION = "joint_friction"
T_PUSH = "push_robot"
T_DELAY = "control_delay"
T_CAM_POS = "camera_pos"
T_CAM_ROT = "camera_rot"
T_CAM_FOV = "camera_fov"

MODE_STARTUP = "startup"
MODE_RESET = "reset"
MODE_INTERVAL = "interval"
MODE_PUSH = "step"
"""The push's mode: a ``step`` event that keeps its own interval timers (march.env.push_event:
mjlab's ``interval`` mode selects the due envs with a host sync every step)."""
"""Inertial terms (set_const) at startup, everything else cheap at reset; see module doc."""


def _sym(h: float) -> tuple[float, float]:
    return (-float(h), float(h))


def paper_dr_events(
    dr: DrCfg,
    robot: str = "robot",
    camera: str | None = None,
    *,
    foot_geoms: tuple[str, ...] = G1_FOOT_GEOMS,
    base_body: str = BASE_BODY,
) -> dict[str, EventTermCfg]:
    """mjlab event terms for every row of the paper's DR table ({} for dr=none).

    ``camera`` is the depth camera's name (a camera on the robot entity, e.g. the
    ``CameraSensorCfg`` name of a camera whose ``parent_body`` is ``"robot/torso_link"``);
    without it the three camera rows are left out. The ``control_delay`` term needs
    :func:`install_control_delay` on the env config.
    """
    if dr.name == "none":
        return {}
    d = dr
    everything = SceneEntityCfg(robot)
    base = SceneEntityCfg(robot, body_names=(base_body,))
    lv, av = d.push_lin_vel, d.push_ang_vel
    com = d.base_com_offset_m
    events: dict[str, EventTermCfg] = {
        T_FRICTION: EventTermCfg(
            func=mjdr.geom_friction,
            mode=MODE_RESET,
            params={
                "asset_cfg": SceneEntityCfg(robot, geom_names=tuple(foot_geoms)),
                "operation": "abs",
                "ranges": tuple(d.friction),
                "axes": [0],
                "shared_random": True,
            },
        ),
        T_LINK_MASS: EventTermCfg(
            func=scale_link_mass,
            mode=MODE_STARTUP,
            params={"asset_cfg": everything, "scale_range": tuple(d.link_mass_scale)},
        ),
        T_BASE_MASS: EventTermCfg(
            func=add_base_mass,
            mode=MODE_STARTUP,
            params={"asset_cfg": base, "mass_range": tuple(d.base_added_mass_kg)},
        ),
        T_ENCODER: EventTermCfg(
            func=mjdr.encoder_bias,
            mode=MODE_RESET,
            params={"asset_cfg": SceneEntityCfg(robot), "bias_range": tuple(d.encoder_bias_rad)},
        ),
        T_BASE_COM: EventTermCfg(
            func=mjdr.body_com_offset,
            mode=MODE_STARTUP,
            params={
                "asset_cfg": SceneEntityCfg(robot, body_names=(base_body,)),
                "operation": "add",
                "ranges": {0: _sym(com[0]), 1: _sym(com[1]), 2: _sym(com[2])},
            },
        ),
        T_EFFORT: EventTermCfg(
            func=mjdr.effort_limits,
            mode=MODE_RESET,
            params={
                "asset_cfg": SceneEntityCfg(robot),
                "effort_limit_range": tuple(d.effort_limit_scale),
                "operation": "scale",
            },
        ),
        T_DAMPING: EventTermCfg(
            func=scale_joint_damping,
            mode=MODE_RESET,
            params={
                "asset_cfg": SceneEntityCfg(robot),
                "scale_range": tuple(d.joint_damping_scale),
            },
        ),
        T_JOINT_FRICTION: EventTermCfg(
            func=mjdr.joint_friction,
            mode=MODE_RESET,
            params={
                "asset_cfg": SceneEntityCfg(robot),
                "operation": "abs",
                "ranges": tuple(d.joint_friction),
            },
        ),
        T_PUSH: EventTermCfg(  # mjlab's interval push without its per-step sync (push_event)
            func=interval_push,
            mode=MODE_PUSH,
            interval_range_s=tuple(d.push_interval_s),
            params={
                "asset_cfg": SceneEntityCfg(robot),
                "velocity_range": {
                    "x": _sym(lv),
                    "y": _sym(lv),
                    "roll": _sym(av),
                    "pitch": _sym(av),
                    "yaw": _sym(av),
                },
            },
        ),
    }
    if d.control_delay_ms[1] > 0:
        events[T_DELAY] = EventTermCfg(
            func=sample_control_delay,
            mode=MODE_RESET,
            params={"asset_cfg": SceneEntityCfg(robot), "delay_ms": tuple(d.control_delay_ms)},
        )
    if camera is not None:
        cam = SceneEntityCfg(robot, camera_names=(camera,))
        roll, pitch, yaw = (math.radians(a) for a in d.camera_rot_deg)
        events[T_CAM_POS] = EventTermCfg(
            func=mjdr.cam_pos,
            mode=MODE_RESET,
            params={
                "asset_cfg": cam,
                "operation": "add",
                "ranges": {i: _sym(d.camera_pos_m) for i in range(3)},
            },
        )
        events[T_CAM_ROT] = EventTermCfg(
            func=mjdr.cam_quat,
            mode=MODE_RESET,
            params={
                "asset_cfg": SceneEntityCfg(robot, camera_names=(camera,)),
                "roll_range": _sym(roll),
                "pitch_range": _sym(pitch),
                "yaw_range": _sym(yaw),
            },
        )
        events[T_CAM_FOV] = EventTermCfg(
            func=mjdr.cam_fovy,
            mode=MODE_RESET,
            params={
                "asset_cfg": SceneEntityCfg(robot, camera_names=(camera,)),
                "operation": "add",
                "ranges": _sym(d.camera_fov_deg),
            },
        )
    return events


def apply_dr(
    cfg: ManagerBasedRlEnvCfg,
    dr: DrCfg,
    robot: str = "robot",
    camera: str | None = None,
) -> None:
    """In place on a mjlab env config: drop mjlab's G1 DR events (:data:`MJLAB_DR_EVENTS`), add
    :func:`paper_dr_events` and, for dr=paper, :func:`install_control_delay`. Other events
    (``reset_base``, ``reset_robot_joints``, ...) are kept."""
    kept = {k: v for k, v in cfg.events.items() if k not in MJLAB_DR_EVENTS}
    cfg.events = {**kept, **paper_dr_events(dr, robot, camera)}
    install_control_delay(cfg, dr, robot)


# ---------------------------------------------------------------------------------------------
# Description for march.inspect.
# ---------------------------------------------------------------------------------------------

PAPER_ROWS: tuple[str, ...] = (
    "Friction Coefficients",
    "Link Mass",
    "Base Additional Mass",
    "Encoder Bias",
    "Base CoM Offset",
    "Motor Effort Limits",
    "Joint Damping",
    "Joint Friction",
    "Push Perturbation",
    "Control Delay",
    "Depth Camera Translation",
    "Depth Camera Rotation (Euler)",
    "Depth Camera FOV",
    "Pixel Dropout",
    "Depth Noise",
)
"""The rows of the paper's table (tab:domain_randomization), in its order."""


def _u(lo: float, hi: float) -> str:
    return f"U({lo:g}, {hi:g})"


def describe_dr(
    dr: DrCfg,
    camera: str | None = None,
    depth: DepthCfg | None = None,
    physics_dt: float = 0.005,
) -> list[dict[str, Any]]:
    """One dict per row of the paper's table: row, term, mode, range, units, note.

    ``mode`` is startup / reset / interval for event terms, "depth pipeline" for the two image
    corruptions (``depth`` gives their values; DepthCfg defaults otherwise), and "off" for a row not
    applied (dr=none, or a camera row without ``camera``).
    """
    d = dr
    e = depth or DepthCfg()
    on = d.name != "none"
    cam_on = on and camera is not None
    com = d.base_com_offset_m
    rx, ry, rz = d.camera_rot_deg
    lag = max_delay_steps(d, physics_dt)
    rows: list[tuple[str, str | None, str, str, str, str, bool]] = [
        (
            PAPER_ROWS[0],
            T_FRICTION,
            MODE_RESET,
            _u(*d.friction),
            "-",
            "tangential friction of the 14 G1 foot collision geoms, one value per env",
            on,
        ),
        (
            PAPER_ROWS[1],
            T_LINK_MASS,
            MODE_STARTUP,
            _u(*d.link_mass_scale) + " x default",
            "-",
            "every robot body, mass and inertia scaled together",
            on,
        ),
        (
            PAPER_ROWS[2],
            T_BASE_MASS,
            MODE_STARTUP,
            _u(*d.base_added_mass_kg),
            "kg",
            f"point mass at the {BASE_BODY} COM",
            on,
        ),
        (
            PAPER_ROWS[3],
            T_ENCODER,
            MODE_RESET,
            _u(*d.encoder_bias_rad),
            "rad",
            "per joint; seen by biased joint_pos observations and position targets",
            on,
        ),
        (
            PAPER_ROWS[4],
            T_BASE_COM,
            MODE_STARTUP,
            f"dx {_u(-com[0], com[0])}, dy {_u(-com[1], com[1])}, dz {_u(-com[2], com[2])}",
            "m",
            f"{BASE_BODY} body_ipos offset",
            on,
        ),
        (
            PAPER_ROWS[5],
            T_EFFORT,
            MODE_RESET,
            _u(*d.effort_limit_scale) + " x default",
            "-",
            "per actuator force range",
            on,
        ),
        (
            PAPER_ROWS[6],
            T_DAMPING,
            MODE_RESET,
            _u(*d.joint_damping_scale) + " x default",
            "-",
            "per joint: passive dof_damping (0 on the G1) and the PD derivative gain kd",
            on,
        ),
        (
            PAPER_ROWS[7],
            T_JOINT_FRICTION,
            MODE_RESET,
            _u(*d.joint_friction),
            "N m",
            "dof_frictionloss per joint",
            on,
        ),
        (
            PAPER_ROWS[8],
            T_PUSH,
            MODE_PUSH,
            f"every {_u(*d.push_interval_s)} s: x, y {_u(-d.push_lin_vel, d.push_lin_vel)} m/s; "
            f"roll, pitch, yaw {_u(-d.push_ang_vel, d.push_ang_vel)} rad/s",
            "m/s, rad/s",
            "added to the root velocity",
            on,
        ),
        (
            PAPER_ROWS[9],
            T_DELAY,
            MODE_RESET,
            _u(*d.control_delay_ms),
            "ms",
            f"per env and episode; rounded to physics steps of {physics_dt * 1000:g} ms "
            f"(lag 0..{lag}); actuator command delay buffer",
            on and d.control_delay_ms[1] > 0,
        ),
        (
            PAPER_ROWS[10],
            T_CAM_POS,
            MODE_RESET,
            f"x, y, z {_u(-d.camera_pos_m, d.camera_pos_m)}",
            "m",
            "added to the mount position, torso frame",
            cam_on,
        ),
        (
            PAPER_ROWS[11],
            T_CAM_ROT,
            MODE_RESET,
            f"roll {_u(-rx, rx)}, pitch {_u(-ry, ry)}, yaw {_u(-rz, rz)}",
            "deg",
            "torso-frame RPY composed on the nominal mount",
            cam_on,
        ),
        (
            PAPER_ROWS[12],
            T_CAM_FOV,
            MODE_RESET,
            _u(-d.camera_fov_deg, d.camera_fov_deg),
            "deg",
            "added to the vertical FOV",
            cam_on,
        ),
    ]
    out = []
    for row, term, mode, rng, units, note, active in rows:
        out.append(
            {
                "row": row,
                "term": term if active else None,
                "mode": mode if active else "off",
                "range": rng,
                "units": units,
                "note": note if active else "not applied",
            }
        )
    out.append(
        {
            "row": PAPER_ROWS[13],
            "term": None,
            "mode": "depth pipeline",
            "range": f"{e.dropout:g}",
            "units": "fraction of pixels",
            "note": "march.env.depth (student training), set to max range",
        }
    )
    out.append(
        {
            "row": PAPER_ROWS[14],
            "term": None,
            "mode": "depth pipeline",
            "range": f"sigma = {e.noise_scale:g} x depth",
            "units": "m",
            "note": "march.env.depth (student training), Gaussian",
        }
    )
    return out
