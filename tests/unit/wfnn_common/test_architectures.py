import numpy as np

from tests.fakes import small_config
from wfnn_common.architectures import ActLearn, LearnArchitecture
from wfnn_common.learner import WFNN


def test_learn_architecture_learns_the_previous_transition_and_skips_invalid_states():
    learner = WFNN(small_config(thinks_per_action=3))
    arch = LearnArchitecture(learner)
    s = np.zeros(3)
    assert arch.learn(s, reward=0.0) is not None  # first tick: nothing to learn yet
    assert learner.buffer.count[0] == 0
    assert arch.learn(s, reward=0.0, valid=False) is None
    assert arch.learn(s + 0.1, reward=-0.2) is not None
    assert learner.buffer.count[0] == 1 and learner.thinks[0] == 3
    assert learner.buffer.reward[0, 0] == -0.2
    assert arch.learn(s, reward=-1.0, terminal=True) is None
    assert learner.buffer.terminal[0, 1]
    arch.learn(s, reward=0.0)  # a new episode: no experience across the terminal state
    assert learner.buffer.count[0] == 2


def test_act_learn_learns_from_the_newest_experience_at_once():
    learner = WFNN(small_config(thinks_per_action=1))
    arch = ActLearn(learner)
    res = arch.act(np.zeros(3))
    before = learner.params.flat.copy()
    assert arch.learn(np.zeros(3), res.action, np.ones(3) * 0.1, -0.5)
    assert learner.thinks[0] == 1 and not np.array_equal(before, learner.params.flat)
    assert not arch.learn(np.full(3, np.nan), res.action, np.zeros(3), -0.5)
