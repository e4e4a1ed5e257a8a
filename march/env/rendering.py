"""Offscreen rendering of a built env (``python -m march.play``): mjlab's offscreen renderer
with a camera following the robot, and a one-line check that this machine can render at all.
"""

from __future__ import annotations

import os
from typing import Any

WIDTH, HEIGHT = 640, 360
"""Video frame size [px]."""
CAMERA = {"distance": 3.5, "elevation": -15.0, "azimuth": 135.0}
"""Tracking camera around the torso: distance [m], elevation and azimuth [deg]."""


def rendering_error() -> str | None:
    """None if MuJoCo can render offscreen in this process, else why not (one line)."""
    xml = "<mujoco><worldbody><geom type='sphere' size='.1'/></worldbody></mujoco>"
    try:
        # mjlab sets MUJOCO_GL=egl on Linux before mujoco loads; with the GL library missing
        # even ``import mujoco`` fails, so the imports are part of the check.
        import mjlab  # noqa: F401
        import mujoco

        renderer = mujoco.Renderer(mujoco.MjModel.from_xml_string(xml), 8, 8)
        renderer.close()
    except Exception as err:  # noqa: BLE001 - any backend failure means the same to the user
        backend = os.environ.get("MUJOCO_GL", "default")
        return (
            f"MuJoCo cannot render offscreen with MUJOCO_GL={backend} "
            f"({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}); "
            "on Debian/Ubuntu install libegl1 libgl1-mesa-dri (EGL), or libosmesa6 and set "
            "MUJOCO_GL=osmesa"
        )
    return None


def make_renderer(env: Any) -> Any:
    """mjlab's offscreen renderer on env 0 with a tracking camera on the torso."""
    from mjlab.viewer import ViewerConfig
    from mjlab.viewer.offscreen_renderer import OffscreenRenderer

    view = ViewerConfig(
        origin_type=ViewerConfig.OriginType.ASSET_BODY,
        entity_name="robot",
        body_name="torso_link",
        width=WIDTH,
        height=HEIGHT,
        max_extra_envs=0,
        **CAMERA,
    )
    renderer = OffscreenRenderer(
        model=env.sim.mj_model,
        cfg=view,
        scene=env.scene,
        sim_model=env.sim.model,
        expanded_fields=env.sim.expanded_fields,
    )
    renderer.initialize()
    return renderer
