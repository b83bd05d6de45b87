"""Exploration strategies applied to the best wire's action (scaled units, range [-1, 1])."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from wfnn_common.config import ExplorationConfig

FloatArray = NDArray[np.float64]


class Explorer:
    """Perturbs the actions of P learners; holds the smooth noise's state.

    `uniform` (Section 3.4): with probability p the action is replaced by a uniform random
    action. `gaussian` (Section 6.4.1): N(0, sigma) is added. `smooth` (suggested in Section
    6.7): an Ornstein-Uhlenbeck process with stationary deviation sigma and correlation time
    tau_steps is added, so consecutive actions vary smoothly.
    """

    def __init__(
        self, config: ExplorationConfig, population: int, action_dim: int, rng: np.random.Generator
    ) -> None:
        self.config = config
        self.rng = rng
        self.noise = np.zeros((population, action_dim))
        self._decay = float(np.exp(-1.0 / config.tau_steps))
        self._drive = config.sigma * float(np.sqrt(1.0 - self._decay**2))

    def __call__(self, action: FloatArray) -> FloatArray:
        """Explored actions [P, A] (clipped to [-1, 1]) for greedy actions [P, A]."""
        cfg = self.config
        if cfg.kind == "none":
            return action
        if cfg.kind == "uniform":
            replace = np.less(self.rng.random(action.shape[0]), cfg.p)
            if not replace.any():
                return action
            out = action.copy()
            out[replace] = self.rng.uniform(-1.0, 1.0, size=(int(replace.sum()), action.shape[1]))
            return out
        if cfg.kind == "gaussian":
            return _clip_unit(action + self.rng.normal(0.0, cfg.sigma, size=action.shape))
        self.noise = self._decay * self.noise + self._drive * self.rng.normal(size=self.noise.shape)
        return _clip_unit(action + self.noise)

    def reset(self, which: NDArray[np.bool_] | None = None) -> None:
        """Restart the smooth noise (e.g. at a new episode)."""
        if which is None:
            self.noise[:] = 0.0
        else:
            self.noise[which] = 0.0


def _clip_unit(u: FloatArray) -> FloatArray:
    """Actions u clipped to [-1, 1] in place (np.clip's dispatch costs more than the robot's whole act)."""
    np.maximum(u, -1.0, out=u)
    return np.minimum(u, 1.0, out=u)
