"""The client's uplink: experiences up to its think servers (see `wfnn_client.remote`).

Queued experiences become batches (sequence numbers, weights version), are journaled, then
published; acks are taken per server; what a server has not acknowledged in time (lost frames,
a restarted or late-joining server) is re-sent from the journal, and experiences damage took
from the journal are declared lost. The client's status heartbeat goes up here too.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import cast

from wfnn_client.brain import Acted, Experience, as_recorded, experience_batch
from wfnn_client.journal import Journal
from wfnn_client.link import RemoteConfig, ServerTable
from wfnn_io.bus import Bus, Channel, Inbox
from wfnn_io.protocol import (
    EXP_AFTER_LOSS,
    MAX_PRODUCED,
    Ack,
    ClientStatus,
    Codec,
    ExperienceBatch,
    Keys,
    MsgType,
    decode,
    max_frame,
    tag_verifies,
    take,
)

log = logging.getLogger(__name__)

SKIP_LOG_S = 30.0
"""Numbers skipped past what servers hold are logged at most this often (the rest counted)."""
ACK_INBOX_BYTES = 4 << 20
"""Acks received and not yet handled, at most (each is under 200 bytes)."""


@dataclass
class _Pending:
    experience: Experience
    source: str
    version: int
    t: float = field(default_factory=time.monotonic)


class Uplink:
    """Experiences up: batches, the journal, acks, re-sends and loss declarations; the status heartbeat.

    Its thread runs `run`. The tick hands it experiences with `add` (never blocks) and the bus
    hands it acks (bytes on a queue); what the servers acknowledge goes into the shared
    `ServerTable`. The status it publishes is built by `status` (the client's figures, which are
    not the uplink's alone).
    """

    def __init__(
        self, config: RemoteConfig, bus: Bus, codec: Codec, journal: Journal, spec_hash: str,
        table: ServerTable, status: Callable[[], ClientStatus], counters: Counter[str],
        rejected: Counter[str],
    ) -> None:  # fmt: skip
        self.config = config
        self.bus = bus
        self.keys = Keys(config.controller)
        self.codec = codec
        self.id = codec.sender
        self.journal = journal
        self.spec_hash = spec_hash
        self.table = table
        self._status = status
        # Shared with the downlink: the client counts its figures and rejections in one place.
        self.counters = counters
        self.rejected = rejected
        self._first_seq = journal.next_seq
        self._added = 0
        """Experiences queued by `add` (the tick's thread is the only one to change it)."""
        self._skipped = 0
        """Numbers skipped because servers already hold them (`_skip_numbers`, this thread only)."""
        self._skip_logged = -math.inf
        """When a skip was last logged (`_skip_numbers`)."""
        counters["uplink/numbers_reserved_skipped"] = journal.skipped_at_open
        self._numbering = False
        """Whether batches may be numbered yet (`_check_numbering`)."""
        self._started = 0.0
        """When `run` started (the wait for the servers' first word counts from there)."""
        self._first_heard: float | None = None
        self._pending: collections.deque[_Pending] = collections.deque()
        self._acks: Inbox[bytes] = Inbox(ACK_INBOX_BYTES)
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._sent: collections.deque[tuple[float, int]] = collections.deque()
        self._overdue = journal.next_seq - 1
        """Experiences through this number are due for re-sending to servers that lack them: at
        first everything an earlier run journaled (it may never have been acknowledged)."""

    @property
    def produced_through(self) -> int:
        """The number the newest experience queued has, or will have when it is sent."""
        return self._first_seq - 1 + self._skipped + self._added

    def experiences_through(self, server: str) -> int | None:
        """The number of the newest experience there is for `server`: queued, sent, journaled or held by it.

        Below `produced_through` only before this run's first experience, after a run that
        crashed: of the numbers it reserved and never journaled, those the server does not hold
        stand for no experience it can be sent until this run's first batch declares them lost,
        so nothing waits meanwhile for it to learn them (a lock-step restart's first sync did,
        until it timed out), while those it holds (the journal's newest records lost in a power
        cut) are still experiences. None until the servers have had their say (`_check_numbering`).
        """
        produced = self.produced_through
        if self._added or self._skipped or self.journal.last_held >= produced:
            return produced
        if not self._numbering:
            return None
        with self.table.lock:
            view = self.table.views.get(server)
            held = view.acked if view is not None else -1
        return min(produced, max(self.journal.last_held, held))

    @property
    def queued(self) -> int:
        """Experiences not yet sent."""
        return len(self._pending)

    def subscribe(self) -> None:
        """Take this client's acks (the bus's callback only hands them over)."""
        self.bus.subscribe(self.keys.ack(self.id), self._on_ack, max_frame(MsgType.ACK))

    def _on_ack(self, key: str, data: bytes) -> None:
        if not self._acks.put(data, len(data)):
            self.rejected["ack_inbox_full"] += 1  # a later ack, or a status, says as much
        self._wake.set()

    def add(self, experience: Experience, acted: Acted | None) -> None:
        """Queue an experience (never blocks)."""
        self._pending.append(_Pending(*as_recorded(experience, acted)))
        self._added += 1
        self._wake.set()

    def all_acked(self) -> bool:
        """Whether some live server has stored every experience there is for it (`experiences_through`)."""
        with self.table.lock:
            alive = [v.server for v in self.table.views.values() if v.alive]
        for server in alive:
            through = self.experiences_through(server)
            with self.table.lock:
                view = self.table.views.get(server)
                if through is not None and view is not None and view.acked >= through:
                    return True
        return False

    def stop(self) -> None:
        """Make `run` send what is queued and return."""
        self._stop.set()
        self._wake.set()

    def run(self) -> None:
        """The uplink thread: batch, journal and send; take acks; re-send; publish the status."""
        cfg = self.config
        next_status = 0.0
        self._started = time.monotonic()
        while True:
            stopping = self._stop.is_set()
            self._wake.wait(timeout=0.005)
            self._wake.clear()
            for data in self._acks.drained():
                take(data, self._take_ack, self.rejected, "ack", "ack_")
            self._check_numbering(stopping)
            while self._pending and self._numbering:
                oldest = self._pending[0].t
                if not (stopping or cfg.lockstep or len(self._pending) >= cfg.batch_max
                        or time.monotonic() - oldest >= cfg.batch_period_s):  # fmt: skip
                    break
                self._send_batch()
            self._resend()
            if self.journal.due():
                self.journal.sync()
            now = time.monotonic()
            if now >= next_status:
                self._publish_status()
                next_status = now + cfg.status_period_s
            if stopping and not self._pending:
                return

    def _check_numbering(self, stopping: bool) -> None:
        """Number batches only past what any server holds of this client.

        A journal whose newest records were lost (a power cut before its fsync, damage, or a
        new journal given an old --client-id) would number new experiences as ones the servers
        already stored, which they would drop as re-sends and acknowledge. So the first batch
        waits until the servers have had their say (a status or ack says what a server holds of
        this client): two status periods after the first word from any, so that the others'
        statuses arrive too, and at most status_timeout_s; and numbering always continues past
        the most any server says it holds. (A server heard only later, holding more, gets what
        was numbered meanwhile as lost: it is counted as `uplink/numbers_skipped`.)
        """
        now = time.monotonic()
        with self.table.lock:
            heard = any(v.heard > 0 or v.acked >= 0 for v in self.table.views.values())
            held = max((max(v.acked, v.held) for v in self.table.views.values()), default=-1)
        if self.journal.next_seq <= held < MAX_PRODUCED:  # beyond: no journal gets there (a forgery)
            self._skip_numbers(held)
        if self._numbering:
            return
        if heard and self._first_heard is None:
            self._first_heard = now
        cfg = self.config
        self._numbering = (
            stopping
            or now - self._started >= cfg.status_timeout_s
            or (self._first_heard is not None and now - self._first_heard >= 2 * cfg.status_period_s)
        )

    def _skip_numbers(self, held: int) -> None:
        """Continue numbering after `held`, which a server holds beyond this journal's numbers."""
        skipped = held + 1 - self.journal.next_seq
        now = time.monotonic()
        if now - self._skip_logged >= SKIP_LOG_S:  # again and again while another journal streams
            self._skip_logged = now
            log.error("servers hold experiences of client %s through %d, beyond this journal's %d (its "
                      "newest records were lost, or another journal had this client id): numbering continues "
                      "at %d (more are counted as uplink/numbers_skipped)", self.id, held,
                      self.journal.next_seq - 1, held + 1)  # fmt: skip
        self.journal.skip_to(held + 1)
        self._skipped += skipped
        self.counters["uplink/numbers_skipped"] += skipped

    def _send_batch(self) -> None:
        """Take up to batch_max queued experiences with one weights source; journal and publish."""
        first = self._pending[0]
        items: list[_Pending] = []
        while (
            self._pending and len(items) < self.config.batch_max and self._pending[0].source == first.source
        ):
            items.append(self._pending.popleft())
        batch = experience_batch(self.id, self.spec_hash, self.journal.next_seq, first.source,
                                 [p.experience for p in items], [p.version for p in items],
                                 self.table.journal)  # fmt: skip
        frame = self.codec.encode(batch)
        self.journal.reserve(batch.last_seq)  # durable before it is published (a server may keep it)
        self.journal.append(frame, batch.last_seq)
        self.bus.put(self.keys.experiences(self.id), frame, Channel.DATA)
        self._sent.append((time.monotonic(), batch.last_seq))
        self.counters["uplink/batches"] += 1

    def _take_ack(self, data: bytes) -> None:
        sender, ack = self.codec.decode(data, Ack)
        if ack.client != self.id or sender != ack.server:
            self.rejected["ack_misrouted"] += 1
            return
        if ack.journal and ack.journal != self.table.journal:
            # The server takes another journal under this client id (a second client given it, or
            # a recording replayed): what it stored is none of this journal's experiences.
            self.rejected["ack_other_journal"] += 1
            return
        if ack.stored_through > self.produced_through:
            # Acks answer what this client sent: beyond it is forged (a server holding more than
            # this journal, after its tail was lost, says so in its status: `_check_numbering`).
            self.rejected["ack_beyond"] += 1
            return
        with self.table.lock:
            view = self.table.view(ack.server)
            if view is None:
                self.rejected["ack_servers_full"] += 1
                return
            if not self.table.announced(view, ack.store, ack.incarnation, ack.started_ns):
                self.rejected["ack_stale"] += 1  # an earlier start's ack, replayed
                return
            view.acked = max(view.acked, ack.stored_through)

    def _resend(self) -> None:
        """Re-send from the journal to live servers missing experiences sent long enough ago."""
        cfg = self.config
        now = time.monotonic()
        while self._sent and now - self._sent[0][0] >= cfg.resend_after_s:
            self._overdue = self._sent.popleft()[1]
        with self.table.lock:  # only servers whose MAC-checked status says they are alive and of this spec
            # Not to one taking another journal of this client id: it refuses ours (and the numbers
            # up to what it holds were skipped, not lost: declared lost, they would be given up).
            views = [(v, v.store, v.acked, v.window_end, v.last_resend) for v in self.table.views.values()
                     if v.alive and v.spec_hash == self.spec_hash
                     and v.taken_journal in ("", self.table.journal)]  # fmt: skip
        for view, store, acked, window_end, last_resend in views:
            if acked >= self._overdue:
                continue
            if acked < window_end and now - last_resend < cfg.resend_after_s:
                continue
            frames, last = self.journal.frames_from(acked + 1, cfg.resend_window)
            if not frames:
                continue
            frames = [self._tagged(frame) for frame in frames]
            if not self.journal.holds(acked + 1):  # damage took them: say so, or it waits forever
                frames[0] = self._declare_loss(frames[0], view.server, acked)
            for frame in frames:
                self.bus.put(self.keys.resend(view.server, self.id), frame, Channel.DATA)
            with self.table.lock:
                # A new store announced meanwhile restarted this server's window: it is not this one.
                if view.store == store:
                    view.last_resend, view.window_end = now, last
            self.counters["uplink/resent_frames"] += len(frames)
            log.info("re-sent %d batches from experience %d to server %s", len(frames), acked + 1,
                     view.server)  # fmt: skip

    def _tagged(self, frame: bytes) -> bytes:
        """A journaled frame as this client sends now: tagged with its key, naming its journal.

        A journal written without a key, or with another, would have its re-sends refused for good;
        so would frames naming another identity than the journal's now (written before protocol 7,
        or before a damaged `log.json` gave the journal a new one), refused as another journal's.
        """
        key = self.codec.key
        batch = cast(
            ExperienceBatch, decode(frame, expect=ExperienceBatch).message
        )  # our own disk: no tag check
        if batch.journal == self.table.journal and (key is None or tag_verifies(frame, key)):
            return frame
        self.counters["uplink/retagged_frames"] += 1
        return self.codec.encode(dataclasses.replace(batch, journal=self.table.journal))

    def _declare_loss(self, frame: bytes, server: str, acked: int) -> bytes:
        """The journaled batch `frame`, re-encoded to declare the experiences after `acked` before it lost."""
        batch = cast(
            ExperienceBatch, decode(frame, expect=ExperienceBatch).message
        )  # our own disk: no tag check
        if batch.first_seq <= acked + 1:
            # It holds the experience after `acked` itself (a record overlapping a damaged one
            # before it indexes only its later part): nothing before it is lost.
            return frame
        flags = batch.flags.copy()
        flags[0] |= EXP_AFTER_LOSS
        if self.journal.skips.get(batch.first_seq - 1, acked + 2) <= acked + 1:
            # Only numbers a crashed run reserved and never journaled (the journal's numbering, read
            # at this start, with no damage there, or this start's own reservation): the expected
            # end of a crash, not damage.
            log.warning("experiences %d-%d were never journaled (numbers a run that did not close its "
                        "journal reserved, or skipped); server %s is told they are lost", acked + 1,
                        batch.first_seq - 1, server)  # fmt: skip
        else:
            log.error("experiences %d-%d are not in the journal (damaged, or numbers skipped past what "
                      "servers held or an earlier run reserved); server %s is told they are lost",
                      acked + 1, batch.first_seq - 1, server)  # fmt: skip
        self.counters["uplink/declared_lost"] += batch.first_seq - acked - 1
        # From where: a late or replayed declaration then gives up only these, never a hole the
        # server met since (after a restart) that this journal still holds.
        return self.codec.encode(dataclasses.replace(batch, flags=flags, lost_from=acked + 1))

    def _publish_status(self) -> None:
        self.bus.put(self.keys.client_status(self.id), self.codec.encode(self._status()), Channel.LATEST)
