"""The client's journal: every experience batch it produced, as sent, in a segment log.

Experiences stay here however long servers take to acknowledge them, so batches produced while
no server was reachable, or lost on the way, are re-sent from here, and a server that joins
late catches up from here. The journal continues across client restarts: the client id and the
next sequence number are recovered from it. The journal is also the run's experience record,
an experience log (`wfnn_io.logs`: the same format as a server store). A local run, which
sends nothing, records its experiences in the same format (`wfnn_client.brain.Recorder`).
"""

from __future__ import annotations

import json
import logging
import secrets
from pathlib import Path
from typing import Any

import numpy as np

from wfnn_common.config import MAX_SAVED_COUNT, LearnerConfig
from wfnn_io.logs import (
    CLIENT_JSON,
    MAX_CONTROLLERS,
    ExperienceLog,
    Task,
    client_meta,
    journal_controllers,
    journal_task,
    same_task,
    set_aside,
    task_difference,
)
from wfnn_io.persist import atomic_write_text, read_regular_text
from wfnn_io.protocol import MAX_PRODUCED, MAX_SEQ, check_id
from wfnn_io.segments import FsyncPolicy, Position

log = logging.getLogger(__name__)

RESERVE_BLOCK = 256
"""Experience numbers reserved in `client.json` at a time, ahead of those published (`reserve`)."""
ROOM = 1 << 40
"""Experience numbers a journal must have left below MAX_SEQ to take more (a year at 30 kHz): one
whose records already end nearer was numbered by something else, and batches numbered past
MAX_SEQ would be written where no reader accepts them."""


def _reserved(meta: dict[str, Any]) -> int:
    """A `client.json`'s reservation (-1 where it holds none)."""
    reserved = meta.get("reserved_through", -1)
    return reserved if isinstance(reserved, int) and 0 <= reserved < MAX_PRODUCED else -1


def check_task(directory: Path, meta: dict[str, Any], task: Task | None) -> Task | None:
    """The task a journal's `client_meta` records (None: none), refused unless it is `task` (where given).

    A record whose task cannot be read is refused too: whose experiences it holds is unknown, and
    it is neither continued nor rewritten.
    """
    try:
        recorded = journal_task(meta)
    except ValueError as exc:
        raise ValueError(f"journal {directory}: {exc}; move the journal out, or use another run "
                         "directory") from None  # fmt: skip
    if task is not None and recorded is not None and not same_task(recorded, task):
        raise ValueError(f"journal {directory} records experiences of another task "
                         f"({task_difference(recorded, task)}): one record holds one task's experiences; "
                         "use another run directory")  # fmt: skip
    return recorded


