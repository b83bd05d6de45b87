"""The single-process architectures of thesis Chapter 5 over one `WFNN` learner.

- `LearnArchitecture` (Fig 5.1): one `learn(state, reward)` call per tick returns the action.
- `ActLearn` (Fig 5.2): `act` on every state (valid or not), `learn` only from valid data.
- `WFNN` itself is act-learn-think (Fig 5.4): `learn` stores, `think(n)` replays.
- `ActLearnThinkMT`: thinking runs in a background thread; `act` reads the newest published
  weight snapshot and never waits for thinking (the compiled think releases the GIL).
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wfnn_common.learner import WFNN, ActResult
from wfnn_common.learners import Learner
from wfnn_common.network import Params

log = logging.getLogger(__name__)
FloatArray = NDArray[np.float64]


class LearnArchitecture:
    """Fig 5.1: the `learn` architecture.

    `learn(state, reward, valid)` learns from the last transition and returns the next action,
    or None when the state is invalid (then nothing is done).
    """

    def __init__(self, learner: WFNN) -> None:
        self.learner = learner
        self._prev: tuple[FloatArray, FloatArray] | None = None

    def learn(
        self, state: ArrayLike, reward: float, valid: bool = True, terminal: bool = False
    ) -> FloatArray | None:
        """One tick: learn (x_prev, u_prev, state, reward) then choose the action for `state`.

        `reward` belongs to the transition into `state`. After a terminal state the next call
        starts a new episode.
        """
        if not valid:
            return None
        if self._prev is not None:
            self.learner.learn(self._prev[0], self._prev[1], state, reward, terminal)
            self.learner.think()
        if terminal:
            self._prev = None
            return None
        action = self.learner.act(state).action
        self._prev = (np.asarray(state, dtype=np.float64), action)
        return action


class ActLearn:
    """Fig 5.2: the `act-learn` architecture.

    `act` every tick; `learn` stores the experience and learns from it at once
    (thinks_per_action replays, the newest experience among the stored ones).
    """

    def __init__(self, learner: WFNN) -> None:
        self.learner = learner

    def act(self, state: ArrayLike, explore: bool = True) -> ActResult:
        """Action for the (possibly suspect) state."""
        return self.learner.act(state, explore)

    def learn(
        self,
        state: ArrayLike,
        action: ArrayLike,
        next_state: ArrayLike,
        reward: ArrayLike,
        terminal: ArrayLike = False,
    ) -> bool:
        """Store the experience and learn; returns whether it was accepted."""
        ok = bool(np.all(self.learner.learn(state, action, next_state, reward, terminal)))
        if ok:
            latest = (self.learner.buffer.added - 1) % self.learner.buffer.capacity
            self.learner.think_on(self.learner.buffer.gather(latest[:, None]))
            self.learner.think(max(self.learner.config.thinks_per_action - 1, 0))
        return ok


class ActLearnThinkMT:
    """act-learn-think-MT: `think` in a background thread, `act` on the newest snapshot.

    `learn` only appends to a queue (thread-safe, never blocks); the think thread moves
    queued experiences into the replay buffer, replays thinks_per_action experiences for each
    one stored (in batches of `think_batch`), and every `publish_period_s` publishes a copy of
    the weights by swapping one reference, so `act` always sees a whole snapshot.
    When `act` sees divergence, the think thread resets the weights and keeps the experiences.

        with ActLearnThinkMT(WFNN(config)) as mt:
            while running:
                u = mt.act(x).action
                x_next, r = robot.step(u)
                mt.learn(x, u, x_next, r)
                x = x_next
    """

    def __init__(
        self,
        learner: Learner,
        think_batch: int = 50,
        publish_period_s: float = 0.02,
        idle_sleep_s: float = 0.001,
    ) -> None:
        self.learner = learner
        self.think_batch = think_batch
        self.publish_period_s = publish_period_s
        self.idle_sleep_s = idle_sleep_s
        self.budget = 0
        """Replays still owed: thinks_per_action for every experience stored (the thesis'
        thinks-per-action setting; more replays than that over-fit, Fig 4.9)."""
        self._queue: collections.deque[tuple[Any, ...]] = collections.deque()
        self._snapshot: Params = learner.snapshot()
        self.version = 0
        """Snapshots published so far."""
        self._published_thinks = 0
        self._reset_requested = np.zeros(learner.population, dtype=np.bool_)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None
        """An exception that stopped the think thread, if any."""

    # ------------------------------------------------------------------ control
    def start(self) -> ActLearnThinkMT:
        """Start the think thread."""
        if self._thread is not None:
            raise RuntimeError("already started")
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="wfnn-think", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 5.0) -> None:
        """Stop the think thread and wait for it; experiences still queued join the replay buffer.

        A robot that outran its think thread keeps every experience it handed over (saved with
        the learner, thought about by whatever learns next), though not every replay owed.
        """
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            if self._thread.is_alive():  # still in a long think: leave the queue to it
                return
            self._thread = None
        while self._queue:
            stored = self.learner.learn(*self._queue.popleft())
            self.budget += self.learner.config.thinks_per_action * int(np.sum(stored))

    def __enter__(self) -> ActLearnThinkMT:
        return self.start()

    def __exit__(self, *_: object) -> None:
        self.stop()

    # ------------------------------------------------------------------ robot side
    @property
    def snapshot(self) -> Params:
        """The weights `act` currently uses."""
        return self._snapshot

    def act(self, state: ArrayLike, explore: bool = True) -> ActResult:
        """Action from the newest snapshot; never waits for thinking."""
        result = self.learner.act(state, explore, params=self._snapshot)
        if np.any(result.diverged):
            self._reset_requested |= np.asarray(result.diverged, dtype=np.bool_).reshape(-1)
        return result

    def learn(
        self,
        state: ArrayLike,
        action: ArrayLike,
        next_state: ArrayLike,
        reward: ArrayLike,
        terminal: ArrayLike = False,
        valid: ArrayLike = True,
    ) -> None:
        """Queue one experience (per learner) for the think thread."""
        self._queue.append((state, action, next_state, reward, terminal, valid))

    @property
    def queued(self) -> int:
        """Experiences waiting for the think thread."""
        return len(self._queue)

    # ------------------------------------------------------------------ think thread
    def _run(self) -> None:
        learner = self.learner
        per_action = learner.config.thinks_per_action
        last_publish = time.perf_counter()
        try:
            while not self._stop.is_set():
                while self._queue:
                    stored = learner.learn(*self._queue.popleft())
                    self.budget += per_action * int(np.sum(stored))
                if self._reset_requested.any():
                    which = self._reset_requested.copy()
                    self._reset_requested[which] = False
                    learner.reset_weights(which)
                    self._publish()
                    log.warning("divergence: reset weights of %d learner(s)", int(which.sum()))
                if self.budget <= 0 or learner.buffer.count.max() == 0:
                    if self.version == 0 or learner.thinks.sum() > self._published_thinks:
                        self._publish()
                    time.sleep(self.idle_sleep_s)
                    continue
                n = min(self.think_batch, self.budget)
                learner.think(n)
                self.budget -= n
                now = time.perf_counter()
                if now - last_publish >= self.publish_period_s:
                    self._publish()
                    last_publish = now
        except BaseException as exc:  # surfaced to the robot side; act keeps the last weights
            self.error = exc
            log.exception("think thread stopped")

    def _publish(self) -> None:
        self._snapshot = self.learner.snapshot()  # one reference swap: atomic for readers
        self._published_thinks = int(self.learner.thinks.sum())
        self.version += 1
