"""Saving what a robot's cameras see, off the control loop.

The control loop hands a tick's camera views (already rendered, so they are of that tick) to a
bounded queue; a background thread encodes and writes them as PNG files. When the writer
falls behind, new views are dropped and counted: the tick is never held up by the disk.
"""

from __future__ import annotations

import logging
import os
import queue
import threading
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

log = logging.getLogger(__name__)

RgbImage = NDArray[np.uint8]


class FrameWriter:
    """Writes `<directory>/<tick>.png`: a tick's camera views side by side (in name order)."""

    def __init__(
        self, directory: Path, queue_size: int = 8, on_png: Callable[[int, bytes], None] | None = None
    ) -> None:
        self.directory = Path(directory)
        self.on_png = on_png
        """Also handed each tick's PNG (from the writer thread): a C/S client publishes it."""
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
            encoded, buffer = cv2.imencode(".png", cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
            png = buffer.tobytes()
            try:
                if not encoded:
                    raise OSError("PNG encoding failed")
                _write_whole(path, png)
                self.written += 1
            except OSError as exc:
                self.failed += 1
                # Once, not once a frame: a full disk fails every frame after it (the count is in
                # the run's stats, and `close` says it again).
                level = logging.WARNING if self.failed == 1 else logging.DEBUG
                log.log(level, "could not write camera frame %s: %s", path, exc)
                continue
            if self.on_png is not None:
                try:
                    self.on_png(tick, png)
                except Exception:  # a picture for people watching must never stop the robot
                    log.exception("could not publish camera frame %d", tick)

    def close(self) -> dict[str, int]:
        """Write what is queued, stop the thread; returns the counts."""
        self._queue.put(None)
        self._thread.join()
        if self.failed > 1:
            log.warning("%d camera frames could not be written (%d were)", self.failed, self.written)
        return {"written": self.written, "dropped": self.dropped, "failed": self.failed}


def _write_whole(path: Path, data: bytes) -> None:
    """Write a file whole or not at all: a write that fails (a full disk) leaves no torn picture.

    Written beside it under a hidden name, then renamed; not synced (a picture is not worth a
    disk flush a frame, and a crash leaves at worst a hidden temporary file).
    """
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        tmp.write_bytes(data)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
