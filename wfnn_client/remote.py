"""act-learn-think-C/S, robot side: experiences up to think servers, weight snapshots down.

    tick (caller):    act on the current snapshot (numpy) -> learn() queues for the uplink
    uplink thread:    `wfnn_client.uplink`: batches -> journal -> publish; acks per server;
                      re-sends from the journal; loss declarations; the status heartbeat
    downlink thread:  `wfnn_client.downlink`: server statuses and presence, weight snapshots;
                      follow one server and fail over; swap the weights `act` uses in one
                      reference assignment

`RemoteBrain` is what the rest of the client uses. The two halves each own their thread, their
inboxes and their state; they share the bus, this client's codec and counters, and the table
of what is known of each server (`wfnn_client.link.ServerTable`, under its lock). Bus callbacks
only put bytes on queues, and no payload larger than expected is copied. Nothing here can block
the tick, and nothing received can end a thread: every message is handled inside a guard that
counts what fails (`wfnn_io.protocol.take`).
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections import Counter
from collections.abc import Iterable
from typing import Any

import numpy as np

from wfnn_client.brain import Acted, Experience
from wfnn_client.downlink import PLACEMENT, Downlink, config_differences, largest_message, max_snapshot_bytes
from wfnn_client.journal import Journal
from wfnn_client.link import RemoteConfig, ServerTable, ServerView, Weights
from wfnn_client.uplink import Uplink
from wfnn_common.learners import Learner
from wfnn_common.learners import Weights as NetworkWeights
from wfnn_io.bus import Bus, Channel, guarded
from wfnn_io.cli_errors import log_failure
from wfnn_io.protocol import MAX_KEY_CHARS, MAX_MAP_ENTRIES, CameraView, ClientStatus, Codec, Keys, load_key

__all__ = [
    "PLACEMENT",
    "RemoteBrain",
    "RemoteConfig",
    "ServerView",
    "Weights",
    "config_differences",
    "largest_message",
    "max_snapshot_bytes",
]

log = logging.getLogger(__name__)


MAX_REPEATED_METRICS = 512
"""Most of the followed server's figures a client repeats (as server/...) in its own figures and
status: that status must stay within the protocol's limits (`MAX_MAP_ENTRIES` entries, keys of
`MAX_KEY_CHARS`) whatever a server's status holds, or every server would refuse it."""


def _fitting(figures: Iterable[tuple[str, float]], most: int) -> dict[str, float]:
    """The first `most` of (name, figure) pairs whose names fit a protocol map's keys."""
    return dict(itertools.islice(((k, v) for k, v in figures if len(k) <= MAX_KEY_CHARS), most))


def _carried(metrics: dict[str, float]) -> dict[str, float]:
    """The figures a status carries: those whose names fit, the first `MAX_MAP_ENTRIES` of them.

    The control loop's figures hold every behaviour's brain's, each under `<behaviour>/` (with
    what each repeats of its server), so several behaviours could pass the protocol's limits.
    """
    return _fitting(metrics.items(), MAX_MAP_ENTRIES)


def _repeated(metrics: dict[str, float]) -> dict[str, float]:
    """A followed server's figures as this client repeats them: server/<name>, those that fit."""
    return _fitting(((f"server/{k}", v) for k, v in metrics.items()), MAX_REPEATED_METRICS)


