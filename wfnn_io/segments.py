"""An append-only log of records in CRC-framed segment files (the client journal and server store).

A directory holds `00000000.seg`, `00000001.seg`, ... Each record is

    length u32 | CRC-32C of the payload u32 | payload

little-endian, length >= 1 (so a zero-filled tail left by a power cut is not read as records).

Reading never changes a file: `read_records` opens segments read-only (it works on a read-only
file system and beside a live writer). A damaged record is skipped by resynchronising on the
next valid record (whose payload starts with `marker`, where the records' payloads share a
known prefix such as the protocol's magic, else at any byte), and every damaged span is
reported (`ReadReport`): in the middle of a segment it is `corrupt`; at the end of the last
segment it is a `tail` (a torn write, or a record being written right now).

Only the owner of a log, opening it to append (`SegmentLog`), repairs it: a torn tail of the
last segment is moved into `quarantine/` beside the segments (a file named after the segment
and the offset it was cut at) before the segment is truncated to its last valid record, so no
byte is ever deleted. Damage in the middle is left where it is for readers to skip.

When an append is durable is set by the fsync policy: `always` (fsync before `append` returns),
`interval` (the owner calls `sync` at most every `fsync_interval_s`, e.g. before acknowledging)
or `never` (the OS decides; survives a process crash, not a power cut).
"""

from __future__ import annotations

import contextlib
import fcntl
import itertools
import logging
import os
import stat
import struct
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from wfnn_io.persist import naming_file, sync_dir
from wfnn_io.protocol import crc32c

log = logging.getLogger(__name__)

RECORD = struct.Struct("<II")
SUFFIX = ".seg"
QUARANTINE = "quarantine"
MAX_RECORD = 64 << 20
MAX_SEGMENT_BYTES = 256 << 20
"""The largest size at which a writer starts a new segment (`SegmentLog`'s `segment_bytes`)."""
MAX_SEGMENT = MAX_SEGMENT_BYTES + 8 + MAX_RECORD
"""No segment written is longer (one record may cross `segment_bytes`): a reader takes at most
this much of one, and reports the rest as damage, rather than read a huge file whole."""
RESYNC_WORK = 8
"""Bytes a scan may checksum while looking past damage, per byte of its segment (besides
reading it once, plus two records): legitimate damage costs about one try; a file crafted with
a false record header every few bytes, each claiming a long record, took quadratic time."""
FsyncPolicy = Literal["always", "interval", "never"]


class LogError(OSError):
    """The log directory cannot be used (e.g. a record larger than the limit)."""


@dataclass(frozen=True, order=True)
class Position:
    """Where a record starts: segment number and byte offset."""

    segment: int
    offset: int


@dataclass(frozen=True)
class Damage:
    """A span of a segment that holds no valid record."""

    segment: int
    offset: int
    length: int
    kind: Literal["corrupt", "tail", "missing"]
    """`tail`: it runs to the end of the last segment (a torn write, or one in progress); `corrupt`:
    anywhere else (a segment is synced before the next one begins, so none ends torn); `missing`:
    whole segments before the last are not there, or empty (offset and length 0: what they held
    is not known)."""
    segments: int = 1
    """How many segments, from `segment` on, the span covers (`missing` ones: any number)."""


@dataclass
class ReadReport:
    """What a read met besides valid records."""

    records: int = 0
    damage: list[Damage] = field(default_factory=list)
    strays: list[str] = field(default_factory=list)
    """Files in the log's folder named like segments (`*.seg`) but not as its writer names them:
    not read (`stray_segments`)."""
    quiet: bool = False
    """Count what the read meets without logging it: a second read of logs whose first read told it."""

    @property
    def skipped_bytes(self) -> int:
        """Bytes in damaged spans."""
        return sum(d.length for d in self.damage)


