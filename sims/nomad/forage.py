"""Foraging: wandering and target pursuit coordinated as in thesis Fig 6.3 and Section 6.6.

Wandering drives the robot until the interest operator finds a target; then target pursuit
dominates until the target passes out of view. With `pursue="every_second"` (Section 6.6) the
first interesting target found is only tracked, so that the servoing learner can learn from
the wandering behaviour's actions, and pursuit dominates for the second; `"never"` only ever
tracks (learning to servo purely by watching the wandering). A target held at the goal for
`collect_s` has been reached: the experimenter picks the ball up and puts it somewhere else,
and the robot wanders on.

The coordinator decides who drives; what each behaviour proposes and learns is up to its
caller (`wfnn-bench nomad`, `wfnn-client --sim nomad --behaviour forage`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal, cast

import numpy as np
from numpy.typing import NDArray

from sims.base import Ranges, Transition
from wfnn_common.config import check_fields

if TYPE_CHECKING:
    from sims.nomad.config import Behaviour
    from sims.nomad.task import NomadVec

Pursue = Literal["every", "every_second", "never"]
PURSUE: tuple[Pursue, ...] = ("every", "every_second", "never")


@dataclass(frozen=True, kw_only=True)
class ForageConfig:
    """When target pursuit takes over from wandering, and when a target counts as reached."""

    pursue: Pursue = "every"
    """Pursue every interesting target, every second one (Section 6.6), or none (watch only)."""
    collect_px: float = 15.0
    """A pursued target within this many pixels of the goal..."""
    collect_s: float = 2.0
    """...for this long has been reached, and is moved elsewhere."""
    quiet_s: float = 2.0
    """After a target is reached, no new one is looked for this long (the robot turns away)."""

    def __post_init__(self) -> None:
        check_fields(self)
        if self.pursue not in PURSUE:
            raise ValueError(f"pursue must be one of {PURSUE}, got {self.pursue!r}")
        if self.collect_px <= 0 or self.collect_s <= 0 or self.quiet_s < 0:
            raise ValueError("collect_px and collect_s must be > 0, quiet_s >= 0")


class Forage:
    """Per robot: which behaviour drives, and the target bookkeeping of foraging."""

    def __init__(self, task: NomadVec, config: ForageConfig | None = None) -> None:
        self.task = task
        self.config = config or ForageConfig()
        n = task.n
        self.found = np.zeros(n, dtype=np.int64)
        """Interesting targets found."""
        self.reached = np.zeros(n, dtype=np.int64)
        """Pursued targets held at the goal for `collect_s`."""
        self._pursuing = np.zeros(n, dtype=np.bool_)
        """Whether the target tracked now is pursued (else only watched)."""
        self._at_goal = np.zeros(n)
        self._quiet_until = np.full(n, -np.inf)

    def update(self) -> NDArray[np.bool_]:
        """Before each action: look for targets, retire reached ones -> pursuit dominates [n]."""
        task, cfg = self.task, self.config
        dt = 1.0 / task.config.rate_hz
        for i, tracker in enumerate(task.trackers):
            if not tracker.active and task.time[i] >= self._quiet_until[i] and task.acquire(i):
                self.found[i] += 1
                self._pursuing[i] = cfg.pursue == "every" or (
                    cfg.pursue == "every_second" and self.found[i] % 2 == 0
                )
                self._at_goal[i] = 0.0
            if not (tracker.active and self._pursuing[i]):
                continue
            close = float(np.hypot(*task.pixels[i])) < cfg.collect_px
            self._at_goal[i] = self._at_goal[i] + dt if close else 0.0
            if self._at_goal[i] >= cfg.collect_s - 1e-9:
                task.collect(i)
                self.reached[i] += 1
                self._quiet_until[i] = task.time[i] + cfg.quiet_s
        return self.pursuing()

    def pursuing(self) -> NDArray[np.bool_]:
        """Whether target pursuit dominates now, per robot [n]."""
        return np.asarray((self.task.tracked() >= 0) & self._pursuing)


class NomadForage:
    """Learned wandering and learned servoing foraging together (`sims.base.Behaviours`).

    `driving`: servoing while a pursued target is tracked, else wandering. The wandering learns
    from every action; the servoing from every action taken while a target is tracked (its own,
    and the wandering's while a target is only watched). The task must be configured to wander
    (its episodes carry on; no target is placed by the experimenter).
    """

    names: tuple[str, ...] = ("servo", "wander")

    def __init__(self, task: NomadVec, config: ForageConfig | None = None) -> None:
        if task.config.behaviour != "wander":
            raise ValueError("foraging drives a Nomad configured to wander")
        self.task = task
        self.forage = Forage(task, config)

    def ranges(self, name: str) -> Ranges:
        """The behaviour's declared state ranges; both command (T, R)."""
        low, high = self.task.state_bounds(self._behaviour(name))
        t = self.task
        return Ranges(low, high, t.action_low, t.action_high, valid_margin=getattr(t, "valid_margin", None),
                      max_reward=t.max_reward_of(self._behaviour(name)))  # fmt: skip

    def driving(self) -> NDArray[np.int64]:
        """0 (servo) where pursuit dominates, else 1 (wander) [n]."""
        return np.where(self.forage.update(), 0, 1).astype(np.int64)

    def observe(self, name: str) -> NDArray[np.float64]:
        """The behaviour's states [n, S]."""
        return self.task.observe(self._behaviour(name))

    def step(self, action: NDArray[np.float64]) -> dict[str, Transition]:
        """One action; the servo transition is learnable while the same target stays tracked."""
        task = self.task
        servo, valid, geoms = task.observe("servo"), task.valid("servo"), task.tracked()
        wander = task.step(action)
        next_servo = task.observe("servo")
        learnable = valid & task.valid("servo") & (task.tracked() == geoms)
        reward = task.reward(servo, action, next_servo, "servo")
        return {"servo": Transition(next_servo, reward, wander.terminal, learnable), "wander": wander}

    def reward(
        self,
        name: str,
        state: NDArray[np.float64],
        action: NDArray[np.float64],
        next_state: NDArray[np.float64],
    ) -> NDArray[np.float64]:
        """The behaviour's reward [n]."""
        return self.task.reward(state, action, next_state, self._behaviour(name))

    def _behaviour(self, name: str) -> Behaviour:
        if name not in self.names:
            raise ValueError(f"no behaviour {name!r}; foraging has {self.names}")
        return cast("Behaviour", name)
