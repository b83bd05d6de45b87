"""Rendered camera images of the HyDrA model, and the template-matching tracker that reads them.

The optional vision path (`VisionConfig.source == "render"`), closer to the real head's vision
card than the projection model: each 30 Hz frame is rendered off-screen by MuJoCo (Mesa EGL or
OSMesa; shadows off, which cost ten times the rest of a frame), turned to grey levels with
camera noise, and searched for the target template by normalised cross-correlation
(Section 7.5.2). The tracker searches a small window around the target's last position; when
the target is not there (hidden, out of view, or moved further than the window in one frame) it
searches the whole image and takes the best match above the threshold, which may be another
target that looks the same. Renders are also what `camera_images` shows a person.

Rendering needs `MUJOCO_GL` set to `egl` or `osmesa` before `mujoco` is imported (`sims` sets
`egl` unless told otherwise) and a renderer is used only by the thread that created it.
"""

from __future__ import annotations

import threading
import weakref
from collections.abc import Iterable

import cv2
import mujoco
import numpy as np
from numpy.typing import NDArray

from sims.hydra.vision import Measurement, VisionConfig

FloatArray = NDArray[np.float64]
GreyImage = NDArray[np.float32]
RgbImage = NDArray[np.uint8]


MIN_TEMPLATE_CONTRAST = 0.1
"""Least standard deviation of a template's grey levels: a plainer patch correlates with any
smooth shading in the image."""


class RenderUnavailable(RuntimeError):
    """Off-screen rendering cannot start here (no GL backend or Mesa libraries)."""


class CameraRenderer:
    """An off-screen renderer of the model's cameras, created on first use by the using thread."""

    def __init__(self, model: mujoco.MjModel, width: int, height: int) -> None:
        self.model = model
        self.width, self.height = width, height
        self._renderer: mujoco.Renderer | None = None
        self._thread: int | None = None
        self._option = mujoco.MjvOption()

    def _open(self) -> mujoco.Renderer:
        if self._renderer is not None:
            if threading.get_ident() != self._thread:
                raise RuntimeError("a camera renderer is used only by the thread that first rendered")
            return self._renderer
        try:
            renderer = mujoco.Renderer(self.model, self.height, self.width)
        except Exception as exc:  # the GL backends raise a variety of types
            import os

            raise RenderUnavailable(
                f"off-screen rendering failed ({type(exc).__name__}: {exc}); it needs MUJOCO_GL=egl or "
                f"osmesa set before mujoco is imported (now {os.environ.get('MUJOCO_GL')!r}) and Mesa's "
                "EGL or OSMesa libraries (deploy/setup.sh installs them)"
            ) from exc
        # Shadows cost ten times the rest of a frame under software GL and a tracker needs none.
        renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
        renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False
        self._renderer, self._thread = renderer, threading.get_ident()
        # OSMesa prints a traceback at exit for a renderer left open.
        weakref.finalize(self, renderer.close)
        return renderer

    def rgb(self, data: mujoco.MjData, camera: str, hidden_groups: Iterable[int] = ()) -> RgbImage:
        """The camera's colour image [height, width, 3], geoms of `hidden_groups` left out."""
        renderer = self._open()
        self._option.geomgroup[:] = 1
        for group in hidden_groups:
            self._option.geomgroup[group] = 0
        renderer.update_scene(data, camera=camera, scene_option=self._option)
        return renderer.render()

    def close(self) -> None:
        """Release the GL context (safe to call twice)."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


def to_grey(image: RgbImage) -> GreyImage:
    """Grey levels 0..1 [H, W] of a colour image (monochrome cameras, as on HyDrA)."""
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY).astype(np.float32) * np.float32(1.0 / 255.0)


def _peak_offset(before: float, at: float, after: float) -> float:
    """Sub-pixel offset of a peak from three samples around it (a parabola), in [-0.5, 0.5]."""
    denom = before - 2.0 * at + after
    if denom >= 0.0:  # not a maximum (flat or noisy): stay on the sample
        return 0.0
    return float(np.clip(0.5 * (before - after) / denom, -0.5, 0.5))


class ImageTracker:
    """Template matching in one camera's grey images, as the thesis' tracker did.

    Positions are pixels from the image centre (x right, y down) in the configured image size,
    whatever the rendered size. `target` counts acquisitions: the tracker cannot tell targets
    that look alike apart, so every new acquisition may be another object.
    """

    def __init__(self, cfg: VisionConfig) -> None:
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

    def acquire(self, image: GreyImage, pixel: FloatArray, radius_px: float) -> bool:
        """Cut the template around a target seen at `pixel` (image units) with this radius.

        Returns False (and keeps no template) when the cut would leave the image or holds too
        little contrast to be matched (nothing there).
        """
        w, h = self.size
        centre = np.array([w / 2, h / 2]) + np.asarray(pixel) * self.scale
        half = int(np.ceil(1.2 * radius_px * self.scale)) + 1
        col, row = (int(v) for v in np.floor(centre))
        if col - half < 0 or row - half < 0 or col + half >= w or row + half >= h:
            return False
        template = image[row - half : row + half + 1, col - half : col + half + 1].copy()
        if float(template.std()) < MIN_TEMPLATE_CONTRAST:
            return False
        self.template = template
        self._offset = centre - (np.array([col, row]) + 0.5)
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
        """Track for one frame of grey levels [h, w] (rendered size)."""
        if self.template is None:
            return Measurement(False, np.zeros(2), -1, False)
        cfg, half = self.cfg, self.half
        h, w = image.shape
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


PROBE_MJCF = (
    '<mujoco><worldbody><camera name="c" pos="0 0 1"/><geom type="sphere" size="0.1"/></worldbody></mujoco>'
)


def render_problem() -> str | None:
    """Why off-screen rendering fails here (a sentence), or None when a frame renders."""
    renderer = CameraRenderer(mujoco.MjModel.from_xml_string(PROBE_MJCF), 32, 24)
    try:
        data = mujoco.MjData(renderer.model)
        mujoco.mj_forward(renderer.model, data)
        image = renderer.rgb(data, "c")
    except RenderUnavailable as exc:
        return str(exc)
    finally:
        renderer.close()
    return None if image.shape == (24, 32, 3) else f"a probe frame came back as {image.shape}"


if __name__ == "__main__":  # `python -m sims.hydra.render`: can this machine render? (exit 0/1)
    import os
    import sys

    problem = render_problem()
    print(problem or f"off-screen rendering works (MUJOCO_GL={os.environ.get('MUJOCO_GL')})")
    sys.exit(1 if problem else 0)
