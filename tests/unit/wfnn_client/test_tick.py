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


def test_a_long_runs_timing_is_kept_in_bounded_memory_and_its_percentiles_hold():
    from wfnn_client.tick import RECENT_KEPT, SAMPLE_KEPT, TickStats

    stats = TickStats()
    n = 4 * SAMPLE_KEPT
    rng = np.random.default_rng(0)
    values = rng.exponential(1e-3, n)
    for v in values:
        stats.add_latency(float(v))
        stats.add_lateness(float(v), 0.0)
    assert stats.count == n and not stats.due_unix
    assert len(stats._latency.sample) == SAMPLE_KEPT and len(stats._latency.recent) == RECENT_KEPT
    whole, recent = stats.summary(), stats.summary(last=1000)
    for q in (50, 99):  # a uniform sample of 65,536 of 262,144: within half a percentile
        lo, hi = np.percentile(values, [q - 0.5, q + 0.5]) * 1e3
        assert lo <= whole[f"act_latency_ms_p{q}"] <= hi
    assert whole["tick_jitter_ms_max"] == values.max() * 1e3
    assert recent["act_latency_ms_p50"] == np.percentile(values[-1000:], 50) * 1e3
    traced = TickStats(keep_all=True)
    for v in values[:100]:
        traced.add_lateness(float(v), 1.0)
    assert traced.lateness_s == list(values[:100]) and traced.due_unix == [1.0] * 100


def test_a_run_at_a_slow_rate_stops_at_its_duration_not_a_period_after(tmp_path):
    """At 0.2 Hz with --duration 0.3 the run waited for its second tick, 5 s on (1,000 s at 0.001 Hz)."""
    from wfnn_client.config import ClientConfig
    from wfnn_client.run import run

    ticker = Ticker(5.0)
    assert ticker.next_due() <= time.perf_counter()  # nothing scheduled yet: due now
    ticker.wait()
    assert ticker.next_due() - time.perf_counter() > 4.0
    t0 = time.perf_counter()
    result = run(ClientConfig(sim="boat", rate_hz=0.2, duration_s=0.3, episodes=3, out=tmp_path / "run"))
    assert time.perf_counter() - t0 < 4.0
    assert len(result["scores"]) == 1 and result["ticks"] == 1
