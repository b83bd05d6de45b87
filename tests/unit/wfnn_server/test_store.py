import dataclasses
import types

import numpy as np
import pytest

from wfnn_io import segments
from wfnn_io.protocol import EXP_AFTER_LOSS, Codec, ExperienceBatch
from wfnn_server.store import Admission, ExperienceStore

ARRAYS = ["state", "action", "next_state", "reward", "terminal", "weights_version", "flags"]


def batch(first_seq, n, client="robot1", s=3, a=2):
    """Experience i of a client carries recognisable values derived from (client, i)."""
    seqs = np.arange(first_seq, first_seq + n)
    base = seqs.astype(np.float64) + (1000.0 if client != "robot1" else 0.0)
    return ExperienceBatch(
        client=client,
        spec_hash="spec",
        first_seq=first_seq,
        weights_source="srv1",
        state=np.repeat(base[:, None], s, axis=1) + np.arange(s) / 10,
        action=np.repeat(-base[:, None], a, axis=1),
        next_state=np.repeat(base[:, None] + 0.5, s, axis=1),
        reward=-base / 7,
        terminal=seqs % 3 == 0,
        weights_version=seqs.astype(np.uint64) * 2,
        flags=(seqs % 32).astype(np.uint8),
    )


def assert_same_batch(got, want):
    assert (got.client, got.first_seq, got.spec_hash, got.weights_source) == (
        want.client, want.first_seq, want.spec_hash, want.weights_source,
    )  # fmt: skip
    for name in ARRAYS:
        g, w = getattr(got, name), getattr(want, name)
        assert g.dtype == w.dtype and g.shape == w.shape, name
        np.testing.assert_array_equal(g, w, err_msg=name)


def store_all(store, *batches):
    for b in batches:
        admitted = store.admit(b)
        assert admitted.new is not None
        store.append(admitted.new)


def seg_files(directory):
    return sorted(directory.glob("*.seg"))


@pytest.fixture
def clock(monkeypatch):
    fake = types.SimpleNamespace(now=500.0)
    monkeypatch.setattr(segments, "time", types.SimpleNamespace(monotonic=lambda: fake.now))
    return fake


# --------------------------------------------------------------------------- admission
def test_admit_new_batch_from_an_empty_store(tmp_path):
    store = ExperienceStore(tmp_path, "srv1")
    b = batch(0, 5)
    admitted = store.admit(b)
    assert admitted.new is b and not admitted.duplicate and not admitted.gap
    assert store.stored_through == {} and store.count == 0  # admit writes nothing
    assert list(store.batches()) == []
    store.close()


def test_admit_first_batch_must_start_at_zero(tmp_path):
    store = ExperienceStore(tmp_path, "srv1")
    assert store.admit(batch(1, 5)) == Admission(None, gap=True)
    store.close()


def test_admit_duplicate_overlap_and_gap(tmp_path):
    store = ExperienceStore(tmp_path, "srv1")
    store_all(store, batch(0, 10))
    assert store.stored_through == {"robot1": 9} and store.count == 10

    for dup in (batch(0, 10), batch(3, 4), batch(9, 1), batch(0, 1)):
        assert store.admit(dup) == Admission(None, duplicate=True)

    overlap = store.admit(batch(6, 8))  # 6..13: 10..13 are new
    assert not overlap.duplicate and not overlap.gap
    assert overlap.new.first_seq == 10 and overlap.new.last_seq == 13 and len(overlap.new) == 4
    assert_same_batch(overlap.new, batch(10, 4))

    edge = store.admit(batch(9, 2))  # 9..10: only 10 is new
    assert edge.new.first_seq == 10 and len(edge.new) == 1

    follow = batch(10, 3)
    assert store.admit(follow).new is follow

    for gap in (batch(11, 2), batch(50, 1)):
        assert store.admit(gap) == Admission(None, gap=True)
    assert store.stored_through == {"robot1": 9} and store.count == 10
    store.close()


