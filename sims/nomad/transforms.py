"""Servoing experiences the Nomad would have met otherwise (thesis Sections 2.5 and 6.6).

- `servo_mirror`: the left-right mirror image. The base is symmetric about its fore-aft axis, so
  a target left of the goal becomes one right of it, its horizontal pixel velocity and the
  rotation (measured and commanded) change sign; the reward (pixel error, energy, smoothness)
  is unchanged. Declared as data (`Symmetry`) for the learner config. Exact only for a camera
  facing straight ahead with the goal on the image's vertical midline (the default); a
  misaligned camera (Fig 6.14) breaks it, and asking for it then is an error.
- `phantom_goals`: learning from other goal positions. The same experience with the goal moved
  by an offset in the image: both pixel errors shift by it, the reward's pixel-error term is
  recomputed, the energy and smoothness terms stay. The state holds the pixel error, not where
  in the image the target is, so this is an approximation: the image motion an action causes
  depends on where the target is (a near target, low in the image, moves faster), and a copy
  says that motion happened at another error. Offsets near the real goal keep it close.

Pure numpy over servo states (x, y, dx, dy, t, r) [N, 6] and actions (T, R) [N, 2].
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from sims.nomad.config import NomadConfig
from wfnn_common.symmetry import Symmetry

FloatArray = NDArray[np.float64]
Block = tuple[FloatArray, FloatArray, FloatArray, FloatArray]

SERVO_MIRROR = Symmetry(
    name="mirror",
    state_index=(0, 1, 2, 3, 4, 5), state_sign=(-1.0, 1.0, -1.0, 1.0, 1.0, -1.0),
    action_index=(0, 1), action_sign=(1.0, -1.0),
)  # fmt: skip
"""The servoing's left-right mirror (see the module docstring)."""


def servo_mirror(config: NomadConfig | None = None) -> Symmetry:
    """The servoing's mirror symmetry, where `config`'s camera and goal make it exact."""
    cfg = config or NomadConfig()
    if cfg.camera_yaw_deg != 0.0 or cfg.vision.goal_px[0] != 0.0:
        raise ValueError(
            "the servoing is left-right symmetric only with the camera facing straight ahead and the "
            f"goal on the image's midline (camera_yaw_deg {cfg.camera_yaw_deg}, goal_px {cfg.vision.goal_px})"
        )
    return SERVO_MIRROR


def phantom_goals(
    state: FloatArray,
    action: FloatArray,
    next_state: FloatArray,
    reward: FloatArray,
    offset: FloatArray,
    config: NomadConfig | None = None,
) -> Block:
    """Servo experiences [N, ...] with the goal moved by `offset` [N, 2] pixels (x right, y down).

    The pixel errors of both states become error - offset; the reward's pixel-error term is that
    of the phantom goal (`NomadVec.reward_components`, Fig 6.10). Experiences must have a
    tracked target in both states (as every learnable servo experience has).
    """
    cfg = config or NomadConfig()
    half_diagonal = cfg.vision.half_diagonal
    offset = np.asarray(offset, dtype=np.float64)
    state, next_state = np.array(state, dtype=np.float64), np.array(next_state, dtype=np.float64)
    before = np.hypot(next_state[:, 0], next_state[:, 1])
    state[:, :2] -= offset
    next_state[:, :2] -= offset
    after = np.hypot(next_state[:, 0], next_state[:, 1])
    shaped = np.asarray(reward, dtype=np.float64) + cfg.position_weight * (before - after) / half_diagonal
    return state, np.array(action, dtype=np.float64), next_state, shaped
