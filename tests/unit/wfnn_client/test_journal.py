"""The client's experience journal (`wfnn_client.journal`)."""

from tests.fakes import small_config
from wfnn_io.protocol import Codec, ExperienceBatch


def test_journal_frames_from_a_sequence_number(tmp_path):
    from tests.unit.wfnn_server.test_server import batch
    from wfnn_client.journal import Journal

    cfg = small_config()
    journal = Journal(tmp_path / "j", "c1", fsync="never")
    for first in (0, 5, 12):
        b = batch(cfg, first, {0: 5, 5: 7, 12: 3}[first])
        journal.append(Codec("c1").encode(b), b.last_seq)
    frames, last = journal.frames_from(6, 1)
    assert len(frames) == 1 and last == 11
    assert Codec("c1").decode(frames[0], ExperienceBatch)[1].first_seq == 5
    frames, last = journal.frames_from(0, 10)
    assert len(frames) == 3 and last == 14
    assert journal.frames_from(15, 10) == ([], -1)
    journal.close()
    again = Journal(tmp_path / "j")
    assert again.client_id == "c1" and again.next_seq == 15 and again.frames_from(12, 5)[1] == 14


def test_a_record_damaged_after_it_was_indexed_is_no_longer_held(tmp_path):
    """Its experiences are then declared lost by the next re-send, rather than waited for forever."""
    from tests.unit.wfnn_server.test_server import batch
    from wfnn_client.journal import Journal

    cfg = small_config()
    journal = Journal(tmp_path / "j", "c1", fsync="never")
    for first in (0, 5, 10, 15):
        b = batch(cfg, first, 5)
        journal.append(Codec("c1").encode(b), b.last_seq)
    journal.sync()
    where = journal._index.where(1)
    segment = tmp_path / "j" / f"{where.segment:08d}.seg"
    data = bytearray(segment.read_bytes())
    data[where.offset + 40] ^= 0xFF  # inside the record of experiences 5-9
    segment.write_bytes(bytes(data))
    assert journal.holds(5)
    frames, last = journal.frames_from(0, 10)
    assert len(frames) == 1 and last == 4  # the frames stop at the gap
    assert not journal.holds(5) and not journal.holds(9) and journal.holds(10)
    frames, last = journal.frames_from(5, 10)  # from the gap: the readable batches after it
    assert [Codec("c1").decode(f, ExperienceBatch)[1].first_seq for f in frames] == [10, 15] and last == 19
    journal.close()


def test_a_journal_whose_records_end_near_the_last_number_is_refused_before_it_takes_more(tmp_path):
    """Batches numbered past MAX_SEQ would be written where no reader accepts them."""
    import pytest

    from tests.unit.wfnn_server.test_server import batch
    from wfnn_client.journal import ROOM, Journal
    from wfnn_io.protocol import MAX_SEQ

    cfg = small_config()
    journal = Journal(tmp_path / "j", "c1", fsync="never")
    b = batch(cfg, MAX_SEQ - ROOM - 10, 10)  # continues ROOM below the last number: still taken
    journal.append(Codec("c1").encode(b), b.last_seq)
    journal.close()
    Journal(tmp_path / "j").close()
    journal = Journal(tmp_path / "j")
    b = batch(cfg, MAX_SEQ - ROOM, 1)
    journal.append(Codec("c1").encode(b), b.last_seq)
    journal.close()
    with pytest.raises(ValueError, match="too near the last number"):
        Journal(tmp_path / "j")


def test_closing_releases_the_reserved_numbers_before_the_lock(tmp_path):
    """A client started on the folder while the last one closes is refused, never misled.

    The closing journal writes its release (closed, numbering from next_seq) while it still holds
    the lock; released first, a second journal opened in between read the reservation as a
    crash's and skipped the reserved numbers.
    """
    import json

    import pytest

    from tests.unit.wfnn_server.test_server import batch
    from wfnn_client.journal import CLIENT_JSON, Journal
    from wfnn_io.segments import LogError

    cfg = small_config()
    first = Journal(tmp_path / "j", "c1", fsync="never")
    first.reserve(9)
    b = batch(cfg, 0, 10)
    first.append(Codec("c1").encode(b), b.last_seq)
    tried: list[str] = []
    write_meta = Journal._write_meta

    def meet_a_second_client(self: Journal, reserved_through: int, closed: bool) -> None:
        if self is first and closed:
            with pytest.raises(LogError, match="in use"):
                Journal(tmp_path / "j", "c1", fsync="never")
            tried.append("refused")
        write_meta(self, reserved_through, closed)

    Journal._write_meta = meet_a_second_client  # type: ignore[method-assign]
    try:
        first.close()
    finally:
        Journal._write_meta = write_meta  # type: ignore[method-assign]
    assert tried == ["refused"]
    assert json.loads((tmp_path / "j" / CLIENT_JSON).read_text())["closed"] is True
    again = Journal(tmp_path / "j", "c1", fsync="never")
    assert again.next_seq == 10 and again.skipped_at_open == 0
    again.close()


