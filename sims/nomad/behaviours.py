"""Hand-coded Nomad behaviours: Cheng and Zelinsky's wandering (Fig 6.7) and the infrared veto.

The hand-coded wandering drives toward the longest uninterrupted vertical strip of carpet in the
carpet match matrix, or turns on the spot when no carpet is seen. The veto is the robot's safety
layer (Section 5.4): a command that would drive the base into something its infrared ring sees
within stopping distance is replaced by turning on the spot away from the nearest obstacle.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sims.nomad.vision import COLS, ROWS

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
    margin: float = 0.12,
    arc_deg: float = 50.0,
    turn: float = 0.5,
) -> Callable[[FloatArray, FloatArray], FloatArray | None]:
    """A veto rule over an infrared ring (the readings come from `ir()` when it is consulted).

    A proposed (T, R) is vetoed when a sensor within `arc_deg` of the direction of travel reads
    less than the stopping distance at the faster of the commanded and measured speed plus
    `margin`. The replacement stops translating and turns at `turn` rad/s away from the nearest
    of those readings (for one dead ahead, the way the proposal turned, else left): keeping the
    proposed rotation could hold the robot against an obstacle its camera does not see.
    """
    cos_arc = np.cos(np.deg2rad(arc_deg))

    def veto(state: FloatArray, action: FloatArray) -> FloatArray | None:
        speed = float(action[0])
        if speed == 0.0:
            return None
        readings = ir()
        ahead = np.cos(angles) * np.sign(speed) >= cos_arc
        fastest = max(abs(speed), abs(measured_speed()))
        stopping = fastest**2 / (2 * max_deceleration) + margin
        close = ahead & (readings < stopping)
        if not close.any():
            return None
        nearest = angles[close][np.argmin(readings[close])]
        side = np.sin(nearest)
        direction = -np.sign(side) if abs(side) > 0.1 else (np.sign(action[1]) or 1.0)
        return np.array([0.0, float(direction * turn)])

    return veto
