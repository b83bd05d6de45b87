"""Cart-pole with continuous force and pure-delayed reward (thesis Section 4.5, Eq 4.3).

Force F in [-10, 10] N; the trial fails when the pole passes 12 degrees or the cart reaches
the end of the 2.4 m track (|x| > 2.4 m from the centre, as in Barto et al. 1983). Reward is
0 on every step and -1 on failure, which is terminal; the system is then reset.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sims.base import TaskEnv, Transition, actions
from wfnn_common.config import check_fields

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, kw_only=True)
class CartPoleConfig:
    """Constants of Eq 4.3 (the thesis' values)."""

    g: float = 9.81
    cart_mass: float = 1.0
    pole_mass: float = 0.1
    half_length: float = 0.5
    cart_friction: float = 0.0005
    pole_friction: float = 0.000002
    dt: float = 0.02
    """Euler step (s), one per action."""
    max_angle: float = float(np.deg2rad(12.0))
    track_limit: float = 2.4
    max_force: float = 10.0
    reset_noise: float = 0.0
    """Uniform noise on every state variable at reset (0: start upright at rest in the centre)."""

    def __post_init__(self) -> None:
        check_fields(self)
        positive = ("g", "cart_mass", "pole_mass", "half_length", "dt", "max_angle", "track_limit")
        for name in (*positive, "max_force"):  # masses or a length of 0 gave NaN states that never failed
            if not 0.0 < getattr(self, name) <= 1e6:
                raise ValueError(f"cart-pole: {name} must be in (0, 1e6], got {getattr(self, name)}")
        for name in ("cart_friction", "pole_friction", "reset_noise"):
            if not 0.0 <= getattr(self, name) <= 1e6:
                raise ValueError(f"cart-pole: {name} must be in [0, 1e6], got {getattr(self, name)}")


class CartPoleVec:
    """n cart-poles as arrays; each resets itself after failing."""

    state_low: tuple[float, ...] = (-2.4, -3.0, -0.21, -3.0)
    state_high: tuple[float, ...] = (2.4, 3.0, 0.21, 3.0)
    action_low: tuple[float, ...] = (-10.0,)
    action_high: tuple[float, ...] = (10.0,)
    state_names = ("x", "x_dot", "theta", "theta_dot")

    def __init__(self, n: int, config: CartPoleConfig | None = None) -> None:
        self.n = n
        self.config = config or CartPoleConfig()
        self.state = np.zeros((n, 4))
        self.steps = np.zeros(n, dtype=np.int64)
        """Steps balanced in the current attempt."""
        self.last_attempt = np.zeros(n, dtype=np.int64)
        """Length in steps of each system's last finished attempt."""
        self._rng = np.random.default_rng(0)

    def reset(self, rng: np.random.Generator) -> FloatArray:
        """All systems upright at rest (plus optional reset noise)."""
        self._rng = rng
        self.restart(np.ones(self.n, dtype=np.bool_))
        return self.observe()

    def restart(self, which: NDArray[np.bool_]) -> None:
        """Start a new attempt for the systems `which` (upright at rest, plus reset noise)."""
        k = int(which.sum())
        self.last_attempt[which] = np.where(
            self.steps[which] > 0, self.steps[which], self.last_attempt[which]
        )
        noise = self.config.reset_noise
        self.state[which] = self._rng.uniform(-noise, noise, size=(k, 4)) if noise > 0 else 0.0
        self.steps[which] = 0

    def observe(self) -> FloatArray:
        """States [n, 4]: x, x_dot, theta, theta_dot."""
        return self.state.copy()

    def step(self, action: FloatArray) -> Transition:
        """One Euler step of Eq 4.3.

        Failed systems report their failure state, then restart: the next `observe` shows the
        fresh start.
        """
        cfg = self.config
        force = np.clip(actions(action, self.n, 1)[:, 0], -cfg.max_force, cfg.max_force)
        x, x_dot, theta, theta_dot = self.state.T
        total = cfg.cart_mass + cfg.pole_mass
        sin, cos = np.sin(theta), np.cos(theta)
        friction = cfg.cart_friction * np.sign(x_dot)
        theta_acc = (
            cfg.g * sin
            + cos * ((-force - cfg.pole_mass * cfg.half_length * theta_dot**2 * sin + friction) / total)
            - cfg.pole_friction * theta_dot / (cfg.pole_mass * cfg.half_length)
        ) / (cfg.half_length * (4.0 / 3.0 - cfg.pole_mass * cos**2 / total))
        x_acc = (
            force + cfg.pole_mass * cfg.half_length * (theta_dot**2 * sin - theta_acc * cos) - friction
        ) / total
        self.state = np.stack(
            [
                x + cfg.dt * x_dot,
                x_dot + cfg.dt * x_acc,
                theta + cfg.dt * theta_dot,
                theta_dot + cfg.dt * theta_acc,
            ],
            axis=1,
        )
        failed = (np.abs(self.state[:, 2]) > cfg.max_angle) | (np.abs(self.state[:, 0]) > cfg.track_limit)
        out = self.state.copy()
        self.steps += 1
        if failed.any():
            self.restart(failed)
        return Transition(out, np.where(failed, -1.0, 0.0), failed, np.ones(self.n, dtype=np.bool_))


class CartPoleEnv(TaskEnv):
    """Gymnasium cart-pole; an episode ends at failure or after `max_steps`."""

    def __init__(self, config: CartPoleConfig | None = None, max_steps: int = 10_000) -> None:
        super().__init__(CartPoleVec(1, config), max_steps)