class Journal:
    """Append-only journal of encoded `ExperienceBatch` frames with an index by sequence number."""

    def __init__(
        self,
        directory: Path,
        client_id: str | None = None,
        *,
        fsync: FsyncPolicy = "interval",
        fsync_interval_s: float = 0.05,
        segment_bytes: int = 8 << 20,
        learner_config: LearnerConfig | None = None,
        controller: str | None = None,
        task: Task | None = None,
    ) -> None:
        """Open (or make) the journal in `directory`, continuing its numbering.

        `task` names what the experiences are of (a run's task and its options): a journal is
        continued only by runs of the task it records (the spec alone does not tell tasks whose
        spaces are the same apart).
        """
        directory = Path(directory)
        self.log = ExperienceLog(directory, learner_config, fsync=fsync, fsync_interval_s=fsync_interval_s,
                                 segment_bytes=segment_bytes)  # fmt: skip
        self._index = _Index()
        self.next_seq = 0
        self.last_version: dict[str, int] = {}
        """The newest weights version each source chose actions by in the journal, so that a run
        continuing it numbers on (only those below MAX_SAVED_COUNT: larger ones are no run's count)."""
        self.skips: dict[int, int] = {}
        """Gaps in the numbering that no damage explains (last -> first): numbers a run that did
        not close the journal reserved (this open's reservation included), or numbering moved past
        what servers held."""
        owner, spec = "", ""
        after: tuple[Position | None, int] = (None, 0)
        """Where the last batch read starts, and how many records reading had refused by then."""
        try:
            for pos, _, batch in self.log.entries():
                owner, spec = owner or batch.client, spec or batch.spec_hash
                if (batch.client, batch.spec_hash) != (owner, spec):
                    # One client's, of one spec: a record of another run copied in would be sent,
                    # and numbered on from, as this client's.
                    raise ValueError(
                        f"journal {directory}: the record at segment {pos.segment}, offset {pos.offset} "
                        f"holds experiences of client {batch.client!r}, learner spec {batch.spec_hash}, "
                        f"where the journal's first is client {owner!r}'s, spec {spec} (a segment of "
                        "another run?): move it out, or use another record directory"
                    )
                if batch.first_seq > self.next_seq and not self._damaged_since(*after, pos):
                    # Logged at every start, among real damage, in its words: a long-lived robot's
                    # log grew a line per crash, and an operator could not tell a loss from them.
                    self.skips[batch.first_seq - 1] = self.next_seq
                elif batch.first_seq > self.next_seq:
                    missing = (self.next_seq, batch.first_seq - 1)
                    log.error("journal batch at %s starts at %d, expected %d (experiences %d-%d missing: "
                              "damaged, or numbers skipped past what servers held or an earlier run "
                              "reserved)",
                              pos, batch.first_seq, self.next_seq, *missing)  # fmt: skip
                elif batch.first_seq < self.next_seq:
                    log.error("journal batch at %s holds experiences %d-%d, of which those through %d are "
                              "journaled before it: only what follows them is kept",
                              pos, batch.first_seq, batch.last_seq, self.next_seq - 1)  # fmt: skip
                counted = batch.weights_version[batch.weights_version < MAX_SAVED_COUNT]
                if len(counted):
                    newest = int(counted.max())
                    source = batch.weights_source
                    self.last_version[source] = max(self.last_version.get(source, newest), newest)
                if batch.last_seq >= self.next_seq:
                    self._add(max(batch.first_seq, self.next_seq), batch.last_seq, pos)
                after = (pos, self.log.counts.unreadable)
            # A client.json that cannot be read is set aside (`_client_id`): what task the records
            # are of is then unknown, and this run's is not written as theirs.
            unknown = owner != "" and (directory / CLIENT_JSON).exists() and not client_meta(directory)
            self.client_id: str = self._client_id(directory, client_id, owner)
            meta = client_meta(directory)  # as _client_id left it (an unreadable one set aside)
            recorded = check_task(directory, meta, task)
            self.task = recorded if recorded is not None or unknown else task
            """The task its experiences are of (None: not said, by a journal from before it was)."""
            if unknown and task is not None:
                log.warning("journal %s: the task of its experiences is unknown (its %s could not be "
                            "read); it goes on without one recorded", directory, CLIENT_JSON)  # fmt: skip
            self.controllers = journal_controllers(meta)
            """The controllers its frames were tagged for, by this run and earlier ones (recorded, so
            that a reader with the key checks them with those controllers' keys: `logs.read_entries`)."""
            self.reserved_through = _reserved(meta)
            """Numbers through this may have been published (`reserve`); -1: none beyond the journal."""
            closed = meta.get("closed") is True
            if controller is not None and controller not in self.controllers:
                self.controllers = [*self.controllers, controller][-MAX_CONTROLLERS:]
                self._write_meta(self.reserved_through, closed=closed)
            elif recorded is None and self.task is not None:  # recorded now, not at its next write
                self._write_meta(self.reserved_through, closed=closed)
        except BaseException:
            self.log.close()
            raise
        if self.skips:
            skipped = sum(last - first + 1 for last, first in self.skips.items())
            log.info("journal %s: %d gaps in its numbering (%d numbers) that runs which did not close it "
                     "reserved, or numbering past what servers held, left (not damage)", directory,
                     len(self.skips), skipped)  # fmt: skip
        self.skipped_at_open = 0
        """Numbers skipped at this open because an earlier run reserved them (`reserve`)."""
        if self.reserved_through >= self.next_seq:
            # Numbers an earlier run reserved may have been published, and the journal's newest
            # records lost (a power cut before their fsync): new experiences must not reuse them.
            self.skipped_at_open = self.reserved_through + 1 - self.next_seq
            if not closed:
                log.warning("journal %s was not closed by its last run: numbering continues after the "
                            "numbers it reserved, at %d (%d-%d, published or not, are not in the "
                            "journal)", directory, self.reserved_through + 1, self.next_seq,
                            self.reserved_through)  # fmt: skip
            # A gap as those read above (`skips`): a server that lacks them is told of a crash's end.
            self.skips[self.reserved_through] = self.next_seq
            self.skip_to(self.reserved_through + 1)
        if self.next_seq > MAX_SEQ - ROOM:
            self.log.close()
            raise ValueError(
                f"journal {directory} continues at experience {self.next_seq}, too near the last "
                f"number a batch may have ({MAX_SEQ}): use another record directory"
            )
        if self.next_seq:
            log.info("journal %s: client %s continues at experience %d", directory, self.client_id,
                     self.next_seq)  # fmt: skip

    def _damaged_since(self, before: Position | None, refused: int, pos: Position) -> bool:
        """Whether reading met damage (or refused a record) after the batch at `before`, up to `pos`."""
        if self.log.counts.unreadable > refused:
            return True
        start = (-1, -1) if before is None else (before.segment, before.offset)
        return any(start < (d.segment, d.offset) < (pos.segment, pos.offset) for d in self.log.counts.damage)

    @staticmethod
    def _client_id(directory: Path, asked: str | None, owner: str) -> str:
        """The journal's client id: client.json's (or, where that is unreadable, its batches')."""
        meta = directory / CLIENT_JSON
        stored = ""
        if meta.exists():
            try:
                stored = check_id(json.loads(read_regular_text(meta))["client"], "client id")
            except (OSError, ValueError, KeyError, TypeError, RecursionError) as exc:
                set_aside(meta, f"unreadable ({exc})")
        if stored and owner and stored != owner:
            raise ValueError(
                f"journal {directory}: its {CLIENT_JSON} names client {stored!r}, its records client "
                f"{owner!r}: move one of them out, or use another record directory"
            )
        stored = stored or owner
        if stored and asked is not None and asked != stored:
            raise ValueError(
                f"journal {directory} belongs to client {stored!r}, not {asked!r}; "
                "use another record directory or the same client id"
            )
        client_id = stored or check_id(asked or f"c{secrets.token_hex(4)}", "client id")
        if not meta.exists():
            atomic_write_text(meta, json.dumps({"client": client_id}))
        return client_id

    def _write_meta(self, reserved_through: int, closed: bool) -> None:
        meta: dict[str, object] = {"client": self.client_id, "reserved_through": reserved_through,
                                   "closed": closed}  # fmt: skip
        if self.controllers:
            meta["controllers"] = self.controllers
        if self.task is not None:
            meta["task"] = self.task
        atomic_write_text(self.log.directory / CLIENT_JSON, json.dumps(meta))
        self.reserved_through = reserved_through

    def reserve(self, through: int) -> None:
        """Make durable, before experience `through` is published, that numbers up to it are used.

        The journal is synced only now and then (its fsync policy), so a power cut can lose
        records that servers already hold; a restart then continues past the reservation instead
        of numbering new experiences as ones the servers would drop as re-sends. Numbers are
        reserved RESERVE_BLOCK ahead (one write per block) and released by `close`.
        """
        if through > self.reserved_through:
            self._write_meta(through + RESERVE_BLOCK, closed=False)

    def _add(self, first_seq: int, last_seq: int, pos: Position) -> None:
        self._index.append(first_seq, last_seq, pos)
        self.next_seq = last_seq + 1

    def append(self, frame: bytes, last_seq: int) -> None:
        """Journal one encoded batch whose last experience is `last_seq` (it continues the journal)."""
        self._add(self.next_seq, last_seq, self.log.append(frame))

    def skip_to(self, seq: int) -> None:
        """Number the next batch from `seq` (the numbers before it, not journaled, are not held)."""
        self.next_seq = max(self.next_seq, seq)

    @property
    def last_held(self) -> int:
        """The newest experience the journal holds (-1: none)."""
        return self._index.last_held()

    def holds(self, seq: int) -> bool:
        """Whether experience `seq` is in the journal (False in a gap that damage left)."""
        i = self._index.find(seq)
        return i < len(self._index) and self._index.first(i) <= seq

    def frames_from(self, seq: int, max_frames: int) -> tuple[list[bytes], int]:
        """Up to `max_frames` journaled frames, from the one holding experience `seq`.

        Returns the frames and the last experience they hold (-1 when there are none).
        """
        index = self._index
        j = index.find(seq)
        out: list[bytes] = []
        last = -1
        while j < len(index) and len(out) < max_frames:
            frame = self.log.frame_at(index.where(j))
            if frame is None:
                # Damaged since it was indexed (counted by the reader): no longer held, so that a
                # re-send from it declares its experiences lost instead of waiting for them forever.
                log.error("journal record at %s (experiences %d-%d) is no longer readable", index.where(j),
                          index.first(j), index.last(j))  # fmt: skip
                index.delete(j)
                if out:  # the frames sent stop at the gap: the next re-send declares it
                    break
                continue
            out.append(frame)
            last = index.last(j)
            j += 1
        return out, last

    def sync(self) -> None:
        """Make the journal durable (per its fsync policy)."""
        self.log.sync()

    def due(self) -> bool:
        """Whether journaled frames wait for `sync`."""
        return self.log.due()

    def close(self) -> None:
        """Sync and close; release the numbers reserved beyond the journal.

        The release is written while the journal's lock is still held: written after it, a
        client started on the same folder in between read the reservation as a crash's, declared
        the reserved numbers lost, and then had its own client.json overwritten by this one.
        """
        try:
            self.log.sync()  # the records first: "closed" must never describe a journal not on disk
            if self.reserved_through >= 0:  # numbering goes on after next_seq - 1, as servers were told
                self._write_meta(self.next_seq - 1, closed=True)
        finally:
            self.log.close()


