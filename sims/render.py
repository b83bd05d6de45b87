"""Off-screen rendering of a MuJoCo model's cameras (Mesa EGL or OSMesa, no display).

Rendering needs `MUJOCO_GL` set to `egl` or `osmesa` before `mujoco` is imported (`sims` sets
it unless told otherwise) and a renderer is used only by the thread that created it.
`python -m sims.render` says whether this machine can render.
"""

from __future__ import annotations

import threading
import weakref
from collections.abc import Iterable

import cv2
import mujoco
import numpy as np
from numpy.typing import NDArray

GreyImage = NDArray[np.float32]
RgbImage = NDArray[np.uint8]


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


if __name__ == "__main__":  # `python -m sims.render`: can this machine render? (exit 0/1)
    import os
    import sys

    problem = render_problem()
    print(problem or f"off-screen rendering works (MUJOCO_GL={os.environ.get('MUJOCO_GL')})")
    sys.exit(1 if problem else 0)
