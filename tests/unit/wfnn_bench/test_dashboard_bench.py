"""`wfnn-bench dashboard`'s figures from its measuring windows (`wfnn_bench.dashboard.run`)."""

import json

import pytest

from wfnn_bench import dashboard as bench


def _window(on: bool, stored: int, cpu: float, dash: float = 0.0005) -> dict:
    per_experience = 1e3 * cpu / stored if stored else None  # as `_one` gives it
    return {"dashboard": on, "window_s": 1.0, "server_cpu_s": cpu, "server_cpu_fraction_of_a_core": cpu,
            "experiences_stored": stored, "server_cpu_ms_per_experience": per_experience,
            "dashboard_cpu_s": dash if on else 0.0, "messages": 4, "kib_per_message": 0.5}  # fmt: skip


def test_windows_that_saw_no_experience_are_left_out_not_divided_by(monkeypatch, tmp_path, caplog):
    """An idle server's window (the robot not yet sending) ended the run in a division by zero,
    after the work, or gave a dashboard share of 5.8e5 and a goal "NOT met" from nothing."""
    cfg = bench.DashboardBenchConfig(seconds=1, warmup_s=1, repeats=1)
    monkeypatch.setattr(bench, "_one", lambda c, on, w: _window(on, 0, 0.01 if on else 0.0))
    result = bench.run(cfg)
    assert result["added_fraction_ab"] is None and result["added_fraction_attributed"] is None
    assert result["goal"]["met"] is None and "saw no experience" in caplog.text
    assert dict(bench.rows(result, cfg))[f"goal {result['goal']['goal']}"] == "not measured"
    json.dumps(result, allow_nan=False)
    bench.plot(result, tmp_path / "empty.png")
    assert (tmp_path / "empty.png").stat().st_size > 0

    monkeypatch.setattr(bench, "_one", lambda c, on, w: _window(on, 100, 0.2 if on else 0.19))
    result = bench.run(cfg)
    assert result["added_fraction_attributed"] == pytest.approx(0.0005 / 0.1995)
    assert result["added_fraction_ab"] == pytest.approx(2.0 / 1.9 - 1.0) and result["goal"]["met"] is True


def test_the_benchmarks_watcher_follows_the_dashboard_past_the_end_of_a_stream(monkeypatch):
    """A stream lasts dashboard.STREAM_S: a watcher that stopped there would report the dashboard's
    CPU as of then for a longer window."""
    import time

    import wfnn_server.dashboard as dashboard_module
    from tests.fakes import wait_for
    from wfnn_bench.dashboard import _Watcher
    from wfnn_server.config import DashboardConfig
    from wfnn_server.dashboard import Dashboard
    from wfnn_server.view import ViewModel

    monkeypatch.setattr(dashboard_module, "STREAM_S", 0.3)
    d = Dashboard(
        DashboardConfig(port=0, update_hz=30), ViewModel(server="s1", incarnation=1, controller="c")
    )
    d.start()
    watcher = _Watcher(d.port)
    try:
        time.sleep(1.0)  # three streams' lives
        seen = watcher.messages
        assert wait_for(lambda: watcher.messages > seen + 5, timeout=5.0)
    finally:
        watcher.close()
        d.stop()


def test_the_window_waits_for_the_dashboards_first_surface_and_says_when_none_came(caplog):
    """The first surface compiles the grid's kernel: in the window, the dashboard's count (as of a
    message sent after the window began) exceeded the whole server's /proc time (charged before)."""
    import logging
    import time

    from wfnn_bench.dashboard import _Watcher
    from wfnn_server.config import DashboardConfig
    from wfnn_server.dashboard import Dashboard
    from wfnn_server.view import ViewModel

    d = Dashboard(
        DashboardConfig(port=0, update_hz=30), ViewModel(server="s1", incarnation=1, controller="c")
    )
    d.start()
    watcher = _Watcher(d.port)
    try:
        t0 = time.monotonic()
        with caplog.at_level(logging.WARNING):
            watcher.wait_for_surface(0.3)  # no learner, no client: no surface ever
        assert 0.3 <= time.monotonic() - t0 < 5.0 and "drew no action-value surface" in caplog.text
    finally:
        watcher.close()
        d.stop()
