"""Gymnasium tasks behind the client's task interface."""

import gymnasium as gym
import numpy as np
import pytest

from sims.gym import MEASURED_MARGIN, GymVec
from wfnn_common.config import LearnerConfig
from wfnn_common.learners import make_learner


def test_pendulum_ranges_steps_and_restarts_at_its_time_limit():
    task = GymVec("Pendulum-v1")
    assert task.state_low == (-1.0, -1.0, -8.0) and task.action_high == (2.0,)
    assert task.max_episode_steps == 200 and task.rate_hz == pytest.approx(20.0)
    rng = np.random.default_rng(0)
    x = task.reset(rng)
    assert x.shape == (1, 3)
    for k in range(200):
        tr = task.step(np.array([[5.0]]))  # clipped to the action space
        assert tr.learnable[0] and not tr.terminal[0]  # a time limit is not a terminal state
        if k < 199:
            np.testing.assert_array_equal(task.observe(), tr.state)
    # The time limit restarted the episode: the state to act from is a new start, not the last.
    assert task.episodes == 1 and len(task.returns) == 1 and task.returns[0] < 0
    assert not np.allclose(task.observe(), tr.state)
    task.close()


def test_a_terminated_episode_is_learned_as_terminal_and_restarts():
    task = GymVec("MountainCarContinuous-v0")
    task.reset(np.random.default_rng(0))
    task.env.unwrapped.state = np.array([0.44, 0.06])  # just short of the goal, moving toward it
    task._obs = task.env.unwrapped.state[None].copy()
    tr = task.step(np.array([[1.0]]))
    assert tr.terminal[0] and tr.state[0, 0] >= 0.45 and task.observe()[0, 0] < 0
    task.close()


def test_tasks_without_box_spaces_or_unknown_ids_are_refused_clearly():
    with pytest.raises(ValueError, match="action space must be a 1-D Box"):
        GymVec("CartPole-v1")
    with pytest.raises(ValueError, match="cannot make"):
        GymVec("NoSuchTask-v9")


class _Drift(gym.Env):
    """Unbounded observations: a random walk the actions push (declared bounds infinite)."""

    observation_space = gym.spaces.Box(-np.inf, np.inf, (2,), np.float64)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.x = np.zeros(2)
        return self.x.copy(), {}

    def step(self, action):
        self.x = self.x + np.array([float(action[0]), 10.0 * self.np_random.normal()])
        return self.x.copy(), 0.0, False, False, {}


def test_infinite_observation_bounds_are_measured_from_random_play():
    gym.register("WfnnTestDrift-v0", entry_point=_Drift, max_episode_steps=100)
    task = GymVec("WfnnTestDrift-v0", probe_steps=3000)
    low, high = np.array(task.state_low), np.array(task.state_high)
    assert np.isfinite(low).all() and np.isfinite(high).all()
    again = GymVec("WfnnTestDrift-v0", probe_steps=3000)  # the same seed measures the same ranges
    assert again.state_low == task.state_low and again.state_high == task.state_high
    again.close()
    # The second coordinate wanders about 17 times further than the first.
    assert 8 < (high[1] - low[1]) / (high[0] - low[0]) < 35  # steps of 10 against about 0.6
    # Measured ranges are estimates: a state far beyond them is still learned (only non-finite
    # ones are refused), by either learner.
    for learner in ("thesis", "deep"):
        lcfg = LearnerConfig.for_task(task, learner=learner)
        assert lcfg.valid_margin == MEASURED_MARGIN
        wfnn = make_learner(lcfg)
        far = high + 50 * (high - low)
        assert wfnn.learn(far, np.zeros(task.env.action_space.shape), far, 0.0)
        assert not wfnn.learn(far * np.nan, np.zeros(task.env.action_space.shape), far, 0.0)
    task.close()
    declared = GymVec("Pendulum-v1")
    assert LearnerConfig.for_task(declared).valid_margin == declared.valid_margin == 1.0
    declared.close()
