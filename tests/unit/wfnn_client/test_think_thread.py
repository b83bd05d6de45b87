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


def test_a_local_brain_whose_learner_fails_keeps_its_record_and_says_why(tmp_path):
    """The think thread's error is what `check` raises; stopping keeps every experience recorded."""
    from wfnn_client.brain import Experience, LocalBrain, Recorder
    from wfnn_io.logs import read_batches

    cfg = small_config()
    learner = WFNN(cfg)
    learned = {"n": 0}
    real_learn = learner.learn

    def failing_learn(*args, **kw):
        learned["n"] += 1
        if learned["n"] > 20:
            raise FloatingPointError("learn failed")
        return real_learn(*args, **kw)

    learner.learn = failing_learn
    brain = LocalBrain(learner, recorder=Recorder(tmp_path / "journal", cfg, batch_max=16, background=True))
    brain.start()
    z = np.zeros(3)
    for _ in range(40):
        brain.learn(Experience(z, np.zeros(2), z, -0.1), None)
        time.sleep(0.002)
    deadline = time.monotonic() + 10
    while brain.mt.error is None and time.monotonic() < deadline:
        time.sleep(0.01)
    try:
        brain.check()
        raise AssertionError("check did not raise")
    except RuntimeError as exc:
        assert "think thread failed" in str(exc) and isinstance(exc.__cause__, FloatingPointError)
    brain.stop()  # does not learn what is queued through the failed learner; closes the record
    assert sum(len(b) for b in read_batches(tmp_path / "journal")) == 40


def test_a_background_record_writes_off_the_calling_thread_in_order(tmp_path):
    from wfnn_client.brain import Experience, Recorder
    from wfnn_io.logs import read_batches
    from wfnn_io.segments import SegmentLog

    writers = set()
    append = SegmentLog.append

    def slow_append(self, record):
        writers.add(threading.current_thread().name)
        time.sleep(0.05)  # a slow disk
        return append(self, record)

    SegmentLog.append = slow_append
    try:
        recorder = Recorder(tmp_path / "journal", small_config(), batch_max=4, background=True)
        t0 = time.perf_counter()
        for i in range(40):
            recorder.add(Experience(np.zeros(3), np.zeros(2), np.zeros(3), -float(i)), "local", i)
        assert time.perf_counter() - t0 < 0.2  # ten appends of 50 ms each did not wait here
        recorder.close()
    finally:
        SegmentLog.append = append
    assert writers == {"wfnn-record"}
    rewards = np.concatenate([b.reward for b in read_batches(tmp_path / "journal")])
    np.testing.assert_array_equal(rewards, -np.arange(40.0))