@dataclass
class Recovery:
    """What opening the log (as its owner) found and did."""

    segments: int = 0
    torn_bytes_cut: int = 0
    """Bytes of a torn tail moved to quarantine and cut from the last segment."""
    quarantined: list[Path] = field(default_factory=list)
    corrupt_spans: int = 0
    """Damaged spans in the middle of segments (left in place; readers skip them)."""


def segment_name(n: int) -> str:
    """File name of segment `n`."""
    return f"{n:08d}{SUFFIX}"


MAX_SEGMENT_NUMBER = 10**12
"""Segment numbers are below this (a writer counts up from 0, one a rotation): a name beyond it,
such as a segment renamed by hand, is none of the log's (its number overflowed the client's
int64 journal index, and every start of that client failed)."""


def _segment_number(path: Path) -> int | None:
    """The segment number `path` names, or None where `segment_name` writes no such name."""
    stem = path.stem
    if not (stem.isascii() and stem.isdigit()) or len(stem) > len(str(MAX_SEGMENT_NUMBER - 1)):
        return None
    n = int(stem)
    return n if segment_name(n) == path.name else None


def stray_segments(directory: Path) -> list[str]:
    """Names in `directory` like segments' (`*.seg`) that its writer does not write: never read.

    `1.seg` beside `00000001.seg` would otherwise be read as the same segment twice; a segment
    renamed so is told (`read_records`), as what it holds is not read.
    """
    directory = Path(directory)
    if not directory.is_dir():
        return []
    return sorted(p.name for p in directory.glob(f"*{SUFFIX}") if _segment_number(p) is None)


def named_strays(strays: list[str]) -> str:
    """`stray_segments`' names for a message: the first five (escaped, cut), and how many more."""
    shown = ", ".join(ascii(n)[:80] for n in strays[:5])
    return shown + (f" and {len(strays) - 5} more" if len(strays) > 5 else "")


def segment_numbers(directory: Path) -> list[int]:
    """Segment numbers present in `directory`, in order (none if it does not exist).

    Only names as `segment_name` writes them count, below MAX_SEGMENT_NUMBER (`stray_segments`).
    """
    directory = Path(directory)
    if not directory.is_dir():
        return []
    numbers: set[int] = set()
    for _ in range(LISTINGS):
        for path in directory.glob(f"*{SUFFIX}"):
            n = _segment_number(path)
            if n is not None:
                numbers.add(n)
        if not numbers or max(numbers) - min(numbers) + 1 == len(numbers):
            break
        # A gap: a directory is listed in several reads, and a segment a writer created meanwhile
        # can move an earlier name past the reader (a reader beside a live log skipped a whole
        # segment, silently). Listed again, what is there is found; a gap that stays is a
        # segment that is not there.
    return sorted(numbers)


LISTINGS = 3
"""Listings of a log's directory at most, while segment numbers are missing between its first and last."""


def _check_segment(path: Path, owner: bool) -> None:
    """LogError unless `path` is a regular file; the owner's may not be a link either.

    Opening a FIFO named as a segment would wait forever, and the owner truncates and appends:
    through a link it would write a file outside the log.
    """
    try:
        mode = (os.lstat if owner else os.stat)(path).st_mode
    except FileNotFoundError:
        return  # gone meanwhile (or a new segment): opening it says so, or makes it
    if not stat.S_ISREG(mode):
        kind = "a link" if stat.S_ISLNK(mode) else "not a regular file"
        raise LogError(f"{path}: a segment of this log is {kind}; move it out of the log to go on")


def _record_at(data: bytes | memoryview, pos: int) -> int:
    """End of the valid record starting at `pos`, or -1 when none starts there."""
    if pos + RECORD.size > len(data):
        return -1
    length, crc = RECORD.unpack_from(data, pos)
    end = pos + RECORD.size + length
    if not 0 < length <= MAX_RECORD or end > len(data):  # a zero-filled tail is not records
        return -1
    return end if crc32c(memoryview(data)[pos + RECORD.size : end]) == crc else -1


class _Exhausted(Exception):
    """A scan has checksummed as much as it may (`RESYNC_WORK`)."""


