"""act-learn-think-MT: thinking in a background thread (`wfnn_client.think_thread`)."""

import threading
import time

import numpy as np

from tests.fakes import random_experiences, small_config
from wfnn_client.think_thread import ActLearnThinkMT
from wfnn_common.learner import WFNN


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