def test_a_journal_holding_records_of_another_client_or_spec_is_refused_naming_the_record(tmp_path):
    """A segment of another run copied into a journal was continued: its batches were sent as this
    client's, and "experiences 1600--1 missing" was logged for its numbering from 0 again."""
    import shutil

    import pytest

    from tests.unit.wfnn_server.test_server import batch
    from wfnn_client.journal import Journal

    cfg = small_config()
    for n, (client, spec) in enumerate([("c2", None), ("c1", "0123456789abcdef")]):
        journal = Journal(tmp_path / f"other{n}", client, fsync="never")
        b = batch(cfg, 0, 5, client=client, spec=spec)
        journal.append(Codec(client).encode(b), b.last_seq)
        journal.close()
        journal = Journal(tmp_path / f"j{n}", "c1", fsync="never")
        b = batch(cfg, 0, 5)
        journal.append(Codec("c1").encode(b), b.last_seq)
        journal.close()
        shutil.copy(tmp_path / f"other{n}" / "00000000.seg", tmp_path / f"j{n}" / "00000001.seg")
        before = sorted((p.name, p.read_bytes()) for p in (tmp_path / f"j{n}").iterdir() if p.is_file())
        with pytest.raises(ValueError, match=f"segment 1, offset 0 holds experiences of client '{client}'"):
            Journal(tmp_path / f"j{n}")
        after = sorted((p.name, p.read_bytes()) for p in (tmp_path / f"j{n}").iterdir() if p.is_file())
        assert after == before  # refused unchanged


def test_a_client_json_naming_another_client_than_the_records_is_refused(tmp_path):
    """A run resumed under the id client.json named, numbering on from the other client's records."""
    import pytest

    from tests.unit.wfnn_server.test_server import batch
    from wfnn_client.journal import Journal

    journal = Journal(tmp_path / "j", "c1", fsync="never")
    b = batch(small_config(), 0, 5)
    journal.append(Codec("c1").encode(b), b.last_seq)
    journal.close()
    (tmp_path / "j" / "client.json").write_text('{"client": "zzz"}')
    with pytest.raises(ValueError, match="names client 'zzz', its records client 'c1'"):
        Journal(tmp_path / "j")


def test_a_batch_repeating_journaled_experiences_is_told_as_such(tmp_path, caplog):
    from tests.unit.wfnn_server.test_server import batch
    from wfnn_client.journal import Journal

    cfg = small_config()
    journal = Journal(tmp_path / "j", "c1", fsync="never")
    for first, n in ((0, 5), (3, 4)):
        b = batch(cfg, first, n)
        journal.log.append(Codec("c1").encode(b))  # as a copied segment would hold it
    journal.close()
    journal = Journal(tmp_path / "j")
    assert journal.next_seq == 7 and journal.frames_from(5, 5)[1] == 6
    assert "holds experiences 3-6, of which those through 4 are journaled before it" in caplog.text
    assert "missing" not in caplog.text
    journal.close()


def test_a_resend_from_a_record_that_overlaps_a_damaged_one_declares_nothing_lost(tmp_path):
    """The record holds the experiences after the acknowledged point: declaring them lost from
    there made a batch whose lost_from follows its first experience, which no receiver takes (and
    the uplink thread died on it)."""
    import collections
    import types

    from tests.unit.wfnn_server.test_server import batch
    from wfnn_client.journal import Journal
    from wfnn_client.uplink import Uplink

    cfg = small_config()
    journal = Journal(tmp_path / "j", "c1", fsync="never")
    for first, n in ((0, 5), (5, 5), (3, 10)):  # the third overlaps the first two
        journal.log.append(Codec("c1").encode(batch(cfg, first, n)))
    journal.close()
    journal = Journal(tmp_path / "j")
    segment = tmp_path / "j" / "00000000.seg"
    data = bytearray(segment.read_bytes())
    data[journal._index.where(1).offset + 60] ^= 0xFF  # experiences 5-9 damaged after the open
    segment.write_bytes(bytes(data))
    frames, _ = journal.frames_from(5, 8)
    assert not journal.holds(5)
    uplink = types.SimpleNamespace(codec=Codec("c1"), counters=collections.Counter())
    sent = Uplink._declare_loss(uplink, frames[0], "s1", 4)  # type: ignore[arg-type]
    got = Codec("c1").decode(sent, ExperienceBatch)[1]
    assert got.first_seq == 3 and got.lost_from == -1 and uplink.counters["uplink/declared_lost"] == 0
    journal.close()


