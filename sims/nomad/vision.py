"""What the Nomad's camera reports (Sections 6.3-6.5): carpet matches, interest, the target.

The carpet match matrix, the interest operator, and the tracked target's pixel error to the
goal position.

From the camera model (the default): each cell of the 5 x 7 grid is looked at along a few rays
through the image; what each ray meets first (carpet, a wall of a similar colour, a pillar, a
ball...) is compared with the carpet's colour as the thesis' colour template matching did (a
sum of absolute RGB differences, Eq 6.1), under lighting that varies across the room and with
noise. The raw mismatches are then filtered as in the thesis: a region above a non-carpet region
is non-carpet, neighbours are smoothed horizontally and frames over time (Eq 6.2).

The interest operator picks an object that is not carpet but is surrounded by carpet; the
tracker then follows that object's point in the image (as template matching would), losing it
out of view, hidden, or moving too fast, with whole-pixel quantisation and noise.

From rendered images (`source="render"`, `sims.nomad.render`): the same matrix and tracking
measured in MuJoCo's images of the camera instead.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from sims.hydra.vision import VisionSource, check_camera
from sims.nomad.model import CARPET
from sims.pinhole import focal_px, project
from wfnn_common.config import check_fields

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
ROWS, COLS = 5, 7


@dataclass(frozen=True, kw_only=True)
class NomadVisionConfig:
    """The camera image, the carpet matching and the tracker."""

    source: VisionSource = "projection"
    """`projection`: the camera model's rays and a tracker with faults (fast); `render`: images
    rendered by MuJoCo, colour template matching for the carpet and the target (sims.nomad.render)."""
    width: int = 320
    height: int = 240
    grid_top: float = 0.2
    """The carpet grid covers the image below this fraction of its height (the floor ahead)."""
    samples: int = 3
    """Rays per cell side (samples x samples per cell)."""
    mismatch_scale: float = 0.6
    """Sum of absolute RGB differences (0..3) that counts as a full mismatch (1)."""
    mismatch_noise: float = 0.04
    """Standard deviation of the noise on each raw cell mismatch."""
    lighting: float = 0.08
    """Brightness varies by up to this fraction across the room (the thesis' corridors)."""
    alpha: float = 0.3
    """Eq 6.2: weight of the previous frame's smoothed value."""
    beta: float = 0.15
    """Eq 6.2: weight of each horizontal neighbour."""
    interest_object: float = 0.5
    """Interest operator: cells at least this mismatched are an object..."""
    interest_carpet: float = 0.35
    """...when all the cells around them are below this (carpet)..."""
    interest_cells: int = 4
    """...and the object covers at most this many cells (a ball, not a wall)."""
    goal_px: tuple[float, float] = (0.0, 60.0)
    """The goal position of a pursued target (x right, y down from the image centre)."""
    noise_px: float = 0.5
    quantise: bool = True
    blur_px_per_frame: float = 40.0
    """A target moving faster than this across the image (pixels per 30 Hz frame) is lost."""
    margin_px: float = 6.0
    render_scale: float = 0.25
    """render: images are rendered at this fraction of width x height (80 x 60 by default: a cell
    of the carpet grid is still about 11 x 10 pixels; positions are reported in width x height)."""
    image_noise: float = 0.01
    """render: standard deviation of the camera's noise on each colour plane (0..1)."""
    window_px: float = 24.0
    """render: the tracker searches this far around the target's last position (pixels); a target
    that moves further in one frame, or is hidden, is lost."""
    min_correlation: float = 0.7
    """render: a match needs at least this normalised correlation with the target's template."""

    def __post_init__(self) -> None:
        check_fields(self)
        check_camera(self)
        if (
            round(self.width * self.render_scale) < 2 * COLS
            or round(self.height * self.render_scale) < 3 * ROWS
        ):
            raise ValueError("render: the rendered image is too small for the 5 x 7 carpet grid")

    @property
    def half_diagonal(self) -> float:
        """Half the image diagonal (px): the servo reward's unit of pixel error, and a lost target's error."""
        return float(np.hypot(self.width, self.height) / 2)


def cell_pixels(cfg: NomadVisionConfig) -> FloatArray:
    """Sample points of each grid cell [ROWS, COLS, samples^2, 2] (x right, y down, from the centre)."""
    w, h = cfg.width, cfg.height
    top = cfg.grid_top * h
    cell_w, cell_h = w / COLS, (h - top) / ROWS
    offsets = (np.arange(cfg.samples) + 0.5) / cfg.samples
    ox, oy = np.meshgrid(offsets, offsets)
    out = np.zeros((ROWS, COLS, cfg.samples**2, 2))
    for r in range(ROWS):
        for c in range(COLS):
            out[r, c, :, 0] = (c + ox.ravel()) * cell_w - w / 2
            out[r, c, :, 1] = top + (r + oy.ravel()) * cell_h - h / 2
    return out


def smooth_carpet(raw: FloatArray, previous: FloatArray | None, alpha: float, beta: float) -> FloatArray:
    """Eq 6.2 on mismatches [..., ROWS, COLS] (row 0 the farthest).

    Horizontal smoothing, a non-carpet region makes the region above it non-carpet, and
    smoothing between frames. The extreme columns take their one neighbour twice; the
    lowermost row has no row below.
    """
    padded = np.concatenate([raw[..., :1], raw, raw[..., -1:]], axis=-1)
    horizontal = (1 - 2 * beta) * raw + beta * padded[..., :-2] + beta * padded[..., 2:]
    out = np.empty_like(raw)
    out[..., ROWS - 1, :] = horizontal[..., ROWS - 1, :]
    for r in range(ROWS - 2, -1, -1):
        out[..., r, :] = np.maximum(horizontal[..., r, :], out[..., r + 1, :])
    if previous is None:
        return out
    return (1 - alpha) * out + alpha * previous


def interesting_cells(raw: FloatArray, cfg: NomadVisionConfig) -> list[list[tuple[int, int]]]:
    """Objects that are not carpet but are surrounded by carpet, as lists of cells (row, col).

    An object is a 4-connected group of cells that are not carpet (at least `interest_carpet`),
    one of them clearly not (at least `interest_object`): so the cells it only partly covers
    belong to it rather than breaking the carpet around it. It is at most `interest_cells`
    cells and none on the grid's edge (it might go on out of view); every cell beside it is then
    carpet.
    """
    groups, count = ndimage.label(raw >= cfg.interest_carpet)
    found = []
    for label in range(1, count + 1):
        cells = np.argwhere(groups == label)
        if len(cells) > cfg.interest_cells:
            continue
        rows, cols = cells[:, 0], cells[:, 1]
        if rows.min() == 0 or cols.min() == 0 or rows.max() == ROWS - 1 or cols.max() == COLS - 1:
            continue
        if raw[rows, cols].max() >= cfg.interest_object:
            found.append([(int(r), int(c)) for r, c in cells])
    return found


class NomadCamera:
    """The pinhole camera on the robot: rays through pixels, and projection of world points."""

    def __init__(self, model: mujoco.MjModel, cfg: NomadVisionConfig, exclude_body: int) -> None:
        self.cfg = cfg
        self.id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, "camera")
        self.focal = focal_px(model, self.id, cfg.height)
        self.exclude_body = exclude_body
        self.grid = cell_pixels(cfg)
        # Ray directions in the camera frame for every grid sample (x right, y up, looking -z).
        px = self.grid.reshape(-1, 2)
        self._grid_dirs = np.stack([px[:, 0] / self.focal, -px[:, 1] / self.focal, -np.ones(len(px))], axis=1)
        self._geomid = np.zeros(len(px), dtype=np.int32)
        self._dist = np.zeros(len(px))
        self.groups = np.ones(6, dtype=np.uint8)
        """Geom groups the rays may meet (all: the robot's own body is excluded by id)."""

    def project(self, data: mujoco.MjData, point: FloatArray) -> tuple[FloatArray, float]:
        """Pixel position (x right, y down, from the centre) and depth of a world point."""
        return project(data, self.id, self.focal, point)

    def look(self, model: mujoco.MjModel, data: mujoco.MjData) -> tuple[NDArray[np.int32], FloatArray]:
        """What each grid ray meets first: geom ids [ROWS, COLS, k] (-1: nothing) and hit points."""
        rot = data.cam_xmat[self.id].reshape(3, 3)
        dirs = self._grid_dirs @ rot.T
        origin = data.cam_xpos[self.id].copy()
        mujoco.mj_multiRay(model, data, origin, dirs.ravel(), self.groups, 1, self.exclude_body,
                           self._geomid, self._dist, None, len(dirs), 20.0)  # fmt: skip
        points = origin + dirs * np.where(self._dist >= 0, self._dist, np.inf)[:, None]
        shape = self.grid.shape[:3]
        return self._geomid.reshape(shape).copy(), points.reshape(*shape, 3)

    def ray(self, model: mujoco.MjModel, data: mujoco.MjData, pixel: FloatArray) -> tuple[int, FloatArray]:
        """What the ray through `pixel` (x right, y down, from the centre) meets first.

        Returns the geom (-1: nothing) and the point [3] (NaN when nothing).
        """
        rot = data.cam_xmat[self.id].reshape(3, 3)
        direction = rot @ np.array([pixel[0] / self.focal, -pixel[1] / self.focal, -1.0])
        start = data.cam_xpos[self.id].copy()
        hit = np.zeros(1, dtype=np.int32)
        dist = mujoco.mj_ray(model, data, start, direction, self.groups, 1, self.exclude_body, hit)
        return int(hit[0]), start + direction * dist if dist >= 0 else np.full(3, np.nan)

    def visible(self, model: mujoco.MjModel, data: mujoco.MjData, geom: int, point: FloatArray) -> bool:
        """Whether a ray from the camera to `point` meets `geom` first."""
        start = data.cam_xpos[self.id]
        hit = np.zeros(1, dtype=np.int32)
        mujoco.mj_ray(model, data, start, point - start, self.groups, 1, self.exclude_body, hit)
        return int(hit[0]) == geom


