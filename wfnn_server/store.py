"""The think server's durable experience store: accepted batches in a segment log.

Experiences of each client are stored once and in order of their sequence numbers, so what is
stored from a client is always the run 0..stored_through[client]: a duplicate (a re-sent
batch) is dropped, an overlap is trimmed, and a batch that leaves a gap is refused (the client
re-sends from the acknowledged point). The one exception is a gap the sender declares lost
(EXP_AFTER_LOSS: its journal lost those experiences to damage), or one met importing logs that
none of them fills: the run goes on after it, and the gap is counted and logged, so that one
damaged record never stalls a client's stream. Records are `ExperienceBatch` frames, the format of the
client journal (`wfnn_io.logs.ExperienceLog`), stored as verified at ingest (untagged).
The store has its own identity (`id`, made when it is created), which the server announces: a
server restarted under the same id with a new, empty store is known to its clients as another
store, and they re-send it everything.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from wfnn_io.logs import ExperienceLog
from wfnn_io.protocol import EXP_AFTER_LOSS, Codec, ExperienceBatch
from wfnn_io.segments import FsyncPolicy

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Admission:
    """What the store made of an offered batch: the new part (if any) and why not otherwise."""

    new: ExperienceBatch | None
    duplicate: bool = False
    gap: bool = False
    lost: int = 0
    """Experiences before `new` that are lost (a declared or accepted gap)."""


class ExperienceStore:
    """Append-only store of experience batches with per-client contiguous sequence numbers."""

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
        self._codec = Codec(server_id)
        self.stored_through: dict[str, int] = {}
        """Per client: every experience numbered <= this is stored (written; durable after `sync`)."""
        self.durable_through: dict[str, int] = {}
        """Per client: what `sync` has made durable (what may be acknowledged)."""
        self.count = 0
        """Experiences stored."""
        self.lost: dict[str, int] = {}
        """Per client: experiences of accepted gaps (lost before reaching this store)."""
        self._moved: set[str] = set()
        """Clients whose stored run grew since the last `sync`: what `due` and `sync` look at, so
        that their cost after each frame does not grow with every client ever stored."""
        self._rebuild()

    def _rebuild(self) -> None:
        """Recount what is stored per client from the log (at start)."""
        for batch in self.batches():
            admitted = self.admit(batch, allow_gap=True)  # what is stored is stored
            if admitted.new is not None:
                self._count(admitted.new)
                if admitted.lost:
                    self.lost[batch.client] = self.lost.get(batch.client, 0) + admitted.lost
        self.durable_through = dict(self.stored_through)
        self._moved.clear()

    @property
    def unreadable(self) -> int:
        """Records of the last read that were intact on disk but are not experience batches."""
        return self.log.counts.unreadable

    def batches(self) -> Iterator[ExperienceBatch]:
        """Every stored batch, oldest first (damaged records and other frames counted and skipped)."""
        for _, _, batch in self.log.entries():
            yield batch

    def admit(self, batch: ExperienceBatch, allow_gap: bool = False) -> Admission:
        """The part of `batch` that continues its client's stored run (nothing is written).

        A gap before it is accepted (as lost) with `allow_gap` or when the batch declares it.
        """
        through = self.stored_through.get(batch.client, -1)
        if batch.last_seq <= through:
            return Admission(None, duplicate=True)
        if batch.first_seq > through + 1:
            if not (allow_gap or batch.flags[0] & EXP_AFTER_LOSS):
                return Admission(None, gap=True)
            return Admission(batch, lost=batch.first_seq - through - 1)
        return Admission(batch.slice(through + 1 - batch.first_seq) if batch.first_seq <= through else batch)

    def append(self, batch: ExperienceBatch, lost: int = 0) -> None:
        """Store an admitted batch (from `admit`, with the gap it accepted before it)."""
        if batch.first_seq != self.stored_through.get(batch.client, -1) + 1 + lost:
            raise ValueError(f"batch from {batch.client} starts at {batch.first_seq}, not where its run ends")
        if lost:
            self.lost[batch.client] = self.lost.get(batch.client, 0) + lost
        self.log.append(self._codec.encode(batch))
        self._count(batch)

    def _count(self, batch: ExperienceBatch) -> None:
        self.stored_through[batch.client] = batch.last_seq
        self.count += len(batch)
        self._moved.add(batch.client)

    def due(self) -> bool:
        """Whether stored experiences wait to be made durable and acknowledged, per the fsync policy."""
        if not self._moved:
            return False
        return self.log.segments.fsync != "interval" or self.log.due()

    def sync(self) -> dict[str, int]:
        """Make everything appended durable; -> the clients whose durable point moved, and to where."""
        self.log.sync()
        moved = {
            c: self.stored_through[c]
            for c in self._moved
            if self.durable_through.get(c, -1) != self.stored_through[c]
        }
        self.durable_through.update(moved)
        self._moved.clear()
        return moved

    def close(self) -> None:
        """Sync and close the log."""
        self.log.close()
