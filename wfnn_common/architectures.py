"""The single-process architectures of thesis Chapter 5 over one `WFNN` learner.

- `LearnArchitecture` (Fig 5.1): one `learn(state, reward)` call per tick returns the action.
- `ActLearn` (Fig 5.2): `act` on every state (valid or not), `learn` only from valid data.
- `WFNN` itself is act-learn-think (Fig 5.4): `learn` stores, `think(n)` replays.

The threaded act-learn-think-MT (thinking in a background thread) lives on the robot side, in
`wfnn_client.think_thread`, as this package holds no threads or clocks.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wfnn_common.learner import WFNN, ActResult

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