class _Index:
    """Each journaled batch's first and last experience and where its record starts, in order.

    In arrays, 32 bytes a batch (and room to grow): as Python lists of ints and `Position`s it
    took about 230, and a client journals a batch per tick at up to 100 Hz (`batch_period_s`),
    so a day's run at 50 Hz held about 1 GB of index. It covers the whole journal: a server
    that joins late catches up from its start.
    """

    def __init__(self) -> None:
        self._rows = np.zeros((4, 1024), dtype=np.int64)
        """first, last, segment and offset (rows) of each batch (columns), the first `_n` in use."""
        self._n = 0

    def __len__(self) -> int:
        return self._n

    def append(self, first_seq: int, last_seq: int, pos: Position) -> None:
        if self._n == self._rows.shape[1]:
            grown = np.zeros((4, 2 * self._n), dtype=np.int64)
            grown[:, : self._n] = self._rows
            self._rows = grown
        self._rows[:, self._n] = (first_seq, last_seq, pos.segment, pos.offset)
        self._n += 1

    def find(self, seq: int) -> int:
        """The first batch whose last experience is at or after `seq` (`len` where none is)."""
        return int(np.searchsorted(self._rows[1, : self._n], seq, side="left"))

    def first(self, j: int) -> int:
        return int(self._rows[0, j])

    def last(self, j: int) -> int:
        return int(self._rows[1, j])

    def last_held(self) -> int:
        """The last experience of the last batch (-1: none)."""
        return int(self._rows[1, self._n - 1]) if self._n else -1

    def where(self, j: int) -> Position:
        return Position(int(self._rows[2, j]), int(self._rows[3, j]))

    def delete(self, j: int) -> None:
        """Forget batch `j` (its record is damaged)."""
        self._rows[:, j : self._n - 1] = self._rows[:, j + 1 : self._n]
        self._n -= 1
