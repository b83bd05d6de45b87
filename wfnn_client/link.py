"""What the two halves of the client's link to its think servers share (`wfnn_client.remote`).

The uplink (`wfnn_client.uplink`: experiences up) and the downlink (`wfnn_client.downlink`:
weights down) each own their thread, their inboxes and their state. Besides the bus, this
client's codec and its counters, they share the settings (`RemoteConfig`) and one table of what
is known of each server (`ServerTable`), read and written under its lock.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from wfnn_common.config import check_fields
from wfnn_common.learners import Weights as NetworkWeights
from wfnn_io.protocol import check_id
from wfnn_io.segments import FsyncPolicy

log = logging.getLogger(__name__)

T = TypeVar("T")


@dataclass(frozen=True, kw_only=True)
class RemoteConfig:
    """How the client reaches its think servers."""

    controller: str = "default"
    client_id: str | None = None
    """Client id (default: the journal's, or a new random one)."""
    journal_dir: Path = Path("runs/latest/journal")
    task: dict[str, Any] | None = None
    """What the experiences are of (`Journal`'s task): a journal of another task is not continued."""
    key_file: Path | None = None
    follow: str | None = None
    """Pin this server id; None follows the longest-alive healthy server."""
    batch_max: int = 256
    """Experiences per batch at most."""
    batch_period_s: float = 0.01
    """A batch waits at most this long for more experiences (lock-step: not at all)."""
    resend_after_s: float = 1.0
    """A server that has not acknowledged an experience this long after it was sent is sent it
    again from the journal (also how a restarted or late server catches up)."""
    resend_window: int = 64
    """Frames per re-send round (the next round starts when they are acknowledged)."""
    snapshot_timeout_s: float = 1.5
    """A followed server with no valid snapshot for this long is unhealthy (a silent peer); no
    new weights applied for this long is logged and counted as a stretch without weights."""
    status_timeout_s: float = 2.0
    """A server whose status has not arrived for this long is no longer alive."""
    diverged_hold_s: float = 10.0
    """How long a server whose weights diverged here is passed over."""
    status_period_s: float = 0.5
    query_timeout_s: float = 0.5
    """Deadline of the query for a server's newest weights when it appears."""
    journal_fsync: FsyncPolicy = "interval"
    lockstep: bool = False

    def __post_init__(self) -> None:
        check_fields(self)
        check_id(self.controller, "controller name")
        for name in ("batch_period_s", "resend_after_s", "snapshot_timeout_s", "status_timeout_s",
                     "diverged_hold_s", "status_period_s", "query_timeout_s"):  # fmt: skip
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.batch_max < 1 or self.resend_window < 1:
            raise ValueError("batch_max and resend_window must be >= 1")
        if self.client_id is not None:
            check_id(self.client_id, "client id")
        if self.follow is not None:
            check_id(self.follow, "server id")


@dataclass
class Weights:
    """A validated snapshot ready for `act`."""

    params: NetworkWeights
    server: str
    incarnation: int
    store: str
    version: int
    published_ns: int
    diverged: bool
    learned_through: dict[str, int]
    received: float
    """time.monotonic() at arrival."""

    @property
    def source(self) -> str:
        """`server:incarnation`, as carried by experiences."""
        return f"{self.server}:{self.incarnation}"


@dataclass
class ServerView:
    """What this client knows of one server."""

    server: str
    alive: bool = False
    """Its MAC-checked status arrived within status_timeout_s, and no token vanished since."""
    heard: float = 0.0
    """time.monotonic() of its latest valid status (0: never)."""
    gone: bool = False
    """Its liveliness token disappeared after its latest status."""
    started_ns: int = 0
    born: float = math.inf
    """When its announced start began, as time.monotonic() here: the earliest of now - its uptime
    over its statuses (each estimate late by its status's delay). Its `started_ns` is its own wall
    clock's, which may be set back or differ from this host's: where the two disagree, this says
    how long it has been alive (`downlink._start_key`)."""
    spec_hash: str = ""
    learner_config: str = ""
    """The learner config it announces that it learns with (JSON), overrides applied."""
    store: str = ""
    """Its store's identity, as announced (status and acks)."""
    incarnation: int = 0
    asked: bool = False
    """The query for its newest weights was sent (once per announced store and incarnation)."""
    acked: int = -1
    """Every experience numbered <= this is stored in its store (of this client's journal's)."""
    held: int = -1
    """The newest experience of this client id its status says it stores, of whichever journal:
    numbering goes past it (`Uplink._check_numbering`), though another journal's are none of ours."""
    taken_journal: str = ""
    """The journal of this client id its latest status says it takes now ("": none streaming). While
    it is another's, this client's experiences are refused there: none is re-sent to it."""
    other_journal: str = ""
    """The last other journal of this client id said to be taken (logged once each)."""
    latest: Weights | None = None
    suspect_until: float = 0.0
    metrics: dict[str, float] = field(default_factory=dict)
    """Figures from its latest status."""
    window_end: int = -1
    """Last experience of the current re-send round."""
    last_resend: float = 0.0
    status_seq: int = -1
    snapshot_seq: int = -1
    """The highest frame numbers (the header's seq, which the MAC covers) of the statuses and the
    snapshots taken from its announced start; with a key, one numbered at or below is a replay."""


MAX_SERVERS = 32
"""Servers a client keeps a view of at once (`ServerTable.view`)."""


class ServerTable:
    """What this client knows of each server: one table, under one lock, for both halves of the link.

    The halves share it because each hears half of what a server is. The downlink learns from its
    MAC-checked statuses whether it is alive, of this spec, and which store and incarnation it
    is; the uplink learns from its acks what it has stored. The uplink re-sends only to servers
    the downlink found alive and of this spec, and a new store announced in a status or an ack
    restarts what was acknowledged and which snapshots may be followed (`announced`).
    """

    def __init__(self, keyed: bool = False, journal: str = "") -> None:
        self.lock = threading.Lock()
        self.journal = journal
        """This client's journal's identity: acks and statuses of another journal under this client
        id tell nothing of what is stored of ours."""
        self.views: dict[str, ServerView] = {}
        """Per server id; its views are read and changed under `lock`."""
        self.keyed = keyed
        """Whether frames carry MAC tags (then a frame is the server's own, or a recording of one)."""
        self._refused_logged: set[tuple[str, str]] = set()
        """(server, store) pairs whose refusal was logged (bounded: ids are forgeable)."""

    def view(self, server: str) -> ServerView | None:
        """Its view, made at the first word from it (caller holds the lock); None while the table is full.

        At most MAX_SERVERS views: a new server takes the place of the one heard least recently
        among those not alive, and is not taken while every one is alive. Without a key anyone can
        announce servers, and each view costs memory and, alive, re-sends from the journal.
        """
        view = self.views.get(server)
        if view is not None:
            return view
        if len(self.views) >= MAX_SERVERS:
            idle = [v for v in self.views.values() if not v.alive]
            if not idle:
                return None
            oldest = min(idle, key=lambda v: v.heard)
            del self.views[oldest.server]
            log.info(
                "server %s forgotten: %d servers known, and %s is new", oldest.server, MAX_SERVERS, server
            )
        view = self.views[server] = ServerView(server)
        return view

    def any_alive(self) -> bool:
        """Whether some server is alive now."""
        with self.lock:
            return any(v.alive for v in self.views.values())

    def announced(self, view: ServerView, store: str, incarnation: int, started_ns: int) -> bool:
        """A server says which store, incarnation and start it is (caller holds the lock); take it?

        Another store than before (a server restarted with a new data directory, or the first
        word from it) holds what it says it holds, whatever was acknowledged before: the
        acknowledged point restarts, so the journal re-sends it everything it lacks. Another
        start of the same store (another incarnation or `started_ns`: a data directory restored
        from a backup counts its incarnations again, and a server's clock may be set back) holds
        what it now says too, which may be less than before. Another store or start also restarts
        the order of its snapshots: weights of one that is no longer announced are not followed.

        A message of an earlier start of the store announced now is refused (False): a recorded
        frame replayed, which a MAC does not tell from a fresh one. While that server is alive, a
        lower incarnation or an earlier start is earlier (a higher incarnation that started before
        the one announced now was lost with a disk and is replayed after a backup was restored:
        taken, it shut the live server out); once it is silent, with a key, only a start earlier by
        both (a lower or equal incarnation that started before), so that a restored backup (a lower
        incarnation started later) and a start after the server's clock was set back (a higher
        incarnation started "before") are still taken; without a key, none: one forged start later
        by both would otherwise shut the real server (and its restarts) out for good.
        Another store: with a key, refused unless it started later than the start announced now
        (a server restarted on another data directory starts after the start it replaces; one
        started before is a frame of an earlier store, replayed, which would drive the robot with
        that store's weights), so a server restarted on another data directory after its clock was
        set back is not followed until this client restarts (counted as `status_stale`, logged
        once). Without a key, where any frame can be forged and a forged start "later" than every
        real one would shut the real server out for good, it is refused only while the server is
        alive.
        """
        if store == view.store:
            if view.alive:  # a higher incarnation that started before: a lost one, replayed after a restore
                earlier = incarnation < view.incarnation or started_ns < view.started_ns
            else:
                earlier = self.keyed and incarnation <= view.incarnation and started_ns < view.started_ns
            if earlier:
                return False
            if (incarnation, started_ns) == (view.incarnation, view.started_ns):
                return True
            log.info("server %s restarted (incarnation %d): re-sending what it lacks", view.server,
                     incarnation)  # fmt: skip
        elif view.store and started_ns <= view.started_ns and (self.keyed or view.alive):
            if len(self._refused_logged) < MAX_SERVERS and (view.server, store) not in self._refused_logged:
                self._refused_logged.add((view.server, store))
                log.warning("server %s announces store %s, which started before the store %s it announced "
                            "since: refused (a recording replayed, or a restart after its clock was set "
                            "back: then restart this client)", view.server, store, view.store)  # fmt: skip
            return False
        elif view.store:
            log.warning("server %s now has store %s (was %s): re-sending what it lacks", view.server,
                        store, view.store)  # fmt: skip
        view.acked, view.held, view.window_end, view.last_resend = -1, -1, -1, 0.0
        view.taken_journal = ""
        view.store, view.incarnation, view.started_ns = store, incarnation, started_ns
        view.born = math.inf  # the new start's age is told by its own statuses
        view.latest, view.asked = None, False
        view.status_seq, view.snapshot_seq = -1, -1
        return True


def drained(inbox: queue.SimpleQueue[T]) -> Iterator[T]:
    """What `inbox` holds, taken one by one without waiting, until it is empty."""
    while True:
        try:
            yield inbox.get_nowait()
        except queue.Empty:
            return
