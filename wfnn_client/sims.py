"""The simulated robots `wfnn-client --sim` can drive, with what the client needs of each.

Each entry builds the task, says how episodes start and are scored, and optionally gives the
reward of an action that was never executed (for learning a vetoed proposal, Eq 5.4) and the
robot's veto rules (sensors outside the learner's state).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sims.base import Behaviours, Ranges, Transition, VecTask
from sims.boat import BoatConfig, BoatVec, handcoded_boat
from sims.boat import reward_terms as boat_reward_terms
from sims.cartpole import CartPoleVec
from sims.gym import GymVec
from sims.hydra import HydraConfig, HydraVec
from sims.nomad import ForageConfig, NomadConfig, NomadForage, NomadVec, handcoded_wander
from sims.positioning import PositioningVec, handcoded_positioning
from wfnn_client.safety import Veto
from wfnn_common.config import check_fields
from wfnn_io.persist import load_weights

FloatArray = NDArray[np.float64]
Policy = Callable[[FloatArray], FloatArray]
"""A controller: state [S] -> action [A] (physical units)."""
RewardOf = Callable[[FloatArray, FloatArray, FloatArray], float]
"""reward_of(state [S], action [A], next_state [S]) -> reward, for an action not executed."""


@dataclass(frozen=True, kw_only=True)
class SimOptions:
    """What building a simulated task takes from the client's options (`ClientConfig.sim_options`)."""

    boat_dt: float = 0.1
    """Boat time per action (see sims.boat)."""
    env: str | None = None
    """`sim` gym: the Gymnasium task id."""
    hydra: HydraConfig = field(default_factory=HydraConfig)
    nomad: NomadConfig = field(default_factory=NomadConfig)
    forage: ForageConfig | None = None
    """nomad: learned wandering and learned servoing, one learner each (Fig 6.3)."""
    seed: int = 0
    weights: Path | None = None
    """The weights the run starts from (`--weights`): gym takes the state ranges saved with them."""

    def __post_init__(self) -> None:
        check_fields(self)


@dataclass(frozen=True)
class SimSpec:
    """How the client drives one simulated task."""

    make: Callable[[SimOptions], VecTask]
    """Build the task (one instance) from the client's options."""
    episode_steps: int | Callable[[Any], int]
    """Actions per episode (or a function of the task instance)."""
    new_episode: Callable[[Any, np.random.Generator], None]
    metric: Callable[[Any], FloatArray]
    """Per-step performance figure, averaged per episode (its name says which way is better)."""
    metric_name: str | Callable[[Any], str]
    reward_of: Callable[[Any], RewardOf] | None = None
    """Build the reward function of never-executed actions for a task instance."""
    veto: Callable[[Any], Veto] | None = None
    """Build the veto rules for a task instance."""
    rate_hz: float = 50.0
    """The task's control rate in real time (when the client is not told otherwise)."""
    exploration: str = "uniform"
    """The exploration kind used unless the client is told otherwise (robots: gaussian, as in
    Section 6.4.1; a uniform random action throws an active head off its target)."""
    advantage_k: float | None = None
    """The task's advantage-learning constant unless the client is told otherwise (None: the
    thesis' default, 0.2)."""
    views: Callable[[Any], dict[str, NDArray[np.uint8]]] | None = None
    """What the robot's cameras see now ({camera: [h, w, 3] RGB}), for tasks with cameras."""
    behaviours: Callable[[Any, SimOptions], Behaviours | None] | None = None
    """Several learned behaviours over the task instance, one learner each (None: the task's one)."""
    handcoded: Callable[[Any], Policy | None] | None = None
    """The task's hand-coded controller for a task instance (state [S] -> action [A]), for
    `--behaviour-policy handcoded`."""


class OneBehaviour:
    """A task's single learned behaviour, as `sims.base.Behaviours` (named "")."""

    names: tuple[str, ...] = ("",)

    def __init__(self, task: VecTask, reward_of: RewardOf | None) -> None:
        self.task = task
        self.reward_of = reward_of

    def ranges(self, name: str) -> Ranges:
        """The task's declared ranges."""
        return Ranges.of(self.task)

    def driving(self) -> NDArray[np.int64]:
        """Always the one behaviour."""
        return np.zeros(self.task.n, dtype=np.int64)

    def observe(self, name: str) -> FloatArray:
        """The task's states."""
        return self.task.observe()

    def step(self, action: FloatArray) -> dict[str, Transition]:
        """The task's step."""
        return {"": self.task.step(action)}

    def reward(self, name: str, state: FloatArray, action: FloatArray, next_state: FloatArray) -> FloatArray:
        """`reward_of` row by row (the sim must provide one)."""
        if self.reward_of is None:
            raise ValueError("this sim cannot reward an action it did not execute")
        return np.array(
            [self.reward_of(s, a, s2) for s, a, s2 in zip(state, action, next_state, strict=True)]
        )


def _boat_reward(task: BoatVec) -> RewardOf:
    cfg = task.config

    def reward_of(state: FloatArray, action: FloatArray, next_state: FloatArray) -> float:
        # Eq 3.8 with the proposed thrusts; the distance is the one observed after the step.
        u = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)[None]
        distance = np.hypot(next_state[None, 0], next_state[None, 1])
        return float(boat_reward_terms(cfg, distance, u, np.asarray(state)[None, 5:7]).sum())

    return reward_of


