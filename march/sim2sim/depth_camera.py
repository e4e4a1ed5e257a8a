"""The student's depth camera by MuJoCo ray casting, as the robot-side loop renders it.

:func:`camera_rays` gives the pinhole's per-pixel ray directions (mujoco_warp's ``compute_ray``),
:func:`normalize_depth` the training's clipping and [0, 1] normalisation
(``march.env.depth.normalize``), and :class:`DepthCamera` casts the rays with ``mj_multiRay``
against the bundle's geom groups into the ONNX ``depth`` input. MuJoCo and numpy only.
"""

from __future__ import annotations

import math
from typing import Any

import mujoco
import numpy as np

from march.sim2sim.deploy_bundle import UsageError


def camera_rays(width: int, height: int, fovy_deg: float) -> np.ndarray:
    """(H*W, 3) unit ray directions in the camera frame, row-major from the top-left pixel.

    MuJoCo cameras look along -z with +y up; pixel (i, j) is the ray through the centre of that
    pixel of a pinhole with vertical field of view ``fovy_deg`` (mujoco_warp's ``compute_ray``).
    """
    t = math.tan(0.5 * math.radians(fovy_deg))
    aspect = width / height
    jj, ii = np.meshgrid(np.arange(width), np.arange(height))
    x = (2.0 * (jj + 0.5) / width - 1.0) * t * aspect
    y = (1.0 - 2.0 * (ii + 0.5) / height) * t
    d = np.stack([x, y, -np.ones_like(x)], axis=-1).reshape(-1, 3)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def normalize_depth(depth: np.ndarray, min_range: float, max_range: float) -> np.ndarray:
    """Invalid (<= 0, non-finite) -> max_range, clip, map to [0, 1] (march.env.depth.normalize)."""
    d = np.where(np.isfinite(depth) & (depth > 0.0), depth, max_range)
    return (np.clip(d, min_range, max_range) - min_range) / (max_range - min_range)


class DepthCamera:
    """The student's depth camera by ray casting against the scene's enabled geom groups."""

    def __init__(self, model: mujoco.MjModel, spec: dict[str, Any]) -> None:
        self.cam = model.camera(spec["camera"]).id
        self.h, self.w = int(spec["height"]), int(spec["width"])
        self.lo, self.hi = float(spec["min_range_m"]), float(spec["max_range_m"])
        fovy = float(model.cam_fovy[self.cam])
        if abs(fovy - float(spec["fovy_deg"])) > 1e-6:
            raise UsageError(f"scene camera fovy {fovy} != bundle's {spec['fovy_deg']}")
        self.rays = camera_rays(self.w, self.h, fovy)
        self.cos = -self.rays[:, 2]  # planar depth = distance x cos(angle to the optical axis)
        self.groups = np.zeros(6, dtype=np.uint8)
        self.groups[list(spec["geom_groups"])] = 1
        # Past the max range every pixel reads 1 whether it hits or not: stop looking there.
        self.cutoff = self.hi / float(self.cos.min()) + 1e-3
        self.n = self.rays.shape[0]
        self._geom = np.zeros(self.n, dtype=np.int32)
        self._dist = np.zeros(self.n, dtype=np.float64)

    def planar(self, model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
        """(H, W) planar depth [m] from the current kinematics; 0 where a ray hits nothing."""
        origin = data.cam_xpos[self.cam].copy()
        world = self.rays @ data.cam_xmat[self.cam].reshape(3, 3).T
        mujoco.mj_multiRay(
            model,
            data,
            origin,
            world.reshape(-1),
            self.groups,
            1,  # static geoms (the terrain) count
            -1,
            self._geom,
            self._dist,
            None,
            self.n,
            self.cutoff,
        )
        depth = np.where(self._geom >= 0, self._dist * self.cos, 0.0)
        return depth.reshape(self.h, self.w)

    def image(self, model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
        """(1, 1, H, W) float32 normalised depth, the ONNX ``depth`` input."""
        d = normalize_depth(self.planar(model, data), self.lo, self.hi)
        return d.astype(np.float32)[None, None]
