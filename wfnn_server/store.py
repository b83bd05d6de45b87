"""The think server's durable experience store: accepted batches in a segment log.

Each experience of a client is stored once. What is stored from a client is the run
0..stored_through[client] less its `holes`, and what may be acknowledged is the part before the
first hole (`durable_through`, once synced): acks promise "everything through here".

A live batch keeps what the store lacks of it: a duplicate (a re-sent batch) is dropped, an
overlap is trimmed, a part that fills a hole is stored where the hole was, and a batch that
starts past the end of the run leaves a gap and is refused (the client re-sends from the
acknowledged point). A gap the sender declares lost (EXP_AFTER_LOSS: its journal lost those
experiences to damage) is given up: what is missing from where the batch says (`lost_from`,
else from the first) to the batch is counted as lost and the run goes on after it, so that one
damaged record never stalls a client's stream. The log does not say which experiences a
declaration gave up (a record damaged before it would be given up too, and acknowledged
unstored), so reopening takes every gap for a hole: the client is asked for what it declared
lost again, and declares it again.

Holes are gaps met in the log itself when the store is opened (a record damaged on disk after
it was acknowledged), or met importing logs that none of them fills. The experiences after a
hole are kept and learned; the acks stop before it, so the client, once it hears of this start,
re-sends the hole from its journal (or declares it lost, if its journal lacks it too).
Records are `ExperienceBatch` frames, the format of the client journal
(`wfnn_io.logs.ExperienceLog`), stored as verified at ingest (untagged); a record that fills a
hole follows records of later experiences. The store has its own identity (`id`, made when it
is created), which the server announces: a server restarted under the same id with a new, empty
store is known to its clients as another store, and they re-send it everything.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

from wfnn_io.logs import ExperienceLog, remove_empty_log
from wfnn_io.protocol import EXP_AFTER_LOSS, Codec, ExperienceBatch
from wfnn_io.segments import FsyncPolicy

log = logging.getLogger(__name__)


Hole = tuple[int, int]
"""Experiences first..last (inclusive) of a client missing from its stored run."""
ENDLESS = 1 << 62
"""The last number of the missing run after a client's stored run (beyond any real number)."""


@dataclass(frozen=True)
class Admission:
    """What the store made of an offered batch: the new part (if any) and why not otherwise."""

    new: ExperienceBatch | None
    duplicate: bool = False
    gap: bool = False
    lost: int = 0
    """Missing experiences before the batch that it declares lost (EXP_AFTER_LOSS): given up."""
    missing: int = 0
    """Missing experiences before `new` that stay missing (holes; only with `allow_gap`)."""


@dataclass(frozen=True)
class _Run:
    """A client's stored run after taking a batch: its end, holes and the experiences given up."""

    through: int
    holes: list[Hole]
    lost: int


