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
