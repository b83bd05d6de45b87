"""act-learn-think-C/S, robot side: experiences up to think servers, weight snapshots down.

    tick (caller):  act on the current snapshot (numpy) -> learn() appends to a deque
    uplink thread:  deque -> batches (sequence numbers, weights version) -> journal -> publish;
                    acks per server; re-send from the journal what a server has not
                    acknowledged in time (lost frames, a restarted or late-joining server)
    downlink thread: statuses (CRC/MAC) say which servers are alive and which store and
                    incarnation each one is; snapshots (CRC/MAC, spec, shape, finite, of the
                    announced store and incarnation, version newer than the last) per server;
                    follow one server and fail over when it is gone, silent or diverged;
                    swap the weights `act` uses in one reference assignment

Bus callbacks only put bytes on queues, and no payload larger than expected is copied. Nothing
here can block the tick, and nothing received can end a thread: every message is handled
inside a guard that counts what fails. Liveliness tokens and queries are not authenticated, so
neither decides anything alone: a server is alive while its MAC-checked status arrives (a
token that disappears marks it gone until its next status), and the query for a server's
newest weights never waits.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import queue
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from wfnn_client.brain import Acted, Experience, as_recorded, experience_batch
from wfnn_client.journal import Journal
from wfnn_common.config import LearnerConfig, check_fields, parse_json
from wfnn_common.learners import Learner, n_params, weights_from_flat
from wfnn_common.learners import Weights as NetworkWeights
from wfnn_io.bus import Bus, Channel
from wfnn_io.protocol import (
    EXP_AFTER_LOSS,
    Ack,
    CameraView,
    ClientStatus,
    Codec,
    ExperienceBatch,
    Keys,
    MsgType,
    ServerStatus,
    WeightSnapshot,
    check_id,
    load_key,
    max_frame,
    take,
)
from wfnn_io.segments import FsyncPolicy

log = logging.getLogger(__name__)


def max_snapshot_bytes(config: LearnerConfig) -> int:
    """The largest weights frame of this learner: its parameters, and room for the rest."""
    return max_frame(MsgType.WEIGHTS, 8 * n_params(config) + (64 << 10))


def largest_message(config: LearnerConfig) -> int:
    """The largest message a client of this learner receives (a snapshot, or a status)."""
    return max(max_snapshot_bytes(config), max_frame(MsgType.SERVER_STATUS))


@dataclass(frozen=True, kw_only=True)
class RemoteConfig:
    """How the client reaches its think servers."""

    controller: str = "default"
    client_id: str | None = None
    """Client id (default: the journal's, or a new random one)."""
    journal_dir: Path = Path("runs/latest/journal")
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
    spec_hash: str = ""
    learner_config: str = ""
    """The learner config it announces that it learns with (JSON), overrides applied."""
    store: str = ""
    """Its store's identity, as announced (status and acks)."""
    incarnation: int = 0
    asked: bool = False
    """The query for its newest weights was sent (once per announced store and incarnation)."""
    acked: int = -1
    """Every experience numbered <= this is stored in its store."""
    latest: Weights | None = None
    suspect_until: float = 0.0
    metrics: dict[str, float] = field(default_factory=dict)
    """Figures from its latest status."""
    window_end: int = -1
    """Last experience of the current re-send round."""
    last_resend: float = 0.0


@dataclass
class _Pending:
    experience: Experience
    source: str
    version: int
    t: float = field(default_factory=time.monotonic)


class RemoteBrain:
    """Robot side of act-learn-think-C/S over a `Bus` (see the module docstring)."""

    def __init__(
        self, learner: Learner, config: RemoteConfig, bus: Bus, initial: NetworkWeights | None = None
    ) -> None:
        self.learner = learner
        self.config = config
        self.bus = bus
        self.keys = Keys(config.controller)
        self.journal = Journal(config.journal_dir, config.client_id, fsync=config.journal_fsync,
                               learner_config=learner.config)  # fmt: skip
        self.id = self.journal.client_id
        self.codec = Codec(self.id, load_key(str(config.key_file) if config.key_file else None))
        self.spec_hash = learner.config.spec_hash()
        self._config_json = learner.config.to_json()
        self._n_params = n_params(learner.config)
        self.max_snapshot_bytes = max_snapshot_bytes(learner.config)
        """No larger weights frame is copied."""
        self._pending: collections.deque[_Pending] = collections.deque()
        self._wake_up = threading.Event()
        self._acks: queue.SimpleQueue[bytes] = queue.SimpleQueue()
        self._statuses: queue.SimpleQueue[bytes] = queue.SimpleQueue()
        self._presence: queue.SimpleQueue[tuple[str, bool]] = queue.SimpleQueue()
        self._snapshots: dict[str, bytes] = {}
        """Newest unprocessed snapshot frame per server (a ring of one)."""
        self._wake_down = threading.Event()
        self._lock = threading.Lock()
        self.servers: dict[str, ServerView] = {}
        self.current: Weights | None = None
        """The weights `act` uses; replaced by one reference assignment."""
        if initial is not None:  # saved weights drive the robot until a server's snapshot arrives
            self.current = Weights(initial, "file", 0, "", 0, time.time_ns(), False, {}, time.monotonic())
        self._following = ""
        self._connected = False
        self._learned = threading.Condition()
        self._sent: collections.deque[tuple[float, int]] = collections.deque()
        self._overdue = -1
        self.produced_through = self.journal.next_seq - 1
        learner.experienced(self.journal.next_seq)  # a robot restarting is not starting to learn
        self.rejected: Counter[str] = Counter()
        self.counters: Counter[str] = Counter()
        self.apply_latency_ms: list[float] = []
        self.applied: list[tuple[float, str, int, int]] = []
        """(Unix time, server, version, this client's experiences learned through) of each snapshot
        applied, for timelines of faults."""
        self.staleness_s: list[float] = []
        self.failovers: list[dict[str, Any]] = []
        self.learned_with: dict[str, str] = {}
        """Per server whose snapshots drove the robot: the learner config it learned with (JSON),
        which is not this client's where the server adopted another's or overrides fields."""
        self._config_warned: set[tuple[str, str]] = set()
        self._lost_at: float | None = None
        self._applied_at: float | None = None
        """time.monotonic() when weights were last applied (None before the first)."""
        self._weightless_since: float | None = None
        self.longest_without_weights_s = 0.0
        """The longest stretch without newly applied weights after the first (a stretch still
        open counted as far as it has gone)."""
        self._loop_metrics: dict[str, float] = {}
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self.error: BaseException | None = None

    # ------------------------------------------------------------------ lifecycle
    @property
    def following(self) -> str:
        """The server whose snapshots `act` uses ("" before the first)."""
        return self._following

    @property
    def connected(self) -> bool:
        """Whether a healthy server is followed (False before the first and during outages)."""
        return self._connected

    def start(self) -> None:
        """Subscribe, announce this client, and start the uplink and downlink threads."""
        bus, keys = self.bus, self.keys
        bus.subscribe(keys.ack(self.id), self._on_ack, max_frame(MsgType.ACK))
        bus.subscribe(keys.server_status(), self._on_status, max_frame(MsgType.SERVER_STATUS))
        bus.subscribe(keys.weights(), self._on_snapshot, self.max_snapshot_bytes)
        bus.watch_presence(keys.server_alive(), self._on_presence)
        bus.declare_token(keys.client_alive(self.id))
        for name, target in (("uplink", self._uplink_loop), ("downlink", self._downlink_loop)):
            thread = threading.Thread(target=self._guard(target), name=f"wfnn-{name}", daemon=True)
            thread.start()
            self._threads.append(thread)
        log.info("client %s: controller %s, journal continues at %d", self.id, self.config.controller,
                 self.journal.next_seq)  # fmt: skip

    # Bus callbacks: hand over and return.
    def _on_ack(self, key: str, data: bytes) -> None:
        self._acks.put(data)
        self._wake_up.set()

    def _on_status(self, key: str, data: bytes) -> None:
        self._statuses.put(data)
        self._wake_down.set()

    def _on_presence(self, key: str, alive: bool) -> None:
        self._presence.put((Keys.last(key), alive))
        self._wake_down.set()

    def _on_snapshot(self, key: str, data: bytes) -> None:
        self._snapshots[Keys.last(key)] = data
        self._wake_down.set()

    def _guard(self, target: Any) -> Any:
        def run() -> None:
            try:
                target()
            except BaseException as exc:
                self.error = exc
                log.exception("client thread failed")

        return run

    def stop(self, flush_timeout_s: float = 2.0) -> None:
        """Send what is queued, wait briefly for acks, stop the threads, close the journal and the bus."""
        deadline = time.monotonic() + flush_timeout_s
        while self._pending and time.monotonic() < deadline and self.error is None:
            time.sleep(0.005)
        while time.monotonic() < deadline and self.error is None and not self.all_acked():
            if not self._live_servers():  # nobody to wait for: the journal keeps the rest
                break
            time.sleep(0.01)
        self._stop.set()
        self._wake_up.set()
        self._wake_down.set()
        for thread in self._threads:
            thread.join(timeout=10)
        self._threads.clear()
        self.journal.close()
        self.bus.close()

    def check(self) -> None:
        """Raise if a background thread failed."""
        if self.error is not None:
            raise RuntimeError("client thread failed") from self.error

    def _live_servers(self) -> bool:
        with self._lock:
            return any(v.alive for v in self.servers.values())

    def all_acked(self) -> bool:
        """Whether some live server has stored everything produced so far."""
        with self._lock:
            return any(v.alive and v.acked >= self.produced_through for v in self.servers.values())

    # ------------------------------------------------------------------ tick side
    def act(self, state: Any, explore: bool = True) -> Acted | None:
        """Action from the current snapshot, or None when no valid weights exist yet."""
        weights = self.current
        if weights is None:
            return None
        result = self.learner.act(state, explore, params=weights.params)
        self.staleness_s.append((time.time_ns() - weights.published_ns) / 1e9)
        if len(self.staleness_s) > 100_000:
            del self.staleness_s[:50_000]
        if result.diverged:
            with self._lock:
                view = self.servers.get(weights.server)
                if view is not None:
                    view.suspect_until = time.monotonic() + self.config.diverged_hold_s
            self._wake_down.set()
        return Acted(result, weights.source, weights.version)

    def learn(self, experience: Experience, acted: Acted | None) -> None:
        """Queue an experience for the uplink (never blocks)."""
        self._pending.append(_Pending(*as_recorded(experience, acted)))
        self.produced_through += 1
        self._wake_up.set()

    def sync(self, timeout_s: float) -> bool:
        """Wait until the followed server's applied snapshot has learned everything produced."""
        target = self.produced_through
        deadline = time.monotonic() + timeout_s
        with self._learned:
            while True:
                w = self.current
                if w is not None and w.learned_through.get(self.id, -1) >= target:
                    return True
                remaining = deadline - time.monotonic()
                if remaining <= 0 or self.error is not None:
                    self.counters["lockstep/timeouts"] += 1
                    return False
                self._learned.wait(min(remaining, 0.1))

    def publish_view(self, tick: int, png: bytes) -> None:
        """Publish what the cameras saw (a PNG) for people watching the servers' dashboards."""
        view = CameraView(client=self.id, tick=tick, png=np.frombuffer(png, dtype=np.uint8))
        self.bus.put(self.keys.camera_view(self.id), self.codec.encode(view), Channel.LATEST)
        self.counters["camera/views_sent"] += 1

    def report(self, metrics: dict[str, Any]) -> None:
        """Control-loop figures for the status heartbeat."""
        self._loop_metrics = {k: float(v) for k, v in metrics.items() if isinstance(v, int | float)}

    def metrics(self) -> dict[str, float]:
        """Transport figures: snapshot latency, staleness, acks, rejections, failovers."""
        out: dict[str, float] = {
            "uplink/produced_through": float(self.produced_through),
            "weights/version": float(self.current.version if self.current else 0),
            "downlink/failovers": float(len(self.failovers)),
            "downlink/longest_without_weights_s": self.longest_without_weights_s,
            **{
                f"downlink/oversized_{k.rsplit('/', 1)[-1]}": float(v)
                for k, v in dict(getattr(self.bus, "oversized", {})).items()
            },
            **{f"downlink/rejected_{k}": float(v) for k, v in self.rejected.items()},
            **{k: float(v) for k, v in self.counters.items()},
        }
        with self._lock:
            acked = [v.acked for v in self.servers.values() if v.alive]
            followed = self.servers.get(self._following)
            if followed is not None:
                out.update({f"server/{k}": v for k, v in followed.metrics.items()})
        out["uplink/acked_through_max"] = float(max(acked)) if acked else -1.0
        for name, values in (("downlink/snapshot_latency_ms", self.apply_latency_ms),
                             ("weights/staleness_s", self.staleness_s)):  # fmt: skip
            if values:
                arr = np.asarray(values[-10_000:])
                out[f"{name}_p50"] = float(np.percentile(arr, 50))
                out[f"{name}_p99"] = float(np.percentile(arr, 99))
        return out

    # ------------------------------------------------------------------ uplink thread
    def _uplink_loop(self) -> None:
        cfg = self.config
        next_status = 0.0
        while True:
            stopping = self._stop.is_set()
            self._wake_up.wait(timeout=0.005)
            self._wake_up.clear()
            while self._pending:
                oldest = self._pending[0].t
                if not (stopping or cfg.lockstep or len(self._pending) >= cfg.batch_max
                        or time.monotonic() - oldest >= cfg.batch_period_s):  # fmt: skip
                    break
                self._send_batch()
            self._take_acks()
            self._resend()
            if self.journal.due():
                self.journal.sync()
            now = time.monotonic()
            if now >= next_status:
                self._publish_status()
                next_status = now + cfg.status_period_s
            if stopping and not self._pending:
                return

    def _send_batch(self) -> None:
        """Take up to batch_max queued experiences with one weights source; journal and publish."""
        first = self._pending[0]
        items: list[_Pending] = []
        while (
            self._pending and len(items) < self.config.batch_max and self._pending[0].source == first.source
        ):
            items.append(self._pending.popleft())
        batch = experience_batch(self.id, self.spec_hash, self.journal.next_seq, first.source,
                                 [p.experience for p in items], [p.version for p in items])  # fmt: skip
        frame = self.codec.encode(batch)
        self.journal.append(frame, batch.last_seq)
        self.bus.put(self.keys.experiences(self.id), frame, Channel.DATA)
        self._sent.append((time.monotonic(), batch.last_seq))
        self.counters["uplink/batches"] += 1

    def _take_acks(self) -> None:
        while True:
            try:
                data = self._acks.get_nowait()
            except queue.Empty:
                return
            take(data, self._take_ack, self.rejected, "ack", "ack_")

    def _take_ack(self, data: bytes) -> None:
        sender, ack = self.codec.decode(data, Ack)
        if ack.client != self.id or sender != ack.server:
            self.rejected["ack_misrouted"] += 1
            return
        with self._lock:
            view = self.servers.setdefault(ack.server, ServerView(ack.server))
            self._announced(view, ack.store, ack.incarnation)
            view.acked = max(view.acked, ack.stored_through)

    def _announced(self, view: ServerView, store: str, incarnation: int) -> None:
        """A server says which store and incarnation it is (caller holds the lock).

        Another store than before (a server restarted with a new data directory, or the first
        word from it) holds what it says it holds, whatever was acknowledged before: the
        acknowledged point restarts, so the journal re-sends it everything it lacks. Another
        store or incarnation also restarts the order of its snapshots: weights of one that is
        no longer announced are not followed.
        """
        if (store, incarnation) == (view.store, view.incarnation):
            return
        if store != view.store:
            if view.store:
                log.warning("server %s now has store %s (was %s): re-sending what it lacks", view.server,
                            store, view.store)  # fmt: skip
            view.acked, view.window_end, view.last_resend = -1, -1, 0.0
        view.store, view.incarnation = store, incarnation
        view.latest, view.asked = None, False

    def _resend(self) -> None:
        """Re-send from the journal to live servers missing experiences sent long enough ago."""
        cfg = self.config
        now = time.monotonic()
        while self._sent and now - self._sent[0][0] >= cfg.resend_after_s:
            self._overdue = self._sent.popleft()[1]
        with self._lock:  # only servers whose MAC-checked status says they are alive and of this spec
            views = [v for v in self.servers.values() if v.alive and v.spec_hash == self.spec_hash]
        for view in views:
            if view.acked >= self._overdue:
                continue
            window_done = view.acked >= view.window_end
            if not window_done and now - view.last_resend < cfg.resend_after_s:
                continue
            frames, last = self.journal.frames_from(view.acked + 1, cfg.resend_window)
            if not frames:
                continue
            if not self.journal.holds(view.acked + 1):  # damage took them: say so, or it waits forever
                frames[0] = self._declare_loss(frames[0], view)
            for frame in frames:
                self.bus.put(self.keys.resend(view.server, self.id), frame, Channel.DATA)
            view.last_resend = now
            view.window_end = last
            self.counters["uplink/resent_frames"] += len(frames)
            log.info("re-sent %d batches from experience %d to server %s", len(frames), view.acked + 1,
                     view.server)  # fmt: skip

    def _declare_loss(self, frame: bytes, view: ServerView) -> bytes:
        """The journaled batch `frame`, re-encoded to declare the experiences before it lost."""
        _, batch = self.codec.decode(frame, ExperienceBatch)
        flags = batch.flags.copy()
        flags[0] |= EXP_AFTER_LOSS
        log.error("experiences %d-%d are lost from the journal (damaged); server %s is told so",
                  view.acked + 1, batch.first_seq - 1, view.server)  # fmt: skip
        self.counters["uplink/declared_lost"] += batch.first_seq - view.acked - 1
        return self.codec.encode(dataclasses.replace(batch, flags=flags))

    def _publish_status(self) -> None:
        with self._lock:
            acked = {v.server: v.acked for v in self.servers.values()}
        weights = self.current
        status = ClientStatus(
            client=self.id, spec_hash=self.spec_hash, learner_config=self._config_json,
            following=self._following, weights_version=weights.version if weights else 0,
            produced_through=self.produced_through, acked=acked,
            metrics={**self._loop_metrics, **self.metrics()},
        )  # fmt: skip
        self.bus.put(self.keys.client_status(self.id), self.codec.encode(status), Channel.LATEST)

    # ------------------------------------------------------------------ downlink thread
    def _downlink_loop(self) -> None:
        while not self._stop.is_set():
            self._wake_down.wait(timeout=0.02)
            self._wake_down.clear()
            self._take_presence()
            self._take_statuses()
            self._refresh()
            for server in list(self._snapshots):
                data = self._snapshots.pop(server, None)
                if data is not None:
                    take(data, self._take_snapshot, self.rejected, "snapshot")
            self._choose()
            self._watch_weights()

    def _take_presence(self) -> None:
        """Tokens are hints: one that disappears marks its server gone until its next status."""
        while True:
            try:
                server, alive = self._presence.get_nowait()
            except queue.Empty:
                return
            with self._lock:
                view = self.servers.get(server)
                if view is not None and not alive and view.heard > 0 and not view.gone:
                    view.gone = True
                    log.info("server %s: its liveliness token is gone", server)

    def _take_statuses(self) -> None:
        while True:
            try:
                data = self._statuses.get_nowait()
            except queue.Empty:
                return
            take(data, self._take_status, self.rejected, "server status", "status_")

    def _take_status(self, data: bytes) -> None:
        sender, status = self.codec.decode(data, ServerStatus)
        if sender != status.server:
            self.rejected["status_misrouted"] += 1
            return
        with self._lock:
            view = self.servers.get(status.server)
            if view is None:
                view = self.servers[status.server] = ServerView(status.server)
                log.info("server %s is alive (store %s, incarnation %d)", status.server, status.store,
                         status.incarnation)  # fmt: skip
            self._announced(view, status.store, status.incarnation)
            view.heard, view.gone = time.monotonic(), False
            view.started_ns, view.spec_hash = status.started_ns, status.spec_hash
            new_config = view.learner_config != status.learner_config and bool(status.learner_config)
            view.metrics = status.metrics
            if self.id in status.stored_through:
                view.acked = max(view.acked, status.stored_through[self.id])
            ask = not view.asked and view.latest is None and status.spec_hash == self.spec_hash
            view.asked = view.asked or ask
        if new_config:  # a config not seen from this server before: checked, and compared with ours once
            try:
                differ = config_differences(self._config_json, status.learner_config)
            except ValueError:
                self.rejected["status_config"] += 1
            else:
                view.learner_config = status.learner_config
                if differ and (status.server, status.learner_config) not in self._config_warned:
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
        with self._lock:
            for view in self.servers.values():
                alive = view.heard > 0 and now - view.heard <= self.config.status_timeout_s and not view.gone
                if view.alive and not alive:
                    log.info("server %s is gone", view.server)
                view.alive = alive

    def _take_snapshot(self, data: bytes) -> None:
        sender, snap = self.codec.decode(data, WeightSnapshot)
        reason = self._invalid(sender, snap)
        if reason:
            self.rejected[reason] += 1
            log.debug("snapshot from %s rejected: %s", sender, reason)
            return
        weights = Weights(
            weights_from_flat(self.learner.config, np.ascontiguousarray(snap.params, dtype=np.float64)),
            snap.server,
            snap.incarnation, snap.store, snap.version, snap.published_ns, snap.diverged,
            snap.learned_through,
            time.monotonic(),
        )  # fmt: skip
        with self._lock:
            view = self.servers.setdefault(snap.server, ServerView(snap.server))
            view.latest = weights
            if weights.diverged:  # it has reset: the weights this client suspected are gone
                view.suspect_until = 0.0
            if not view.spec_hash:
                view.spec_hash = snap.spec_hash

    def _invalid(self, sender: str, snap: WeightSnapshot) -> str:
        """Why a decoded snapshot must not drive the robot ("" when it may)."""
        if sender != snap.server:
            return "misrouted"
        if snap.spec_hash != self.spec_hash:
            if self.counters["downlink/spec_warned_" + snap.server] == 0:
                self.counters["downlink/spec_warned_" + snap.server] = 1
                log.error("server %s publishes weights for spec %s; this client is spec %s: ignored",
                          snap.server, snap.spec_hash, self.spec_hash)  # fmt: skip
            return "spec"
        if snap.params.shape != (1, self._n_params):
            return "shape"
        if not np.isfinite(snap.params).all():
            return "non_finite"
        with self._lock:
            view = self.servers.get(snap.server)
            if view is None or (snap.store, snap.incarnation) != (view.store, view.incarnation):
                return "unannounced"  # not what that server's own status says it is
            latest = view.latest
        if latest is not None and snap.version <= latest.version:
            return "stale"
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

    def _relearning(self, view: ServerView, now: float) -> bool:
        """Fresh weights it relearns after a divergence reset."""
        w = self._fresh_weights(view, now)
        return w is not None and w.diverged

    def _choose(self) -> None:
        """Follow the pinned or longest-alive healthy server; apply its newest snapshot.

        With no healthy server, a server relearning after a divergence reset is followed on
        its fresh weights (Section 7.6.2) rather than keep acting on weights known to have
        diverged; otherwise the last weights stay in use.
        """
        now = time.monotonic()
        with self._lock:
            views = list(self.servers.values())
            if self.config.follow is not None:
                views = [v for v in views if v.server == self.config.follow]
            # The longest-alive: deterministic for every client, and a restarted server (a new
            # start time) never takes over from one that kept running.
            chosen = min((v for v in views if self._healthy(v, now)), key=_age, default=None)
            relearning = min((v for v in views if self._relearning(v, now)), key=_age, default=None)
        self._connected = chosen is not None
        if chosen is None:
            if self._following and self._lost_at is None:
                self._lost_at = now
                fallback = f"the weights {relearning.server} relearns" if relearning else "its last weights"
                log.warning("server %s unhealthy and no other healthy server: acting on %s",
                            self._following, fallback)  # fmt: skip
            if relearning is not None and relearning.latest is not None:
                self._apply(relearning.latest)
            return
        if chosen.server != self._following:
            previous = self.servers.get(self._following)
            if previous is not None and not self._healthy(previous, now):
                self.failovers.append({"from": self._following, "to": chosen.server, "at_unix": time.time()})
                log.warning("failover: following server %s instead of %s", chosen.server, self._following)
            else:  # the first, or one alive longer than the one followed has just become known
                log.info("following server %s", chosen.server)
            self._following = chosen.server
        self._lost_at = None
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
                        self.current.version if self.current else 0, self._following or "-")  # fmt: skip

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
            view = self.servers.get(w.server)
            if view is not None and view.learner_config:
                self.learned_with[w.server] = view.learner_config
            if len(self.apply_latency_ms) > 100_000:
                del self.apply_latency_ms[:50_000]
                del self.applied[:50_000]
            with self._learned:
                self._learned.notify_all()


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


def _age(view: ServerView) -> tuple[int, str]:
    """Sort key: the longest-alive server first (ties by id)."""
    return view.started_ns, view.server
