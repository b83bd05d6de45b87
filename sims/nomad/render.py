"""The Nomad's vision measured in rendered colour images (`NomadVisionConfig(source="render")`).

Closer to the thesis' vision system (Section 6.3) than the camera model: the camera's frames are
rendered off-screen by MuJoCo (`sims.render`) at `render_scale` of the image size, with noise on
each colour plane.

- Carpet matching (Eq 6.1): at start-up the camera looks at open carpet and every cell of the
  5 x 7 grid keeps its patch of that view as its template (perspective and the room's lights make
  the carpet look different in each cell). A cell's raw mismatch is the mean, over its pixels, of
  the sum of absolute colour differences from its template, in units of `mismatch_scale`. The
  filtering (Eq 6.2) and the interest operator are the camera model's (`sims.nomad.vision`).
- Targets: the interest operator's object is where the mismatched pixels of its cells are; a
  colour template is cut there and followed by template matching in a window around its last
  position (`sims.hydra.render.ImageTracker`). A target not found in its window (hidden, out of
  view, or moved further in one frame) is lost: with several balls of a colour in the room, a
  search of the whole image would as likely find another one.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from sims.nomad.vision import COLS, ROWS, NomadVisionConfig
from sims.render import RgbImage

FloatImage = NDArray[np.float32]
FloatArray = NDArray[np.float64]


def to_colour(image: RgbImage, noise: float, rng: np.random.Generator) -> FloatImage:
    """A rendered frame as colours 0..1 [h, w, 3] with the camera's noise."""
    out = image.astype(np.float32) * np.float32(1.0 / 255.0)
    if noise > 0:
        out += rng.standard_normal(out.shape, dtype=np.float32) * np.float32(noise)
    return out


class CarpetGrid:
    """The 5 x 7 carpet grid over a rendered image, and the carpet templates of its cells."""

    def __init__(self, cfg: NomadVisionConfig) -> None:
        self.cfg = cfg
        self.scale = cfg.render_scale
        w, h = round(cfg.width * cfg.render_scale), round(cfg.height * cfg.render_scale)
        self.size = (w, h)
        """Rendered (width, height)."""
        self.row_edges = np.round(np.linspace(cfg.grid_top * h, h, ROWS + 1)).astype(np.int64)
        self.col_edges = np.round(np.linspace(0, w, COLS + 1)).astype(np.int64)
        self._cell_pixels = np.outer(np.diff(self.row_edges), np.diff(self.col_edges)).astype(np.float32)
        self.template: FloatImage | None = None
        """The start-up view of open carpet [h, w, 3]."""

    def acquire(self, image: FloatImage) -> None:
        """Keep a view of open carpet as the cells' templates (start-up)."""
        if image.shape[:2] != self.size[::-1]:
            raise ValueError(f"a carpet view must be {self.size[0]} x {self.size[1]}, got {image.shape[:2]}")
        self.template = image.copy()

    def difference(self, image: FloatImage) -> FloatImage:
        """Sum of absolute colour differences from the carpet template, per pixel [h, w] (Eq 6.1)."""
        if self.template is None:
            raise RuntimeError("no carpet template: acquire a view of open carpet first")
        return np.abs(image - self.template).sum(axis=2)

    def mismatch(self, difference: FloatImage) -> FloatArray:
        """Raw mismatch of each cell with its template [ROWS, COLS], 0 (carpet) .. 1."""
        top = int(self.row_edges[0])
        # Sums over each cell's rows, then its columns (cells tile the grid region exactly).
        rows = np.add.reduceat(difference[top:], self.row_edges[:-1] - top, axis=0)
        cells = np.add.reduceat(rows, self.col_edges[:-1], axis=1) / self._cell_pixels
        return np.clip(cells.astype(np.float64) / self.cfg.mismatch_scale, 0.0, 1.0)

    def object_at(
        self, difference: FloatImage, cells: list[tuple[int, int]]
    ) -> tuple[FloatArray, float] | None:
        """Where an interesting object is: its pixel and radius, or None.

        The pixel (image units from the centre, x right, y down) and radius (image units) come
        from the mismatched pixels of its cells and the carpet cells around them (which hold its
        edges); None if there are none.
        """
        around = {(r + dr, c + dc) for r, c in cells for dr in (-1, 0, 1) for dc in (-1, 0, 1)}
        mask = np.zeros(difference.shape, dtype=np.bool_)
        for r, c in around & {(r, c) for r in range(ROWS) for c in range(COLS)}:
            rows = slice(self.row_edges[r], self.row_edges[r + 1])
            cols = slice(self.col_edges[c], self.col_edges[c + 1])
            mask[rows, cols] = difference[rows, cols] >= self.cfg.interest_object * self.cfg.mismatch_scale
        ys, xs = np.nonzero(mask)
        if len(xs) == 0:
            return None
        w, h = self.size
        centre = np.array([xs.mean() + 0.5 - w / 2, ys.mean() + 0.5 - h / 2]) / self.scale
        return centre, float(np.sqrt(len(xs) / np.pi)) / self.scale
