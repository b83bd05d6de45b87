"""Rendered camera images of the HyDrA model, and the template-matching tracker that reads them.

The optional vision path (`VisionConfig.source == "render"`), closer to the real head's vision
card than the projection model: each 30 Hz frame is rendered off-screen by MuJoCo (Mesa EGL or
OSMesa; shadows off, which cost ten times the rest of a frame), turned to grey levels with
camera noise, and searched for the target template by normalised cross-correlation
(Section 7.5.2). The tracker searches a small window around the target's last position; when
the target is not there (hidden, out of view, or moved further than the window in one frame) it
searches the whole image and takes the best match above the threshold, which may be another
target that looks the same. Renders are also what `camera_images` shows a person.

Rendering itself is `sims.render`.
"""

from __future__ import annotations

from typing import Protocol

import cv2
import numpy as np
from numpy.typing import NDArray

from sims.hydra.vision import Measurement
from sims.render import GreyImage, RgbImage

FloatArray = NDArray[np.float64]


class TrackerSettings(Protocol):
    """What an `ImageTracker` reads from its camera's configuration (HyDrA's or the Nomad's)."""

    @property
    def width(self) -> int:
        """Image width in image units (pixels)."""

    @property
    def height(self) -> int:
        """Image height in image units."""

    @property
    def render_scale(self) -> float:
        """Rendered size as a fraction of the image size."""

    @property
    def window_px(self) -> float:
        """How far around its last position the target is searched for (image units)."""

    @property
    def min_correlation(self) -> float:
        """Least normalised correlation of a match."""

    @property
    def quantise(self) -> bool:
        """Whether positions are reported in whole pixels."""


MIN_TEMPLATE_CONTRAST = 0.1
"""Least standard deviation of a template's grey levels: a plainer patch correlates with any
smooth shading in the image."""


def _peak_offset(before: float, at: float, after: float) -> float:
    """Sub-pixel offset of a peak from three samples around it (a parabola), in [-0.5, 0.5]."""
    denom = before - 2.0 * at + after
    if denom >= 0.0:  # not a maximum (flat or noisy): stay on the sample
        return 0.0
    return float(np.clip(0.5 * (before - after) / denom, -0.5, 0.5))


