"""The small interface every vectorised task offers, and a Gymnasium adapter over it."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol

import gymnasium as gym
import numpy as np
from numpy.typing import NDArray

from wfnn_common.symmetry import Symmetry

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


class Transition(NamedTuple):
    """What a vectorised task returns from `step` (n instances).

    Attributes:
        state: next states [n, S] (for a terminal step: the state at failure).
        reward: raw rewards [n] (the learner squashes them).
        terminal: [n] the step ended in a terminal state (failure); no next state is learned.
        learnable: [n] False where the transition is irrelevant (e.g. the target jumped) and
            must not be learned (Section 5.1).
    """

    state: FloatArray
    reward: FloatArray
    terminal: BoolArray
    learnable: BoolArray


def actions(action: Any, n: int, dim: int) -> FloatArray:
    """`action` as [n, dim] float64, else a ValueError saying why.

    np.clip keeps NaN: one NaN action left a boat's state NaN for good, and a cart-pole's then
    never failed (NaN compares False) and was paid 0, the best reward; and indexing the first
    column took actions of any width.
    """
    u = np.asarray(action, dtype=np.float64)
    if u.shape != (n, dim):
        raise ValueError(f"actions must be of shape [{n}, {dim}], got {list(u.shape)}")
    if np.isnan(u).any():
        raise ValueError("an action is not a number (NaN)")
    return u


class VecTask(Protocol):
    """n independent instances of one task, advanced together as arrays."""

    n: int

    @property
    def state_low(self) -> tuple[float, ...]:
        """Lower ends of the declared state ranges."""
        ...

    @property
    def state_high(self) -> tuple[float, ...]:
        """Upper ends of the declared state ranges."""
        ...

    @property
    def action_low(self) -> tuple[float, ...]:
        """Lower ends of the action ranges."""
        ...

    @property
    def action_high(self) -> tuple[float, ...]:
        """Upper ends of the action ranges."""
        ...

    def reset(self, rng: np.random.Generator) -> FloatArray:
        """Start every instance afresh; returns states [n, S]."""
        ...

    def observe(self) -> FloatArray:
        """Current states [n, S]."""
        ...

    def step(self, action: FloatArray) -> Transition:
        """Apply actions [n, A] for one control step."""
        ...


@dataclass(frozen=True)
class Ranges:
    """Declared ranges of one behaviour's states and actions (what `LearnerConfig.for_task` reads)."""

    state_low: tuple[float, ...]
    state_high: tuple[float, ...]
    action_low: tuple[float, ...]
    action_high: tuple[float, ...]
    symmetries: tuple[Symmetry, ...] = ()
    """The behaviour's declared symmetries (`wfnn_common.symmetry`), if any."""
    valid_margin: float | None = None
    """How far outside the state ranges (in range widths) its states may still be learned; None: the
    learner's default. A Gymnasium task whose ranges were measured declares a wide one."""
    max_reward: float | None = 0.0
    """Its largest reward: 0 for the thesis' tasks, None where unknown (a Gymnasium task's)."""

    @classmethod
    def of(cls, task: Any) -> Ranges:
        """A task's declared ranges, margin, largest reward and symmetries (what it leaves out: defaults)."""
        return cls(
            tuple(task.state_low), tuple(task.state_high), tuple(task.action_low), tuple(task.action_high),
            tuple(getattr(task, "symmetries", ())), getattr(task, "valid_margin", None),
            getattr(task, "max_reward", 0.0),
        )  # fmt: skip


class Behaviours(Protocol):
    """Several learned behaviours sharing one vectorised robot, one driving at a time.

    A behaviour-based system (thesis Fig 6.3): each behaviour has its own state, reward and
    learner; `driving` says whose action goes to the motors; every behaviour learns from every
    executed action, whichever behaviour chose it (learning from other behaviours, Section 6.6).
    """

    @property
    def names(self) -> tuple[str, ...]:
        """The behaviours, in a fixed order."""
        ...

    def ranges(self, name: str) -> Ranges:
        """Declared ranges of behaviour `name`."""
        ...

    def driving(self) -> NDArray[np.int64]:
        """Index into `names` of the behaviour driving each instance now [n]; once per tick, before acting."""
        ...

    def observe(self, name: str) -> FloatArray:
        """Behaviour `name`'s current states [n, S_name]."""
        ...

    def step(self, action: FloatArray) -> dict[str, Transition]:
        """Apply actions [n, A]; each behaviour's view of the step."""
        ...

    def reward(self, name: str, state: FloatArray, action: FloatArray, next_state: FloatArray) -> FloatArray:
        """Behaviour `name`'s reward [n] for an action, executed or not (learning a vetoed proposal)."""
        ...


class TaskEnv(gym.Env[FloatArray, FloatArray]):
    """Gymnasium view of one instance of a vectorised task (episodes of `max_steps`)."""

    metadata: dict[str, Any] = {"render_modes": []}  # noqa: RUF012

    def __init__(self, task: VecTask, max_steps: int) -> None:
        if task.n != 1:
            raise ValueError("TaskEnv wraps a task with n == 1")
        if not 1 <= max_steps <= 10**9:  # 0 or fewer truncated every episode at its first step
            raise ValueError(f"max_steps must be in [1, 1e9], got {max_steps}")
        self.task = task
        self.max_steps = max_steps
        self.max_reward: float | None = getattr(task, "max_reward", 0.0)
        """The largest reward (this project's tasks: 0, the thesis' convention; `LearnerConfig.for_task`)."""
        # The declared ranges scale the learner's inputs; they are not hard limits, so the
        # observation space is ten times as wide around the same centre.
        low, high = np.asarray(task.state_low), np.asarray(task.state_high)
        mid, half = 0.5 * (high + low), 0.5 * (high - low)
        self.observation_space = gym.spaces.Box(mid - 10.0 * half, mid + 10.0 * half, dtype=np.float64)
        self.action_space = gym.spaces.Box(
            np.asarray(task.action_low), np.asarray(task.action_high), dtype=np.float64
        )
        self._steps = 0

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[FloatArray, dict[str, Any]]:
        """Gymnasium reset."""
        super().reset(seed=seed)
        self._steps = 0
        return self._obs(self.task.reset(self.np_random)), {}

    def step(self, action: FloatArray) -> tuple[FloatArray, float, bool, bool, dict[str, Any]]:
        """Gymnasium step: (obs, reward, terminated, truncated, info)."""
        # A NaN, missing or mis-sized action is refused by the task's own `actions` check.
        tr = self.task.step(np.asarray(action, dtype=np.float64).reshape(1, -1))
        self._steps += 1
        info = {"learnable": bool(tr.learnable[0])}
        return (
            self._obs(tr.state),
            float(tr.reward[0]),
            bool(tr.terminal[0]),
            self._steps >= self.max_steps and not bool(tr.terminal[0]),
            info,
        )

    def _obs(self, state: FloatArray) -> FloatArray:
        space = self.observation_space
        assert isinstance(space, gym.spaces.Box)
        return np.clip(state[0], space.low, space.high)
