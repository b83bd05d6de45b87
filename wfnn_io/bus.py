"""The message bus between clients and think servers, and its Zenoh implementation.

`Bus` is the small interface the client and server are written against (publish, subscribe,
a queryable, liveliness); `ZenohBus` is the only place a Zenoh session is opened and
configured. Callbacks run on the bus's threads and must only hand work to a queue.

Publication channels are chosen per kind of traffic:
- `DATA` (experiences): reliable, congestion control BLOCK, so nothing is dropped under load
  (the caller is the uplink thread, never the control tick);
- `CONTROL` (acks): reliable, DROP, express (sent at once, not batched), high priority: an ack
  says all that earlier ones did (every experience through a number), and a dropped one is made
  good by the next or by a re-send's; blocking instead, a server's ingest, which acks every
  batch, would wait on any peer that subscribes to acks and stops reading (Zenoh holds a full
  link 5 s before closing it), for every client;
- `LATEST` (weights, status): reliable, DROP, express, highest priority: under congestion the
  newest snapshot matters, not an old one.

Size limits are enforced before anything is copied: Zenoh drops a message larger than
`NetConfig.max_message_bytes` while reassembling it, and a subscription given `max_bytes` hands
on no payload longer than that (counted in `ZenohBus.oversized`). A query never blocks: its
replies arrive on a callback.

Exposure: a session listens on loopback unless told otherwise, and `check_exposure` refuses
a non-loopback endpoint without a key unless the user says `insecure` (as Redis' protected mode
does): without a key anyone who reaches the port can drive the robot or feed the learner.
"""

from __future__ import annotations

import ipaddress
import json
import logging
import queue
import re
import threading
import time
from collections import Counter, OrderedDict
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from enum import Enum
from typing import Any, Generic, Literal, Protocol, TypeVar

from wfnn_common.config import check_fields
from wfnn_io.persist import read_regular_text
from wfnn_io.protocol import MAX_FRAME

log = logging.getLogger(__name__)


T = TypeVar("T")

INBOX_BYTES = 256 << 20
"""Bytes of received frames a receiver holds before it handles them (`Inbox`)."""
ITEM_OVERHEAD = 256
"""Bytes an `Inbox` charges each item besides its own: a queued frame's objects cost about 130
bytes of memory whatever its size (empty frames were never counted against the limit)."""


class Inbox(Generic[T]):
    """Received frames waiting for their thread, bounded in bytes.

    A bus callback only hands frames over; a flood faster than the handling thread (large frames
    whose checks fail late, say) would otherwise grow memory without bound. What arrives beyond
    `max_bytes` is dropped and counted: an experience frame dropped is re-sent from the journal,
    a status is superseded by the next one.
    """

    def __init__(self, max_bytes: int = INBOX_BYTES) -> None:
        self.max_bytes = max_bytes
        self.dropped = 0
        self._queue: queue.SimpleQueue[tuple[T, int]] = queue.SimpleQueue()
        self._bytes = 0
        self._lock = threading.Lock()

    def put(self, item: T, size: int) -> bool:
        """Queue `item` of `size` bytes; False (counted in `dropped`) when the inbox is full.

        Each item is charged ITEM_OVERHEAD bytes besides its size: what queuing it costs in
        memory, so that a flood of empty or tiny frames is bounded too.
        """
        size += ITEM_OVERHEAD
        with self._lock:
            if self._bytes + size > self.max_bytes:
                self.dropped += 1
                return False
            self._bytes += size
        self._queue.put((item, size))
        return True

    def get(self, timeout: float | None = None) -> T:
        """The oldest item; raises queue.Empty after `timeout`."""
        item, size = self._queue.get_nowait() if timeout == 0 else self._queue.get(timeout=timeout)
        with self._lock:
            self._bytes -= size
        return item

    def drained(self) -> Iterator[T]:
        """What the inbox holds, taken one by one without waiting, until it is empty."""
        while True:
            try:
                yield self.get(timeout=0)
            except queue.Empty:
                return


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

    def subscribe(self, key: str, callback: Callback, max_bytes: int | None = None) -> None:
        """Call `callback(key, payload)` for every publication matching `key`.

        Payloads longer than `max_bytes` are dropped, uncopied, and counted.
        """
        ...

    def queryable(self, key: str, answer: Callable[[], bytes | None]) -> None:
        """Answer queries on `key` with `answer()` (no reply when it returns None)."""
        ...

    def query(self, key: str, timeout_s: float, callback: Callback, max_bytes: int | None = None) -> None:
        """Query `key` without waiting.

        Each reply that arrives within `timeout_s` goes to `callback(key, payload)` (on the bus's
        thread); payloads longer than `max_bytes` are dropped, uncopied, and counted.
        """
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


