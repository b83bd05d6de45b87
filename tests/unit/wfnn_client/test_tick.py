"""The client's fixed tick (`wfnn_client.tick`)."""

import time

import numpy as np
import pytest

from wfnn_client.tick import Ticker


def test_the_tick_keeps_an_absolute_schedule():
    ticker = Ticker(0.02)  # 20 ms: a slow tick's 12 ms leaves room for a busy machine
    starts = []
    for k in range(40):
        ticker.wait()
        starts.append(ticker.deadline)
        if k == 10:
            time.sleep(0.012)  # a slow tick shifts nothing after it
    np.testing.assert_allclose(np.diff(starts), 0.02, atol=1e-9)
    assert ticker.stats.overruns == 0 and len(ticker.stats.lateness_s) == 40


def test_an_overrun_skips_the_missed_ticks_and_keeps_the_phase():
    ticker = Ticker(0.01)
    ticker.wait()
    first = ticker.deadline
    time.sleep(0.035)  # misses the ticks due at +10 and +20 ms (and +30 ms)
    ticker.wait()
    assert ticker.stats.overruns in (2, 3)
    phase = (ticker.deadline - first) / 0.01
    assert abs(phase - round(phase)) < 1e-6 and ticker.late_now() < 0.01
    with pytest.raises(ValueError):
        Ticker(-1.0)