def carpet_mismatch(
    model: mujoco.MjModel,
    geoms: NDArray[np.int32],
    points: FloatArray,
    cfg: NomadVisionConfig,
    rng: np.random.Generator,
) -> FloatArray:
    """Raw mismatch of each cell with the carpet template [ROWS, COLS], 0 (carpet) .. 1.

    Each ray's colour is its geom's colour under the room's lighting at the hit point; the
    template is the carpet's colour under the lighting where it was acquired (the room's mean).
    """
    colour = np.where(geoms[..., None] >= 0, model.geom_rgba[geoms, :3], 1.0)  # nothing hit: bright
    x, y = points[..., 0], points[..., 1]
    light = 1.0 + cfg.lighting * np.sin(np.nan_to_num(x, posinf=0.0, neginf=0.0) / 1.3) * np.cos(
        np.nan_to_num(y, posinf=0.0, neginf=0.0) / 1.7
    )
    seen = colour * light[..., None]
    sad = np.abs(seen - np.asarray(CARPET)).sum(axis=-1)  # Eq 6.1 over the colour planes
    raw = np.clip(sad.mean(axis=-1) / cfg.mismatch_scale, 0.0, 1.0)
    raw += rng.normal(0.0, cfg.mismatch_noise, raw.shape)
    return np.clip(raw, 0.0, 1.0)