class OfflineBus:
    """A `Bus` that joins no network: what is published goes nowhere and nothing arrives.

    For a server learning from logs alone (`--replay-only` naming no endpoint): it needs no port,
    so it neither takes one another server uses nor opens one to anybody.
    """

    def put(self, key: str, payload: bytes, channel: Channel) -> None:
        """Nothing is sent."""

    def subscribe(self, key: str, callback: Callback, max_bytes: int | None = None) -> None:
        """Nothing will arrive."""

    def queryable(self, key: str, answer: Callable[[], bytes | None]) -> None:
        """Nobody will ask."""

    def query(self, key: str, timeout_s: float, callback: Callback, max_bytes: int | None = None) -> None:
        """Nobody will answer."""

    def declare_token(self, key: str) -> None:
        """Nobody will see it."""

    def watch_presence(self, key: str, callback: PresenceCallback) -> None:
        """Nobody is present."""

    def close(self) -> None:
        """Nothing to leave."""


def guarded(target: Callable[[], object], on_error: Callable[[BaseException], object]) -> Callable[[], None]:
    """`target` for a thread that handles what the bus hands over: whatever ends it goes to `on_error`.

    A thread that fails would otherwise end unseen; `on_error` keeps the failure for its owner to
    surface (the client's `check`, the server's stop). It is called inside the handler, so a
    `logger.exception` there logs the traceback.
    """

    def run() -> None:
        try:
            target()
        except BaseException as exc:
            on_error(exc)

    return run


MAX_PUBLISHERS = 8192
"""Publishers a bus keeps declared (the least recently used goes first): each key published on
needs one, and acks carry the client's id in their key. Above a server's bound on the clients it
hears (4,096) and its own few keys, so that acks going round that many clients in turn never
declare a publisher each (about 90 us); about 3 KB each at most."""


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
    block_close_ms: int = 1000
    """A link that takes no experience (sent blocking) for this long is closed (Zenoh's own
    default is 5 s). A blocked send holds what comes after it: a client's status and its
    experiences to every other server, and a router's forwarding of them. At 5 s, one server's
    link going down in lock-step cut the robot off its healthy server for 3-4 s.
    Sustained traffic over a link slower than a batch (64 KB) in this time (about 0.5 Mbit/s) has
    the link closed and reopened: what it did not take comes again from the journal. A
    `zenoh_config` file that sets `wait_before_close` keeps its own."""
    shared_memory: bool = False  # the CLIs' default too (`SHARED_MEMORY_HELP`)
    """Let processes on one host pass large messages through shared memory (Zenoh's default).
    Off by default: Zenoh 1.10 keeps every peer process's segments mapped after it exits (two per
    process start, about 18 MB), so a robot whose local server restarted grew by that much each
    time; and it made no consistent difference to throughput here (`wfnn-bench transport`)."""
    zenoh_config: str | None = None
    """A Zenoh JSON5 config file applied first (TLS, user/password, ...); the fields above override."""
    max_message_bytes: int = MAX_FRAME + 1024
    """Zenoh drops any message larger than this as it reassembles it (before the process copies
    it): the largest frame the protocol allows by default; a client lowers it to what it expects."""

    def __post_init__(self) -> None:
        check_fields(self)
        if self.mode not in ("peer", "client", "router"):
            raise ValueError(f"mode must be peer, client or router, got {self.mode!r}")
        if self.lease_ms < 100 or self.retry_ms < 10 or self.block_close_ms < 10:
            raise ValueError("lease_ms must be >= 100, retry_ms >= 10 and block_close_ms >= 10")
        if not 1 << 16 <= self.max_message_bytes <= 1 << 30:
            raise ValueError(f"max_message_bytes must be in [64 KiB, 1 GiB], got {self.max_message_bytes}")
        for endpoint in self.listen:
            parse_endpoint(endpoint)
        for endpoint in self.connect:
            parse_endpoint(endpoint, to_connect=True)


SHARED_MEMORY_HELP = (
    "Zenoh shared memory between local processes (off: Zenoh keeps a restarted peer's segments mapped, "
    "~18 MB each start)."
)
"""`--shared-memory`'s help, the client's and the server's."""


class NetError(OSError):
    """The network cannot be joined as configured (a bad endpoint, a port in use, ...)."""


class Stopped(Exception):
    """A client-mode session's wait for its router ended by its `stop` (a signal, say)."""


RETRY_OPEN_S = 1.0
"""A client-mode session tries its router at most this often."""


