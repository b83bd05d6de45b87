"""One robot step, written once: execute what the safety layer decided, then learn (twice).

Every loop that drives a robot and learns from it (the client's control loop, and the
benchmarks' populations of simulated robots) goes through `robot_step`:

1. the caller acts (a learner, another controller, or a hand-coded behaviour proposes),
2. the caller's safety layer or veto decides what to execute (`Decided`),
3. `robot_step` executes it, and every behaviour that learns (`Pupil`) learns the executed
   action from its own view of the step (Section 6.6: all behaviours learn from the executed
   action, whichever chose it),
4. and, where a veto replaced a proposal, the behaviour that proposed it also learns the
   proposal with the reward it would have earned (learning twice, Eq 5.4).

Thinking is left to the caller: a benchmark thinks in the same loop, the client in another
thread or on think servers. Rows are robots (or learners of a population) [P].
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import NamedTuple, overload

import numpy as np
from numpy.typing import NDArray

from sims.base import Transition

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

Learn = Callable[[FloatArray, FloatArray, FloatArray, FloatArray, BoolArray, BoolArray], object]
"""learn(state [P, S], action [P, A], next_state [P, S], reward [P], terminal [P], valid [P])."""
Reward = Callable[[FloatArray, FloatArray, FloatArray], FloatArray]
"""reward(state [P, S], action [P, A], next_state [P, S]) -> [P]: what an action earned, executed or not."""


class Decided(NamedTuple):
    """What the safety layer (or veto) made of a proposal, per robot."""

    executed: FloatArray
    """Actions to execute [P, A]."""
    proposed: FloatArray
    """The proposals [P, A], as they are learned where a veto replaced them."""
    vetoed: BoolArray
    """[P] a veto replaced the proposal (only these rows learn twice)."""

    @staticmethod
    def unchanged(action: FloatArray) -> Decided:
        """Nothing stood between the proposal and the actuators."""
        return Decided(action, action, np.zeros(len(action), dtype=np.bool_))


@dataclass(frozen=True)
class Pupil:
    """A behaviour that learns from the step: its view before it, and how it learns."""

    state: FloatArray
    """Its state before the step [P, S]."""
    learn: Learn
    """Stores (and may count, or send) one experience per robot."""
    behaviour: str = ""
    """Its transition in a task of several behaviours (a dict of transitions); "" for one."""
    reward: Reward | None = None
    """Its reward for a vetoed proposal; None: it never learns twice."""
    drove: BoolArray | bool = True
    """Rows where its proposal was the one decided on (only the proposer learns twice)."""
    learn_proposal: Learn | None = None
    """How it learns a vetoed proposal, where that differs from `learn` (e.g. flagged)."""


@overload
def robot_step(
    decided: Decided, execute: Callable[[FloatArray], Transition], pupils: Sequence[Pupil]
) -> Transition: ...


@overload
def robot_step(
    decided: Decided, execute: Callable[[FloatArray], Mapping[str, Transition]], pupils: Sequence[Pupil]
) -> Mapping[str, Transition]: ...


def robot_step(
    decided: Decided,
    execute: Callable[[FloatArray], Transition] | Callable[[FloatArray], Mapping[str, Transition]],
    pupils: Sequence[Pupil],
) -> Transition | Mapping[str, Transition]:
    """Execute `decided.executed` [P, A] and let each pupil learn, in order; -> what `execute` returned.

    Each pupil learns the executed action where its transition is learnable, then, with a
    `reward`, the proposal where it drove, a veto replaced the proposal and the step is learnable.
    """
    outcome = execute(decided.executed)
    for pupil in pupils:
        tr = outcome if isinstance(outcome, Transition) else outcome[pupil.behaviour]
        pupil.learn(pupil.state, decided.executed, tr.state, tr.reward, tr.terminal, tr.learnable)
        if pupil.reward is None:
            continue
        twice = decided.vetoed & tr.learnable & pupil.drove
        if twice.any():
            r = pupil.reward(pupil.state, decided.proposed, tr.state)
            learn = pupil.learn_proposal or pupil.learn
            learn(pupil.state, decided.proposed, tr.state, r, tr.terminal, twice)
    return outcome