class ExperienceStore:
    """Append-only store of experience batches: per client, a run of sequence numbers with holes."""

    def __init__(
        self,
        directory: Path,
        server_id: str,
        *,
        fsync: FsyncPolicy = "interval",
        fsync_interval_s: float = 0.02,
        segment_bytes: int = 64 << 20,
    ) -> None:
        self.log = ExperienceLog(directory, segment_bytes=segment_bytes, fsync=fsync,
                                 fsync_interval_s=fsync_interval_s)  # fmt: skip
        self.id = self.log.id
        """The store's identity (announced in acks and status)."""
        self.made = self.log.made
        """Whether opening it made its folder (a new store: `remove_if_new`)."""
        self._codec = Codec(server_id)
        self.stored_through: dict[str, int] = {}
        """Per client: its newest experience stored (those before it are stored, but for `holes`)."""
        self.holes: dict[str, list[Hole]] = {}
        """Per client: the ranges missing before stored_through, in order (none: no entry)."""
        self.durable_through: dict[str, int] = {}
        """Per client: every experience through this is stored and durable, as of the last `sync`
        (what may be acknowledged: the run before its first hole)."""
        self.count = 0
        """Experiences stored."""
        self.lost: dict[str, int] = {}
        """Per client: experiences of declared gaps (lost before reaching this store)."""
        self._missing_count = 0
        self._moved: set[str] = set()
        """Clients whose stored run changed since the last `sync`: what `due` and `sync` look at, so
        that their cost after each frame does not grow with every client ever stored."""
        self._rebuild()

    def _rebuild(self) -> None:
        """Recount what is stored per client from the log (at start); gaps in it become holes."""
        for batch in self.batches():
            for admitted in self.parts(batch, allow_gap=True):
                if admitted.new is not None:
                    self._commit(admitted.new, self._run_after(admitted.new, False, True))
        self.durable_through = {c: self._acknowledgeable(c) for c in self.stored_through}
        self._moved.clear()

    def parts(self, batch: ExperienceBatch, allow_gap: bool = False) -> Iterator[Admission]:
        """`admit` of each new part of `batch` in turn (one admission gives one contiguous part).

        A batch may reach into several holes and past the run's end. The first admission is
        always given (it may bring nothing: a duplicate or a gap); later ones only while they
        bring something. Each part must be stored (`append`) before the next is asked for.
        """
        rest = batch
        admitted = self.admit(rest, allow_gap)
        yield admitted
        while admitted.new is not None:
            after = admitted.new.last_seq + 1 - rest.first_seq
            if after >= len(rest):
                return
            # Only the first part carries the declared loss: it has been given up by now.
            rest = _undeclared(rest.slice(after))
            admitted = self.admit(rest, allow_gap)
            if admitted.new is not None:
                yield admitted

    def _missing(self, client: str) -> list[Hole]:
        """The client's missing runs in order: its holes, then everything after its stored run."""
        return [*self.holes.get(client, ()), (self.stored_through.get(client, -1) + 1, ENDLESS)]

    def _acknowledgeable(self, client: str) -> int:
        """The last experience before the client's first missing one."""
        return self._missing(client)[0][0] - 1

    @property
    def unreadable(self) -> int:
        """Records of the last read that were intact on disk but are not experience batches."""
        return self.log.counts.unreadable

    def missing(self) -> int:
        """Experiences missing in holes (all clients): what their clients are asked to re-send."""
        return self._missing_count

    def batches(self) -> Iterator[ExperienceBatch]:
        """Every stored batch in the order stored (damaged records and other frames counted and skipped)."""
        for _, _, batch in self.log.entries():
            yield batch

    def admit(self, batch: ExperienceBatch, allow_gap: bool = False) -> Admission:
        """The first part of `batch` that its client's store lacks (nothing is written).

        A batch that starts past the end of the client's stored run is a gap, refused, unless
        it declares the missing experiences before it lost (EXP_AFTER_LOSS), or with
        `allow_gap` (a log read whole: reopening, importing), where they stay missing (a hole)
        and a declaration counts for nothing. A declared loss that brings nothing new is a
        duplicate with `lost` set: `declare_lost` gives those experiences up.
        """
        f, last = batch.first_seq, batch.last_seq
        runs = self._missing(batch.client)
        declared = bool(batch.flags[0] & EXP_AFTER_LOSS) and not allow_gap  # a log's gaps are holes
        start_lost = _declared_from(batch)
        lost = _within(runs, start_lost, f - 1) if declared else 0
        reached = next(((a, b) for a, b in runs if b >= f and a <= last), None)
        if reached is None:
            return Admission(None, duplicate=True, lost=lost)
        end_of_run = runs[-1][0]
        if f > end_of_run and not ((declared and start_lost <= end_of_run) or allow_gap):
            return Admission(None, gap=True)  # a declaration from further on leaves a gap before it
        start, end = max(reached[0], f), min(reached[1], last)
        new = batch if (start, end) == (f, last) else batch.slice(start - f, end + 1 - f)
        missing = start - end_of_run if start > end_of_run and not declared else 0
        return Admission(new, lost=lost, missing=missing)

    def append(self, batch: ExperienceBatch, lost: int = 0, allow_gap: bool = False) -> None:
        """Store an admitted part (from `admit` or `parts`, with the loss it declared, `lost`).

        ValueError, with nothing written, where it holds an experience already stored, starts
        past the end of its client's run (unless it declares a loss, or `allow_gap`), or
        declares another loss than the store's.
        """
        run = self._run_after(batch, lost > 0, allow_gap)
        if run.lost != lost:
            raise ValueError(f"batch from {batch.client} declares {lost} experiences lost; the store "
                             f"lacks {run.lost} before it")  # fmt: skip
        self.log.append(self._codec.encode(batch))
        self._commit(batch, run)

    def declare_lost(self, batch: ExperienceBatch) -> int:
        """Give up what `batch` declares lost of its client's holes; -> how many experiences.

        For a declaring batch that brought nothing new. Not in the log: after a restart, they
        are asked for again (and declared lost again).
        """
        holes = self.holes.get(batch.client, [])
        start, end = _declared_from(batch), batch.first_seq - 1
        lost = _within(holes, start, end)
        if lost:
            self._set_holes(batch.client, without(holes, start, end))
            self.lost[batch.client] = self.lost.get(batch.client, 0) + lost
            self._moved.add(batch.client)
        return lost

    def _run_after(self, batch: ExperienceBatch, declared: bool, allow_gap: bool) -> _Run:
        """The client's run once `batch` is stored (nothing changed); ValueError where it does not fit."""
        client, f, last = batch.client, batch.first_seq, batch.last_seq
        through = self.stored_through.get(client, -1)
        holes = list(self.holes.get(client, ()))
        lost = 0
        if declared:  # what is missing of the declared span before the batch is given up
            start = _declared_from(batch)
            if f > through + 1 and start > through + 1:
                raise ValueError(
                    f"batch from {client} declares {start}-{f - 1} lost, its run ends at {through}"
                )
            lost = _within(holes, start, f - 1) + max(0, f - 1 - through)
            holes = without(holes, start, f - 1)
            through = max(through, f - 1)
        if f > through:
            if f > through + 1:
                if not allow_gap:
                    raise ValueError(f"batch from {client} starts at {f}, not where its run ends ({through})")
                holes.append((through + 1, f - 1))
            return _Run(last, holes, lost)
        if not any(a <= f and last <= b for a, b in holes):  # a fill lies within one hole
            raise ValueError(f"batch from {client} ({f}-{last}) holds experiences already stored")
        return _Run(through, without(holes, f, last), lost)

    def _commit(self, batch: ExperienceBatch, run: _Run) -> None:
        client = batch.client
        self.stored_through[client] = run.through
        self._set_holes(client, run.holes)
        if run.lost:
            self.lost[client] = self.lost.get(client, 0) + run.lost
        self.count += len(batch)
        self._moved.add(client)

    def _set_holes(self, client: str, holes: list[Hole]) -> None:
        # A running count: the status, in another thread, reads it while holes change.
        self._missing_count += _size(holes) - _size(self.holes.get(client, ()))
        if holes:
            self.holes[client] = holes
        else:
            self.holes.pop(client, None)

    def due(self) -> bool:
        """Whether stored experiences wait to be made durable and acknowledged, per the fsync policy."""
        if not self._moved:
            return False
        segments = self.log.segments
        # Nothing appended waits (a declared loss changes no record): syncing costs nothing, and
        # waiting for a record to make it due would hold that client's acks until another came.
        return segments.fsync != "interval" or not segments.dirty or segments.due()

    def sync(self) -> dict[str, int]:
        """Make everything appended durable; -> the clients whose durable point moved, and to where."""
        self.log.sync()
        moved = {c: self._acknowledgeable(c) for c in self._moved}
        moved = {c: through for c, through in moved.items() if self.durable_through.get(c, -1) != through}
        self.durable_through.update(moved)
        self._moved.clear()
        return moved

    def close(self) -> None:
        """Sync and close the log."""
        self.log.close()

    def remove_if_new(self, served: bool = True) -> None:
        """After `close`, for a refused start: the folder this store made goes, if still empty.

        Left as it is where it was there before, holds a record, or another server has opened it
        meanwhile (`remove_empty_log`); a failure to remove it is not what to report. A start
        refused before it served (`served` false) took no frame: what this store holds came from
        the logs it imported, which still hold it, and it goes with its records.
        """
        if self.made:
            with contextlib.suppress(OSError):
                remove_empty_log(self.log.directory, records=not served)


def _size(holes: Iterable[Hole]) -> int:
    return sum(b - a + 1 for a, b in holes)


def _declared_from(batch: ExperienceBatch) -> int:
    """The first experience a declaring batch says is lost (0: all before it, for an older sender)."""
    return batch.lost_from if batch.lost_from >= 0 else 0


def _within(runs: Iterable[Hole], start: int, end: int) -> int:
    """How many experiences of `runs` lie in start..end."""
    return sum(max(0, min(b, end) - max(a, start) + 1) for a, b in runs)


def without(holes: Iterable[Hole], start: int, end: int) -> list[Hole]:
    """`holes` less start..end."""
    out: list[Hole] = []
    for a, b in holes:
        out += [h for h in ((a, min(b, start - 1)), (max(a, end + 1), b)) if h[0] <= h[1]]
    return out


def _undeclared(batch: ExperienceBatch) -> ExperienceBatch:
    """`batch` without a declared loss on its first experience (a later part of a declaring batch)."""
    if not batch.flags[0] & EXP_AFTER_LOSS and batch.lost_from == -1:
        return batch
    flags = batch.flags.copy()
    flags[0] &= ~EXP_AFTER_LOSS & 0xFF
    return dataclasses.replace(batch, flags=flags, lost_from=-1)