_ENDPOINT = re.compile(r"(?P<proto>[a-z0-9-]+)/(?P<address>[^?#]+)(?P<rest>[?#].*)?")
_HOST_PORT = re.compile(r"(?:\[(?P<v6>[^\]]+)\]|(?P<host>[^:\[\]]+)):(?P<port>\d{1,5})")


MAX_ENDPOINT = 1 << 16
MAX_ADDRESS = 1024
"""The longest endpoint taken, and its address (a host name has at most 253 characters, a socket's
path 108; the options after `#` may carry certificates inline, several KB)."""
SHOWN = 120
"""Characters of an endpoint that messages show: a 30 KB one took seconds to wrap in a warning."""


def shown(endpoint: str) -> str:
    """An endpoint as messages show it: at most SHOWN characters."""
    return endpoint if len(endpoint) <= SHOWN else f"{endpoint[:SHOWN]}... ({len(endpoint)} characters)"


def parse_endpoint(endpoint: str, to_connect: bool = False) -> tuple[str, str | None]:
    """A Zenoh endpoint -> (protocol, host) (host None for a local socket); ValueError if malformed.

    One to connect to (`to_connect`) may not have port 0, which asks the system for a free port.
    """
    if isinstance(endpoint, str) and len(endpoint) > MAX_ENDPOINT:
        raise ValueError(f"endpoint {shown(endpoint)!r} is longer than {MAX_ENDPOINT} characters")
    m = _ENDPOINT.fullmatch(endpoint.strip()) if isinstance(endpoint, str) else None
    if m is None:
        raise ValueError(
            f"endpoint {shown(str(endpoint))!r} is not of the form <protocol>/<address>, e.g. "
            "tcp/127.0.0.1:7447"
        )
    proto, address = m["proto"], m["address"]
    if len(address) > MAX_ADDRESS:
        raise ValueError(f"endpoint {shown(endpoint)!r}: its address is longer than {MAX_ADDRESS} characters")
    if proto.startswith("unixsock") or proto == "unixpipe":
        return proto, None
    hp = _HOST_PORT.fullmatch(address)
    if hp is None or not 0 <= int(hp["port"]) <= 65535:
        raise ValueError(
            f"endpoint {shown(endpoint)!r}: the address must be HOST:PORT (port 0-65535), got {address!r}"
        )
    if to_connect and int(hp["port"]) == 0:
        raise ValueError(f"endpoint {shown(endpoint)!r}: port 0 is no port to connect to")
    return proto, hp["v6"] or hp["host"]


def is_loopback(endpoint: str) -> bool:
    """Whether an endpoint stays on this machine (loopback address, localhost, a local socket)."""
    _, host = parse_endpoint(endpoint)
    if host is None or host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # a host name: it may resolve anywhere


def endpoints(net: NetConfig) -> tuple[list[str], list[str]]:
    """The endpoints a session of `net` listens on and connects to (the Zenoh file's included)."""
    return _endpoints(zenoh_config(net), net.mode)


def _endpoints(conf: Any, mode: str) -> tuple[list[str], list[str]]:
    """The listen and connect endpoints a `zenoh.Config` gives a session of `mode`."""

    def read(path: str) -> list[str]:
        value = json.loads(conf.get_json(path))
        if isinstance(value, dict):  # per-mode lists: {"router": [...], "peer": [...]}
            value = value.get(mode, [])
        return [str(v) for v in value or []]

    return read("listen/endpoints"), read("connect/endpoints")


def check_exposure(net: NetConfig, keyed: bool, insecure: bool) -> list[str]:
    """Refuse non-loopback endpoints without a key unless `insecure`; -> the warnings, also logged.

    Raises ValueError naming the endpoints and the two ways out (a key file, or --insecure).
    """
    listen, connect = endpoints(net)
    exposed = [e for e in (*listen, *connect) if not is_loopback(e)]
    if not exposed:
        return []
    names = ", ".join(shown(e) for e in exposed)
    if not keyed and not insecure:
        raise ValueError(
            f"{names} reach(es) beyond this machine and no --key-file is given: anyone who can reach "
            "it could drive the robot or feed the learner. Give a shared key (--key-file), or "
            "--insecure on a network you trust"
        )
    if not keyed:
        warning = f"insecure: {names} without a key; any host that reaches it is trusted"
    else:
        warning = (
            f"{names}: frames are authenticated by the shared key but not encrypted (TLS: deploy/README.md)"
        )
    log.warning("%s", warning)
    return [warning]


MAX_ZENOH_CONFIG_BYTES = 1 << 20
MAX_ZENOH_CONFIG_DEPTH = 64
"""A Zenoh config file's largest size and nesting: Zenoh's parser took 4 GB for a 50 MB file and
overflowed its stack (the process crashed without a word) at 50,000 levels."""


