"""Small configs and data shared by the tests."""

from __future__ import annotations

import numpy as np

from wfnn_common.config import LearnerConfig
from wfnn_common.replay import Experiences


def small_config(state_dim: int = 3, action_dim: int = 2, **kw: object) -> LearnerConfig:
    base: dict[str, object] = {
        "state_low": (-1.0,) * state_dim,
        "state_high": (1.0,) * state_dim,
        "action_low": (-1.0,) * action_dim,
        "action_high": (1.0,) * action_dim,
        "n_hidden": 6,
        "n_wires": 4,
        "replay_capacity": 500,
    }
    base.update(kw)
    return LearnerConfig(**base)  # type: ignore[arg-type]


def random_experiences(
    rng: np.random.Generator, n: int, state_dim: int, action_dim: int, p_terminal: float = 0.1
) -> Experiences:
    return Experiences(
        rng.uniform(-1, 1, (n, state_dim)),
        rng.uniform(-1, 1, (n, action_dim)),
        rng.uniform(-1, 1, (n, state_dim)),
        rng.uniform(-2, 0.5, n),
        rng.random(n) < p_terminal,
    )