def test_append_stores_overlap_remainder_and_advances(tmp_path):
    store = ExperienceStore(tmp_path, "srv1")
    store_all(store, batch(0, 10), batch(6, 8))
    assert store.stored_through == {"robot1": 13} and store.count == 14
    stored = list(store.batches())
    assert [(b.first_seq, len(b)) for b in stored] == [(0, 10), (10, 4)]
    store.close()


@pytest.mark.parametrize("first_seq", [0, 5, 11, 12])
def test_append_refuses_a_batch_that_does_not_continue_the_run(tmp_path, first_seq):
    store = ExperienceStore(tmp_path, "srv1")
    store_all(store, batch(0, 10))
    size = store.log.segments.position
    with pytest.raises(ValueError, match="robot1"):
        store.append(batch(first_seq, 3))
    assert store.stored_through == {"robot1": 9} and store.count == 10
    assert store.log.segments.position == size  # nothing written
    store.append(batch(10, 1))
    assert store.stored_through == {"robot1": 10}
    store.close()


def test_append_refuses_a_first_batch_not_starting_at_zero(tmp_path):
    store = ExperienceStore(tmp_path, "srv1")
    with pytest.raises(ValueError):
        store.append(batch(3, 2))
    assert store.stored_through == {} and list(store.batches()) == []
    store.close()


# --------------------------------------------------------------------------- durability
def test_sync_returns_clients_whose_durable_point_moved(tmp_path):
    store = ExperienceStore(tmp_path, "srv1", fsync="never")
    assert store.sync() == {}
    store_all(store, batch(0, 5, "robot1"), batch(0, 3, "robot2"))
    assert store.durable_through == {}
    assert store.sync() == {"robot1": 4, "robot2": 2}
    assert store.durable_through == {"robot1": 4, "robot2": 2}
    assert store.sync() == {}
    store_all(store, batch(3, 2, "robot2"))
    assert store.sync() == {"robot2": 4}
    assert store.durable_through == {"robot1": 4, "robot2": 4}
    store.close()


def test_due_under_interval_policy(tmp_path, clock):
    store = ExperienceStore(tmp_path, "srv1", fsync="interval", fsync_interval_s=0.5)
    assert not store.due()
    store_all(store, batch(0, 2))
    assert not store.due()
    clock.now += 0.25
    assert not store.due()
    clock.now += 0.25
    assert store.due()
    assert store.sync() == {"robot1": 1}
    assert not store.due()
    clock.now += 10
    assert not store.due()  # nothing new stored
    store_all(store, batch(2, 1))
    assert store.due()  # the last sync was long ago
    store.sync()
    store_all(store, batch(3, 1))
    assert not store.due()
    store.close()


def test_due_under_never_policy(tmp_path, clock):
    store = ExperienceStore(tmp_path, "srv1", fsync="never", fsync_interval_s=100.0)
    assert not store.due()
    store_all(store, batch(0, 2))
    assert store.due()  # no interval to wait for
    assert store.sync() == {"robot1": 1}
    assert not store.due()
    store.close()


def test_due_under_always_policy_until_acknowledged(tmp_path, clock):
    store = ExperienceStore(tmp_path, "srv1", fsync="always")
    store_all(store, batch(0, 2))
    assert not store.log.due()  # already fsynced by append
    assert store.due()  # but not yet reported as durable
    assert store.sync() == {"robot1": 1}
    assert not store.due()
    store.close()


# --------------------------------------------------------------------------- reopening
def test_reopen_rebuilds_counters_and_batches(tmp_path):
    written = [batch(0, 4), batch(0, 3, "robot2"), batch(4, 6), batch(3, 2, "robot2"), batch(10, 1)]
    store = ExperienceStore(tmp_path, "srv1", segment_bytes=2000)
    store_all(store, *written)
    store.close()
    assert len(seg_files(tmp_path)) > 1  # the rebuild crosses segment files

    again = ExperienceStore(tmp_path, "srv2", segment_bytes=2000)
    assert again.stored_through == {"robot1": 10, "robot2": 4}
    assert again.durable_through == {"robot1": 10, "robot2": 4}
    assert again.count == 16 and again.unreadable == 0
    assert not again.due() and again.sync() == {}
    stored = list(again.batches())
    assert len(stored) == len(written)
    for got, want in zip(stored, written, strict=True):
        assert_same_batch(got, want)
    assert again.admit(batch(5, 3)) == Admission(None, duplicate=True)
    assert again.admit(batch(12, 1)) == Admission(None, gap=True)
    store_all(again, batch(11, 2))
    again.close()

    third = ExperienceStore(tmp_path, "srv1", segment_bytes=2000)
    assert third.stored_through == {"robot1": 12, "robot2": 4} and third.count == 18
    assert [(b.client, b.first_seq) for b in third.batches()][-1] == ("robot1", 11)
    third.close()


