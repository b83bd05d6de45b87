"""What HyDrA's cameras report: the tracked target's pixel position, with a real tracker's faults.

Each camera projects candidate targets through a pinhole model (its pose from the simulation).
A candidate is visible when it is in front of the camera, inside the image, not hidden by
another object (a ray from the camera reaches it first) and not blurred (moving across the image
faster than `blur_px_per_frame`). The tracker keeps its current target while that stays visible
(it searches a small window around the last position); when it is lost, it searches the whole
image and takes any visible candidate, which may be the wrong one (Section 7.5.2). Measurements
are quantised to whole pixels plus Gaussian noise.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import mujoco
import numpy as np
from numpy.typing import NDArray

from sims.pinhole import focal_px, project
from wfnn_common.config import check_fields

FloatArray = NDArray[np.float64]


VisionSource = Literal["projection", "render"]
VISION_SOURCES: tuple[VisionSource, ...] = ("projection", "render")


def check_camera(cfg: Any) -> None:
    """Refuse camera settings (HyDrA's or the Nomad's vision config) that cannot work."""
    if cfg.source not in VISION_SOURCES:
        raise ValueError(f"vision source must be one of {VISION_SOURCES}, got {cfg.source!r}")
    if cfg.width < 16 or cfg.height < 16:
        raise ValueError(f"image must be at least 16 x 16 pixels, got {cfg.width} x {cfg.height}")
    if not 0.1 <= cfg.render_scale <= 1.0:
        raise ValueError(f"render_scale must be in [0.1, 1], got {cfg.render_scale}")
    if not 0.0 < cfg.min_correlation < 1.0:
        raise ValueError(f"min_correlation must be in (0, 1), got {cfg.min_correlation}")


@dataclass(frozen=True, kw_only=True)
class VisionConfig:
    """Camera images and tracker faults."""

    source: VisionSource = "projection"
    """`projection`: targets projected through the camera model with the faults below (fast);
    `render`: images rendered by MuJoCo and tracked by template matching (sims.hydra.render)."""
    width: int = 320
    height: int = 240
    noise_px: float = 0.3
    """Standard deviation of the tracker's position noise (pixels)."""
    quantise: bool = True
    """Report whole pixels, as template matching does."""
    blur_px_per_frame: float = 25.0
    """A target moving faster than this across the image (pixels per 30 Hz frame) blurs and is lost."""
    margin_px: float = 4.0
    """Targets closer than this to the image border are not found."""
    render_scale: float = 1.0
    """render: images are rendered at this fraction of width x height (positions are still
    reported in width x height pixels)."""
    image_noise: float = 0.01
    """render: standard deviation of the camera's grey-level noise (grey levels 0..1)."""
    window_px: float = 24.0
    """render: the tracker searches this far around the target's last position (pixels); a
    target that moves further between frames is lost there and searched for over the whole image."""
    min_correlation: float = 0.7
    """render: a match needs at least this normalised correlation with the template."""

    def __post_init__(self) -> None:
        check_fields(self)
        check_camera(self)


@dataclass
class Measurement:
    """One camera's tracker output for one frame."""

    found: bool
    pixel: FloatArray
    """Target position relative to the image centre (x right, y down), pixels [2]."""
    target: int
    """Index of the tracked candidate (-1 when lost)."""
    switched: bool
    """The tracker (re)acquired its target in this frame by a search of the whole image."""


class Camera:
    """A pinhole camera of the model and the tracker that follows one target in its image."""

    def __init__(self, model: mujoco.MjModel, name: str, cfg: VisionConfig, rng: np.random.Generator) -> None:
        self.cfg = cfg
        self.id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, name)
        if self.id < 0:
            raise ValueError(f"no camera {name!r} in the model")
        self.focal = focal_px(model, self.id, cfg.height)
        """Focal length in pixels."""
        self.body = int(model.cam_bodyid[self.id])
        self.rng = rng
        self.current = -1
        self._last: dict[int, FloatArray] = {}
        """Each candidate's projection in the previous frame (for blur)."""

    def reset(self) -> None:
        """Forget the tracked target and the previous frame."""
        self.current = -1
        self._last = {}

    def project(self, data: mujoco.MjData, point: FloatArray) -> tuple[FloatArray, float]:
        """Pixel position (x right, y down, from the centre) and depth of a world point."""
        return project(data, self.id, self.focal, point)

    def _visible(
        self,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        geom: int,
        point: FloatArray,
        groups: NDArray[np.uint8],
    ) -> bool:
        start = data.cam_xpos[self.id]
        vec = point - start
        hit = np.zeros(1, dtype=np.int32)
        mujoco.mj_ray(model, data, start, vec, groups, 1, self.body, hit)
        return int(hit[0]) == geom or int(hit[0]) == -1

    def observe(
        self,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        candidates: list[tuple[int, FloatArray]],
        groups: NDArray[np.uint8],
    ) -> Measurement:
        """Track for one frame among candidates [(geom id, world position)]."""
        cfg = self.cfg
        half = np.array([cfg.width / 2 - cfg.margin_px, cfg.height / 2 - cfg.margin_px])
        seen: dict[int, FloatArray] = {}
        previous = self._last
        self._last = {}
        for index, (geom, point) in enumerate(candidates):
            pixel, depth = self.project(data, point)
            if depth <= 0 or np.any(np.abs(pixel) > half):
                continue
            self._last[index] = pixel
            moved = previous.get(index)
            if moved is not None and np.hypot(*(pixel - moved)) > cfg.blur_px_per_frame:
                continue
            if self._visible(model, data, geom, point, groups):
                seen[index] = pixel
        switched = False
        if self.current not in seen:
            if seen:
                self.current = list(seen)[int(self.rng.integers(len(seen)))]
                switched = True
            else:
                self.current = -1
        if self.current == -1:
            return Measurement(False, np.zeros(2), -1, False)
        pixel = seen[self.current] + self.rng.normal(0.0, cfg.noise_px, 2)
        if cfg.quantise:
            pixel = np.round(pixel)
        return Measurement(True, pixel, self.current, switched)