def nesting(text: str) -> int:
    """The deepest nesting of objects and arrays in JSON5 text (outside strings and comments)."""
    depth = deepest = i = 0
    n = len(text)
    while i < n:
        c = text[i]
        if c in "\"'":  # a string: up to the same quote not escaped
            i += 1
            while i < n and text[i] != c:
                i += 2 if text[i] == "\\" else 1
        elif text.startswith("//", i):
            i = text.find("\n", i)
            i = n if i < 0 else i
        elif text.startswith("/*", i):
            i = text.find("*/", i + 2)
            i = n if i < 0 else i + 1
        elif c in "{[":
            depth += 1
            deepest = max(deepest, depth)
        elif c in "}]":
            depth -= 1
        i += 1
    return deepest


def _names_listen(conf: Any, text: str) -> bool:
    """Whether a Zenoh config read from `text` names its listen endpoints (an empty list too).

    Zenoh fills in its default where the file says nothing, so a value equal to the default was
    written only where the file spells out the default's address ([::]).
    """
    import zenoh

    return conf.get_json("listen/endpoints") != zenoh.Config().get_json("listen/endpoints") or "[::]" in text


def zenoh_config(net: NetConfig) -> Any:
    """A `zenoh.Config` for `net`."""
    import zenoh

    text = ""
    if net.zenoh_config:  # checked before Zenoh reads it (a FIFO there would hold the tool for good)
        try:
            text = read_regular_text(net.zenoh_config, MAX_ZENOH_CONFIG_BYTES)
        except (OSError, UnicodeDecodeError) as exc:
            raise NetError(
                f"Zenoh config {net.zenoh_config}: {getattr(exc, 'strerror', None) or exc}"
            ) from None
        if "__config__" in text:  # an included file would reach Zenoh's parser unchecked
            raise NetError(
                f"Zenoh config {net.zenoh_config}: includes (__config__) are not taken; give one file"
            )
        depth = nesting(text)
        if depth > MAX_ZENOH_CONFIG_DEPTH:
            raise NetError(
                f"Zenoh config {net.zenoh_config}: nested {depth} deep, more than {MAX_ZENOH_CONFIG_DEPTH}"
            )
    try:
        conf = zenoh.Config.from_file(net.zenoh_config) if net.zenoh_config else zenoh.Config()
    except zenoh.ZError as exc:
        raise NetError(f"Zenoh config {net.zenoh_config}: {_zenoh_message(exc)}") from None
    conf.insert_json5("mode", json.dumps(net.mode))
    if net.listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(net.listen)))
    elif net.mode != "client" and not _names_listen(conf, text):
        # Zenoh's own default is every interface ([::]); a robot listens on loopback unless told,
        # by an option or by the file (a file that names no endpoint is no word to listen everywhere).
        port = 7447 if net.mode == "router" else 0
        conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
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
    block = "transport/link/tx/queue/congestion_control/block/wait_before_close"
    if "wait_before_close" not in text:  # a `zenoh_config` file's own is kept (for a slow link)
        conf.insert_json5(block, str(net.block_close_ms * 1000))  # microseconds
    conf.insert_json5("transport/link/rx/max_message_size", str(net.max_message_bytes))
    return conf


def _zenoh_message(exc: BaseException) -> str:
    """Zenoh's error text without the source locations it appends."""
    text = re.sub(r" at /\S+\.rs:\d+\.?", "", str(exc))
    m = re.search(r'msg: "([^"]+)"', text)
    return (m[1] if m else text).strip().rstrip(".]") or type(exc).__name__


