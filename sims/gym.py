"""Any Gymnasium task with Box observations and actions, as a task the client can drive.

`GymVec(env_id)` wraps one environment (n = 1) behind the `sims.base.VecTask` interface:
states are observations, actions are clipped to the action space, and an episode that ends
(terminated or truncated) is restarted inside `step`, so `observe` is always the state to act
from. The transition into the end is learned: as a terminal one when the task terminated (no
value after it), as an ordinary one when only the time limit truncated it.

Declared ranges (the learner scales states and actions by them) come from the spaces. Where an
observation bound is infinite (most MuJoCo tasks), its range is measured instead: the 1st and
99th percentiles of the observations met over `probe_steps` random actions, widened by half
their span on each side. Such ranges are estimates from a random policy, which rarely goes
where a good one does (a balanced pole's cart drifts far beyond where random pushes ever
took it), so the task then declares `valid_margin` = MEASURED_MARGIN: the learner's sanity
limits refuse only non-finite observations, not those beyond an estimated range.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from numpy.typing import NDArray

from sims.base import Transition

FloatArray = NDArray[np.float64]
MEASURED_MARGIN = 1e6
"""The sanity margin of a task whose ranges were measured: only non-finite states are refused."""


def make_env(env_id: str, **make_kwargs: Any) -> gym.Env[Any, Any]:
    """`gym.make(env_id)`, checked: both spaces 1-D Boxes, the actions bounded.

    Anything else is refused with a ValueError that says why.
    """
    try:
        env = gym.make(env_id, **make_kwargs)
    except gym.error.Error as exc:
        raise ValueError(f"Gymnasium cannot make {env_id!r}: {exc}") from exc
    except ModuleNotFoundError as exc:
        raise ValueError(f"{env_id!r} needs a package that is not installed: {exc}") from exc
    for what, space in (("observation", env.observation_space), ("action", env.action_space)):
        if not isinstance(space, gym.spaces.Box) or len(space.shape) != 1:
            env.close()
            raise ValueError(f"{env_id}: the {what} space must be a 1-D Box, got {space}")
    act = env.action_space
    assert isinstance(act, gym.spaces.Box)
    if not (np.isfinite(act.low).all() and np.isfinite(act.high).all()):
        env.close()
        raise ValueError(f"{env_id}: the action space must be bounded, got {act}")
    return env


class GymVec:
    """One Gymnasium environment as a vectorised task of one instance."""

    n = 1

    def __init__(self, env_id: str, seed: int = 0, probe_steps: int = 2000, **make_kwargs: Any) -> None:
        self.env = make_env(env_id, **make_kwargs)
        obs, act = self.env.observation_space, self.env.action_space
        assert isinstance(obs, gym.spaces.Box) and isinstance(act, gym.spaces.Box)
        self.env_id = env_id
        self.seed = seed
        self.action_low = tuple(float(v) for v in act.low)
        self.action_high = tuple(float(v) for v in act.high)
        low, high = obs.low.astype(np.float64), obs.high.astype(np.float64)
        self.valid_margin = 1.0
        """How far outside its ranges (in range widths) a state is still learned (`LearnerConfig`)."""
        if not (np.isfinite(low).all() and np.isfinite(high).all()):
            low, high = self._measured_ranges(low, high, probe_steps)
            self.valid_margin = MEASURED_MARGIN
        self.state_low = tuple(float(v) for v in low)
        self.state_high = tuple(float(v) for v in high)
        self.state_names = tuple(f"obs_{i}" for i in range(len(low)))
        spec = self.env.spec
        self.max_episode_steps = int(spec.max_episode_steps) if spec and spec.max_episode_steps else 1000
        dt = getattr(self.env.unwrapped, "dt", None)
        self.rate_hz = 1.0 / float(dt) if dt else 50.0
        """The task's own control rate (1 / its time step, where it declares one)."""
        self._obs = np.zeros((1, len(low)))
        self.last_reward = np.zeros(1)
        self.episode_return = 0.0
        self.returns: list[float] = []
        """Returns of the episodes finished so far (the task's own score)."""
        self.episodes = 0

    def _measured_ranges(
        self, low: FloatArray, high: FloatArray, steps: int
    ) -> tuple[FloatArray, FloatArray]:
        rng = np.random.default_rng(self.seed + 12345)
        seen = []
        obs, _ = self.env.reset(seed=self.seed + 12345)
        self.env.action_space.seed(self.seed + 12345)  # unseeded, the ranges would differ per run
        for _ in range(steps):
            seen.append(obs)
            obs, _, terminated, truncated, _ = self.env.step(self.env.action_space.sample())
            if terminated or truncated:
                obs, _ = self.env.reset(seed=int(rng.integers(2**31)))
        data = np.asarray(seen, dtype=np.float64)
        p1, p99 = np.percentile(data, [1, 99], axis=0)
        span = np.maximum(p99 - p1, 1e-3)
        measured_low, measured_high = p1 - 0.5 * span, p99 + 0.5 * span
        return (
            np.where(np.isfinite(low), low, measured_low),
            np.where(np.isfinite(high), high, measured_high),
        )

    def reset(self, rng: np.random.Generator) -> FloatArray:
        """A new episode -> states [1, S]."""
        obs, _ = self.env.reset(seed=int(rng.integers(2**31)))
        self._obs = np.asarray(obs, dtype=np.float64)[None]
        self.episode_return = 0.0
        return self.observe()

    def observe(self) -> FloatArray:
        """The observation to act from [1, S]."""
        return self._obs.copy()

    def step(self, action: FloatArray) -> Transition:
        """One environment step with actions [1, A]; a finished episode restarts at once."""
        u = np.clip(np.asarray(action, dtype=np.float64).reshape(1, -1)[0], self.action_low, self.action_high)
        obs, reward, terminated, truncated, _ = self.env.step(u.astype(self.env.action_space.dtype))
        next_state = np.asarray(obs, dtype=np.float64)[None]
        self.last_reward = np.array([float(reward)])
        self.episode_return += float(reward)
        if terminated or truncated:
            self.returns.append(self.episode_return)
            self.episodes += 1
            self.episode_return = 0.0
            obs, _ = self.env.reset()
        self._obs = np.asarray(obs, dtype=np.float64)[None]
        return Transition(
            next_state, self.last_reward.copy(), np.array([bool(terminated)]), np.ones(1, dtype=np.bool_)
        )

    def close(self) -> None:
        """Close the environment."""
        self.env.close()
