"""`wfnn-bench transport`'s accounting of an outage (`wfnn_bench.transport`)."""

from tests.fakes import small_config
from wfnn_io.protocol import Codec


def test_journal_holds_counts_the_journaled_part_of_a_range(tmp_path):
    """Experiences a server lacks are split into those the journal holds and those it does not."""
    from tests.unit.wfnn_server.test_server import batch
    from wfnn_bench.transport import journal_holds
    from wfnn_client.journal import Journal

    cfg = small_config()
    journal = Journal(tmp_path / "j", "c1", fsync="never")
    for first, n in ((0, 5), (5, 5), (20, 5)):  # 10-19 numbered past, never journaled
        journal.skip_to(first)
        b = batch(cfg, first, n)
        journal.append(Codec("c1").encode(b), b.last_seq)
    journal.close()
    before = sorted((p.name, p.stat().st_size, p.stat().st_mtime_ns) for p in (tmp_path / "j").iterdir())
    assert journal_holds(tmp_path / "j", 3, 25) == 2 + 5 + 5
    assert journal_holds(tmp_path / "j", 8, 22) == 2 + 2
    assert journal_holds(tmp_path / "j", 25, 30) == 0
    assert journal_holds(tmp_path / "j", 5, 5) == 0
    after = sorted((p.name, p.stat().st_size, p.stat().st_mtime_ns) for p in (tmp_path / "j").iterdir())
    assert after == before  # reading it changed nothing


def test_an_outage_phase_too_short_for_its_restart_is_refused():
    """`--outage-seconds 4` killed the server and ended before restarting it, then reported the 60
    experiences sent meanwhile as "missing after restart"."""
    import pytest

    from wfnn_bench.transport import TransportBenchConfig

    TransportBenchConfig(outage_seconds=0.0)  # no outage phase
    TransportBenchConfig(outage_seconds=9.0)
    with pytest.raises(ValueError, match=r"at least 8\.6"):
        TransportBenchConfig(outage_seconds=4.0)