def _record_within(data: bytes, pos: int, budget: list[int]) -> int:
    """`_record_at`, its checksum charged to `budget` (bytes left, shared by one scan)."""
    if pos + RECORD.size > len(data):
        return -1
    length = RECORD.unpack_from(data, pos)[0]
    if 0 < length <= MAX_RECORD and pos + RECORD.size + length <= len(data):
        if budget[0] < length:
            raise _Exhausted
        budget[0] -= length
    return _record_at(data, pos)


def _resync(data: bytes, pos: int, marker: bytes, budget: list[int]) -> int:
    """Start of the next valid record after a damaged one at `pos`, or len(data) when none."""
    q = pos + 1
    while q + RECORD.size < len(data):
        if marker:
            found = data.find(marker, q + RECORD.size)
            if found < 0:
                break
            q = found - RECORD.size
        if _record_within(data, q, budget) > 0:
            return q
        q += 1
    return len(data)


def scan(data: bytes, marker: bytes = b"") -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """One segment's bytes -> ([(offset, end)] of valid records, [(offset, length)] of damaged spans).

    The checksums it computes are bounded (`RESYNC_WORK`): past that, the rest is damage.
    """
    records: list[tuple[int, int]] = []
    damage: list[tuple[int, int]] = []
    budget = [(RESYNC_WORK + 1) * len(data) + 2 * MAX_RECORD]
    pos = 0
    try:
        while pos < len(data):
            end = _record_within(data, pos, budget)
            if end > 0:
                records.append((pos, end))
                pos = end
                continue
            nxt = _resync(data, pos, marker, budget)
            damage.append((pos, nxt - pos))
            pos = nxt
    except _Exhausted:
        log.warning("a segment holds more false record headers than damage leaves: its last %d bytes "
                    "are taken as damaged", len(data) - pos)  # fmt: skip
        if damage and damage[-1][0] == pos:
            damage.pop()
        damage.append((pos, len(data) - pos))
    return records, damage


def read_segment(path: Path) -> tuple[bytes, int]:
    """A segment's bytes, at most MAX_SEGMENT of them, and the file's size (more: damage)."""
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        return f.read(min(size, MAX_SEGMENT)), size


def _missing(directory: Path, start: int, n: int, report: ReadReport | None) -> None:
    """Report segments `start`..`n`-1 as missing, one span (deleted, never copied, or emptied)."""
    if report is None:  # as damage: told where reported
        return
    last = report.damage[-1] if report.damage else None
    if last is not None and last.kind == "missing" and last.segment + last.segments == start:
        report.damage[-1] = Damage(last.segment, 0, 0, "missing", segments=n - last.segment)  # one span
    else:
        report.damage.append(Damage(start, 0, 0, "missing", segments=n - start))
    if report.quiet:
        return
    log.warning("%s: %s missing: what %s held is not read", directory,
                f"segments {segment_name(start)} to {segment_name(n - 1)} are" if n - start > 1
                else f"segment {segment_name(start)} is", "they" if n - start > 1 else "it")  # fmt: skip


