"""act-learn-think-MT (thesis Chapter 5): thinking in a background thread, `act` never waits.

`act` reads the newest published weight snapshot; the compiled think releases the GIL, so the
think thread runs beside the robot's tick.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from wfnn_common.learner import ActResult
from wfnn_common.learners import Learner
from wfnn_common.network import Params
from wfnn_common.schedule import ThinkSchedule

log = logging.getLogger(__name__)


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
        version: int = 0,
    ) -> None:
        self.learner = learner
        self.think_batch = think_batch
        self.publish_period_s = publish_period_s
        self.idle_sleep_s = idle_sleep_s
        self.schedule = ThinkSchedule()
        """Replays owed: thinks_per_action for every experience stored (the thesis'
        thinks-per-action setting; more replays than that over-fit, Fig 4.9)."""
        self._queue: collections.deque[tuple[Any, ...]] = collections.deque()
        self._snapshot: Params = learner.snapshot()
        self.version = version
        """The last snapshot's number: snapshots published so far, after `version` (those of the
        run that saved the weights this one resumed)."""
        self._first_version = version
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

    @property
    def thinking(self) -> bool:
        """Whether the think thread runs (after `stop`: whether it outlived the wait)."""
        return self._thread is not None and self._thread.is_alive()

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
        if self.error is not None:  # the learner failed: what is queued stays unlearned (the record keeps it)
            return
        while self._queue:
            stored = self.learner.learn(*self._queue.popleft())
            self.schedule.owe(self.learner.config.thinks_per_action * int(np.sum(stored)))

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
    def budget(self) -> int:
        """Replays still owed."""
        return self.schedule.budget

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
                    self.schedule.owe(per_action * int(np.sum(stored)))
                if self._reset_requested.any():
                    which = self._reset_requested.copy()
                    self._reset_requested[which] = False
                    learner.reset_weights(which)
                    self._publish()
                    log.warning("divergence: reset weights of %d learner(s)", int(which.sum()))
                n = self.schedule.next_thinks(self.think_batch, 0, stored=learner.buffer.count.max() > 0)
                if n == 0:
                    if self.version == self._first_version or learner.thinks.sum() > self._published_thinks:
                        self._publish()
                    time.sleep(self.idle_sleep_s)
                    continue
                learner.think(n)
                now = time.perf_counter()
                if now - last_publish >= self.publish_period_s:
                    self._publish()
                    last_publish = now
        except BaseException as exc:  # surfaced to the robot side; act keeps the last weights
            self.error = exc
            # One line: the run ends on it with its own error line (--verbose shows where).
            log.error("think thread stopped: %s", exc)
            log.debug("think thread stopped", exc_info=True)

    def _publish(self) -> None:
        self._snapshot = self.learner.snapshot()  # one reference swap: atomic for readers
        self._published_thinks = int(self.learner.thinks.sum())
        self.version += 1
