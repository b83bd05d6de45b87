"""What a Nomad task is configured with (`NomadConfig`): read by its physics, room, senses and rewards."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from sims.nomad.model import MAX_BALLS, N_BALLS
from sims.nomad.vision import COLS, ROWS, NomadVisionConfig
from wfnn_common.config import check_fields

Behaviour = Literal["servo", "wander"]
BEHAVIOURS: tuple[Behaviour, ...] = ("servo", "wander")


@dataclass(frozen=True, kw_only=True)
class NomadConfig:
    """The behaviour learned, the robot's limits, rewards and episodes."""

    behaviour: Behaviour = "servo"
    rate_hz: float = 10.0
    substeps: int = 50
    """Physics steps per action."""
    max_translation: float = 0.5
    """Largest translational velocity command (m/s), forward or backward."""
    max_rotation: float = 0.8
    """Largest rotational velocity command (rad/s)."""
    max_acceleration: tuple[float, float] = (0.5, 2.0)
    """Acceleration limits of the low-level controller (m/s^2, rad/s^2)."""
    encoder_noise: tuple[float, float] = (0.01, 0.02)
    """Standard deviation of the measured velocities (m/s, rad/s)."""
    encoder_glitch: float = 0.001
    """Probability per action that the encoders report a wild value."""
    camera_yaw_deg: float = 0.0
    """Camera turned away from the direction of travel (Fig 6.14)."""
    pixel_velocity_range: float = 400.0
    """Declared range of target pixel velocities (px/s) for the learner's scaling."""
    position_weight: float = 3.0
    """servo: penalty per half image diagonal of pixel error."""
    energy_weight: float = 0.01
    """servo: penalty weight of (T^2 + R^2), velocities in units of their limits."""
    smoothness_weight: float = 0.05
    """Penalty weight of ((T - t)^2 + (R - r)^2), velocities in units of their limits. Small:
    the base accelerates slowly, so a command differs from the measured velocity for several
    actions; with 0.5 (and energy 0.1) the servo controllers hardly drove toward far targets in
    early `wfnn-bench nomad` runs, made before the velocity ramp was corrected and not repeated
    since."""
    carpet_weight: float = 1.0
    """wander: penalty weight of the row-weighted carpet mismatch (0..1)."""
    forward_weight: float = 0.5
    """wander: reward weight of the measured forward velocity (in units of its limit)."""
    target_distance: tuple[float, float] = (0.8, 2.6)
    """servo: a new target is placed this far ahead of the camera (m)..."""
    target_bearing_deg: float = 18.0
    """...within this bearing of the camera's direction."""
    lost_reset_s: float = 1.0
    """servo: after the target has been lost this long it is placed again (not learned across)."""
    ir_sensors: int = 16
    ir_range: float = 1.0
    """Infrared readings saturate at this range (m from the robot's surface)."""
    person_speed: float = 0.4
    """The walking person's speed (m/s; 0 keeps them still)."""
    balls: int = N_BALLS
    """Balls in the arena (objects to pursue)."""
    vision: NomadVisionConfig = field(default_factory=NomadVisionConfig)

    def __post_init__(self) -> None:
        check_fields(self)
        if self.behaviour not in BEHAVIOURS:
            raise ValueError(f"behaviour must be one of {BEHAVIOURS}, got {self.behaviour!r}")
        if not 1 <= self.balls <= MAX_BALLS:  # checked here too: a run's config is made before its model
            raise ValueError(f"balls must be in [1, {MAX_BALLS}], got {self.balls}")
        if not 0 < self.rate_hz <= 1000 or self.substeps < 3:
            raise ValueError(
                f"rate_hz must be in (0, 1000] and substeps >= 3, got {self.rate_hz}, {self.substeps}"
            )

    @property
    def max_velocity(self) -> tuple[float, float]:
        """Largest (T, R) commands (m/s, rad/s)."""
        return (self.max_translation, self.max_rotation)

    @property
    def state_names(self) -> tuple[str, ...]:
        """Names of the state variables, in order."""
        motion = ("t_measured", "r_measured")
        if self.behaviour == "servo":
            return ("x_error_px", "y_error_px", "x_velocity_px_s", "y_velocity_px_s", *motion)
        return tuple(f"carpet_{r}_{c}" for r in range(ROWS) for c in range(COLS)) + motion
