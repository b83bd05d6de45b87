"""An append-only log of records in CRC-framed segment files (the client journal and server store).

A directory holds `00000000.seg`, `00000001.seg`, ... Each record is

    length u32 | CRC-32C of the payload u32 | payload

little-endian, length >= 1 (so a zero-filled tail left by a power cut is not read as records).
A process that dies mid-append leaves a torn record at the end of the last segment; opening the
log detects it (short or failing its CRC), cuts it off and counts the bytes. A bad record
inside an older segment is corruption, not a torn write: it is logged, counted, and reading
that segment stops there. When an append is durable is set by the fsync policy: `always` (fsync
before `append` returns), `interval` (the owner calls `sync` at most every `fsync_interval_s`,
e.g. before acknowledging) or `never` (the OS decides; survives a process crash, not a power
cut).

Both wfnn logs store protocol frames (`ExperienceBatch`), so a client journal and a server
store are the same format.
"""

from __future__ import annotations

import logging
import os
import struct
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from wfnn_common.protocol import crc32c

log = logging.getLogger(__name__)

RECORD = struct.Struct("<II")
SUFFIX = ".seg"
MAX_RECORD = 64 << 20
FsyncPolicy = Literal["always", "interval", "never"]


class LogError(OSError):
    """The log directory cannot be used (e.g. a record larger than the limit)."""


@dataclass(frozen=True)
class Position:
    """Where a record starts: segment number and byte offset."""

    segment: int
    offset: int


@dataclass
class Recovery:
    """What opening the log found."""

    segments: int = 0
    torn_bytes_cut: int = 0
    corrupt_segments: int = 0


def _segment_name(n: int) -> str:
    return f"{n:08d}{SUFFIX}"


def _scan(path: Path) -> tuple[list[tuple[int, bytes]], int, bool]:
    """Valid records of one segment file -> ([(offset, payload)], end of the valid part, clean)."""
    data = path.read_bytes()
    out: list[tuple[int, bytes]] = []
    pos = 0
    while pos < len(data):
        if pos + RECORD.size > len(data):
            return out, pos, False
        length, crc = RECORD.unpack_from(data, pos)
        end = pos + RECORD.size + length
        if not 0 < length <= MAX_RECORD or end > len(data):  # a zero-filled tail is not records
            return out, pos, False
        payload = data[pos + RECORD.size : end]
        if crc32c(payload) != crc:
            return out, pos, False
        out.append((pos, payload))
        pos = end
    return out, pos, True


class SegmentLog:
    """Append records to, and read them back from, a directory of segment files."""

    def __init__(
        self,
        directory: Path,
        *,
        segment_bytes: int = 64 << 20,
        fsync: FsyncPolicy = "interval",
        fsync_interval_s: float = 0.02,
    ) -> None:
        if fsync not in ("always", "interval", "never"):
            raise ValueError(f"fsync must be always, interval or never, got {fsync!r}")
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.segment_bytes = segment_bytes
        self.fsync = fsync
        self.fsync_interval_s = fsync_interval_s
        self.recovery = Recovery()
        self._last_sync = time.monotonic()
        self._dirty = False
        self._corrupt: set[int] = set()
        numbers = self.segment_numbers()
        self.recovery.segments = len(numbers)
        current = numbers[-1] if numbers else 0
        if numbers:
            self._cut_torn_tail(self.directory / _segment_name(current))
        self._segment = current
        self._file = open(self.directory / _segment_name(current), "ab")
        self._size = self._file.tell()

    # ------------------------------------------------------------------ opening
    def segment_numbers(self) -> list[int]:
        """Segment numbers present, in order."""
        return sorted(int(p.stem) for p in self.directory.glob(f"*{SUFFIX}") if p.stem.isdigit())

    def _cut_torn_tail(self, path: Path) -> None:
        _, valid_end, clean = _scan(path)
        if clean:
            return
        cut = path.stat().st_size - valid_end
        log.warning("%s: cutting a torn or corrupt tail of %d bytes at offset %d", path, cut, valid_end)
        with open(path, "r+b") as f:
            f.truncate(valid_end)
            f.flush()
            os.fsync(f.fileno())
        self.recovery.torn_bytes_cut += cut

    # ------------------------------------------------------------------ writing
    @property
    def position(self) -> Position:
        """Where the next record will start."""
        return Position(self._segment, self._size)

    def append(self, payload: bytes) -> Position:
        """Write one record; returns where it starts. Durable per the fsync policy."""
        if not 0 < len(payload) <= MAX_RECORD:
            raise LogError(f"a record holds 1 to {MAX_RECORD} bytes, got {len(payload)}")
        if self._size > 0 and self._size + RECORD.size + len(payload) > self.segment_bytes:
            self._rotate()
        pos = Position(self._segment, self._size)
        self._file.write(RECORD.pack(len(payload), crc32c(payload)) + payload)
        self._size += RECORD.size + len(payload)
        self._dirty = True
        if self.fsync == "always":
            self.sync()
        else:
            self._file.flush()  # in the OS: survives a crash of this process
        return pos

    def due(self) -> bool:
        """Whether unsynced records wait and the interval policy says to sync now."""
        return self._dirty and (
            self.fsync != "interval" or time.monotonic() - self._last_sync >= self.fsync_interval_s
        )

    def sync(self) -> None:
        """Make every appended record durable (fsync unless the policy is `never`)."""
        if not self._dirty:
            return
        self._file.flush()
        if self.fsync != "never":
            os.fsync(self._file.fileno())
        self._dirty = False
        self._last_sync = time.monotonic()

    def _rotate(self) -> None:
        self.sync()
        self._file.close()
        self._segment += 1
        self._file = open(self.directory / _segment_name(self._segment), "ab")
        self._size = 0
        if self.fsync != "never":  # the new file's directory entry must survive too
            fd = os.open(self.directory, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)

    def close(self) -> None:
        """Sync and close."""
        if not self._file.closed:
            self.sync()
            self._file.close()

    def __enter__(self) -> SegmentLog:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    # ------------------------------------------------------------------ reading
    def read(self, start: Position | None = None) -> Iterator[tuple[Position, bytes]]:
        """Every valid record from `start` (default: the beginning), oldest first.

        Reads what has been appended so far (flushed to the OS); safe beside a writer in the
        same process as long as the caller holds the writer's lock.
        """
        self._file.flush()
        first = start.segment if start else None
        for n in self.segment_numbers():
            if first is not None and n < first:
                continue
            path = self.directory / _segment_name(n)
            records, _, clean = _scan(path)
            for offset, payload in records:
                if start is not None and n == start.segment and offset < start.offset:
                    continue
                yield Position(n, offset), payload
            if not clean and n != self._segment and n not in self._corrupt:
                self._corrupt.add(n)
                self.recovery.corrupt_segments += 1
                log.error("%s: corrupt record; the rest of this segment is unreadable", path)
