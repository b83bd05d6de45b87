"""The message bus between clients and think servers, and its Zenoh implementation.

`Bus` is the small interface the client and server are written against (publish, subscribe,
a queryable, liveliness); `ZenohBus` is the only place a Zenoh session is opened and
configured. Callbacks run on the bus's threads and must only hand work to a queue.

Publication channels are chosen per kind of traffic:
- `DATA` (experiences): reliable, congestion control BLOCK, so nothing is dropped under load
  (the caller is the uplink thread, never the control tick);
- `CONTROL` (acks): reliable, BLOCK, express (sent at once, not batched), high priority;
- `LATEST` (weights, status): reliable, DROP, express, highest priority: under congestion the
  newest snapshot matters, not an old one.
"""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from typing import Any, Literal, Protocol

log = logging.getLogger(__name__)

Callback = Callable[[str, bytes], None]
"""callback(key, payload)."""
PresenceCallback = Callable[[str, bool], None]
"""callback(key, alive)."""


class Channel(Enum):
    """Kinds of traffic (see the module docstring)."""

    DATA = "data"
    CONTROL = "control"
    LATEST = "latest"


class Bus(Protocol):
    """What clients and servers need from the network."""

    def put(self, key: str, payload: bytes, channel: Channel) -> None:
        """Publish `payload` on `key`."""
        ...

    def subscribe(self, key: str, callback: Callback) -> None:
        """Call `callback(key, payload)` for every publication matching `key`."""
        ...

    def queryable(self, key: str, answer: Callable[[], bytes | None]) -> None:
        """Answer queries on `key` with `answer()` (no reply when it returns None)."""
        ...

    def get(self, key: str, timeout_s: float) -> list[bytes]:
        """Query `key`; the replies that arrive within `timeout_s`."""
        ...

    def declare_token(self, key: str) -> None:
        """Announce presence on `key` until the bus closes (or the process dies)."""
        ...

    def watch_presence(self, key: str, callback: PresenceCallback) -> None:
        """Call `callback(key, alive)` for tokens matching `key` (those present now included)."""
        ...

    def close(self) -> None:
        """Leave the network."""
        ...


@dataclass(frozen=True, kw_only=True)
class NetConfig:
    """How a process joins the Zenoh network."""

    mode: Literal["peer", "client", "router"] = "peer"
    listen: tuple[str, ...] = ()
    """Endpoints to listen on, e.g. tcp/127.0.0.1:7447."""
    connect: tuple[str, ...] = ()
    """Endpoints to connect to; retried in the background until they answer."""
    multicast_scouting: bool = False
    """Discover peers by UDP multicast (off: only the endpoints given)."""
    lease_ms: int = 3000
    """A peer silent for this long is dropped (its liveliness tokens vanish)."""
    retry_ms: int = 250
    """Period of connection retries to `connect` endpoints."""
    shared_memory: bool = True
    """Let processes on one host pass large messages through shared memory (Zenoh's default);
    False forces TCP, as between hosts."""
    zenoh_config: str | None = None
    """A Zenoh JSON5 config file applied first (TLS, user/password, ...); the fields above override."""

    def __post_init__(self) -> None:
        if self.mode not in ("peer", "client", "router"):
            raise ValueError(f"mode must be peer, client or router, got {self.mode!r}")
        if self.lease_ms < 100 or self.retry_ms < 10:
            raise ValueError("lease_ms must be >= 100 and retry_ms >= 10")


def zenoh_config(net: NetConfig) -> Any:
    """A `zenoh.Config` for `net`."""
    import zenoh

    conf = zenoh.Config.from_file(net.zenoh_config) if net.zenoh_config else zenoh.Config()
    conf.insert_json5("mode", json.dumps(net.mode))
    if net.listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(net.listen)))
    if net.connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(net.connect)))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(net.multicast_scouting))
    # Keep retrying endpoints that do not answer yet: a server may start before or after the
    # client. A peer's open() then returns at once (no scouting delay); for client mode see
    # `ZenohBus._open`.
    conf.insert_json5("connect/timeout_ms", "-1")
    conf.insert_json5("connect/exit_on_failure", "false")
    conf.insert_json5("scouting/delay", "0")
    conf.insert_json5("transport/shared_memory/enabled", json.dumps(net.shared_memory))
    retry = {"period_init_ms": net.retry_ms, "period_max_ms": net.retry_ms, "period_increase_factor": 1.0}
    conf.insert_json5("connect/retry", json.dumps(retry))
    conf.insert_json5("listen/exit_on_failure", "true")
    conf.insert_json5("transport/link/tx/lease", str(net.lease_ms))
    conf.insert_json5("transport/link/tx/keep_alive", "4")
    return conf