def _positioning_reward(task: PositioningVec) -> RewardOf:
    cfg = task.config

    def reward_of(state: FloatArray, action: FloatArray, next_state: FloatArray) -> float:
        # The velocity the proposed command asks for is charged, not the one executed.
        return -(
            abs(float(next_state[0])) + cfg.velocity_weight * abs(cfg.gain * float(np.clip(action[0], -1, 1)))
        )

    return reward_of


def positioning_wall_veto(task: PositioningVec, wall: float = 1.2) -> Veto:
    """Stop commands that drive the object further past +-wall (an absolute position sensor)."""

    def veto(state: FloatArray, action: FloatArray) -> FloatArray | None:
        position = float(task.position[0])
        if abs(position) >= wall and np.sign(action[0]) == np.sign(position):
            return np.zeros_like(action)
        return None

    return veto


SIMS: dict[str, SimSpec] = {
    "boat": SimSpec(
        make=lambda c: BoatVec(1, BoatConfig(dt=c.boat_dt)),
        episode_steps=200,
        new_episode=lambda task, rng: task.new_targets(rng),
        metric=lambda task: task.distance(),
        metric_name="mean distance to target",
        reward_of=_boat_reward,
        handcoded=lambda task: lambda state: handcoded_boat(state[None])[0],
    ),
    "positioning": SimSpec(
        make=lambda c: PositioningVec(1),
        episode_steps=200,
        new_episode=lambda task, rng: None,
        metric=lambda task: np.abs(task.target - task.position),
        metric_name="mean position error",
        reward_of=_positioning_reward,
        veto=positioning_wall_veto,
        handcoded=lambda task: lambda state: handcoded_positioning(state[None])[0],
    ),
    "cartpole": SimSpec(
        make=lambda c: CartPoleVec(1),
        episode_steps=500,
        new_episode=lambda task, rng: None,
        metric=lambda task: (task.steps == 0).astype(np.float64),
        metric_name="failures per step",
    ),
}
SIMS["hydra"] = SimSpec(
    make=lambda c: HydraVec(1, c.hydra, seed=c.seed),
    episode_steps=450,
    new_episode=lambda task, rng: task.new_targets(rng),
    metric=lambda task: task.pixel_error(),
    metric_name="mean |pixel error| (lost: half the image)",
    rate_hz=HydraConfig().rate_hz,  # the rate it is simulated at: one source
    exploration="gaussian",
    # Measured on this simulation (README): advantage learning (k 0.2) diverges and is reset
    # repeatedly where one-step Q-learning learns steadily.
    advantage_k=1.0,
    views=lambda task: task.camera_images(0),
)


def _nomad_reward(task: NomadVec) -> RewardOf:
    def reward_of(state: FloatArray, action: FloatArray, next_state: FloatArray) -> float:
        return float(task.reward(state[None], action[None], next_state[None])[0])

    return reward_of


SIMS["nomad"] = SimSpec(
    make=lambda c: NomadVec(1, c.nomad, seed=c.seed),
    episode_steps=lambda task: 150 if task.config.behaviour == "servo" else 600,
    new_episode=lambda task, rng: task.new_targets(rng),
    metric=lambda task: task.pixel_error() if task.config.behaviour == "servo" else task.speed(),
    metric_name=lambda task: (
        "mean |pixel error to the goal| (lost: 200)"
        if task.config.behaviour == "servo"
        else "metres per second"
    ),
    reward_of=_nomad_reward,
    veto=lambda task: task.veto(0),
    rate_hz=NomadConfig().rate_hz,  # the rate it is simulated at: one source
    exploration="gaussian",
    views=lambda task: task.camera_images(0),
    behaviours=lambda task, c: NomadForage(task, c.forage) if c.forage is not None else None,
    # Wandering toward the longest strip of carpet (Section 6.5); servoing has no hand-coded rule.
    handcoded=lambda task: (
        (lambda state: handcoded_wander(task.carpet[0])) if task.config.behaviour == "wander" else None
    ),
)
SIMS["position"] = SIMS["positioning"]


def _saved_ranges(config: SimOptions) -> tuple[tuple[float, ...], tuple[float, ...]] | None:
    """The state ranges saved with the weights given (a gym task's, measured when they were made).

    Taken instead of measuring them again with random actions sent to the task (a robot's,
    it may be): the saved weights need those ranges anyway. Weights that cannot be read are
    refused here (PersistError, OSError), before the task is sent anything.
    """
    if config.weights is None:
        return None
    saved = load_weights(config.weights)[0]
    return saved.state_low, saved.state_high


SIMS["gym"] = SimSpec(
    make=lambda c: GymVec(
        c.env or "", seed=c.seed, state_ranges=_saved_ranges(c), ranges_from=str(c.weights)
    ),
    # One client episode per time limit; an episode the task ends early restarts inside it, so
    # the score times the time limit is no return (a hopper falling every 30 steps earns most of
    # a standing one's healthy reward): the task's own returns are in metrics.json (task_returns).
    episode_steps=lambda task: task.max_episode_steps,
    new_episode=lambda task, rng: None,
    metric=lambda task: task.last_reward,
    metric_name="mean reward per step",
)
