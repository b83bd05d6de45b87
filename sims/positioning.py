"""1-DOF positioning by velocity control (thesis Appendix A).

dp/dt = 0.2 u with u in [-1, 1], one action per time unit. The state is the position error
(target - p) and the object's velocity; the reward penalises both. The target jumps to a new
random position at random moments; the transition across a jump is irrelevant to the learner
(the step reports `learnable = False`), as the thesis' "don't learn" input does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sims.base import TaskEnv, Transition, actions
from wfnn_common.config import check_fields

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, kw_only=True)
class PositioningConfig:
    """Positioning task parameters."""

    dt: float = 1.0
    """Time per action."""
    gain: float = 0.2
    """dp/dt = gain * u."""
    target_range: float = 1.0
    """Targets are uniform in [-target_range, target_range]."""
    jump_probability: float = 0.02
    """Probability per step that the target jumps (mean 50 steps between jumps)."""
    velocity_weight: float = 0.5
    """Reward: -(|error| + velocity_weight * |velocity|)."""

    def __post_init__(self) -> None:
        check_fields(self)
        jump, weight = self.jump_probability, self.velocity_weight
        checks = [
            (0.0 < self.dt <= 100.0 and 0.0 < self.gain <= 100.0, f"dt and gain must be in (0, 100], got "
                                                                  f"{self.dt} and {self.gain}"),
            (0.0 < self.target_range <= 1e3, f"target_range must be in (0, 1000], got {self.target_range}"),
            (0.0 <= jump <= 1.0, f"jump_probability must be in [0, 1], got {jump}"),
            # Negative, it paid rewards above 0, the largest the task declares.
            (0.0 <= weight <= 1e3, f"velocity_weight must be in [0, 1000], got {weight}"),
        ]  # fmt: skip
        for ok, message in checks:
            if not ok:
                raise ValueError(f"positioning: {message}")


class PositioningVec:
    """n positioning systems as arrays."""

    state_low: tuple[float, ...] = (-2.0, -0.2)
    state_high: tuple[float, ...] = (2.0, 0.2)
    action_low: tuple[float, ...] = (-1.0,)
    action_high: tuple[float, ...] = (1.0,)
    state_names = ("error", "velocity")

    def __init__(self, n: int, config: PositioningConfig | None = None) -> None:
        self.n = n
        self.config = config or PositioningConfig()
        self.position = np.zeros(n)
        self.velocity = np.zeros(n)
        self.target = np.zeros(n)
        self._rng = np.random.default_rng(0)

    def reset(self, rng: np.random.Generator) -> FloatArray:
        """Objects at rest at 0, new random targets."""
        self._rng = rng
        self.position[:] = 0.0
        self.velocity[:] = 0.0
        r = self.config.target_range
        self.target = rng.uniform(-r, r, self.n)
        return self.observe()

    def observe(self) -> FloatArray:
        """States [n, 2]: position error and velocity."""
        return np.stack([self.target - self.position, self.velocity], axis=1)

    def step(self, action: FloatArray) -> Transition:
        """Move by the commanded velocity; maybe jump the target (then not learnable)."""
        cfg = self.config
        u = np.clip(actions(action, self.n, 1)[:, 0], -1.0, 1.0)
        self.velocity = cfg.gain * u
        self.position = self.position + cfg.dt * self.velocity
        error = self.target - self.position
        reward = -(np.abs(error) + cfg.velocity_weight * np.abs(self.velocity))
        jump = self._rng.random(self.n) < cfg.jump_probability
        if jump.any():
            r = cfg.target_range
            self.target = np.where(jump, self._rng.uniform(-r, r, self.n), self.target)
        return Transition(self.observe(), reward, np.zeros(self.n, dtype=np.bool_), ~jump)


def handcoded_positioning(state: FloatArray, gain: float = 5.0) -> FloatArray:
    """Proportional velocity command toward the target: states [n, 2] -> actions [n, 1]."""
    return np.clip(gain * state[:, :1], -1.0, 1.0)


class PositioningEnv(TaskEnv):
    """Gymnasium positioning task (episodes of `max_steps`)."""

    def __init__(self, config: PositioningConfig | None = None, max_steps: int = 500) -> None:
        super().__init__(PositioningVec(1, config), max_steps)