class ZenohBus:
    """`Bus` over one Zenoh session."""

    def __init__(self, net: NetConfig) -> None:
        import zenoh

        self._zenoh = zenoh
        self.net = net
        self.session = self._open()
        self._publishers: dict[tuple[str, Channel], Any] = {}
        self._entities: list[Any] = []
        self._lock = threading.Lock()
        self._closed = False

    def _open(self) -> Any:
        """Open the session.

        A client-mode session cannot connect later, so it is retried here, a second at a time,
        saying what it waits for (Ctrl-C or SIGTERM end the wait).
        """
        zenoh, net = self._zenoh, self.net
        conf = zenoh_config(net)
        if net.mode != "client":
            return zenoh.open(conf)
        conf.insert_json5("connect/timeout_ms", "1000")
        conf.insert_json5("connect/exit_on_failure", "true")
        waited = 0
        while True:
            try:
                return zenoh.open(conf)
            except zenoh.ZError as exc:
                if waited % 10 == 0:
                    log.warning("client mode: no router answers at %s yet (%s); retrying",
                                ", ".join(net.connect) or "(no endpoint)", exc)  # fmt: skip
                waited += 1

    def _publisher(self, key: str, channel: Channel) -> Any:
        z = self._zenoh
        with self._lock:
            pub = self._publishers.get((key, channel))
            if pub is None:
                block, drop = z.CongestionControl.BLOCK, z.CongestionControl.DROP
                options: dict[Channel, dict[str, Any]] = {
                    Channel.DATA: {"congestion_control": block, "priority": z.Priority.DATA},
                    Channel.CONTROL: {"congestion_control": block, "priority": z.Priority.INTERACTIVE_HIGH,
                                      "express": True},
                    Channel.LATEST: {"congestion_control": drop, "priority": z.Priority.REAL_TIME,
                                     "express": True},
                }  # fmt: skip
                reliable = z.Reliability.RELIABLE
                pub = self.session.declare_publisher(key, reliability=reliable, **options[channel])
                self._publishers[(key, channel)] = pub
            return pub

    def put(self, key: str, payload: bytes, channel: Channel) -> None:
        """Publish on a declared publisher (declared on first use)."""
        if not self._closed:
            self._publisher(key, channel).put(payload)

    def subscribe(self, key: str, callback: Callback) -> None:
        """Subscribe with a callback (runs on a Zenoh thread)."""

        def on_sample(sample: Any) -> None:
            callback(str(sample.key_expr), sample.payload.to_bytes())

        self._entities.append(self.session.declare_subscriber(key, on_sample))

    def queryable(self, key: str, answer: Callable[[], bytes | None]) -> None:
        """Reply to queries with the current answer."""

        def on_query(query: Any) -> None:
            payload = answer()
            if payload is not None:
                query.reply(key, payload)

        self._entities.append(self.session.declare_queryable(key, on_query))

    def get(self, key: str, timeout_s: float) -> list[bytes]:
        """Query and collect the replies that arrive before the deadline."""
        out = []
        for reply in self.session.get(key, timeout=timeout_s):
            if reply.ok is not None:
                out.append(reply.ok.payload.to_bytes())
        return out

    def declare_token(self, key: str) -> None:
        """Liveliness token held until close."""
        self._entities.append(self.session.liveliness().declare_token(key))

    def watch_presence(self, key: str, callback: PresenceCallback) -> None:
        """Liveliness subscriber, current tokens included."""
        put = self._zenoh.SampleKind.PUT

        def on_sample(sample: Any) -> None:
            callback(str(sample.key_expr), sample.kind == put)

        self._entities.append(self.session.liveliness().declare_subscriber(key, on_sample, history=True))

    def close(self) -> None:
        """Undeclare everything and close the session."""
        if self._closed:
            return
        self._closed = True
        for entity in [*self._publishers.values(), *reversed(self._entities)]:
            try:
                entity.undeclare()
            except Exception as exc:  # closing must go on whatever one entity says
                log.debug("undeclare failed: %s", exc)
        self._publishers.clear()
        self._entities.clear()
        self.session.close()