def read_records(
    directory: Path, start: Position | None = None, report: ReadReport | None = None, marker: bytes = b""
) -> Iterator[tuple[Position, bytes]]:
    """Every valid record of a log from `start` (default: the beginning), oldest first.

    Read-only: files are opened for reading and nothing is written, renamed or truncated.
    Damaged spans are skipped and added to `report` (with where they are and how long), and so
    are segments that are not there: a log begins at segment 0 and its writer leaves none
    missing or empty before its last (nothing else would say that what they held is not read).
    """
    directory = Path(directory)
    numbers = segment_numbers(directory)
    strays = stray_segments(directory)
    if strays:
        if report is not None:
            report.strays = strays
        if report is None or not report.quiet:
            log.warning("%s: %d files named like segments, not as this log names them, are not read: %s",
                        directory, len(strays), named_strays(strays))  # fmt: skip
    expected = 0 if start is None else start.segment
    """The segment that should come next (a start names one that was written)."""
    i = 0
    while i < len(numbers):
        n = numbers[i]
        if start is not None and n < start.segment:
            i += 1
            continue
        if n > expected:
            # Listed again: a writer rotating segments fast can move a name past a listing
            # (`segment_numbers`); what is there now is read, what is not is missing.
            found = [m for m in segment_numbers(directory) if expected <= m < n and m not in numbers]
            if found:
                numbers[i:i] = found
                continue
            _missing(directory, expected, n, report)
        expected = n + 1
        i += 1
        _check_segment(directory / segment_name(n), owner=False)
        data, size = read_segment(directory / segment_name(n))
        if size == 0 and n != numbers[-1]:
            _missing(directory, n, n + 1, report)
        records, damage = scan(data, marker)
        if size > len(data):  # longer than any segment written: read no further
            damage = [*damage, (len(data), size - len(data))]
        if report is not None:
            for offset, length in damage:
                # Only the last segment can end in a torn write: a segment is synced before the next begins.
                last = n == numbers[-1] and offset + length == size
                kind: Literal["corrupt", "tail"] = "tail" if last else "corrupt"
                report.damage.append(Damage(n, offset, length, kind))
                if not report.quiet:
                    log.warning("%s: %d damaged bytes at offset %d (%s) skipped",
                                directory / segment_name(n), length, offset, kind)  # fmt: skip
        for offset, end in records:
            if start is not None and n == start.segment and offset < start.offset:
                continue
            if report is not None:
                report.records += 1
            yield Position(n, offset), data[offset + RECORD.size : end]


@contextlib.contextmanager
def naming(path: Path) -> Iterator[None]:
    """An OSError raised inside names `path`.

    A write, flush or fsync that fails (a full disk) names no file, where the tools' one-line
    errors must say which one failed.
    """
    try:
        yield
    except OSError as exc:
        raise naming_file(exc, path) from exc


LOCK = ".lock"
"""The file a log's owner holds an exclusive lock on (`flock`), so that a second writer is refused."""


def _in_use(directory: Path) -> LogError:
    return LogError(f"{directory}: in use by another writer (a run, server or merge has it open)")


def _not_regular(directory: Path) -> LogError:
    return LogError(f"{directory / LOCK} is not a regular file: move it away to use this log")


def _open_lock(directory: Path, flags: int) -> int:
    """`directory`'s LOCK file opened without waiting -> its descriptor; LogError unless a regular file.

    A FIFO there would block the open for good, beyond the reach of SIGTERM (Python retries an
    interrupted open), and a directory or device cannot stand for the lock.
    """
    try:
        fd = os.open(directory / LOCK, flags | os.O_NONBLOCK, 0o644)
    except IsADirectoryError:  # opened for writing; for reading, fstat tells below
        raise _not_regular(directory) from None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise _not_regular(directory)
    except BaseException:
        os.close(fd)
        raise
    return fd


def take_lock(directory: Path) -> int:
    """Lock `directory`'s LOCK file for this log's lifetime -> its descriptor; LogError if held."""
    fd = _open_lock(directory, os.O_RDWR | os.O_CREAT)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise _in_use(directory) from None
    except OSError:  # a file system without locks: the one-writer rule is then the user's
        pass
    return fd


def check_free(directory: Path) -> None:
    """LogError if a writer holds the log in `directory` now (nothing is made or changed).

    For a tool that writes beside a log before opening it (a run's config.json): a second run
    on the same directory is refused before it overwrites the first one's record.
    """
    try:
        fd = _open_lock(Path(directory), os.O_RDONLY)
    except LogError:  # not a regular file (a LogError is an OSError: said, not taken for free)
        raise
    except OSError:  # no log or no lock file yet, or one that cannot be opened: nobody holds it
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        raise _in_use(directory) from None
    except OSError:
        pass
    finally:
        os.close(fd)  # closing drops the lock just taken


