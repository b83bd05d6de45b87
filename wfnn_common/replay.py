"""A bounded experience replay buffer for a population of learners (oldest overwritten)."""

from __future__ import annotations

from collections import OrderedDict
from typing import Any, NamedTuple, cast

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
IntArray = NDArray[np.int64]

OPEN_LINKS = 1 << 16
"""Most experiences per learner waiting for a successor (`ReplayBuffer.link_successors`)."""


class Experiences(NamedTuple):
    """A block of experiences in the learner's scaled units.

    Attributes:
        state: [..., S]; action: [..., A]; next_state: [..., S];
        reward: raw (unsquashed) reward [...]; terminal: [...] (next_state unused where
        True): bool, or 0/1 float in the views `ReplayBuffer.arrays` returns.
    """

    state: FloatArray
    action: FloatArray
    next_state: FloatArray
    reward: FloatArray
    terminal: NDArray[Any]


class ReplayBuffer:
    """P ring buffers of `capacity` experiences each.

    One experience is one row of a single array [P, capacity, S + A + S + 2] (state, action,
    next state, reward, terminal as 0/1), so replaying it touches two or three cache lines
    instead of one per field; `state`, `action`, ... are views into it.
    """

    def __init__(self, population: int, capacity: int, state_dim: int, action_dim: int) -> None:
        self.capacity = capacity
        s, a = state_dim, action_dim
        self.data = np.zeros((population, capacity, 2 * s + a + 2))
        self.state = self.data[:, :, :s]
        self.action = self.data[:, :, s : s + a]
        self.next_state = self.data[:, :, s + a : 2 * s + a]
        self.reward = self.data[:, :, 2 * s + a]
        self._terminal = self.data[:, :, 2 * s + a + 1]
        self.count = np.zeros(population, dtype=np.int64)
        """Stored experiences per learner (at most capacity)."""
        self.added = np.zeros(population, dtype=np.int64)
        """Experiences ever added per learner (the ring's write position is added % capacity)."""
        self.successor: IntArray | None = None
        """Where linking (`link_successors`): per learner and stored experience [P, capacity], the
        number (in `added`'s count) of the experience that continues it, -1 for none yet."""
        self._open: list[OrderedDict[int, int]] = []
        """Where linking: per learner, the experiences still waiting for their successor (not
        terminal), by a hash of their next state's bytes (a state of 1,024 numbers would keep
        8 KiB a row), oldest first."""

    def link_successors(self) -> None:
        """From now on, link each stored experience to the one stored later that continues it.

        An experience continues another when it starts exactly from that one's next state, and
        that was not terminal; the first such experience stored is the one linked (where several
        end at one state, the newest of them waits for it). Experiences from several sources
        (clients, a task's mirrored images) arrive interleaved in any order, and each chain is
        followed on its own. At most OPEN_LINKS experiences per learner wait for a successor (the
        oldest gives up first), so the bookkeeping stays bounded.
        """
        if self.successor is None:
            self.successor = np.full((self.population, self.capacity), -1, dtype=np.int64)
            self._open = [OrderedDict() for _ in range(self.population)]

    @property
    def terminal(self) -> BoolArray:
        """Terminal flags [P, capacity] (a copy)."""
        return self._terminal != 0.0

    @property
    def population(self) -> int:
        """Number of learners."""
        return int(self.count.shape[0])

    def add(self, exp: Experiences, mask: BoolArray | None = None) -> None:
        """Append one experience per learner ([P, ...] arrays); learners where mask is False skip."""
        rows = np.arange(self.population) if mask is None else np.flatnonzero(mask)
        if rows.size == 0:
            return
        pos = self.added[rows] % self.capacity
        self.state[rows, pos] = exp.state[rows]
        self.action[rows, pos] = exp.action[rows]
        self.next_state[rows, pos] = exp.next_state[rows]
        self.reward[rows, pos] = exp.reward[rows]
        self._terminal[rows, pos] = exp.terminal[rows]
        if self.successor is not None:
            for learner in rows.tolist():
                ended = np.asarray(exp.terminal[learner]).reshape(1)
                self._link(learner, int(self.added[learner]), exp.state[learner][None],
                           exp.next_state[learner][None], ended)  # fmt: skip
        self.added[rows] += 1
        self.count[rows] = np.minimum(self.added[rows], self.capacity)

    def extend(self, learner: int, exp: Experiences) -> None:
        """Append a block of experiences ([N, ...] arrays) to one learner's buffer."""
        n = int(exp.reward.shape[0])
        if n == 0:
            return
        if n > self.capacity:  # only the newest fit
            exp = Experiences._make(a[-self.capacity :] for a in exp)
            self.added[learner] += n - self.capacity
            n = self.capacity
        pos = (self.added[learner] + np.arange(n)) % self.capacity
        self.state[learner, pos] = exp.state
        self.action[learner, pos] = exp.action
        self.next_state[learner, pos] = exp.next_state
        self.reward[learner, pos] = exp.reward
        self._terminal[learner, pos] = exp.terminal
        if self.successor is not None:
            self._link(learner, int(self.added[learner]), exp.state, exp.next_state, exp.terminal)
        self.added[learner] += n
        self.count[learner] = min(int(self.added[learner]), self.capacity)

    def _link(
        self, learner: int, first: int, state: FloatArray, next_state: FloatArray, terminal: NDArray[Any]
    ) -> None:
        """Link the experiences just stored (rows [n, ...], numbered first, first + 1, ...).

        Each is linked from the experience it continues, and waits for its own successor.
        """
        successor, waiting = cast(IntArray, self.successor)[learner], self._open[learner]
        ends_stored = self.next_state[learner]
        oldest = first + len(state) - self.capacity  # numbers below this are overwritten by now
        starts = np.ascontiguousarray(state, dtype=self.data.dtype)  # as stored: bytes compare alike
        ends = np.ascontiguousarray(next_state, dtype=self.data.dtype)
        ended = np.asarray(terminal).astype(np.bool_)
        for i in range(len(state)):
            number = first + i
            successor[number % self.capacity] = -1  # a new experience in this slot: none yet
            start = starts[i].tobytes()
            before = waiting.pop(hash(start), -1)
            # Still stored, and truly ending where this starts (not another state of equal hash).
            if before >= 0 and before >= oldest and ends_stored[before % self.capacity].tobytes() == start:
                successor[before % self.capacity] = number
            if not ended[i]:
                key = hash(ends[i].tobytes())
                waiting.pop(key, None)  # the newest with this next state waits, and is newest in line
                waiting[key] = number
                if len(waiting) > OPEN_LINKS:
                    waiting.popitem(last=False)

    def continuation(self, learner: int, idx: IntArray) -> tuple[IntArray, BoolArray]:
        """Slots [n] of the experiences that continue those at slots idx [n], and which do.

        Needs `link_successors`; an experience whose successor has been overwritten, or never
        came, has none (its slot is returned unchanged).
        """
        number = cast(IntArray, self.successor)[learner][idx]
        has = number >= self.added[learner] - self.count[learner]  # -1 never passes
        return np.where(has, number % self.capacity, idx), has

    def sample_indices(self, rng: np.random.Generator, n: int) -> IntArray:
        """Uniform indices [P, n] into each learner's stored experiences (0 where it has none)."""
        return (rng.random((self.population, n)) * self.count[:, None]).astype(np.int64)

    def take(self, learner: int, idx: IntArray) -> Experiences:
        """Copies of one learner's experiences at idx [n] -> arrays [n, ...], in one gather.

        The fields are views into one gathered block [n, S + A + S + 2] (one row per experience,
        as stored); `terminal` is the 0/1 float column, as in `arrays`.
        """
        rows = self.data[learner].take(idx, axis=0)
        s, a = self.state.shape[-1], self.action.shape[-1]
        return Experiences(rows[:, :s], rows[:, s : s + a], rows[:, s + a : 2 * s + a], rows[:, 2 * s + a],
                           rows[:, 2 * s + a + 1])  # fmt: skip

    def arrays(self) -> Experiences:
        """Views of the buffer [P, capacity, ...] (no copy; rows past `count` are unused).

        `terminal` is the 0/1 float column here, not a bool copy.
        """
        return Experiences(self.state, self.action, self.next_state, self.reward, self._terminal)

    def gather(self, idx: IntArray) -> Experiences:
        """Copies of the experiences at idx [P, n] -> arrays [P, n, ...]."""
        rows = np.arange(self.population)[:, None]
        return Experiences(
            self.state[rows, idx],
            self.action[rows, idx],
            self.next_state[rows, idx],
            self.reward[rows, idx],
            self._terminal[rows, idx] != 0.0,
        )

    def contents(self, learner: int) -> Experiences:
        """One learner's stored experiences, oldest first, as copies [N, ...]."""
        n = int(self.count[learner])
        start = int(self.added[learner]) - n
        pos = (start + np.arange(n)) % self.capacity
        return Experiences(
            self.state[learner, pos].copy(),
            self.action[learner, pos].copy(),
            self.next_state[learner, pos].copy(),
            self.reward[learner, pos].copy(),
            self._terminal[learner, pos] != 0.0,
        )
