"""The client's downlink: weight snapshots down from its think servers (see `wfnn_client.remote`).

    statuses (CRC/MAC) say which servers are alive and which store and incarnation each one
    is; snapshots (CRC/MAC, spec, shape, finite, of the announced store and incarnation,
    version newer than the last) per server; follow one server and fail over when it is gone,
    silent or diverged; swap the weights `act` uses in one reference assignment

With a key, a status or snapshot numbered (the frame header's seq, which the MAC covers) at or
below one taken from the same start of its server is a recorded frame replayed, and is refused:
otherwise an old status could drop the newest weights as unconfirmed, or mark a dead server alive.

Liveliness tokens and queries are not authenticated, so neither decides anything alone: a
server is alive while its MAC-checked status arrives (a token that disappears marks it gone
until its next status), and the query for a server's newest weights never waits.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections import Counter
from typing import Any, cast

import numpy as np

from wfnn_client.link import MAX_SERVERS, RemoteConfig, ServerTable, ServerView, Weights, drained
from wfnn_common.config import LearnerConfig, parse_json
from wfnn_common.learners import Weights as NetworkWeights
from wfnn_common.learners import n_params, ready_to_act, weights_from_flat
from wfnn_io.bus import Bus, Inbox
from wfnn_io.protocol import (
    MAX_PRODUCED,
    Codec,
    Keys,
    MsgType,
    ProtocolError,
    ServerStatus,
    WeightSnapshot,
    check_frame,
    count_rejected,
    decode,
    max_frame,
    older_peer,
    take,
)

log = logging.getLogger(__name__)

STATUS_INBOX_BYTES = 16 << 20
"""Server statuses received and not yet handled, at most (each is at most a few hundred KB)."""


def max_snapshot_bytes(config: LearnerConfig) -> int:
    """The largest weights frame of this learner: its parameters, and room for the rest."""
    return max_frame(MsgType.WEIGHTS, 8 * n_params(config) + (64 << 10))


def largest_message(config: LearnerConfig) -> int:
    """The largest message a client of this learner receives (a snapshot, or a status)."""
    return max(max_snapshot_bytes(config), max_frame(MsgType.SERVER_STATUS))


class Downlink:
    """Weights down: server presence and statuses, snapshots, which server to follow, the weights `act` uses.

    Its thread runs `run`. The bus hands it statuses, presence changes and snapshots (bytes on
    queues, the newest snapshot per server); what statuses say goes into the shared
    `ServerTable`. `current` is replaced by one reference assignment, and `learned` is notified
    each time.
    """

    def __init__(
        self, learner_config: LearnerConfig, config: RemoteConfig, bus: Bus, codec: Codec, table: ServerTable,
        counters: Counter[str], rejected: Counter[str], initial: NetworkWeights | None = None,
    ) -> None:  # fmt: skip
        self.learner_config = learner_config
        self.config = config
        self.bus = bus
        self.keys = Keys(config.controller)
        self.codec = codec
        self.id = codec.sender
        self._older: set[str] = set()
        """Servers told to speak an older protocol version (`older_peer`)."""
        self.spec_hash = learner_config.spec_hash()
        self._config_json = learner_config.to_json()
        self._n_params = n_params(learner_config)
        self.max_snapshot_bytes = max_snapshot_bytes(learner_config)
        """No larger weights frame is copied."""
        self.table = table
        # Shared with the uplink: the client counts its figures and rejections in one place.
        self.counters = counters
        self.rejected = rejected
        self._statuses: Inbox[bytes] = Inbox(STATUS_INBOX_BYTES)
        self._presence: queue.SimpleQueue[tuple[str, bool]] = queue.SimpleQueue()
        self._snapshots: dict[str, tuple[int, bytes]] = {}
        """The highest-numbered unprocessed snapshot frame per server, with its number."""
        self._lower: dict[str, bytes] = {}
        """The latest unprocessed one numbered below it, per server (with a key): a recording
        replayed, or the first of a start that restarted its numbers; read before it."""
        self._wake = threading.Event()
        self._stop = threading.Event()
        self.current: Weights | None = None
        """The weights `act` uses; replaced by one reference assignment."""
        if initial is not None:  # saved weights drive the robot until a server's snapshot arrives
            self.current = Weights(initial, "file", 0, "", 0, time.time_ns(), False, {}, time.monotonic())
        self.following = ""
        """The server whose snapshots `act` uses ("" before the first)."""
        self.connected = False
        """Whether a healthy server is followed (False before the first and during outages)."""
        self.learned = threading.Condition()
        """Notified each time weights are applied."""
        self.apply_latency_ms: list[float] = []
        self.applied: list[tuple[float, str, int, int]] = []
        """(Unix time, server, version, this client's experiences learned through) of each snapshot
        applied, for timelines of faults."""
        self.failovers: list[dict[str, Any]] = []
        self.learned_with: dict[str, str] = {}
        """Per server whose snapshots drove the robot: the learner config it learned with (JSON),
        which is not this client's where the server adopted another's or overrides fields."""
        self._config_warned: set[tuple[str, str]] = set()
        self.other_specs: dict[str, str] = {}
        """The spec of each server heard learning for another, said once each (this and
        `_config_warned` bounded: ids are forgeable)."""
        self._lost_at: float | None = None
        self._newer_told = False
        """Whether this outage's move to a diverged server's newer weights was told (`_choose`)."""
        self._applied_at: float | None = None
        """time.monotonic() when weights were last applied (None before the first)."""
        self._weightless_since: float | None = None
        self._started = time.monotonic()
        self._told_unheard = False
        self.longest_without_weights_s = 0.0
        """The longest stretch without newly applied weights after the first (a stretch still
        open counted as far as it has gone)."""

    def subscribe(self) -> None:
        """Take server statuses, snapshots and presence (the bus's callbacks only hand them over)."""
        bus, keys = self.bus, self.keys
        bus.subscribe(keys.server_status(), self._on_status, max_frame(MsgType.SERVER_STATUS))
        bus.subscribe(keys.weights(), self._on_snapshot, self.max_snapshot_bytes)
        bus.watch_presence(keys.server_alive(), self._on_presence)

    def _on_status(self, key: str, data: bytes) -> None:
        try:  # checked before it is queued: a flood of junk (with a key: frames failing the tag)
            sender, _ = check_frame(data, self.codec.key, ServerStatus)  # pushed genuine statuses out
        except ProtocolError as exc:
            count_rejected(exc, data, self.rejected, "server status", "status_")
            return
        if sender != Keys.last(key):
            self.rejected["status_misrouted"] += 1
            return
        if not self._statuses.put(data, len(data)):
            self.rejected["status_inbox_full"] += 1
        self._wake.set()

    def _on_presence(self, key: str, alive: bool) -> None:
        self._presence.put((Keys.last(key), alive))
        self._wake.set()

    def _on_snapshot(self, key: str, data: bytes) -> None:
        server = Keys.last(key)
        try:  # one frame per server waits to be decoded: junk must not push out a genuine snapshot
            sender, seq = check_frame(data, self.codec.key, WeightSnapshot)
        except ProtocolError as exc:  # told as every other frame's refusal is (`take`)
            count_rejected(exc, data, self.rejected, "weight snapshot")
            return
        if sender != server:
            self.rejected["misrouted"] += 1
            return
        waiting = self._snapshots.get(server)
        if self.codec.key is not None and waiting is not None and waiting[0] > seq:
            # With a key the number is the server's own: a lower one (a recording replayed, or the
            # first of the server's next start) must not push out the higher one waiting, nor be
            # pushed out by it; both are read, and their starts and versions decide.
            self._lower[server] = data
        else:
            self._snapshots[server] = (seq, data)
        self._wake.set()

    def suspect(self, server: str) -> None:
        """Pass `server` over for diverged_hold_s: its weights diverged when acted on (the tick)."""
        with self.table.lock:
            view = self.table.views.get(server)
            if view is not None:
                view.suspect_until = time.monotonic() + self.config.diverged_hold_s
        self._wake.set()

    def stop(self) -> None:
        """Make `run` return after its current round."""
        self._stop.set()
        self._wake.set()

    def run(self) -> None:
        """The downlink thread: presence, statuses, snapshots; choose whom to follow; apply."""
        while not self._stop.is_set():
            self._wake.wait(timeout=0.02)
            self._wake.clear()
            self._take_presence()
            for frame in self._statuses.drained():
                take(frame, self._take_status, self.rejected, "server status", "status_")
            self._refresh()
            for server in set(self._snapshots) | set(self._lower):
                lower, waiting = self._lower.pop(server, None), self._snapshots.pop(server, None)
                for data in (lower, waiting[1] if waiting is not None else None):
                    if data is not None:
                        take(data, self._take_snapshot, self.rejected, "snapshot")
            self._choose()
            self._watch_weights()
            self._tell_unheard()

    def _tell_unheard(self) -> None:
        """Say once that the server `--follow` names is unheard while others are alive.

        Its snapshots alone may drive the robot: without a word it acted on its safe action (or
        its last weights) for the whole run, while the others stored everything.
        """
        follow = self.config.follow
        if (
            follow is None
            or self._told_unheard
            or time.monotonic() - self._started < self.config.status_timeout_s
        ):
            return
        with self.table.lock:
            pinned = self.table.views.get(follow)
            others = sorted(v.server for v in self.table.views.values() if v.alive and v.server != follow)
        if (pinned is None or pinned.heard == 0) and others:
            self._told_unheard = True
            log.warning("--follow %s: no status from it in %.0f s, while %s %s alive: acting on %s till then",
                        follow, self.config.status_timeout_s, ", ".join(others[:5]),
                        "is" if len(others) == 1 else "are",
                        "the weights given" if self.current is not None else "the safe action")  # fmt: skip

    def _take_presence(self) -> None:
        """Tokens are hints: one that disappears marks its server gone until its next status."""
        for server, alive in drained(self._presence):
            with self.table.lock:
                view = self.table.views.get(server)
                if view is not None and not alive and view.heard > 0 and not view.gone:
                    view.gone = True
                    log.info("server %s: its liveliness token is gone", server)

    def _take_status(self, data: bytes) -> None:
        sender, seq, message = decode(data, self.codec.key, ServerStatus)
        status = cast(ServerStatus, message)
        if sender != status.server:
            self.rejected["status_misrouted"] += 1
            return
        older_peer(data, f"server {status.server}", self._older, "this client's experiences and status")
        with self.table.lock:
            new = status.server not in self.table.views
            view = self.table.view(status.server)
            if view is None:
                self.rejected["status_servers_full"] += 1  # MAX_SERVERS alive already
                return
            if new:
                log.info("server %s is alive (store %s, incarnation %d)", status.server, status.store,
                         status.incarnation)  # fmt: skip
            if not self.table.announced(view, status.store, status.incarnation, status.started_ns):
                self.rejected["status_stale"] += 1  # an earlier start's status, replayed
                return
            if self.codec.key is not None:  # the MAC covers the frame's number: an older one is replayed
                if seq <= view.status_seq:
                    self.rejected["status_replayed"] += 1
                    return
                view.status_seq = seq
            view.heard, view.gone, view.alive = time.monotonic(), False, True  # as `_refresh` would say
            view.born = min(view.born, _born(status, view.heard))
            view.spec_hash = status.spec_hash
            new_config = view.learner_config != status.learner_config and bool(status.learner_config)
            view.metrics = status.metrics
            through = status.stored_through.get(self.id)
            if through is not None and through > MAX_PRODUCED:
                # More than any client numbers (a forgery): taken, it would count everything as
                # stored there, and re-sends to that server would stop for good.
                self.rejected["status_beyond"] += 1
            elif through is not None:
                view.held = through
                journal = view.taken_journal = status.journals.get(self.id, "")
                if not journal or journal == self.table.journal:
                    # What this start's own status says, not the most anything ever said: one forged
                    # ack of a huge number would otherwise stop re-sends to this server for good.
                    view.acked = through
                elif view.other_journal != journal:
                    view.other_journal = journal
                    log.error("server %s takes the experiences of another journal (%s) of client id %s: this "
                              "client's are refused there while it streams (give each client its own "
                              "--client-id)", status.server, journal, self.id)  # fmt: skip
            latest = view.latest
            if (latest is not None and latest.version > status.weights_version
                    and time.monotonic() - latest.received >= self.config.status_timeout_s):  # fmt: skip
                # A version its server's statuses have not reached status_timeout_s later: not
                # its own (a forged number would make every real snapshot look stale for good).
                view.latest = None
                self.rejected["unconfirmed"] += 1
                log.warning("server %s: weights version %d is not one its statuses announce (%d): "
                            "dropped", status.server, latest.version, status.weights_version)  # fmt: skip
            ask = not view.asked and view.latest is None and status.spec_hash == self.spec_hash
            view.asked = view.asked or ask
        if status.spec_hash and status.spec_hash != self.spec_hash:
            self._other_spec(status.server, status.spec_hash)
        if new_config:  # a config not seen from this server before: checked, and compared with ours once
            try:
                differ = config_differences(self._config_json, status.learner_config)
            except ValueError:
                self.rejected["status_config"] += 1
            else:
                view.learner_config = status.learner_config
                warned = (status.server, status.learner_config) in self._config_warned
                # A server of another spec is no server of this client's (said once, as its
                # snapshots are ignored): what it learns with neither applies nor is recorded.
                ours = status.spec_hash == self.spec_hash
                if ours and differ and not warned and len(self._config_warned) < MAX_SERVERS:
                    self._config_warned.add((status.server, status.learner_config))
                    log.warning("server %s learns with a config that is not this client's (%s): its "
                                "own applies, and metrics.json records it",
                                status.server, ", ".join(differ))  # fmt: skip
        if ask:  # its newest weights now rather than at its next publication; replies come later
            self.bus.query(self.keys.weights(status.server), self.config.query_timeout_s, self._on_snapshot,
                           self.max_snapshot_bytes)  # fmt: skip

    def _refresh(self) -> None:
        """Which servers are alive now (a recent status, no token gone since)."""
        now = time.monotonic()
        with self.table.lock:
            for view in self.table.views.values():
                alive = view.heard > 0 and now - view.heard <= self.config.status_timeout_s and not view.gone
                if view.alive and not alive:
                    log.info("server %s is gone", view.server)
                view.alive = alive

    def _take_snapshot(self, data: bytes) -> None:
        # Only frames `_on_snapshot` checked (CRC and tag) wait here: neither is checked twice (a
        # pass over a large snapshot holds the interpreter's lock from the tick).
        sender, seq, message = decode(data, expect=WeightSnapshot, crc_checked=True)
        snap = cast(WeightSnapshot, message)
        reason = self._invalid(sender, seq, snap)
        if reason:
            self.rejected[reason] += 1
            log.debug("snapshot from %s rejected: %s", sender, reason)
            return
        # Made ready for `act` in this thread: in the tick's first act on them, a large network's
        # layout (30 ms for 1,024 x 1,024) made the tick late at every new snapshot.
        params = weights_from_flat(self.learner_config, np.ascontiguousarray(snap.params, dtype=np.float64))
        weights = Weights(
            ready_to_act(params),
            snap.server,
            snap.incarnation, snap.store, snap.version, snap.published_ns, snap.diverged,
            snap.learned_through,
            time.monotonic(),
        )  # fmt: skip
        with self.table.lock:
            view = self.table.view(snap.server)
            if view is None:
                self.rejected["snapshot_servers_full"] += 1
                return
            # Checked again: the uplink may have taken another start of this server meanwhile.
            reason = self._out_of_turn(view, seq, snap)
            if reason:
                self.rejected[reason] += 1
                return
            view.latest = weights
            view.snapshot_seq = max(view.snapshot_seq, seq)
            if weights.diverged:  # it has reset: the weights this client suspected are gone
                view.suspect_until = 0.0
            if not view.spec_hash:
                view.spec_hash = snap.spec_hash

    def _other_spec(self, server: str, spec: str) -> None:
        """Say once per server (and not for every forged id) that it learns for another spec.

        From its status too: a snapshot larger than this client's own network (a deep learner's
        to a thesis client) is dropped by the bus before it is read, and the robot sat on its safe
        action with nothing said.
        """
        if server not in self.other_specs and len(self.other_specs) < MAX_SERVERS:
            self.other_specs[server] = spec
            log.error("server %s learns for spec %s; this client is spec %s (another task, ranges or "
                      "learner): its weights are ignored", server, spec, self.spec_hash)  # fmt: skip

    def _invalid(self, sender: str, seq: int, snap: WeightSnapshot) -> str:
        """Why a decoded snapshot (frame number `seq`) must not drive the robot ("" when it may)."""
        if sender != snap.server:
            return "misrouted"
        if snap.spec_hash != self.spec_hash:
            self._other_spec(snap.server, snap.spec_hash)
            return "spec"
        if snap.params.shape != (1, self._n_params):
            return "shape"
        if not np.isfinite(snap.params).all():
            return "non_finite"
        with self.table.lock:
            view = self.table.views.get(snap.server)
            return "unannounced" if view is None else self._out_of_turn(view, seq, snap)

    def _out_of_turn(self, view: ServerView, seq: int, snap: WeightSnapshot) -> str:
        """Why `snap` (frame `seq`) may not follow what `view` holds ("" when it may; caller holds the lock).

        Not the start that server's own status announces: an earlier one's, replayed, or of a store
        restored from a backup that counts its incarnations again. Not newer than the snapshot held:
        stale. With a key, numbered at or below a snapshot taken from this start: replayed (the
        weights held may have been dropped as unconfirmed, so the version alone cannot tell).
        """
        if (snap.store, snap.incarnation, snap.started_ns) != (view.store, view.incarnation, view.started_ns):
            return "unannounced"
        if view.latest is not None and snap.version <= view.latest.version:
            return "stale"
        if self.codec.key is not None and seq <= view.snapshot_seq:
            return "replayed"
        return ""

    def _fresh_weights(self, view: ServerView, now: float) -> Weights | None:
        """Its newest weights if it is alive (its status heard lately) and they are fresh."""
        w = view.latest
        if w is None or not view.alive or view.started_ns <= 0:
            return None
        return w if now - w.received <= self.config.snapshot_timeout_s else None

    def _healthy(self, view: ServerView, now: float) -> bool:
        """Fresh weights that have not diverged, from a server this client does not suspect."""
        w = self._fresh_weights(view, now)
        return w is not None and not w.diverged and now >= view.suspect_until

    def _suspected_newer(self, view: ServerView, now: float) -> bool:
        """Newer fresh weights, not flagged diverged, of the suspected server whose weights are acted on.

        Only that server's: another suspected server's weights diverged here too, and the weights
        of a server that never diverged (one failed over to, its snapshots paused) stay in use.
        """
        w, current = self._fresh_weights(view, now), self.current
        return (w is not None and not w.diverged and now < view.suspect_until and current is not None
                and w is not current and current.server == view.server)  # fmt: skip

    def _relearning(self, view: ServerView, now: float) -> bool:
        """Fresh weights it relearns after a divergence reset."""
        w = self._fresh_weights(view, now)
        return w is not None and w.diverged

    def _choose(self) -> None:
        """Follow the pinned or longest-alive healthy server; apply its newest snapshot.

        With no healthy server, a server relearning after a divergence reset is followed on
        its fresh weights (Section 7.6.2) rather than keep acting on weights known to have
        diverged; else a server passed over because its weights diverged on this robot, on its
        newer weights once they come (the robot kept acting on the weights that diverged, and
        each tick's divergence renewed the hold: one forged snapshot that diverges held an
        unkeyed robot on it for good); otherwise the last weights stay in use.
        """
        now = time.monotonic()
        with self.table.lock:
            views = list(self.table.views.values())
            if self.config.follow is not None:
                views = [v for v in views if v.server == self.config.follow]
            chosen = _longest_alive([v for v in views if self._healthy(v, now)])
            relearning = _longest_alive([v for v in views if self._relearning(v, now)])
            newer = _longest_alive([v for v in views if self._suspected_newer(v, now)])
        self.connected = chosen is not None
        if chosen is None:
            if self.following and self._lost_at is None:
                self._lost_at = now
                fallback = f"the weights {relearning.server} relearns" if relearning else "its last weights"
                log.warning("server %s unhealthy and no other healthy server: acting on %s",
                            self.following, fallback)  # fmt: skip
            if relearning is not None and relearning.latest is not None:
                self._apply(relearning.latest)
            elif newer is not None and newer.latest is not None:
                if not self._newer_told:  # the outage's warning came while only the diverged ones were there
                    self._newer_told = True
                    log.warning("acting on newer weights (version %d) of server %s, whose weights diverged "
                                "here", newer.latest.version, newer.server)  # fmt: skip
                self._apply(newer.latest)
            return
        if chosen.server != self.following:
            previous = self.table.views.get(self.following)
            if previous is not None and not self._healthy(previous, now):
                self.failovers.append({"from": self.following, "to": chosen.server, "at_unix": time.time()})
                log.warning("failover: following server %s instead of %s", chosen.server, self.following)
            else:  # the first, or one alive longer than the one followed has just become known
                log.info("following server %s", chosen.server)
            self.following = chosen.server
        self._lost_at, self._newer_told = None, False
        assert chosen.latest is not None
        self._apply(chosen.latest)

    def _watch_weights(self) -> None:
        """Log and count a stretch without newly applied weights (after the first weights)."""
        if self._applied_at is None:
            return
        gap = time.monotonic() - self._applied_at
        self.longest_without_weights_s = max(self.longest_without_weights_s, gap)
        if gap > self.config.snapshot_timeout_s and self._weightless_since is None:
            self._weightless_since = self._applied_at
            self.counters["downlink/weightless_stretches"] += 1
            log.warning("no new weights applied for %.1f s (acting on version %d from %s)", gap,
                        self.current.version if self.current else 0, self.following or "-")  # fmt: skip

    def _apply(self, w: Weights) -> None:
        """Make `w` the weights `act` uses (one reference swap)."""
        if w is not self.current:
            now = time.monotonic()
            if self._weightless_since is not None:
                log.warning("new weights applied after %.1f s without", now - self._weightless_since)
                self._weightless_since = None
            self._applied_at = now
            self.current = w
            self.apply_latency_ms.append((time.time_ns() - w.published_ns) / 1e6)
            self.applied.append((time.time(), w.server, w.version, w.learned_through.get(self.id, -1)))
            view = self.table.views.get(w.server)
            if view is not None and view.learner_config:
                self.learned_with[w.server] = view.learner_config
            if len(self.apply_latency_ms) > 100_000:
                del self.apply_latency_ms[:50_000]
                del self.applied[:50_000]
            with self.learned:
                self.learned.notify_all()


PLACEMENT = ("deep.device", "deep.compile")
"""Where and how a server runs its updates: its own choice, not a difference in what is learned."""


def config_differences(mine: str, theirs: str) -> list[str]:
    """The fields (dotted: `deep.lr`) in which two learner configs, as JSON objects, differ.

    Raises ValueError when `theirs` is not a JSON object.
    """

    def flat(data: Any, prefix: str = "") -> dict[str, Any]:
        if not isinstance(data, dict):
            raise ValueError("a learner config must be a JSON object")
        out: dict[str, Any] = {}
        for key, value in data.items():
            out.update(flat(value, f"{prefix}{key}.") if isinstance(value, dict) else {prefix + key: value})
        return out

    a, b = flat(parse_json(mine, "learner config")), flat(parse_json(theirs, "learner config"))
    return sorted(k for k in a.keys() | b.keys() if a.get(k) != b.get(k) and k not in PLACEMENT)


CLOCK_TOLERANCE_S = 1.0
"""A server's announced start counts as on this host's clock while the two differ by at most this
(`_start_key`): more than a status's delay, less than the clock steps it is there for."""


def _born(status: ServerStatus, heard: float) -> float:
    """When the start that sent `status` (heard at `heard`) began, on this host's monotonic clock.

    A server of protocol version 5 or earlier tells no uptime: its wall-clock start against this
    host's wall clock then, as before.
    """
    if status.uptime_ms >= 0:
        return heard - status.uptime_ms / 1000.0
    return heard - (time.time_ns() - status.started_ns) / 1e9


def _longest_alive(views: list[ServerView]) -> ServerView | None:
    """The server alive longest: the earliest `_start_key` (ties by id); None among none.

    One number per server, so a server not chosen never changes the choice by coming or going,
    and clients whose clocks agree with the servers' follow the same one.
    """
    if not views:
        return None
    wall, now = time.time_ns(), time.monotonic()
    return min(views, key=lambda v: (_start_key(v, wall, now), v.server))


def _start_key(view: ServerView, wall_ns: int, now: float) -> float:
    """When a server started, in ns on this host's wall clock (`wall_ns` at monotonic `now`).

    Its announced `started_ns` where that agrees with its uptime (`ServerView.born`, placed on
    this wall clock) within CLOCK_TOLERANCE_S: exact, so servers started moments apart on one
    host are ordered as they started. Otherwise the server's clock is off, or was set back since
    a restart: its uptime says when it started (late by a status's delay), so a restarted server
    never takes over from one that kept running, whatever its clock says.
    """
    if not math.isfinite(view.born):  # a start announced (by an ack) but not yet by its status:
        return math.inf  # its clock is unchecked, so it is not followed before its first status
    born = wall_ns - (now - view.born) * 1e9
    return float(view.started_ns) if abs(born - view.started_ns) <= CLOCK_TOLERANCE_S * 1e9 else born