class SegmentLog:
    """Append records to a directory of segment files: the log's owner (one process at a time).

    The owner holds a lock on the directory's LOCK file while the log is open: two clients given
    one --out, or two servers one --data-dir, would each append its own numbers to one log, and
    one of them would be lost as duplicates. Readers take no lock.
    """

    def __init__(
        self,
        directory: Path,
        *,
        segment_bytes: int = 64 << 20,
        fsync: FsyncPolicy = "interval",
        fsync_interval_s: float = 0.02,
        marker: bytes = b"",
        lock: int | None = None,
    ) -> None:
        # `lock`: the directory's lock, where the caller took it (`take_lock`) to read and write
        # files beside the segments first; the log owns it once opened (a failed open leaves it
        # to the caller, who closes it once).
        if fsync not in ("always", "interval", "never"):
            raise ValueError(f"fsync must be always, interval or never, got {fsync!r}")
        self.directory = Path(directory)
        if lock is None:
            self.directory.mkdir(parents=True, exist_ok=True)
        self._lock = take_lock(self.directory) if lock is None else lock
        try:
            self._open(segment_bytes, fsync, fsync_interval_s, marker)
        except BaseException:
            if lock is None:
                os.close(self._lock)
            raise

    def _open(self, segment_bytes: int, fsync: FsyncPolicy, fsync_interval_s: float, marker: bytes) -> None:
        self.segment_bytes = segment_bytes
        self.fsync = fsync
        self.fsync_interval_s = fsync_interval_s
        self.marker = marker
        self.recovery = Recovery()
        self._last_sync = time.monotonic()
        self._dirty = False
        numbers = segment_numbers(self.directory)
        for n in numbers:
            _check_segment(self.directory / segment_name(n), owner=True)
        self.recovery.segments = len(numbers)
        current = numbers[-1] if numbers else 0
        if numbers:
            self._repair(current)
        self._segment = current
        self._file = open(self.directory / segment_name(current), "ab")
        self._size = self._file.tell()
        if self.fsync != "never":
            # What a writer that crashed left in the OS but never synced reads back as the log's
            # own: durable only once synced (a restarted server acknowledged it, and a power cut
            # then lost it). Every segment: one written under the `never` policy was not synced
            # before the next began. A synced one has nothing to write.
            for n in numbers[:-1]:
                fd = os.open(self.directory / segment_name(n), os.O_RDONLY)
                try:
                    os.fsync(fd)
                finally:
                    os.close(fd)
            if numbers:
                os.fsync(self._file.fileno())
            sync_dir(self.directory)

    # ------------------------------------------------------------------ opening
    def segment_numbers(self) -> list[int]:
        """Segment numbers present, in order."""
        return segment_numbers(self.directory)

    def _repair(self, n: int) -> None:
        """Move a torn tail of the last segment to quarantine and cut it off; count inner damage."""
        path = self.directory / segment_name(n)
        data, size = read_segment(path)
        records, damage = scan(data, self.marker)
        valid_end = records[-1][1] if records else 0
        self.recovery.corrupt_spans += sum(1 for offset, _ in damage if offset < valid_end)
        if valid_end == size:
            return
        cut = size - valid_end
        quarantine = self.directory / QUARANTINE
        if not quarantine.is_dir():
            quarantine.mkdir()
            sync_dir(self.directory)  # durable before the segment is cut: its tail lives in there
        kept = quarantine / f"{n:08d}-{valid_end:010d}.torn"
        for k in itertools.count(1):  # a tail torn at the same place before stays: never overwritten
            try:
                fd = os.open(kept, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
                break
            except FileExistsError:
                kept = quarantine / f"{n:08d}-{valid_end:010d}.{k}.torn"
        try:
            # In pieces (a tail may be longer than any segment), each failure naming its own file:
            # a segment that could not be read was reported as its quarantine copy, just deleted.
            with os.fdopen(fd, "wb") as f:
                with naming(path):
                    torn = open(path, "rb")  # closed below
                with torn:
                    with naming(path):
                        torn.seek(valid_end)
                    while True:
                        with naming(path):
                            piece = torn.read(1 << 20)
                        if not piece:
                            break
                        with naming(kept):
                            f.write(piece)
                with naming(kept):
                    f.flush()
                    os.fsync(f.fileno())
        except BaseException:  # a full disk: no partial copy left to pass for the tail (it is still in place)
            kept.unlink(missing_ok=True)
            raise
        sync_dir(quarantine)
        log.warning("%s: a torn tail of %d bytes at offset %d moved to %s", path, cut, valid_end, kept)
        with open(path, "r+b") as f:
            f.truncate(valid_end)
            f.flush()
            os.fsync(f.fileno())
        self.recovery.torn_bytes_cut += cut
        self.recovery.quarantined.append(kept)

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
        with naming(self.directory / segment_name(self._segment)):
            self._file.write(RECORD.pack(len(payload), crc32c(payload)) + payload)
            self._size += RECORD.size + len(payload)
            self._dirty = True
            if self.fsync == "always":
                self.sync()
            else:
                self._file.flush()  # in the OS: survives a crash of this process
        return pos

    def flush(self) -> None:
        """Hand appended records to the OS (readers in this process see them)."""
        with naming(self.directory / segment_name(self._segment)):
            self._file.flush()

    @property
    def dirty(self) -> bool:
        """Whether appended records wait for `sync`."""
        return self._dirty

    def due(self) -> bool:
        """Whether unsynced records wait and the interval policy says to sync now."""
        return self._dirty and (
            self.fsync != "interval" or time.monotonic() - self._last_sync >= self.fsync_interval_s
        )

    def sync(self) -> None:
        """Make every appended record durable (fsync unless the policy is `never`)."""
        if not self._dirty:
            return
        with naming(self.directory / segment_name(self._segment)):
            self._file.flush()
            if self.fsync != "never":
                os.fsync(self._file.fileno())
        self._dirty = False
        self._last_sync = time.monotonic()

    def _rotate(self) -> None:
        self.sync()
        # The next segment opened before this one is left: where that fails (no file handles left,
        # say), the log stays as it was, and the next append tries the same segment again (it had
        # moved on by one at each failure, leaving segments that readers rightly call missing).
        following = self._segment + 1
        _check_segment(self.directory / segment_name(following), owner=True)
        opened = open(self.directory / segment_name(following), "ab")
        self._file.close()
        self._segment, self._file, self._size = following, opened, 0
        if self.fsync != "never":  # the new file's directory entry must survive too
            sync_dir(self.directory)

    def close(self) -> None:
        """Sync and close."""
        if not self._file.closed:
            self.sync()
            self._file.close()
            os.close(self._lock)  # the lock goes with it

    def __enter__(self) -> SegmentLog:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    # ------------------------------------------------------------------ reading
    def read(self, start: Position | None = None, report: ReadReport | None = None) -> Iterator[
        tuple[Position, bytes]
    ]:  # fmt: skip
        """Every valid record from `start` (default: the beginning), oldest first (`read_records`).

        Reads what has been appended so far; safe beside the writer in the same process as long
        as the caller holds the writer's lock.
        """
        self.flush()
        return read_records(self.directory, start, report, self.marker)

    def read_at(self, position: Position) -> bytes | None:
        """The record starting at `position` (from `append` or `read`), or None if it is not valid."""
        self.flush()
        try:
            with open(self.directory / segment_name(position.segment), "rb") as f:
                f.seek(position.offset)
                head = f.read(RECORD.size)
                if len(head) < RECORD.size:
                    return None
                length, crc = RECORD.unpack(head)
                if not 0 < length <= MAX_RECORD:
                    return None
                payload = f.read(length)
        except FileNotFoundError:
            return None
        return payload if len(payload) == length and crc32c(payload) == crc else None