class ImageTracker:
    """Template matching in one camera's images, as the thesis' trackers did.

    Images are grey levels [h, w] (HyDrA's monochrome cameras) or colours [h, w, 3] (the Nomad's
    colour camera), float32 0..1; the correlation is over all colour planes.

    Positions are pixels from the image centre (x right, y down) in the configured image size,
    whatever the rendered size. `target` counts acquisitions: the tracker cannot tell targets
    that look alike apart, so every new acquisition may be another object.
    """

    def __init__(self, cfg: TrackerSettings) -> None:
        self.cfg = cfg
        self.scale = cfg.render_scale
        self.size = (round(cfg.width * cfg.render_scale), round(cfg.height * cfg.render_scale))
        """Rendered (width, height)."""
        self.template: GreyImage | None = None
        self._offset = np.zeros(2)
        """Where the target's centre lies in the template, from the template's centre pixel."""
        self.acquisitions = 0
        self.current = -1
        self.position: FloatArray | None = None
        """Template centre in the rendered image (x, y in pixels from its top-left corner)."""
        self.last_correlation = float("nan")

    @property
    def half(self) -> int:
        """Half the template's side (rendered pixels)."""
        return 0 if self.template is None else self.template.shape[0] // 2

    def reset(self) -> None:
        """Forget the tracked target (the template is kept)."""
        self.current = -1
        self.position = None

    def acquire(self, image: GreyImage, pixel: FloatArray, radius_px: float, follow: bool = False) -> bool:
        """Cut the template around a target seen at `pixel` (image units) with this radius.

        Returns False (and keeps no template) when the cut would leave the image or holds too
        little contrast to be matched (nothing there). `follow`: the target is tracked from
        there (the next frame searches around it, not the whole image).
        """
        w, h = self.size
        centre = np.array([w / 2, h / 2]) + np.asarray(pixel) * self.scale
        if not (np.all(np.isfinite(centre)) and np.isfinite(radius_px)):
            return False  # not in front of the camera
        half = int(np.ceil(1.2 * radius_px * self.scale)) + 1
        col, row = (int(v) for v in np.floor(centre))
        if col - half < 0 or row - half < 0 or col + half >= w or row + half >= h:
            return False
        template = image[row - half : row + half + 1, col - half : col + half + 1].copy()
        if float(template.std()) < MIN_TEMPLATE_CONTRAST:
            return False
        self.template = template
        self._offset = centre - (np.array([col, row]) + 0.5)
        if follow:
            self.acquisitions += 1
            self.current = self.acquisitions
            self.position = np.array([col, row]) + 0.5
        return True

    def share_template(self, other: ImageTracker) -> None:
        """Use another tracker's template (the same camera on another head)."""
        self.template, self._offset = other.template, other._offset

    def _best(self, image: GreyImage, x0: int, y0: int) -> tuple[float, FloatArray]:
        """Best match in `image` (a region whose top-left is x0, y0): correlation, centre (x, y)."""
        assert self.template is not None
        scores = cv2.matchTemplate(image, self.template, cv2.TM_CCOEFF_NORMED)
        _, best, _, (bx, by) = cv2.minMaxLoc(scores)
        dx = _peak_offset(*scores[by, bx - 1 : bx + 2]) if 0 < bx < scores.shape[1] - 1 else 0.0
        dy = _peak_offset(*scores[by - 1 : by + 2, bx]) if 0 < by < scores.shape[0] - 1 else 0.0
        centre = np.array([x0 + bx + dx, y0 + by + dy]) + self.half + 0.5
        return float(best), centre

    def observe(self, image: GreyImage) -> Measurement:
        """Track for one frame [h, w] or [h, w, 3] (rendered size)."""
        if self.template is None:
            return Measurement(False, np.zeros(2), -1, False)
        cfg, half = self.cfg, self.half
        h, w = image.shape[:2]
        switched = False
        found = False
        if self.position is not None:
            reach = int(np.ceil(cfg.window_px * self.scale))
            cx, cy = (int(v) for v in np.floor(self.position))
            x0, y0 = max(cx - reach - half, 0), max(cy - reach - half, 0)
            x1, y1 = min(cx + reach + half + 1, w), min(cy + reach + half + 1, h)
            if x1 - x0 > 2 * half and y1 - y0 > 2 * half:
                score, centre = self._best(image[y0:y1, x0:x1], x0, y0)
                found = score >= cfg.min_correlation
        if not found:
            score, centre = self._best(image, 0, 0)
            found = score >= cfg.min_correlation
            if found:
                self.acquisitions += 1
                self.current = self.acquisitions
                switched = True
        self.last_correlation = score
        if not found:
            self.current, self.position = -1, None
            return Measurement(False, np.zeros(2), -1, False)
        self.position = centre
        pixel = (centre + self._offset - np.array([w / 2, h / 2])) / self.scale
        if cfg.quantise:
            pixel = np.round(pixel)
        return Measurement(True, pixel, self.current, switched)


def draw_tracker(
    image: RgbImage, tracker: ImageTracker | None, pixel: FloatArray | None, scale: float
) -> RgbImage:
    """A copy of `image` with the tracked target boxed (green) and the search window (yellow).

    `pixel` is the reported target position (image units, from the centre) or None when lost
    (a red frame); `tracker` adds its search window and template size when given.
    """
    out = np.ascontiguousarray(image).copy()
    h, w = out.shape[:2]
    if pixel is None or not np.all(np.isfinite(pixel)):
        cv2.rectangle(out, (0, 0), (w - 1, h - 1), (220, 30, 30), 2)
        return out
    cx, cy = (round(float(v)) for v in np.array([w / 2, h / 2]) + np.asarray(pixel) * scale)
    half = tracker.half if tracker is not None and tracker.half else max(4, int(0.06 * h))
    cv2.rectangle(out, (cx - half, cy - half), (cx + half, cy + half), (30, 200, 30), 1)
    if tracker is not None:
        reach = half + int(np.ceil(tracker.cfg.window_px * scale))
        cv2.rectangle(out, (cx - reach, cy - reach), (cx + reach, cy + reach), (230, 200, 30), 1)
    return out