class RemoteBrain:
    """Robot side of act-learn-think-C/S over a `Bus` (see the module docstring).

    A façade: the tick's side (`act`, `learn`, `sync`, `metrics`) and the lifecycle here, the
    work in `uplink` and `downlink`, each with its own thread.
    """

    def __init__(
        self, learner: Learner, config: RemoteConfig, bus: Bus, initial: NetworkWeights | None = None
    ) -> None:
        self.learner = learner
        self.config = config
        self.bus = bus
        self.keys = Keys(config.controller)
        self.journal = Journal(config.journal_dir, config.client_id, fsync=config.journal_fsync,
                               learner_config=learner.config, controller=config.controller,
                               task=config.task)  # fmt: skip
        self.id = self.journal.client_id
        key = load_key(str(config.key_file) if config.key_file else None)
        self.codec = Codec(self.id, key, config.controller)
        self.spec_hash = learner.config.spec_hash()
        self._config_json = learner.config.to_json()
        self.table = ServerTable(keyed=key is not None, journal=self.journal.log.id)
        self.rejected: Counter[str] = Counter()
        self.counters: Counter[str] = Counter()
        self.uplink = Uplink(config, bus, self.codec, self.journal, self.spec_hash, self.table, self._status,
                             self.counters, self.rejected)  # fmt: skip
        self.downlink = Downlink(learner.config, config, bus, self.codec, self.table, self.counters,
                                 self.rejected, initial)  # fmt: skip
        learner.experienced(self.journal.next_seq)  # a robot restarting is not starting to learn
        self._version_seen, self._source_seen = -1, ""
        """The weights `act` last counted the experiences of."""
        self.staleness_s: list[float] = []
        self._loop_metrics: dict[str, float] = {}
        self._threads: list[threading.Thread] = []
        self.error: BaseException | None = None
        self._failure_lock = threading.Lock()

    # ------------------------------------------------------------------ what the halves hold
    @property
    def following(self) -> str:
        """The server whose snapshots `act` uses ("" before the first)."""
        return self.downlink.following

    @property
    def connected(self) -> bool:
        """Whether a healthy server is followed (False before the first and during outages)."""
        return self.downlink.connected

    @property
    def current(self) -> Weights | None:
        """The weights `act` uses (the downlink replaces them by one reference assignment)."""
        return self.downlink.current

    @property
    def servers(self) -> dict[str, ServerView]:
        """What this client knows of each server, by id (read under `table.lock`)."""
        return self.table.views

    @property
    def produced_through(self) -> int:
        """The number of the newest experience produced (learned here)."""
        return self.uplink.produced_through

    @property
    def max_snapshot_bytes(self) -> int:
        """No larger weights frame is copied."""
        return self.downlink.max_snapshot_bytes

    @property
    def failovers(self) -> list[dict[str, Any]]:
        """Each time the followed server was left for another: from, to, at_unix."""
        return self.downlink.failovers

    def why_no_weights(self) -> str:
        """What the client heard that explains its having no weights ("" where nothing does)."""
        other = self.downlink.other_specs
        if not other:
            return ""
        heard = ", ".join(f"{server} (spec {spec})" for server, spec in list(other.items())[:4])
        return f"the servers heard learn for another spec than this client's {self.spec_hash}: {heard}"

    @property
    def learned_with(self) -> dict[str, str]:
        """Per server whose snapshots drove the robot: the learner config it learned with (JSON)."""
        return self.downlink.learned_with

    @property
    def apply_latency_ms(self) -> list[float]:
        """Per snapshot applied: milliseconds from its publication."""
        return self.downlink.apply_latency_ms

    @property
    def applied(self) -> list[tuple[float, str, int, int]]:
        """(Unix time, server, version, this client's experiences learned through) per snapshot applied."""
        return self.downlink.applied

    @property
    def longest_without_weights_s(self) -> float:
        """The longest stretch without newly applied weights after the first."""
        return self.downlink.longest_without_weights_s

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Subscribe, announce this client, and start the uplink and downlink threads."""
        self.uplink.subscribe()
        self.downlink.subscribe()
        self.bus.declare_token(self.keys.client_alive(self.id))
        for name, target in (("uplink", self.uplink.run), ("downlink", self.downlink.run)):
            thread = threading.Thread(target=guarded(target, self._failed), name=f"wfnn-{name}", daemon=True)
            thread.start()
            self._threads.append(thread)
        log.info("client %s: controller %s, journal continues at %d", self.id, self.config.controller,
                 self.journal.next_seq)  # fmt: skip

    def _failed(self, exc: BaseException) -> None:
        """A thread ended by `exc` (called in its handler): kept for `check`, and logged.

        The first failure is kept: it is the cause, and the threads failing after it (the same
        full disk, another file) name only their own symptom.
        """
        with self._failure_lock:
            if self.error is None:
                self.error = exc
        log_failure(log, "client thread failed", exc)

    def stop(self, flush_timeout_s: float = 2.0) -> None:
        """Send what is queued, wait briefly for acks, stop the threads, close the journal and the bus."""
        deadline = time.monotonic() + flush_timeout_s
        try:
            while self.uplink.queued and time.monotonic() < deadline and self.error is None:
                time.sleep(0.005)
            while time.monotonic() < deadline and self.error is None and not self.all_acked():
                if not self.table.any_alive():  # nobody to wait for: the journal keeps the rest
                    break
                time.sleep(0.01)
        finally:  # interrupted or not, the threads stop and the journal and session close
            try:
                self.uplink.stop()
                self.downlink.stop()
                for thread in self._threads:
                    thread.join(timeout=10)
                self._threads.clear()
            finally:
                try:
                    self.journal.close()
                finally:
                    self.bus.close()

    def check(self) -> None:
        """Raise if a background thread failed."""
        if self.error is not None:
            raise RuntimeError("client thread failed") from self.error

    def all_acked(self) -> bool:
        """Whether some live server has stored everything produced so far."""
        return self.uplink.all_acked()

    # ------------------------------------------------------------------ tick side
    def act(self, state: Any, explore: bool = True) -> Acted | None:
        """Action from the current snapshot, or None when no valid weights exist yet."""
        weights = self.downlink.current
        if weights is None:
            return None
        if weights.version != self._version_seen or weights.source != self._source_seen:
            # Weights that have learned from N experiences (all their thinks done, of any robot:
            # the snapshot's learned_through) leave a robot new to them past that much of its warm-up.
            self._version_seen, self._source_seen = weights.version, weights.source
            self.learner.experienced(sum(seq + 1 for seq in weights.learned_through.values()))
        result = self.learner.act(state, explore, params=weights.params)
        self.staleness_s.append((time.time_ns() - weights.published_ns) / 1e9)
        if len(self.staleness_s) > 100_000:
            del self.staleness_s[:50_000]
        if result.diverged:
            self.downlink.suspect(weights.server)
        return Acted(result, weights.source, weights.version)

    def learn(self, experience: Experience, acted: Acted | None) -> None:
        """Queue an experience for the uplink (never blocks); its reward sizes what `act` judges diverged."""
        self.learner.rewarded([experience.reward])
        self.uplink.add(experience, acted)

    def sync(self, timeout_s: float) -> bool:
        """Wait until the followed server's applied snapshot has learned every experience so far."""
        deadline = time.monotonic() + timeout_s
        with self.downlink.learned:
            while True:
                w = self.downlink.current
                target = self.uplink.experiences_through(w.server) if w is not None else None
                if w is not None and target is not None and w.learned_through.get(self.id, -1) >= target:
                    return True
                remaining = deadline - time.monotonic()
                if remaining <= 0 or self.error is not None:
                    self.counters["lockstep/timeouts"] += 1
                    return False
                self.downlink.learned.wait(min(remaining, 0.1))

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
        current = self.downlink.current
        out: dict[str, float] = {
            "uplink/produced_through": float(self.produced_through),
            "weights/version": float(current.version if current else 0),
            "downlink/failovers": float(len(self.failovers)),
            "downlink/longest_without_weights_s": self.longest_without_weights_s,
            **{
                f"downlink/oversized_{k.rsplit('/', 1)[-1]}": float(v)
                for k, v in dict(getattr(self.bus, "oversized", {})).items()
            },
            **{f"downlink/rejected_{k}": float(v) for k, v in dict(self.rejected).items()},
            **{k: float(v) for k, v in dict(self.counters).items()},
        }
        with self.table.lock:
            acked = [v.acked for v in self.table.views.values() if v.alive]
            acked_by_any = max((v.acked for v in self.table.views.values()), default=-1)
            followed = self.table.views.get(self.following)
            if followed is not None:
                out.update(_repeated(followed.metrics))
        out["uplink/acked_through_max"] = float(max(acked)) if acked else -1.0
        out["uplink/acked_by_any"] = float(acked_by_any)  # live or gone since: whether any server took any
        for name, values in (("downlink/snapshot_latency_ms", self.apply_latency_ms),
                             ("weights/staleness_s", self.staleness_s)):  # fmt: skip
            if values:
                arr = np.asarray(values[-10_000:])
                out[f"{name}_p50"] = float(np.percentile(arr, 50))
                out[f"{name}_p99"] = float(np.percentile(arr, 99))
        return out

    def _status(self) -> ClientStatus:
        """This client's status heartbeat (the uplink publishes it): both halves' figures and the tick's."""
        with self.table.lock:
            acked = {v.server: v.acked for v in self.table.views.values()}
        weights = self.downlink.current
        own = self.metrics()
        loop = {k: v for k, v in self._loop_metrics.items() if k not in own}
        return ClientStatus(
            client=self.id, spec_hash=self.spec_hash, learner_config=self._config_json,
            following=self.following, weights_version=weights.version if weights else 0,
            produced_through=self.produced_through, acked=acked, metrics=_carried({**own, **loop}),
            journal=self.table.journal,
        )  # fmt: skip
