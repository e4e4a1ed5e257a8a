"""The feasibility report's picture and film: the error floor per output group and level
(matplotlib), and the kinematic G1 following a plan on the stones (MuJoCo's offscreen
renderer, EGL or OSMesa as ``MUJOCO_GL`` says; mjlab's default is EGL).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from march.env.g1 import g1_mjcf_spec

if TYPE_CHECKING:
    from march.audit.ik_walk import WalkTrace
    from march.audit.kinematic_g1 import KinematicG1

FILM_SIZE = (640, 360)
"""Film frame width and height [px]."""
FILM_CAMERA = {"distance": 2.8, "azimuth": 120.0, "elevation": -20.0}
"""Camera around the pelvis: distance [m], azimuth and elevation [deg]."""


def draw_floors(
    levels: list[dict[str, Any]], path: Path, tol_com: float, tol_swing_pos: float
) -> Path:
    """Four panels over the curriculum levels (``levels``: the report's per-level dicts): the
    90th-percentile and median |eta| of each output group (positions in cm, angles in degrees)
    with the CoM reference's jump at touchdowns, V / Vmax (median, 90th percentile; log scale;
    the saturated share printed) and the share of planned steps the G1 reaches (whole step,
    and the positions-at-touchdown criterion), with what misses most; ``tol_com`` and
    ``tol_swing_pos`` [m] are drawn as the reach tolerances."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = np.array([s["level"] for s in levels])

    def series(get: Any) -> np.ndarray:
        return np.array([np.nan if get(s) is None else get(s) for s in levels], dtype=float)

    fig, axes = plt.subplots(2, 2, figsize=(14, 9.5))
    (pos_ax, ang_ax), (v_ax, reach_ax) = axes
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for c, (group, label) in enumerate((("com", "CoM"), ("swing_pos", "swing foot position"))):
        for q, style in (("p90", "-o"), ("median", ":")):
            y = series(lambda s, g=group, q=q: s["eta_abs"]["groups"][g][q])
            pos_ax.plot(x, 100 * y, style, color=colors[c], label=f"{label}, {q}", ms=4)
    jump = series(lambda s: s["jump_at_touchdown"]["position_group_norm"]["com"]["p90"])
    pos_ax.plot(
        x, 100 * jump, "--s", color=colors[2], ms=4, label="CoM reference jump at touchdown, p90"
    )
    for tol, name in ((tol_swing_pos, "swing foot"), (tol_com, "CoM")):
        pos_ax.axhline(100 * tol, color="grey", lw=0.8, ls="--")
        pos_ax.text(x[-1], 100 * tol, f"{name} reach tolerance ", va="bottom", ha="right")
    pos_ax.set(xlabel="curriculum level (difficulty 0 -> 1)", ylabel="|y - y_ref| [cm]")
    pos_ax.set_title("position outputs: error the G1's best pose keeps")
    angles = (
        ("pelvis", "pelvis"),
        ("swing_ori", "swing foot orientation"),
        ("upper", "upper body"),
    )
    for c, (group, label) in enumerate(angles, start=3):
        for q, style in (("p90", "-o"), ("median", ":")):
            y = series(lambda s, g=group, q=q: s["eta_abs"]["groups"][g][q])
            ang_ax.plot(x, np.degrees(y), style, color=colors[c], label=f"{label}, {q}", ms=4)
    ang_ax.set(xlabel="curriculum level (difficulty 0 -> 1)", ylabel="|y - y_ref| [deg]")
    ang_ax.set_title("angle outputs: error the G1's best pose keeps")
    for ax in (pos_ax, ang_ax):
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    v_ax.semilogy(x, series(lambda s: s["v_over_vmax"]["median"]), "-o", ms=4, label="median")
    v_ax.semilogy(x, series(lambda s: s["v_over_vmax"]["p90"]), "-s", ms=4, label="90th percentile")
    v_ax.semilogy(
        x,
        series(lambda s: s["v_position_over_vmax"]["p90"]),
        "--",
        label="90th percentile, position errors only (etadot = 0)",
    )
    v_ax.axhline(1.0, color="red", lw=0.8, ls="--")
    v_ax.text(x[0], 1.05, " Vmax: r_clf flat at e^-1 above", color="red", va="bottom")
    for s, xi in zip(levels, x, strict=True):
        sat = s["v_over_vmax"]["saturated"]
        if sat is not None:
            v_ax.text(xi, 2.2, f"{100 * sat:.1f}%", ha="center", fontsize=7)
    v_ax.text(x[-1], 3.6, "share of ticks V >= Vmax", ha="right", fontsize=8)
    v_ax.set_ylim(top=6.0)
    v_ax.set(xlabel="curriculum level (difficulty 0 -> 1)", ylabel="V / Vmax")
    v_ax.set_title("CLF value of the kinematic trajectory (its floor)")
    v_ax.legend(fontsize=8, loc="lower right")
    v_ax.grid(alpha=0.3, which="both")
    whole = series(lambda s: s["reach"]["whole_step"])
    touchdown = series(lambda s: s["reach"]["touchdown_tick_positions"])
    ci = np.array(
        [s["reach"].get("whole_step_ci95") or [np.nan, np.nan] for s in levels], dtype=float
    ).reshape(-1, 2)
    reach_ax.bar(
        x - 0.2,
        100 * whole,
        0.4,
        yerr=100 * np.abs(np.stack([whole - ci[:, 0], ci[:, 1] - whole])),
        capsize=2,
        error_kw={"lw": 0.8},
        label="reached: every output and rate in tolerance at every tick,\nslide <= 1 cm, "
        "real touchdown (bar: 95 % interval over the level's steps)",
    )
    reach_ax.bar(x + 0.2, 100 * touchdown, 0.4, label="old: positions at the touchdown tick only")
    for s, xi, t, top in zip(levels, x, whole, ci[:, 1], strict=True):
        misses = s["reach"]["misses_by_cause"]
        if misses and np.isfinite(t):
            worst = next(iter(misses))
            above = 100 * (top if np.isfinite(top) else t) + 1
            reach_ax.text(xi - 0.2, above, worst, rotation=90, ha="center", va="bottom", fontsize=7)
    reach_ax.set(
        xlabel="curriculum level (difficulty 0 -> 1)", ylabel="planned steps [%]", ylim=(0, 150)
    )
    reach_ax.set_title("planned steps the G1 reaches (label: what missed most)")
    reach_ax.legend(fontsize=8, loc="upper right")
    courses = levels[0]["courses"] if levels else 0
    fig.suptitle(
        "Kinematic floor of the CLF reference: mjlab's G1 posed by whole-body IK (mink, stance "
        "foot held, joint limits, no dynamics) at 50 Hz along planned walks, "
        f"{courses} course(s) per level",
        fontsize=11,
    )
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def course_spec(layout: Any) -> Any:
    """mjlab's G1 MJCF with the course's boxes (tops at their heights, down to the pit
    floor) and two markers: the CoM reference (red) and the swing-foot reference (green)."""
    import mujoco

    spec = g1_mjcf_spec()
    world = spec.worldbody
    bottom = float(layout.bottom)
    for k in range(layout.num_boxes):
        cx, cy, top = (float(v) for v in layout.center[k])
        hx, hy = (float(v) for v in layout.half_size[k])
        half_z = 0.5 * (top - bottom)
        world.add_geom(
            type=mujoco.mjtGeom.mjGEOM_BOX,
            pos=[cx, cy, top - half_z],
            size=[hx, hy, half_z],
            rgba=[0.55, 0.5, 0.45, 1.0] if k % 2 else [0.6, 0.56, 0.5, 1.0],
            contype=0,
            conaffinity=0,
        )
    world.add_geom(
        type=mujoco.mjtGeom.mjGEOM_PLANE,
        pos=[0.5 * layout.size[0], 0.5 * layout.size[1], bottom],
        size=[layout.size[0], layout.size[1], 0.1],
        rgba=[0.2, 0.22, 0.25, 1.0],
        contype=0,
        conaffinity=0,
    )
    for name, rgba in (("com_ref", [1, 0.1, 0.1, 0.8]), ("swing_ref", [0.1, 0.9, 0.1, 0.8])):
        body = world.add_body(name=name, mocap=True)
        body.add_geom(
            type=mujoco.mjtGeom.mjGEOM_SPHERE,
            size=[0.03, 0, 0],
            rgba=rgba,
            contype=0,
            conaffinity=0,
        )
    spec.visual.headlight.ambient = [0.4, 0.4, 0.4]
    return spec


