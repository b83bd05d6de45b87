"""The safety layer between the learner's proposed action and the actuators (thesis Section 5.4).

In order, each tick: no valid weights -> the safe action; the action filter limits how fast
each action component may change (a maximum acceleration for velocity commands); a veto
(hand-written rules over sensors outside the learner's state) may replace the action; and a
command computed after its deadline is stale, so the safe action goes out instead. Every
substitution is counted. A vetoed tick is learned twice: the executed action (Eq 5.1) and the
proposed one with the observed outcome and its own reward (Eq 5.4).
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from wfnn_common.config import check_fields
from wfnn_io.protocol import EXP_FILTERED, EXP_SAFE_ACTION, EXP_VETO_ACTUAL

log = logging.getLogger(__name__)
FloatArray = NDArray[np.float64]

Veto = Callable[[FloatArray, FloatArray], FloatArray | None]
"""veto(state [S], action [A]) -> the action to execute instead, or None to allow it."""


@dataclass(frozen=True, kw_only=True)
class SafetyConfig:
    """Filters, vetoes and the safe action of the client."""

    safe_action: tuple[float, ...] | None = None
    """Executed when no valid weights exist yet or a command misses its deadline (None: zero,
    clipped into the action range, e.g. zero velocity); one outside the action range is refused."""
    max_action_rate: tuple[float, ...] | None = None
    """Largest change of each action component per second (None: no filter)."""
    act_deadline_fraction: float = 0.5
    """A command ready later than this fraction of the tick period after the tick's deadline is
    stale and replaced by the safe action (real-time runs only)."""
    veto: bool = True
    """Apply the robot's veto rules, where it has any."""
    learn_twice: bool = True
    """Learn a vetoed proposal as well as the executed action (Eq 5.1 and 5.4)."""

    def __post_init__(self) -> None:
        check_fields(self)
        if not 0.0 < self.act_deadline_fraction <= 1.0:
            raise ValueError(f"act_deadline_fraction must be in (0, 1], got {self.act_deadline_fraction}")
        if self.max_action_rate is not None and any(not r > 0 for r in self.max_action_rate):
            raise ValueError(f"max_action_rate must be positive, got {self.max_action_rate}")


class Decision(NamedTuple):
    """What goes to the actuators this tick, and why."""

    executed: FloatArray
    """Action executed [A]."""
    proposed: FloatArray | None
    """The learner's action [A] when a veto replaced it (to learn twice), else None."""
    flags: int
    """EXP_* flags of the executed action's experience."""


class SafetyLayer:
    """Applies `SafetyConfig` to one robot's actions and counts what it changed."""

    def __init__(
        self,
        config: SafetyConfig,
        action_low: tuple[float, ...],
        action_high: tuple[float, ...],
        period_s: float,
        veto: Veto | None = None,
        step_s: float = 1.0,
    ) -> None:
        """A safety layer for one robot.

        `period_s` is the tick's period (0: as fast as possible); `step_s` the period one tick
        stands for then, for the rate filter: the task's own real-time tick.
        """
        self.config = config
        self.low = np.asarray(action_low, dtype=np.float64)
        self.high = np.asarray(action_high, dtype=np.float64)
        safe = (
            np.zeros_like(self.low) if config.safe_action is None else np.asarray(config.safe_action, float)
        )
        if safe.shape != self.low.shape:
            raise ValueError(f"safe_action needs {self.low.size} components, got {safe.size}")
        if config.safe_action is not None:
            # A stand-in the robot cannot execute is a mistake to say, not to clip silently: the
            # clipped action may be far from the safe one meant (a full brake clipped to half).
            outside = [i for i in range(safe.size) if not self.low[i] <= safe[i] <= self.high[i]]
            if outside:
                i = outside[0]
                raise ValueError(f"safe_action component {i} is {safe[i]:g}, outside the action range "
                                 f"[{self.low[i]:g}, {self.high[i]:g}]")  # fmt: skip
        self.safe = np.clip(safe, self.low, self.high)
        self.max_step: FloatArray | None = None
        if config.max_action_rate is not None:
            rate = np.asarray(config.max_action_rate, dtype=np.float64)
            if rate.shape != self.low.shape:
                raise ValueError(f"max_action_rate needs {self.low.size} components, got {rate.size}")
            # As fast as possible (period 0) is a simulation: one tick stands for a tick at the
            # task's own real-time rate, so the same robot is filtered alike at its own rate and
            # in lock-step (it counted as a second: a filter 15 to 50 times looser there). The
            # boat's and positioning's real-time ticks (50 Hz) are not their simulated steps (0.1
            # and 1 time unit): "per second" is the robot's wall-clock second, as on hardware.
            self.max_step = rate * (period_s if period_s > 0 else step_s)
        self.deadline_s = config.act_deadline_fraction * period_s if period_s > 0 else float("inf")
        self.veto = veto if config.veto else None
        self.previous = self.safe.copy()
        self._last_warning = -1e9
        self.counts: Counter[str] = Counter()
        """Substitutions by reason: no_weights, late, vetoed, filtered."""

    def decide(self, proposed: FloatArray | None, state: FloatArray, late_s: float) -> Decision:
        """The action to execute for the learner's `proposed` (None: no valid weights) in `state`.

        `late_s` is how long after the tick's deadline the proposal became ready. Without valid
        weights, with a non-finite proposal or a late one, the safe action stands in for it; the
        action filter and the veto then apply to whichever it is (a non-zero safe action is still
        an action: it must not jump, nor drive into what the veto forbids).
        """
        out_proposed = None
        stand_in = ("no_weights" if proposed is None
                    else "non_finite" if not np.isfinite(proposed).all()  # clipping keeps a NaN
                    else "late" if late_s > self.deadline_s else "")  # fmt: skip
        if stand_in:
            self.counts[stand_in] += 1
            action, flags = self._filtered(self.safe.copy(), EXP_SAFE_ACTION)
        else:
            action, flags = self._filtered(np.clip(np.asarray(proposed), self.low, self.high), 0)
        if self.veto is not None:
            replacement = self.veto(state, action)
            if replacement is not None:
                self.counts["vetoed"] += 1
                now = time.monotonic()
                if now - self._last_warning >= 1.0:  # the audible warning, at most once a second
                    self._last_warning = now
                    log.warning("veto: proposed action %s replaced by %s (%d vetoes so far)",
                                np.round(action, 3), replacement, self.counts["vetoed"])  # fmt: skip
                # Only the learner's own proposal is learned twice: the safe action is not its choice.
                out_proposed = None if flags & EXP_SAFE_ACTION else action
                action = np.clip(np.asarray(replacement, dtype=np.float64), self.low, self.high)
                flags |= EXP_VETO_ACTUAL
                if not np.isfinite(action).all():  # a behaviour's veto gone wrong: stop instead
                    self.counts["non_finite"] += 1
                    action, flags = self._filtered(self.safe.copy(), EXP_SAFE_ACTION)
                    out_proposed = None
        self.previous = action
        return Decision(action, out_proposed, flags)

    def _filtered(self, action: FloatArray, flags: int) -> tuple[FloatArray, int]:
        """`action` [A] moved at most `max_step` from the last one executed, and its flags."""
        if self.max_step is None:
            return action, flags
        limited = np.clip(action, self.previous - self.max_step, self.previous + self.max_step)
        if np.array_equal(limited, action):
            return action, flags
        self.counts["filtered"] += 1
        return limited, flags | EXP_FILTERED
