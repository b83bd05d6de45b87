import threading
import time

import numpy as np

from tests.fakes import random_experiences, small_config
from wfnn_common.architectures import ActLearn, ActLearnThinkMT, LearnArchitecture
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


def test_mt_thinks_in_background_and_publishes_whole_snapshots():
    learner = WFNN(small_config(thinks_per_action=20))
    with ActLearnThinkMT(learner, think_batch=10, publish_period_s=0.0) as mt:
        first = mt.snapshot
        rng = np.random.default_rng(0)
        for _ in range(50):
            x = rng.uniform(-1, 1, 3)
            u = mt.act(x).action
            mt.learn(x, u, rng.uniform(-1, 1, 3), -0.3)
        deadline = time.monotonic() + 20
        while (mt.queued or mt.budget > 0) and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.05)
    assert mt.error is None
    assert learner.buffer.count[0] == 50
    assert learner.thinks[0] == 50 * 20  # exactly thinks_per_action per stored experience
    assert mt.version > 1 and mt.snapshot is not first
    np.testing.assert_array_equal(mt.snapshot.flat, learner.params.flat)


def test_mt_act_is_not_blocked_by_a_long_think():
    """A think call running the compiled loop must leave `act` free: acts complete while the
    think counter stays unchanged (the think call has not returned)."""
    cfg = small_config(thinks_per_action=400_000, replay_capacity=2000)
    learner = WFNN(cfg)
    learner.buffer.extend(0, random_experiences(np.random.default_rng(0), 2000, 3, 2))
    learner.think(10)
    mt = ActLearnThinkMT(learner, think_batch=400_000)
    started = threading.Event()
    original = learner.think

    def think_and_flag(n=None):
        started.set()
        return original(n)

    learner.think = think_and_flag  # type: ignore[method-assign]
    with mt:
        mt.learn(np.zeros(3), np.zeros(2), np.zeros(3), -0.1)
        assert started.wait(10)
        thinks_before = int(learner.thinks[0])
        acts = sum(1 for _ in range(200) if mt.act(np.zeros(3)).valid)
        still_thinking = int(learner.thinks[0]) == thinks_before
    assert acts == 200
    assert still_thinking, "act waited for the think call to finish"


def test_mt_stop_keeps_the_experiences_the_think_thread_had_not_taken_yet():
    learner = WFNN(small_config(thinks_per_action=5))
    mt = ActLearnThinkMT(learner)  # never started: everything stays queued until stop
    rng = np.random.default_rng(1)
    for _ in range(40):
        mt.learn(rng.uniform(-1, 1, 3), rng.uniform(-1, 1, 2), rng.uniform(-1, 1, 3), -0.2)
    mt.learn(np.full(3, np.nan), np.zeros(2), np.zeros(3), -0.2)  # refused by the sanity limits
    assert mt.queued == 41 and learner.buffer.count[0] == 0
    mt.stop()
    assert mt.queued == 0 and learner.buffer.count[0] == 40
    assert mt.budget == 40 * 5 and learner.thinks[0] == 0  # stored, not yet replayed