def film_walk(trace: WalkTrace, layout: Any, path: Path, kin: KinematicG1) -> str | None:
    """The kinematic G1's walk ``trace`` on ``layout`` as an MP4 at the control rate; None,
    or why this machine cannot render (one line, :func:`march.env.rendering.rendering_error`)."""
    import imageio_ffmpeg
    import mediapy
    import mujoco

    from march.env.rendering import rendering_error

    problem = rendering_error()
    if problem is not None:
        return problem
    model = course_spec(layout).compile()
    data = mujoco.MjData(model)
    com_ref, swing_ref = model.body("com_ref").mocapid[0], model.body("swing_ref").mocapid[0]
    width, height = FILM_SIZE
    renderer = mujoco.Renderer(model, height=height, width=width)
    camera = mujoco.MjvCamera()
    camera.distance = FILM_CAMERA["distance"]
    camera.azimuth = FILM_CAMERA["azimuth"]
    camera.elevation = FILM_CAMERA["elevation"]
    frames = []
    try:
        for qpos, y_ref in zip(trace.qpos, trace.y_ref, strict=True):
            data.qpos[: kin.model.nq] = qpos
            data.mocap_pos[com_ref] = y_ref[0:3]
            data.mocap_pos[swing_ref] = y_ref[6:9]
            mujoco.mj_forward(model, data)
            camera.lookat[:] = data.body("pelvis").xpos
            renderer.update_scene(data, camera)
            frames.append(renderer.render().copy())
    finally:
        renderer.close()
    mediapy.set_ffmpeg(imageio_ffmpeg.get_ffmpeg_exe())
    path.parent.mkdir(parents=True, exist_ok=True)
    mediapy.write_video(path, frames, fps=round(1.0 / kin.cfg.dt), codec="h264")
    return None