class ZenohBus:
    """`Bus` over one Zenoh session."""

    def __init__(self, net: NetConfig, stop: threading.Event | None = None) -> None:
        """Join the network; a client-mode session waits for its router until `stop` is set (`Stopped`)."""
        import zenoh

        self._zenoh = zenoh
        self.net = net
        self.session = self._open(stop)
        self._publishers: OrderedDict[tuple[str, Channel], Any] = OrderedDict()
        """Publishers declared, least recently used first (at most MAX_PUBLISHERS)."""
        self._entities: list[Any] = []
        self._lock = threading.Lock()
        self._closed = False
        self.oversized: Counter[str] = Counter()
        """Payloads dropped for their size before being copied, per key prefix."""

    def _open(self, stop: threading.Event | None) -> Any:
        """Open the session.

        A client-mode session cannot connect later, so it is retried here, a second at a time,
        saying what it waits for, until `stop` is set (`Stopped`) or a signal's handler raises.
        """
        zenoh, net = self._zenoh, self.net
        conf = zenoh_config(net)
        if net.mode != "client":
            try:
                return zenoh.open(conf)
            except zenoh.ZError as exc:
                where = ", ".join(net.listen) or "the configured endpoints"
                raise NetError(
                    f"cannot join the Zenoh network (listening on {where}): {_zenoh_message(exc)}"
                ) from None
        _, routers = _endpoints(conf, net.mode)  # the config just made, not one made again
        if not routers:  # else each try failed at once: a loop at full speed that waited for nothing
            raise NetError("client mode needs an endpoint to connect to (a router's), in the options or "
                           "the Zenoh config's connect/endpoints")  # fmt: skip
        where = ", ".join(shown(e) for e in routers)
        conf.insert_json5("connect/timeout_ms", "1000")
        conf.insert_json5("connect/exit_on_failure", "true")
        waited = 0
        while True:
            started = time.monotonic()
            try:
                return zenoh.open(conf)
            except zenoh.ZError as exc:
                if waited % 10 == 0:
                    log.warning("client mode: no router answers at %s yet (%s); retrying", where,
                                _zenoh_message(exc))  # fmt: skip
                waited += 1
            rest = max(0.0, RETRY_OPEN_S - (time.monotonic() - started))  # a refusal comes at once
            if stop is None:
                time.sleep(rest)
            elif stop.wait(rest):
                raise Stopped(f"stopped while waiting for a router at {where}")

    def _publisher(self, key: str, channel: Channel) -> Any:
        z = self._zenoh
        with self._lock:
            pub = self._publishers.get((key, channel))
            if pub is None:
                block, drop = z.CongestionControl.BLOCK, z.CongestionControl.DROP
                options: dict[Channel, dict[str, Any]] = {
                    Channel.DATA: {"congestion_control": block, "priority": z.Priority.DATA},
                    Channel.CONTROL: {"congestion_control": drop, "priority": z.Priority.INTERACTIVE_HIGH,
                                      "express": True},
                    Channel.LATEST: {"congestion_control": drop, "priority": z.Priority.REAL_TIME,
                                     "express": True},
                }  # fmt: skip
                reliable = z.Reliability.RELIABLE
                pub = self.session.declare_publisher(key, reliability=reliable, **options[channel])
                self._publishers[(key, channel)] = pub
                if len(self._publishers) > MAX_PUBLISHERS:
                    # The least recently used goes: acks name their client in the key, and every
                    # client id a server ever answered (any sender may pick one) kept a publisher.
                    # Dropped, not undeclared here: a put on another thread may still hold it, and
                    # Zenoh undeclares a publisher once nothing refers to it.
                    self._publishers.popitem(last=False)
            else:
                self._publishers.move_to_end((key, channel))
            return pub

    def put(self, key: str, payload: bytes, channel: Channel) -> None:
        """Publish on a declared publisher (declared on first use)."""
        if not self._closed:
            self._publisher(key, channel).put(payload)

    def _checked(self, callback: Callback, max_bytes: int | None) -> Callable[[str, Any], None]:
        """`callback` behind a size check made before the payload is copied out of Zenoh."""

        def deliver(key: str, payload: Any) -> None:
            if max_bytes is not None and len(payload) > max_bytes:
                self.oversized[key.rsplit("/", 1)[0]] += 1
                return
            callback(key, payload.to_bytes())

        return deliver

    def subscribe(self, key: str, callback: Callback, max_bytes: int | None = None) -> None:
        """Subscribe with a callback (runs on a Zenoh thread); see `Bus.subscribe`."""
        deliver = self._checked(callback, max_bytes)

        def on_sample(sample: Any) -> None:
            deliver(str(sample.key_expr), sample.payload)

        self._entities.append(self.session.declare_subscriber(key, on_sample))

    def queryable(self, key: str, answer: Callable[[], bytes | None]) -> None:
        """Reply to queries with the current answer."""

        def on_query(query: Any) -> None:
            payload = answer()
            if payload is not None:
                query.reply(key, payload)

        self._entities.append(self.session.declare_queryable(key, on_query))

    def query(self, key: str, timeout_s: float, callback: Callback, max_bytes: int | None = None) -> None:
        """Query without waiting; replies go to `callback` (see `Bus.query`)."""
        deliver = self._checked(callback, max_bytes)

        def on_reply(reply: Any) -> None:
            if reply.ok is not None:
                deliver(str(reply.ok.key_expr), reply.ok.payload)

        # No consolidation: each reply is handed on as it comes, not held for the slowest one.
        self.session.get(key, on_reply, timeout=timeout_s, consolidation=self._zenoh.ConsolidationMode.NONE)

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
