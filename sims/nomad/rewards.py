"""The Nomad's rewards: learned servoing (Fig 6.10) and learned wandering (Fig 6.8).

Both penalise rough motion, -((T - t)^2 + (R - r)^2): the command against the velocity the
encoders measured before it, in units of the velocity limits. Servoing adds -|pixel error|
(moving the target to the goal) and -(T^2 + R^2) (saving energy); wandering adds the
row-weighted carpet mismatch in view (nearer rows weighing more) as a penalty and the measured
forward velocity as a reward.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from sims.nomad.config import Behaviour, NomadConfig
from sims.nomad.vision import COLS, ROWS

FloatArray = NDArray[np.float64]


class Rewards:
    """Both behaviours' rewards over rows of (state, action, next_state).

    `behaviour` None: the configured one.
    """

    def __init__(self, config: NomadConfig) -> None:
        self.config = config

    def components(
        self,
        state: FloatArray,
        action: FloatArray,
        next_state: FloatArray,
        behaviour: Behaviour | None = None,
    ) -> FloatArray:
        """Fig 6.10 (servo) or Fig 6.8 (wander) terms, signed as they add up [n, 3].

        servo: (-pixel error, -energy, -roughness); wander: (-carpet mismatch, +forward,
        -roughness). `state` gives the measured (t, r) the smoothness penalty compares with.
        """
        cfg = self.config
        limits = np.asarray(cfg.max_velocity)
        state, next_state = np.atleast_2d(state), np.atleast_2d(next_state)

        def measured(s: FloatArray) -> FloatArray:
            """A state's measured (t, r) in units of their limits (a wild reading clipped)."""
            return np.asarray(np.clip(s[:, -2:], -limits, limits) / limits)

        u = np.atleast_2d(action) / limits
        rough = -cfg.smoothness_weight * ((u - measured(state)) ** 2).sum(axis=1)
        if (behaviour or cfg.behaviour) == "servo":
            half_diagonal = cfg.vision.half_diagonal
            error = np.hypot(*np.nan_to_num(next_state[:, :2].T, nan=half_diagonal))
            return np.stack([-cfg.position_weight * error / half_diagonal,
                             -cfg.energy_weight * (u**2).sum(axis=1), rough], axis=1)  # fmt: skip
        rows = np.arange(1, ROWS + 1, dtype=np.float64)
        carpet = next_state[:, : ROWS * COLS].reshape(-1, ROWS, COLS).mean(axis=2) @ rows / rows.sum()
        forward = measured(next_state)[:, 0]
        return np.stack([-cfg.carpet_weight * carpet, cfg.forward_weight * forward, rough], axis=1)

    def total(
        self,
        state: FloatArray,
        action: FloatArray,
        next_state: FloatArray,
        behaviour: Behaviour | None = None,
    ) -> FloatArray:
        """The behaviour's reward [n] for (state, action, next_state) [n, ...]."""
        return np.asarray(self.components(state, action, next_state, behaviour).sum(axis=1))
