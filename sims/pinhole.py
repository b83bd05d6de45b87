"""The pinhole model of a MuJoCo camera, in the image coordinates the simulated trackers report.

Pixels are measured from the image centre, x to the right and y down; the focal length comes
from the camera's vertical field of view and the image height.
"""

from __future__ import annotations

import mujoco
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def focal_px(model: mujoco.MjModel, camera: int, height: int) -> float:
    """Focal length in pixels of `camera` for an image `height` pixels high."""
    return float((height / 2) / np.tan(np.deg2rad(model.cam_fovy[camera]) / 2))


def project(data: mujoco.MjData, camera: int, focal: float, point: FloatArray) -> tuple[FloatArray, float]:
    """Pixel position [2] and depth of a world point; infinite pixels for a point behind the camera.

    MuJoCo cameras look along their -z with +y up.
    """
    rel = data.cam_xmat[camera].reshape(3, 3).T @ (point - data.cam_xpos[camera])
    depth = float(-rel[2])
    if depth <= 1e-6:
        return np.array([np.inf, np.inf]), depth
    return np.array([focal * rel[0] / depth, -focal * rel[1] / depth]), depth
