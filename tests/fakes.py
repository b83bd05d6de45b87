"""Small configs and data shared by the tests."""

from __future__ import annotations

import functools

import numpy as np

from wfnn_common.config import DeepConfig, LearnerConfig
from wfnn_common.replay import Experiences


def small_config(state_dim: int = 3, action_dim: int = 2, **kw: object) -> LearnerConfig:
    base: dict[str, object] = {
        "state_low": (-1.0,) * state_dim,
        "state_high": (1.0,) * state_dim,
        "action_low": (-1.0,) * action_dim,
        "action_high": (1.0,) * action_dim,
        "n_hidden": 6,
        "n_wires": 4,
        "replay_capacity": 500,
    }
    if kw.get("learner") == "deep":  # small networks, learning from the first experience
        base.update({"deep": DeepConfig(hidden=(8, 8), value_hidden=4, warmup=0), "batch_size": 16})
    base.update(kw)
    return LearnerConfig(**base)  # type: ignore[arg-type]


def random_experiences(
    rng: np.random.Generator, n: int, state_dim: int, action_dim: int, p_terminal: float = 0.1
) -> Experiences:
    return Experiences(
        rng.uniform(-1, 1, (n, state_dim)),
        rng.uniform(-1, 1, (n, action_dim)),
        rng.uniform(-1, 1, (n, state_dim)),
        rng.uniform(-2, 0.5, n),
        rng.random(n) < p_terminal,
    )


def wait_for(predicate, timeout=10.0):
    """Poll `predicate` until it holds (True) or the timeout passes (False)."""
    import time

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.005)
    return False


def key_matches(pattern: str, key: str) -> bool:
    """Zenoh key-expression matching for the subset wfnn uses: `*` is one chunk, `**` any number."""
    p, k = pattern.split("/"), key.split("/")

    def match(i: int, j: int) -> bool:
        if i == len(p):
            return j == len(k)
        if p[i] == "**":
            return any(match(i + 1, jj) for jj in range(j, len(k) + 1))
        return j < len(k) and (p[i] == "*" or p[i] == k[j]) and match(i + 1, j + 1)

    return match(0, 0)


class Hub:
    """An in-process network for `LoopbackBus` instances; `tap` may alter or drop payloads."""

    def __init__(self) -> None:
        import threading

        self.lock = threading.RLock()
        self.subscribers: list[tuple[LoopbackBus, str, object]] = []
        self.queryables: list[tuple[LoopbackBus, str, object]] = []
        self.tokens: dict[str, LoopbackBus] = {}
        self.watchers: list[tuple[LoopbackBus, str, object]] = []
        self.tap = None  # tap(key, payload) -> payload or None (dropped)
        self.puts: list[tuple[str, int]] = []
        self.queries: list[str] = []

    def bus(self) -> LoopbackBus:
        return LoopbackBus(self)


class LoopbackBus:
    """The `Bus` interface over a `Hub`: delivery is synchronous, in the publisher's thread."""

    def __init__(self, hub: Hub) -> None:
        import collections

        self.hub = hub
        self.closed = False
        self.oversized = collections.Counter()

    def put(self, key, payload, channel) -> None:
        if self.closed:
            return
        hub = self.hub
        with hub.lock:
            hub.puts.append((key, len(payload)))
            targets = [(b, cb) for b, pat, cb in hub.subscribers if not b.closed and key_matches(pat, key)]
        for _, callback in targets:
            data = hub.tap(key, payload) if hub.tap is not None else payload
            if data is not None:
                callback(key, bytes(data))

    def _checked(self, callback, max_bytes):
        def deliver(key, payload):
            if max_bytes is not None and len(payload) > max_bytes:
                self.oversized[key.rsplit("/", 1)[0]] += 1
                return
            callback(key, payload)

        return deliver

    def subscribe(self, key, callback, max_bytes=None) -> None:
        with self.hub.lock:
            self.hub.subscribers.append((self, key, self._checked(callback, max_bytes)))

    def queryable(self, key, answer) -> None:
        with self.hub.lock:
            self.hub.queryables.append((self, key, answer))

    def query(self, key, timeout_s, callback, max_bytes=None):
        """Answered in a thread of its own, as a real bus would (a queryable may never answer)."""
        import threading

        with self.hub.lock:
            self.hub.queries.append(key)
            answers = [a for b, pat, a in self.hub.queryables if not b.closed and key_matches(key, pat)]
        deliver = self._checked(callback, max_bytes)

        def ask():
            for answer in answers:
                reply = answer()
                if reply is not None:
                    deliver(key, bytes(reply))

        threading.Thread(target=ask, daemon=True).start()

    def declare_token(self, key) -> None:
        with self.hub.lock:
            self.hub.tokens[key] = self
            watchers = [(pat, cb) for b, pat, cb in self.hub.watchers if not b.closed]
        for pat, cb in watchers:
            if key_matches(pat, key):
                cb(key, True)

    def watch_presence(self, key, callback) -> None:
        with self.hub.lock:
            self.hub.watchers.append((self, key, callback))
            present = [k for k in self.hub.tokens if key_matches(key, k)]
        for k in present:
            callback(k, True)

    def close(self) -> None:
        with self.hub.lock:
            if self.closed:
                return
            self.closed = True
            gone = [k for k, b in self.hub.tokens.items() if b is self]
            for k in gone:
                del self.hub.tokens[k]
            watchers = [(pat, cb) for b, pat, cb in self.hub.watchers if not b.closed]
        for k in gone:
            for pat, cb in watchers:
                if key_matches(pat, k):
                    cb(k, False)


@functools.cache
def render_problem() -> str | None:
    """Why off-screen rendering fails here, or None when it works (checked once per session)."""
    from sims.render import render_problem as probe

    return probe()


def unchecked_frame(msg: object, sender: str, seq: int = 0, key: bytes | None = None) -> bytes:
    """A frame of `msg` as `encode` frames it, without the checks that refuse what no receiver takes
    (`protocol.Unsendable`): what a hostile or broken peer can still put on the bus."""
    import msgpack

    from wfnn_io import protocol

    body = msgpack.packb(protocol._body(msg), use_bin_type=True)  # type: ignore[arg-type]
    return protocol._framed(msg.TYPE, body, sender, seq, key)  # type: ignore[attr-defined]
