"""robot_step: execute what was decided, every behaviour learns it, a vetoed proposal is learned twice."""

from __future__ import annotations

from typing import Any

import numpy as np

from sims.base import Transition
from wfnn_client.step import Decided, Pupil, robot_step


class Log:
    """A learner that records what it was asked to learn."""

    def __init__(self) -> None:
        self.calls: list[tuple[Any, ...]] = []

    def __call__(self, *experience: Any) -> None:
        self.calls.append(tuple(np.array(a, copy=True) for a in experience))


def transition(n: int, learnable: list[bool], shift: float = 1.0) -> Transition:
    return Transition(
        np.arange(2 * n, dtype=np.float64).reshape(n, 2) + shift,
        np.full(n, -1.0),
        np.zeros(n, dtype=np.bool_),
        np.array(learnable),
    )


def test_unchanged_executes_the_proposal_and_vetoes_nothing() -> None:
    u = np.array([[0.5], [-0.5]])
    decided = Decided.unchanged(u)
    assert decided.executed is u and decided.proposed is u
    assert decided.vetoed.dtype == np.bool_ and not decided.vetoed.any() and decided.vetoed.shape == (2,)


def test_the_executed_action_is_executed_and_learned_from_the_transition() -> None:
    executed: list[Any] = []
    tr = transition(2, [True, False])

    def execute(u: Any) -> Transition:
        executed.append(u)
        return tr

    x = np.zeros((2, 2))
    learn = Log()
    u = np.array([[0.1], [0.2]])
    out = robot_step(Decided.unchanged(u), execute, [Pupil(x, learn, reward=lambda *a: np.zeros(2))])
    assert out is tr and len(executed) == 1 and executed[0] is u
    assert len(learn.calls) == 1  # nothing was vetoed: no second experience
    _, a, sn, _, _, valid = learn.calls[0]
    np.testing.assert_array_equal(a, u)
    np.testing.assert_array_equal(sn, tr.state)
    np.testing.assert_array_equal(valid, [True, False])


def test_a_vetoed_proposal_is_learned_twice_where_learnable_by_the_proposer_only() -> None:
    n = 3
    tr = {"servo": transition(n, [True, True, False]), "wander": transition(n, [True, True, True], 5.0)}
    executed = np.array([[0.0], [0.0], [0.0]])
    proposed = np.array([[0.9], [0.8], [0.7]])
    vetoed = np.array([True, False, True])
    rewards: list[Any] = []

    def reward(s: Any, a: Any, sn: Any) -> Any:
        rewards.append((a.copy(), sn.copy()))
        return np.full(n, 7.0)

    servo, servo_twice, wander = Log(), Log(), Log()
    pupils = [
        Pupil(np.ones((n, 2)), servo, "servo", reward, True, servo_twice),
        Pupil(np.ones((n, 2)), wander, "wander", reward, np.array([False, False, False])),
    ]
    robot_step(Decided(executed, proposed, vetoed), lambda u: tr, pupils)
    # Both behaviours learn the executed action, each from its own transition.
    assert len(servo.calls) == 1 and len(wander.calls) == 1
    np.testing.assert_array_equal(servo.calls[0][1], executed)
    np.testing.assert_array_equal(wander.calls[0][2], tr["wander"].state)
    # The proposer learns the proposal with its own reward, only where vetoed and learnable.
    assert len(servo_twice.calls) == 1 and len(rewards) == 1
    _, a, _, r, _, valid = servo_twice.calls[0]
    np.testing.assert_array_equal(a, proposed)
    np.testing.assert_array_equal(r, np.full(n, 7.0))
    np.testing.assert_array_equal(valid, [True, False, False])
    np.testing.assert_array_equal(rewards[0][1], tr["servo"].state)


def test_without_a_reward_or_a_learnable_veto_nothing_is_learned_twice() -> None:
    tr = transition(2, [False, True])
    vetoed = np.array([True, False])  # vetoed where the step is not learnable
    with_reward, without = Log(), Log()
    calls: list[int] = []
    decided = Decided(np.zeros((2, 1)), np.ones((2, 1)), vetoed)
    pupil = Pupil(np.zeros((2, 2)), with_reward, reward=lambda *a: calls.append(1))
    robot_step(decided, lambda u: tr, [pupil])
    robot_step(Decided(np.zeros((2, 1)), np.ones((2, 1)), np.array([True, True])), lambda u: tr,
               [Pupil(np.zeros((2, 2)), without)])  # fmt: skip
    assert len(with_reward.calls) == 1 and not calls
    assert len(without.calls) == 1