@dataclass
class Track:
    """The tracker's output for one frame."""

    found: bool
    pixel: FloatArray
    """Target position from the image centre (x right, y down) [2]."""


class TargetTracker:
    """Follows one object's point in the image, with a real tracker's faults."""

    def __init__(self, camera: NomadCamera, rng: np.random.Generator) -> None:
        self.camera = camera
        self.rng = rng
        self.geom = -1
        """The tracked geom (-1: none)."""
        self._local = np.zeros(3)
        """The tracked point in the geom's frame."""
        self._last: FloatArray | None = None

    @property
    def active(self) -> bool:
        """Whether a target is being tracked."""
        return self.geom >= 0

    def start(self, data: mujoco.MjData, geom: int, point: FloatArray) -> None:
        """Track the object `geom` at the world point `point` (its template is taken there)."""
        self.geom = geom
        rot = data.geom_xmat[geom].reshape(3, 3)
        self._local = rot.T @ (np.asarray(point) - data.geom_xpos[geom])
        self._last = None

    def stop(self) -> None:
        """Forget the target."""
        self.geom, self._last = -1, None

    def point(self, data: mujoco.MjData) -> FloatArray:
        """The tracked point in the world now [3]."""
        rot = data.geom_xmat[self.geom].reshape(3, 3)
        return np.asarray(data.geom_xpos[self.geom] + rot @ self._local)

    def observe(self, model: mujoco.MjModel, data: mujoco.MjData) -> Track:
        """One 30 Hz frame; loses (and forgets) the target out of view, hidden or blurred."""
        if not self.active:
            return Track(False, np.zeros(2))
        cfg = self.camera.cfg
        point = self.point(data)
        pixel, depth = self.camera.project(data, point)
        half = np.array([cfg.width / 2 - cfg.margin_px, cfg.height / 2 - cfg.margin_px])
        previous, self._last = self._last, pixel
        blurred = previous is not None and bool(np.hypot(*(pixel - previous)) > cfg.blur_px_per_frame)
        if depth <= 0 or np.any(np.abs(pixel) > half) or blurred or not self._seen(model, data, point):
            self.stop()
            return Track(False, np.zeros(2))
        measured = pixel + self.rng.normal(0.0, cfg.noise_px, 2)
        return Track(True, np.round(measured) if cfg.quantise else measured)

    def _seen(self, model: mujoco.MjModel, data: mujoco.MjData, point: FloatArray) -> bool:
        """Whether nothing else is between the camera and the tracked point."""
        start = data.cam_xpos[self.camera.id]
        hit = np.zeros(1, dtype=np.int32)
        # The distance comes in units of the vector to the point: 1 is the point itself.
        dist = mujoco.mj_ray(model, data, start, point - start, self.camera.groups, 1,
                             self.camera.exclude_body, hit)  # fmt: skip
        return int(hit[0]) == self.geom or dist < 0 or dist >= 0.98
