"""Hand-coded Nomad behaviours: Cheng and Zelinsky's wandering (Fig 6.7) and the infrared veto.

The hand-coded wandering drives toward the longest uninterrupted vertical strip of carpet in the
carpet match matrix, or turns on the spot when no carpet is seen. The veto is the robot's safety
layer (Section 5.4): a command whose arc would bring the base into something its infrared ring
sees before it could stop is replaced by turning on the spot away from the nearest obstacle.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sims.nomad.vision import COLS, ROWS
from wfnn_common.config import check_fields

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, kw_only=True)
class WanderConfig:
    """Cheng and Zelinsky's wandering (Fig 6.7)."""

    carpet_below: float = 0.5
    """A cell whose filtered mismatch is below this counts as carpet."""
    speed: float = 0.4
    """Forward speed when the whole strip is carpet (m/s); less for shorter strips."""
    turn: float = 0.6
    """Rotational velocity toward the outermost column, and when turning on the spot (rad/s)."""

    def __post_init__(self) -> None:
        check_fields(self)


def strip_lengths(carpet: FloatArray, carpet_below: float) -> NDArray[np.int64]:
    """Uninterrupted carpet cells from the bottom row up, per column [COLS]."""
    is_carpet = np.asarray(carpet).reshape(ROWS, COLS) < carpet_below
    lengths = np.zeros(COLS, dtype=np.int64)
    for c in range(COLS):
        r = ROWS - 1
        while r >= 0 and is_carpet[r, c]:
            lengths[c] += 1
            r -= 1
    return lengths


def handcoded_wander(carpet: FloatArray, cfg: WanderConfig | None = None) -> FloatArray:
    """(T, R) toward the longest vertical strip of carpet (ties: nearest the middle)."""
    cfg = cfg or WanderConfig()
    lengths = strip_lengths(carpet, cfg.carpet_below)
    if lengths.max() == 0:
        return np.array([0.0, cfg.turn])
    middle = (COLS - 1) / 2
    best = max(range(COLS), key=lambda c: (lengths[c], -abs(c - middle)))
    # Column 0 is the image's left: turning left is a positive rotation.
    rotation = cfg.turn * (middle - best) / middle
    return np.array([cfg.speed * lengths[best] / ROWS, rotation])


def ir_veto(
    ir: Callable[[], FloatArray],
    angles: FloatArray,
    measured_speed: Callable[[], float],
    max_deceleration: float,
    radius: float,
    margin: float = 0.07,
    clearance: float = 0.05,
    turn: float = 0.5,
) -> Callable[[FloatArray, FloatArray], FloatArray | None]:
    """A veto rule over an infrared ring (the readings come from `ir()` when it is consulted).

    A proposed (T, R) is vetoed when the base, driving the arc it asks for over the stopping
    distance (at the deceleration limit, from the faster of the commanded and measured speed)
    plus `margin`, would come nearer than `clearance` to what the infrared sensors see, and
    nearer than it is now (sliding along a wall it already touches is allowed; moving toward
    it is not). Arcs matter: a robot turning while it drives sweeps its side into a pillar that
    a look straight ahead misses. The replacement stops translating and turns at `turn` rad/s
    away from the nearest seen point (for one dead ahead, the way the proposal turned, else
    left), and keeps turning that way while the vetoes continue: re-choosing every tick can
    rock the robot between two obstacles for ever. Keeping the proposed rotation could hold it
    against an obstacle its camera does not see. Turning on the spot is never vetoed (the base
    is round).
    """
    directions = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    fractions = np.linspace(0.0, 1.0, 9)[1:]
    turning = 0.0
    """The replacement's turn direction while vetoes continue (0: none vetoed last time)."""

    def veto(state: FloatArray, action: FloatArray) -> FloatArray | None:
        nonlocal turning
        speed, rotation = float(action[0]), float(action[1])
        if speed == 0.0:
            turning = 0.0
            return None
        points = (radius + ir()[:, None]) * directions  # what the ring sees, in the robot's frame
        fastest = max(abs(speed), abs(measured_speed()))
        length = fastest**2 / (2 * max_deceleration) + margin
        travelled = fractions * length
        heading = rotation / abs(speed) * travelled  # the arc's heading after each distance
        # Position on the arc after each distance (sinc keeps the straight line exact).
        along = travelled * np.sinc(heading / np.pi)
        aside = travelled * heading / 2 * np.sinc(heading / (2 * np.pi)) ** 2
        centres = np.sign(speed) * np.stack([along, aside], axis=1)  # [steps, 2]
        gaps = np.linalg.norm(points[None, :, :] - centres[:, None, :], axis=2).min(axis=0) - radius
        now = np.linalg.norm(points, axis=1) - radius
        if not (gaps.min() < clearance and gaps.min() < now.min() - 1e-3):
            turning = 0.0
            return None
        if not turning:
            side = np.sin(angles[np.argmin(now)])
            turning = float(-np.sign(side)) if abs(side) > 0.1 else float(np.sign(rotation) or 1.0)
        return np.array([0.0, turning * turn])

    return veto
