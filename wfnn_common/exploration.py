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
    tau_steps is added, so consecutive actions vary smoothly. `pink`: noise whose power falls
    as 1/frequency (Eberhard et al. 2023, "Pink noise is all you need"), between what one
    action and tau_steps actions can hold: the sum of independent Ornstein-Uhlenbeck processes
    of equal deviation whose correlation times run from 1 to tau_steps, a factor of at most
    `PINK_RATIO` apart. A process's power is flat below its corner frequency and falls as
    1/frequency^2 above it; equal powers at corners spaced evenly in log frequency add up to a
    1/frequency spectrum between the first and last corner (flat below, as a sequence of
    tau_steps pink samples is). Its deviation is sigma, as the others'.
    """

    def __init__(
        self, config: ExplorationConfig, population: int, action_dim: int, rng: np.random.Generator
    ) -> None:
        self.config = config
        self.rng = rng
        self.noise = np.zeros((population, action_dim))
        """The smooth noise [P, A]; the pink noise's processes [P, K, A]."""
        self._decay: FloatArray | float = float(np.exp(-1.0 / config.tau_steps))
        self._drive: FloatArray | float = config.sigma * float(np.sqrt(1.0 - self._decay**2))
        if config.kind == "pink":
            taus = pink_taus(config.tau_steps)
            self._decay = np.exp(-1.0 / taus)[:, None]
            self._spread = config.sigma / np.sqrt(len(taus))
            """Each process's deviation: the sum's is sigma."""
            self._drive = self._spread * np.sqrt(1.0 - self._decay**2)
            # Started where they stand at any later time (not at 0, as the smooth noise is): a slow
            # process started at 0 would take thousands of actions to reach its deviation.
            self.noise = self._spread * rng.normal(size=(population, len(taus), action_dim))

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
        if cfg.kind == "pink":
            return _clip_unit(action + self.noise.sum(axis=1))
        return _clip_unit(action + self.noise)

    def reset(self, which: NDArray[np.bool_] | None = None) -> None:
        """Restart the smooth noise (e.g. at a new episode): from 0; the pink noise, anew."""
        rows = np.ones(len(self.noise), dtype=bool) if which is None else which
        if self.config.kind == "pink":
            self.noise[rows] = self._spread * self.rng.normal(size=self.noise[rows].shape)
        else:
            self.noise[rows] = 0.0


PINK_RATIO = 4.0
"""Largest ratio of two neighbouring correlation times of the pink noise's processes (wider
spacing leaves ripples in the sum's spectrum; at 4 its log-log slope measures -1.0 +- 0.05 over
each decade from periods of 20 to 2,000 actions where tau_steps is 1,000)."""


def pink_taus(tau_steps: float) -> FloatArray:
    """Correlation times [K] of the pink noise's processes: 1 to tau_steps, evenly in log."""
    k = 1 + int(np.ceil(np.log(tau_steps) / np.log(PINK_RATIO) - 1e-9))
    return np.asarray(tau_steps ** (np.arange(k) / max(k - 1, 1)), dtype=np.float64)


def _clip_unit(u: FloatArray) -> FloatArray:
    """Actions u clipped to [-1, 1] in place (np.clip's dispatch costs more than the robot's whole act)."""
    np.maximum(u, -1.0, out=u)
    return np.minimum(u, 1.0, out=u)
