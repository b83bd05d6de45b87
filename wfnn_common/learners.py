"""One learner interface over the thesis' learner (`WFNN`) and the deep one (`DeepWFNN`).

The local brain, the think server, persistence, the dashboard and the benchmarks use a learner
through `Learner` only, and make one from its config with `make_learner`: the config's
`learner` field names which. A learner's weights for `act` (`Weights`) are one flat float64
vector per network whatever the learner, so snapshots, checkpoints and the wire protocol carry
both alike; `weights_from_flat` gives them their layout from the config.

Nothing here imports torch: the robot side makes learners to act with.
"""

from __future__ import annotations

from contextlib import AbstractContextManager
from typing import Any, Protocol, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wfnn_common.config import LearnerConfig
from wfnn_common.deep_net import DeepParams, DeepShapes
from wfnn_common.learner import WFNN, ActResult, DivergenceMonitor
from wfnn_common.network import Params, Shapes
from wfnn_common.replay import Experiences, ReplayBuffer
from wfnn_common.update import UpdateStats

Weights = Params | DeepParams
"""What `act` needs: the weights of P networks over a flat [P, n_params] float64 array."""


class Learner(Protocol):
    """What the service asks of a learner (both learners are populations of P; deep: P = 1)."""

    config: LearnerConfig
    population: int
    params: Any
    """The current weights (`Weights`) that `act` uses when no snapshot is given."""
    buffer: ReplayBuffer
    monitor: DivergenceMonitor
    thinks: NDArray[np.int64]
    """Weight updates done per learner."""
    resets: NDArray[np.int64]
    """Divergence resets per learner."""
    rejected: NDArray[np.int64]
    """Experiences refused by the sanity limits per learner."""

    def act(self, state: ArrayLike, explore: bool = True, params: Any = None) -> ActResult:
        """Part 1: the best wire's action (explored if asked), from `params` or the learner's own weights."""

    def learn(self, state: ArrayLike, action: ArrayLike, next_state: ArrayLike, reward: ArrayLike,
              terminal: ArrayLike = False, valid: ArrayLike = True) -> Any:  # fmt: skip
        """Part 1i: store an experience (checked by the sanity limits); -> whether it was stored."""

    def learn_many(self, state: ArrayLike, action: ArrayLike, next_state: ArrayLike, reward: ArrayLike,
                   terminal: ArrayLike) -> NDArray[np.bool_]:  # fmt: skip
        """Store a block of experiences [N, ...]; -> which were stored [N]."""

    def think(self, n: int | None = None) -> UpdateStats:
        """Parts 2-3: n updates (default thinks_per_action)."""

    def think_on(self, exp: Experiences, active: Any = None, params: Any = None) -> UpdateStats:
        """Learn from the given experiences (not from the replay buffer)."""

    def snapshot(self) -> Any:
        """A copy of the weights `act` uses (`Weights`)."""

    def evaluating(self) -> AbstractContextManager[Any]:
        """Greedy evaluation beside training: a copy of the weights to act on (`WFNN.evaluating`)."""

    def reset_weights(self, which: NDArray[np.bool_]) -> None:
        """Fresh weights for the learners `which` (after divergence); experiences kept."""

    def greedy_values(self, state: ArrayLike) -> NDArray[np.float64]:
        """Value of the best wire at states [N, S] -> [P, N]."""

    def q_value(self, state: ArrayLike, action: ArrayLike) -> Any:
        """Q(x, u) by wire fitting."""

    def experienced(self, n: int) -> None:
        """Count n experiences this robot produced before (a journal's): the deep learner's warm-up."""

    def rewarded(self, reward: ArrayLike) -> None:
        """Rewards [N] a robot acting on snapshots met (not learned here).

        What `learn` would judge values by: the deep learner's divergence threshold follows the
        rewards' size.
        """

    def prepare_thinking(self, compile: bool = False) -> None:
        """Load what thinking needs now, before the caller starts its threads (the deep learner: torch).

        With `compile`, also compile what thinking would compile in its first call (the deep learner's
        update, where deep.compile is set): for a caller beside whose loop thinking runs later.
        """

    def training_state(self) -> dict[str, NDArray[Any]]:
        """What training needs beyond the weights to resume (saved with checkpoints)."""

    def load_training_state(self, state: dict[str, Any]) -> None:
        """Resume from `training_state`'s arrays (ValueError if they do not fit)."""


W = TypeVar("W")


def ready_to_act(params: W) -> W:
    """`params`, with what `act` derives from them made now (the deep learner's layout).

    The thread that hands new weights to a robot's tick calls this: made in the tick's first `act`
    on them, a large network's layout (tens of milliseconds) made that tick late.
    """
    getattr(params, "act_layout", None)  # made once and kept by the weights; the thesis' have none
    return params


def make_learner(config: LearnerConfig, population: int = 1, params: Weights | None = None) -> Learner:
    """The learner the config names, with given weights (for `act`) or fresh ones."""
    kind = DeepParams if config.learner == "deep" else Params
    if params is not None and not isinstance(params, kind):
        raise ValueError(f"weights of type {type(params).__name__} do not fit learner {config.learner!r}")
    if config.learner == "deep":
        from wfnn_common.deep import DeepWFNN

        return DeepWFNN(config, population, params)  # type: ignore[arg-type]
    return WFNN(config, population, params)  # type: ignore[arg-type]


def n_params(config: LearnerConfig) -> int:
    """Parameters of one network `act` uses (the length of a snapshot's vector)."""
    return DeepShapes.of(config).n_params if config.learner == "deep" else Shapes.of(config).n_params


def weights_from_flat(config: LearnerConfig, flat: NDArray[np.float64]) -> Weights:
    """Weights over a flat [P, n_params] float64 array (ValueError where it does not fit)."""
    if config.learner == "deep":
        return DeepParams(flat, DeepShapes.of(config))
    return Params(flat, Shapes.of(config))


def make_population(config: LearnerConfig, population: int) -> Any:
    """P independently learning controllers of the config's learner, fresh, for benchmarks.

    The thesis' learner is one `WFNN` over P networks; the deep learner, P `DeepWFNN`s behind
    the same array interface (`deep.DeepPopulation`: act, learn, think, snapshot, counters).
    """
    if config.learner == "deep":
        from wfnn_common.deep import DeepPopulation

        return DeepPopulation(config, population)
    return WFNN(config, population)