def test_the_index_finds_every_batch_past_its_growth_and_after_a_damaged_one_is_forgotten(tmp_path):
    """The index is kept in arrays that grow (a day's run at 50 Hz journals millions of batches)."""
    from tests.unit.wfnn_server.test_server import batch
    from wfnn_client.journal import Journal

    cfg, codec = small_config(), Codec("c1")
    journal = Journal(tmp_path / "j", "c1", fsync="never")
    for i in range(2_500):  # past the initial capacity, twice
        b = batch(cfg, 2 * i, 2)
        journal.append(codec.encode(b), b.last_seq)
    assert journal.last_held == 4_999 and journal.holds(0) and journal.holds(4_999)
    assert not journal.holds(5_000)
    frames, last = journal.frames_from(4_097, 3)
    firsts = [codec.decode(f, ExperienceBatch)[1].first_seq for f in frames]
    assert firsts == [4_096, 4_098, 4_100] and last == 4_101
    journal._index.delete(2_048)  # experiences 4,096-4,097 forgotten, as after damage
    assert not journal.holds(4_096) and not journal.holds(4_097) and journal.holds(4_098)
    frames, last = journal.frames_from(4_096, 2)
    assert [codec.decode(f, ExperienceBatch)[1].first_seq for f in frames] == [4_098, 4_100] and last == 4_101
    journal.close()
    again = Journal(tmp_path / "j")
    assert again.next_seq == 5_000 and again.holds(4_096) and len(again._index) == 2_500
    again.close()


def test_gaps_no_damage_explains_are_skips_told_once_and_damage_is_still_an_error(tmp_path, caplog):
    """Each start logged every crash's reserved numbers as an error, in damage's words: a line more
    per crash, among which the one real loss could not be told apart."""
    import logging

    from tests.unit.wfnn_server.test_server import batch
    from wfnn_client.journal import Journal

    cfg, codec = small_config(), Codec("c1")
    journal = Journal(tmp_path / "j", "c1", fsync="never")
    for first in (0, 5):
        journal.append(codec.encode(batch(cfg, first, 5)), first + 4)
    journal.skip_to(20)  # numbers 10-19 never journaled (as a crashed run's reservation leaves them)
    for first in (20, 25, 30):
        journal.append(codec.encode(batch(cfg, first, 5)), first + 4)
    journal.sync()
    where = journal._index.where(3)  # experiences 25-29
    journal.close()
    segment = tmp_path / "j" / f"{where.segment:08d}.seg"
    data = bytearray(segment.read_bytes())
    data[where.offset + 40] ^= 0xFF
    segment.write_bytes(bytes(data))
    with caplog.at_level(logging.INFO, logger="wfnn_client.journal"):
        again = Journal(tmp_path / "j")
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert again.skips == {19: 10}
    assert len(errors) == 1 and "experiences 25-29 missing" in errors[0], errors
    assert "1 gaps in its numbering (10 numbers)" in caplog.text
    again.close()


def test_a_journal_that_lost_its_first_segment_calls_it_damage_not_a_skip(tmp_path, caplog):
    import logging

    from tests.unit.wfnn_server.test_server import batch
    from wfnn_client.journal import Journal

    cfg, codec = small_config(), Codec("c1")
    journal = Journal(tmp_path / "j", "c1", fsync="never", segment_bytes=600)
    for first in range(0, 30, 5):
        journal.append(codec.encode(batch(cfg, first, 5)), first + 4)
    journal.close()
    assert len(list((tmp_path / "j").glob("*.seg"))) >= 3
    (tmp_path / "j" / "00000000.seg").unlink()
    with caplog.at_level(logging.INFO, logger="wfnn_client.journal"):
        again = Journal(tmp_path / "j")
    assert again.skips == {} and not again.holds(0)
    assert any(r.levelno >= logging.ERROR and "missing" in r.getMessage() for r in caplog.records)
    again.close()


def test_a_journal_with_a_segment_renamed_to_a_huge_number_still_opens(tmp_path):
    """Its number overflowed the int64 index: every start of the client failed with no file named."""
    from tests.unit.wfnn_server.test_server import batch
    from wfnn_client.journal import Journal

    cfg = small_config()
    journal = Journal(tmp_path / "j", "c1", fsync="never")
    b = batch(cfg, 0, 5)
    journal.append(Codec("c1").encode(b), b.last_seq)
    journal.close()
    (tmp_path / "j" / "00000000.seg").rename(tmp_path / "j" / f"{2**64}.seg")
    again = Journal(tmp_path / "j")
    assert again.client_id == "c1" and not again.holds(0)
    again.close()
