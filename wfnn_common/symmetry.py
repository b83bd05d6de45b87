"""Declared symmetries of a task: experiences the robot would have met in a mirrored world.

A symmetry here is a signed permutation of the state variables and of the action variables that
leaves the reward unchanged: if the robot met (x, u, x', r), it would equally have met
(Tx, Ru, Tx', r). The boat is symmetric about its fore-aft axis (swap the thrusters, negate the
sway, the target's side and the turn rate), a mobile robot left-right, a binocular head about its
midline. A task declares them as data, so they travel inside the learner config to a think
server that knows nothing of the task, and every learner fed the same experiences learns the
same mirrored copies. Pure numpy; in physical units, before the learner scales anything.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from wfnn_common.checks import check_fields

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, kw_only=True)
class Symmetry:
    """new_state[..., i] = state_sign[i] * state[..., state_index[i]]; likewise for actions."""

    name: str
    state_index: tuple[int, ...]
    state_sign: tuple[float, ...]
    action_index: tuple[int, ...]
    action_sign: tuple[float, ...]

    def __post_init__(self) -> None:
        for name in ("state_index", "state_sign", "action_index", "action_sign"):
            if isinstance(getattr(self, name), list):  # JSON and callers give lists: taken as tuples
                object.__setattr__(self, name, tuple(getattr(self, name)))
        # Integers and real signs as given, never converted: 1.7 or true taken as an index, or
        # "-1" as a sign, would be another symmetry than the one written (or fail at learn).
        check_fields(self)
        for what in ("state", "action"):  # signs held as floats, as they always were (spec hashes)
            object.__setattr__(self, f"{what}_sign", tuple(float(x) for x in getattr(self, f"{what}_sign")))
        for what, index, sign in (("state", self.state_index, self.state_sign),
                                  ("action", self.action_index, self.action_sign)):  # fmt: skip
            if sorted(index) != list(range(len(index))):
                raise ValueError(f"symmetry {self.name!r}: {what}_index must be a permutation, got {index}")
            if len(sign) != len(index) or any(s not in (-1.0, 1.0) for s in sign):
                raise ValueError(
                    f"symmetry {self.name!r}: {what}_sign must be one +1 or -1 per variable, got {sign}"
                )

    def check_dims(self, state_dim: int, action_dim: int) -> None:
        """Raise ValueError unless this symmetry is over `state_dim` states and `action_dim` actions."""
        if len(self.state_index) != state_dim or len(self.action_index) != action_dim:
            raise ValueError(
                f"symmetry {self.name!r} is over {len(self.state_index)} state and "
                f"{len(self.action_index)} action variables, the task has {state_dim} and {action_dim}"
            )

    def states(self, state: FloatArray) -> FloatArray:
        """Transform states [..., S]."""
        return np.asarray(state, dtype=np.float64)[..., list(self.state_index)] * np.asarray(self.state_sign)

    def actions(self, action: FloatArray) -> FloatArray:
        """Transform actions [..., A]."""
        return np.asarray(action, dtype=np.float64)[..., list(self.action_index)] * np.asarray(
            self.action_sign
        )

    def __call__(
        self, state: FloatArray, action: FloatArray, next_state: FloatArray, reward: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """The transformed experiences: (state [N, S], action [N, A], next_state [N, S], reward [N])."""
        return (self.states(state), self.actions(action), self.states(next_state),
                np.array(reward, dtype=np.float64))  # fmt: skip

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Symmetry:
        """Inverse of `dataclasses.asdict` (JSON lists become tuples); unknown keys are refused."""
        fields = {"name", "state_index", "state_sign", "action_index", "action_sign"}
        if isinstance(data, dict) and set(data) - fields:  # a typo ("statesign") was dropped unseen
            unknown = sorted(str(k)[:40] for k in set(data) - fields)[:10]
            raise ValueError(f"not a symmetry: unknown fields {unknown}")
        try:
            return cls(
                name=data["name"],
                state_index=tuple(data["state_index"]),
                state_sign=tuple(data["state_sign"]),
                action_index=tuple(data["action_index"]),
                action_sign=tuple(data["action_sign"]),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"not a symmetry: {str(data)[:200]} ({exc})") from exc
