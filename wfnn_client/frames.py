"""Saving what a robot's cameras see, off the control loop.

The control loop hands a tick's camera views (already rendered, so they are of that tick) to a
bounded queue; a background thread encodes and writes them as PNG files. When the writer
falls behind, new views are dropped and counted: the tick is never held up by the disk.
"""

from __future__ import annotations

import logging
import queue
import threading
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

log = logging.getLogger(__name__)

RgbImage = NDArray[np.uint8]


class FrameWriter:
    """Writes `<directory>/<tick>.png`: a tick's camera views side by side (in name order)."""

    def __init__(self, directory: Path, queue_size: int = 8) -> None:
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.written = 0
        self.dropped = 0
        self.failed = 0
        self._queue: queue.Queue[tuple[int, dict[str, RgbImage]] | None] = queue.Queue(maxsize=queue_size)
        self._thread = threading.Thread(target=self._write_all, name="frame-writer", daemon=True)
        self._thread.start()

    def submit(self, tick: int, views: dict[str, RgbImage]) -> bool:
        """Queue one tick's views; False (and counted) when the writer is behind."""
        try:
            self._queue.put_nowait((tick, views))
        except queue.Full:
            self.dropped += 1
            return False
        return True

    def _write_all(self) -> None:
        while (item := self._queue.get()) is not None:
            tick, views = item
            image = np.concatenate([views[name] for name in sorted(views)], axis=1)
            path = self.directory / f"{tick:07d}.png"
            # cv2 encodes without the GIL, so the control loop keeps running meanwhile.
            if cv2.imwrite(str(path), cv2.cvtColor(image, cv2.COLOR_RGB2BGR)):
                self.written += 1
            else:
                self.failed += 1
                log.warning("could not write camera frame %s", path)

    def close(self) -> dict[str, int]:
        """Write what is queued, stop the thread; returns the counts."""
        self._queue.put(None)
        self._thread.join()
        return {"written": self.written, "dropped": self.dropped, "failed": self.failed}
