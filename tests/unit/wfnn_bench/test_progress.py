"""Progress of a benchmark whose output is not a terminal: plain lines, now and then."""

from wfnn_bench.cli import LineProgress


def test_lines_come_at_start_every_interval_and_at_the_end():
    now = [0.0]
    lines: list[str] = []
    with LineProgress(lines.append, every_s=60.0, clock=lambda: now[0]) as bar:
        task = bar.add_task("passive", total=10)
        for _ in range(4):
            now[0] += 20.0
            bar.advance(task, 1)
        assert len(lines) == 2  # the start, then one at 60 s: not one per advance
        for _ in range(6):
            now[0] += 20.0
            bar.advance(task, 1)
    # At 60 s three of ten were done: seven more at 20 s each, about 140 s.
    assert lines == [
        "passive: 0/10 (0%), 0 s elapsed",
        "passive: 3/10 (30%), 60 s elapsed, about 2 min left",
        "passive: 6/10 (60%), 2 min elapsed, about 80 s left",
        "passive: 9/10 (90%), 3 min elapsed, about 20 s left",
        "passive: 10/10 (100%), 3 min elapsed",
    ]


def test_a_task_without_a_total_counts_up():
    lines: list[str] = []
    with LineProgress(lines.append, every_s=0.0, clock=lambda: 0.0) as bar:
        bar.advance(bar.add_task("faults"), 2)
    assert lines == ["faults: 0, 0 s elapsed", "faults: 2, 0 s elapsed", "faults: 2, 0 s elapsed"]


def test_nan_mean_and_finite_median_are_quiet_where_a_slice_holds_no_figure():
    """No controller found the target: the figure is NaN, without numpy's warnings in the output."""
    import warnings

    import numpy as np

    from wfnn_bench.common import finite_median, nan_mean

    a = np.array([[np.nan, np.nan], [1.0, 3.0], [np.nan, 4.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = nan_mean(a, axis=1)
        assert np.isnan(got[0]) and got[1] == 2.0 and got[2] == 4.0
        assert np.array_equal(nan_mean(a, axis=0), np.array([1.0, 3.5]))
        assert np.isnan(finite_median([np.nan, np.nan])) and finite_median([np.nan, 2.0, 4.0]) == 3.0


def test_a_table_cell_without_a_figure_is_a_dash():
    from wfnn_bench.cli import _cell

    assert [_cell(v) for v in (None, float("nan"), 1.23456, 3, "a/b")] == ["-", "-", "1.235", "3", "a/b"]


def test_huge_returns_print_in_powers_of_ten_and_usual_ones_in_whole_units():
    """A diverging task's return of 1e300 filled a table cell with 300 digits."""
    from wfnn_bench.common import whole

    assert whole(1e300) == "1e+300" and whole(-3.2e12) == "-3.2e+12"
    assert whole(-121.6) == "-122" and whole(1000.0) == "1000" and whole(float("nan")) == "nan"