def test_reopen_empty_store(tmp_path):
    ExperienceStore(tmp_path, "srv1").close()
    store = ExperienceStore(tmp_path, "srv1")
    assert store.stored_through == {} and store.count == 0 and list(store.batches()) == []
    store.close()


def test_torn_tail_is_cut_on_reopen_without_losing_earlier_batches(tmp_path):
    written = [batch(0, 4), batch(4, 4), batch(8, 4)]
    store = ExperienceStore(tmp_path, "srv1", fsync="always")
    store_all(store, *written)
    store.close()
    (path,) = seg_files(tmp_path)
    intact = path.stat().st_size
    torn = Codec("srv1").encode(batch(12, 4))
    torn_record = segments.RECORD.pack(len(torn), segments.crc32c(torn)) + torn
    with open(path, "ab") as f:
        f.write(torn_record[: len(torn_record) // 2])

    again = ExperienceStore(tmp_path, "srv1")
    assert again.log.segments.recovery.torn_bytes_cut == len(torn_record) // 2
    assert path.stat().st_size == intact
    assert again.stored_through == {"robot1": 11} and again.count == 12 and again.unreadable == 0
    for got, want in zip(again.batches(), written, strict=True):
        assert_same_batch(got, want)
    assert again.admit(batch(12, 4)).new is not None
    store_all(again, batch(12, 4))
    again.close()
    third = ExperienceStore(tmp_path, "srv1")
    assert third.stored_through == {"robot1": 15} and third.log.segments.recovery.torn_bytes_cut == 0
    third.close()


def test_last_batch_cut_mid_record_is_forgotten_and_can_be_resent(tmp_path):
    store = ExperienceStore(tmp_path, "srv1", fsync="always")
    store_all(store, batch(0, 4))
    last_at = store.log.segments.position.offset
    store_all(store, batch(4, 4))
    store.close()
    (path,) = seg_files(tmp_path)
    size = path.stat().st_size
    with open(path, "r+b") as f:
        f.truncate(size - 10)
    again = ExperienceStore(tmp_path, "srv1")
    assert again.log.segments.recovery.torn_bytes_cut == size - 10 - last_at
    assert again.stored_through == {"robot1": 3} and again.count == 4
    assert again.admit(batch(0, 8)).new.first_seq == 4  # the client re-sends from its ack
    again.close()


def test_records_that_are_not_batches_are_counted_and_skipped(tmp_path):
    store = ExperienceStore(tmp_path, "srv1")
    store_all(store, batch(0, 2))
    store.log.segments.append(b"not a frame")
    frame = Codec("x").encode(dataclasses.replace(batch(0, 1), client="other"))
    store.log.segments.append(b"XXXX" + frame[4:])  # intact record, but not a wfnn frame
    store_all(store, batch(2, 2))
    store.close()
    again = ExperienceStore(tmp_path, "srv1")
    assert again.unreadable == 2
    assert again.stored_through == {"robot1": 3} and again.count == 4
    again.close()


# --------------------------------------------------------------------------- several clients
def test_interleaved_clients_keep_separate_counters(tmp_path):
    store = ExperienceStore(tmp_path, "srv1")
    store_all(store, batch(0, 3, "a"), batch(0, 5, "b"), batch(3, 2, "a"))
    assert store.stored_through == {"a": 4, "b": 4} and store.count == 10
    assert store.admit(batch(0, 5, "b")).duplicate
    assert store.admit(batch(5, 1, "a")).new is not None
    assert store.admit(batch(6, 1, "b")).gap
    overlap = store.admit(batch(3, 4, "b"))
    assert overlap.new.client == "b" and overlap.new.first_seq == 5 and len(overlap.new) == 2
    store.append(overlap.new)
    with pytest.raises(ValueError):
        store.append(batch(7, 1, "a"))  # "a" continues at 5
    assert store.stored_through == {"a": 4, "b": 6} and store.count == 12
    store.close()

    again = ExperienceStore(tmp_path, "srv1")
    assert again.stored_through == {"a": 4, "b": 6} and again.count == 12
    assert [(b.client, b.first_seq, len(b)) for b in again.batches()] == [
        ("a", 0, 3), ("b", 0, 5), ("a", 3, 2), ("b", 5, 2),
    ]  # fmt: skip
    again.close()


# --------------------------------------------------------------------------- holes
def declared(b, lost_from=-1):
    """`b` declaring the experiences its receiver lacks before it lost (as a client's re-send does),
    from `lost_from` on (-1: all, as an older client's declaration)."""
    flags = b.flags.copy()
    flags[0] |= EXP_AFTER_LOSS
    return dataclasses.replace(b, flags=flags, lost_from=lost_from)


def store_with_hole(directory):
    """robot1's 0-9 and 20-29 stored: 10-19 missing (as a damaged record leaves them)."""
    store = ExperienceStore(directory, "srv1")
    store_all(store, batch(0, 10))
    gap = store.admit(batch(20, 10), allow_gap=True)
    assert gap.new is not None and gap.missing == 10 and gap.lost == 0
    store.append(gap.new, allow_gap=True)
    return store


def stored_numbers(store, client="robot1"):
    return sorted(
        s for b in store.batches() if b.client == client for s in range(b.first_seq, b.last_seq + 1)
    )


def test_a_hole_is_acknowledged_before_and_filled_by_a_resend_that_runs_past_it(tmp_path):
    store = store_with_hole(tmp_path)
    assert store.holes == {"robot1": [(10, 19)]} and store.stored_through == {"robot1": 29}
    assert store.missing() == 10 and store.lost == {} and store.count == 20
    assert store.sync() == {"robot1": 9}  # acks promise everything through: not past the hole
    assert store.admit(batch(30, 5)).new is not None  # the live stream goes on after the run
    assert store.admit(batch(31, 1)).gap and store.admit(batch(22, 3)).duplicate
    admissions = []
    for admitted in store.parts(batch(5, 30)):  # a re-send from the acknowledged point: 5-34
        admissions.append((admitted.new.first_seq, admitted.new.last_seq))
        store.append(admitted.new)
    assert admissions == [(10, 19), (30, 34)]
    assert store.holes == {} and store.count == 35 and store.stored_through == {"robot1": 34}
    assert store.sync() == {"robot1": 34}
    assert stored_numbers(store) == list(range(35))
    for got, want in zip(
        store.batches(), [batch(0, 10), batch(20, 10), batch(10, 10), batch(30, 5)], strict=True
    ):
        assert_same_batch(got, want)
    store.close()
    again = ExperienceStore(tmp_path, "srv1")
    assert (
        again.holes == {}
        and again.stored_through == {"robot1": 34}
        and again.durable_through == {"robot1": 34}
    )
    assert again.count == 35 and again.lost == {}
    again.close()


def test_reopening_keeps_the_holes_and_acknowledges_before_the_first(tmp_path):
    store = store_with_hole(tmp_path)
    store.append(store.admit(batch(40, 5), allow_gap=True).new, allow_gap=True)
    store.close()
    again = ExperienceStore(tmp_path, "srv1")
    assert again.holes == {"robot1": [(10, 19), (30, 39)]} and again.missing() == 20
    assert again.durable_through == {"robot1": 9} and again.stored_through == {"robot1": 44}
    store_all(again, batch(10, 10))
    assert again.sync() == {"robot1": 29}
    again.close()


def test_a_fill_may_split_a_hole(tmp_path):
    store = store_with_hole(tmp_path)
    fill = store.admit(batch(12, 3))
    assert fill.new is not None and (fill.new.first_seq, fill.new.last_seq) == (12, 14)
    store.append(fill.new)
    assert store.holes == {"robot1": [(10, 11), (15, 19)]} and store.sync() == {"robot1": 9}
    store.close()


def test_a_declared_loss_that_brings_nothing_new_gives_up_the_holes_before_it(tmp_path):
    store = store_with_hole(tmp_path)
    store.sync()
    admitted = store.admit(declared(batch(25, 3)))
    assert admitted == Admission(None, duplicate=True, lost=10)
    assert store.holes == {"robot1": [(10, 19)]}  # admit changes nothing
    assert store.declare_lost(declared(batch(25, 3))) == 10
    assert store.holes == {} and store.lost == {"robot1": 10} and store.sync() == {"robot1": 29}
    assert store.declare_lost(declared(batch(25, 3))) == 0
    store.close()


def test_a_declared_loss_that_appends_nothing_is_due_at_once_under_the_interval_policy(tmp_path, clock):
    """No record waits to make it due: the client's acks stayed before the hole until another came."""
    store_with_hole(tmp_path).close()
    again = ExperienceStore(tmp_path, "srv1", fsync="interval", fsync_interval_s=0.5)
    assert again.declare_lost(declared(batch(25, 3))) == 10
    assert again.due() and again.sync() == {"robot1": 29}
    store_all(again, batch(30, 1))
    assert not again.due()  # an appended record waits for the interval as before
    again.close()


def test_a_declared_loss_past_the_run_gives_up_the_holes_and_the_gap_until_reopened(tmp_path):
    store = store_with_hole(tmp_path)
    admitted = store.admit(declared(batch(35, 5)))
    assert admitted.new is not None and admitted.lost == 15  # 10-19 and 30-34
    store.append(admitted.new, admitted.lost)
    assert store.holes == {} and store.stored_through == {"robot1": 39} and store.lost == {"robot1": 15}
    assert store.sync() == {"robot1": 39}
    store.close()
    # The log does not say what the declaration gave up: reopened, those are holes, asked for again.
    again = ExperienceStore(tmp_path, "srv1")
    assert again.holes == {"robot1": [(10, 19), (30, 34)]} and again.lost == {}
    assert again.stored_through == {"robot1": 39} and again.durable_through == {"robot1": 9}
    admitted = again.admit(declared(batch(35, 5)))  # the client's journal still lacks them: said again
    assert admitted == Admission(None, duplicate=True, lost=15)
    assert again.declare_lost(declared(batch(35, 5))) == 15 and again.sync() == {"robot1": 39}
    again.close()


def test_a_declared_loss_inside_a_hole_gives_up_only_what_is_before_it(tmp_path):
    store = store_with_hole(tmp_path)
    parts = store.parts(declared(batch(15, 10)))  # 15-24: 10-14 lost, 15-19 fill the rest of the hole
    first = next(parts)
    assert first.lost == 5 and (first.new.first_seq, first.new.last_seq) == (15, 19)
    store.append(first.new, first.lost)
    assert list(parts) == []  # 20-24 are stored
    assert store.holes == {} and store.lost == {"robot1": 5} and store.count == 25
    store.close()
    again = ExperienceStore(tmp_path, "srv1")
    assert (
        again.holes == {"robot1": [(10, 14)]} and again.lost == {} and again.durable_through == {"robot1": 9}
    )
    again.close()


def test_a_record_damaged_before_a_declared_loss_is_a_hole_when_reopened_not_acknowledged(tmp_path):
    """Reopening gave up everything missing before a declaration, a damaged record's experiences
    too, and acknowledged them though they were not stored."""
    store = ExperienceStore(tmp_path, "srv1", fsync="always")
    store_all(store, batch(0, 10))
    admitted = store.admit(declared(batch(20, 10)))
    store.append(admitted.new, admitted.lost)
    store.close()
    (path,) = seg_files(tmp_path)
    raw = bytearray(path.read_bytes())
    raw[segments.RECORD.size + 40] ^= 0xFF  # inside the first record (0-9)
    path.write_bytes(bytes(raw))
    again = ExperienceStore(tmp_path, "srv1")
    assert again.holes == {"robot1": [(0, 19)]} and again.durable_through == {"robot1": -1}
    assert again.lost == {} and again.count == 10
    again.close()


def test_a_flag_inside_a_batch_declares_nothing_for_the_part_stored_from_it(tmp_path):
    store = store_with_hole(tmp_path)
    flagged = batch(26, 10)  # 26-35: 30-35 new; the flag sits on 30, not on the batch's first
    flagged.flags[4] |= EXP_AFTER_LOSS
    flagged.flags[0] &= ~EXP_AFTER_LOSS & 0xFF
    (admitted,) = list(store.parts(flagged))
    assert admitted.lost == 0 and (admitted.new.first_seq, admitted.new.last_seq) == (30, 35)
    store.append(admitted.new, admitted.lost)
    assert store.holes == {"robot1": [(10, 19)]} and store.lost == {}
    store.close()
    again = ExperienceStore(tmp_path, "srv1")
    assert (
        again.holes == {"robot1": [(10, 19)]} and again.lost == {} and again.stored_through == {"robot1": 35}
    )
    again.close()


@pytest.mark.parametrize(("first", "n", "lost"), [(5, 10, 0), (18, 5, 0), (10, 10, 3), (30, 2, 1)])
def test_append_refuses_what_does_not_fit_and_writes_nothing(tmp_path, first, n, lost):
    store = store_with_hole(tmp_path)
    size = store.log.segments.position
    with pytest.raises(ValueError, match="robot1"):
        store.append(batch(first, n), lost)
    assert store.log.segments.position == size
    assert (
        store.holes == {"robot1": [(10, 19)]} and store.stored_through == {"robot1": 29} and store.count == 20
    )
    store.close()


def test_a_declaration_gives_up_only_what_it_names_not_a_hole_before_it(tmp_path):
    """A declaration made before a restart (replayed, or delivered late) gave up every hole before
    it, one the client's journal still holds among them, and acknowledged it unstored."""
    store = store_with_hole(tmp_path)  # 10-19 missing, stored through 29
    store.sync()
    late = declared(batch(35, 5), lost_from=30)  # "my journal lacks 30-34", said when 0-29 were acknowledged
    admitted = store.admit(late)
    assert admitted.lost == 5 and admitted.new is not None
    store.append(admitted.new, admitted.lost)
    assert store.holes == {"robot1": [(10, 19)]} and store.lost == {"robot1": 5}
    assert store.sync() == {} and store.durable_through == {"robot1": 9}  # the hole is still asked for
    nothing_new = declared(batch(25, 3), lost_from=20)  # names none of the hole: gives none of it up
    assert store.admit(nothing_new) == Admission(None, duplicate=True, lost=0)
    assert store.declare_lost(nothing_new) == 0 and store.holes == {"robot1": [(10, 19)]}
    partly = declared(batch(25, 3), lost_from=15)
    assert store.declare_lost(partly) == 5 and store.holes == {"robot1": [(10, 14)]}
    store.close()


def test_a_declaration_that_starts_past_the_end_of_the_run_leaves_a_gap_and_is_refused(tmp_path):
    store = ExperienceStore(tmp_path, "srv1")
    store_all(store, batch(0, 10))
    assert store.admit(declared(batch(20, 5), lost_from=15)) == Admission(
        None, gap=True
    )  # 10-14 named by none
    with pytest.raises(ValueError, match="its run ends at 9"):
        store.append(declared(batch(20, 5), lost_from=15), 5)
    admitted = store.admit(declared(batch(20, 5), lost_from=10))
    assert admitted.lost == 10
    store.append(admitted.new, admitted.lost)
    assert store.stored_through == {"robot1": 24} and store.lost == {"robot1": 10}
    store.close()
