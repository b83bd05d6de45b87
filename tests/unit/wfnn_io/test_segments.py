import os
import types

import pytest

from wfnn_io import segments
from wfnn_io.protocol import crc32c
from wfnn_io.segments import RECORD, LogError, Position, SegmentLog


def payloads(n, size=20, tag=b"r"):
    return [tag + bytes([i % 256]) * size + str(i).encode() for i in range(n)]


def seg_path(directory, n):
    return directory / f"{n:08d}.seg"


def read_all(log, start=None):
    return list(log.read(start))


class FakeClock:
    def __init__(self):
        self.now = 1000.0

    def monotonic(self):
        return self.now


@pytest.fixture
def clock(monkeypatch):
    fake = FakeClock()
    monkeypatch.setattr(segments, "time", types.SimpleNamespace(monotonic=fake.monotonic))
    return fake


# --------------------------------------------------------------------------- append and read
def test_append_read_round_trip_and_positions(tmp_path):
    records = payloads(10)
    with SegmentLog(tmp_path, fsync="never") as log:
        with pytest.raises(LogError):
            log.append(b"")  # an empty record would be indistinguishable from a zero-filled tail
        assert log.position == Position(0, 0)
        positions = [log.append(p) for p in records]
        expected, offset = [], 0
        for p in records:
            expected.append(Position(0, offset))
            offset += RECORD.size + len(p)
        assert positions == expected
        assert log.position == Position(0, offset)
        assert read_all(log) == list(zip(expected, records, strict=True))
    assert seg_path(tmp_path, 0).stat().st_size == offset
    with SegmentLog(tmp_path) as again:
        assert read_all(again) == list(zip(expected, records, strict=True))
        assert again.position == Position(0, offset)
        assert again.recovery.segments == 1 and again.recovery.torn_bytes_cut == 0


def test_record_format_on_disk(tmp_path):
    with SegmentLog(tmp_path) as log:
        log.append(b"hello")
    data = seg_path(tmp_path, 0).read_bytes()
    assert data == RECORD.pack(5, crc32c(b"hello")) + b"hello"


def test_empty_directory_reads_nothing(tmp_path):
    with SegmentLog(tmp_path / "new" / "dir") as log:
        assert read_all(log) == []
        assert log.recovery.segments == 0
        assert log.segment_numbers() == [0]  # the first segment file is created at open


def test_rotation_to_new_segments(tmp_path):
    records = payloads(10, size=40)  # 8 + 42 or 43 bytes each
    with SegmentLog(tmp_path, segment_bytes=120, fsync="always") as log:
        positions = [log.append(p) for p in records]
        assert log.segment_numbers() == [0, 1, 2, 3, 4]
        assert [p.segment for p in positions] == [0, 0, 1, 1, 2, 2, 3, 3, 4, 4]
        assert all(p.offset == 0 for p in positions[::2])
        assert [p.offset for p in positions[1::2]] == [RECORD.size + len(records[i]) for i in range(0, 10, 2)]
        for n in range(5):
            assert seg_path(tmp_path, n).stat().st_size <= 120
        assert read_all(log) == list(zip(positions, records, strict=True))
    with SegmentLog(tmp_path, segment_bytes=120) as again:
        assert again.recovery.segments == 5
        assert [p for _, p in again.read()] == records
        assert again.append(b"x" * 60) == Position(5, 0)  # segment 4 is full
        assert again.position.segment == 5


def test_a_segment_missing_between_others_is_reported_as_damage(tmp_path):
    """A deleted middle segment was read past without a word: its records were simply not there."""
    with SegmentLog(tmp_path, segment_bytes=120, fsync="always") as log:
        for p in payloads(10, size=40):
            log.append(p)
    seg_path(tmp_path, 1).unlink()
    seg_path(tmp_path, 2).unlink()
    report = segments.ReadReport()
    assert len(list(segments.read_records(tmp_path, report=report))) == 6
    assert [(d.segment, d.segments, d.kind) for d in report.damage] == [(1, 2, "missing")]  # one span
    report = segments.ReadReport()
    list(segments.read_records(tmp_path, start=Position(3, 0), report=report))  # read from after them
    assert report.damage == []
    seg_path(tmp_path, 4).rename(seg_path(tmp_path, 10**7))  # a stray number: still one span, at once
    report = segments.ReadReport()
    list(segments.read_records(tmp_path, report=report))
    assert [(d.segment, d.segments) for d in report.damage] == [(1, 2), (4, 10**7 - 4)]


def test_a_missing_first_segment_an_emptied_one_and_one_a_listing_missed_are_told_apart(
    tmp_path, monkeypatch
):
    """A log begins at segment 0 and its writer leaves none empty before its last: a deleted first
    segment and an emptied middle one were read past without a word. A segment the first listing
    missed (a writer rotating fast) is read, not called missing."""
    with SegmentLog(tmp_path, segment_bytes=120, fsync="always") as log:
        for p in payloads(10, size=40):
            log.append(p)
    seg_path(tmp_path, 0).unlink()
    seg_path(tmp_path, 2).write_bytes(b"")
    report = segments.ReadReport()
    assert len(list(segments.read_records(tmp_path, report=report))) == 6
    assert [(d.segment, d.segments, d.kind) for d in report.damage] == [(0, 1, "missing"), (2, 1, "missing")]
    listed = segments.segment_numbers
    calls = []

    def first_misses_three(directory):
        calls.append(1)
        numbers = listed(directory)
        return [n for n in numbers if n != 3] if len(calls) == 1 else numbers

    monkeypatch.setattr(segments, "segment_numbers", first_misses_three)
    report = segments.ReadReport()
    positions = [pos for pos, _ in segments.read_records(tmp_path, report=report)]
    assert [p.segment for p in positions] == [1, 1, 3, 3, 4, 4] and len(report.damage) == 2


def test_missing_segments_from_a_start_and_side_by_side_are_one_span_each_run(tmp_path):
    with SegmentLog(tmp_path, segment_bytes=120, fsync="always") as log:
        for p in payloads(12, size=40):
            log.append(p)
    seg_path(tmp_path, 2).unlink()
    report = segments.ReadReport()
    list(segments.read_records(tmp_path, start=Position(2, 0), report=report))  # a start names a written one
    assert [(d.segment, d.segments) for d in report.damage] == [(2, 1)]
    seg_path(tmp_path, 3).write_bytes(b"")  # emptied beside the missing one: one span
    report = segments.ReadReport()
    list(segments.read_records(tmp_path, report=report))
    assert [(d.segment, d.segments, d.kind) for d in report.damage] == [(2, 2, "missing")]


def test_a_rotation_that_cannot_open_the_next_segment_leaves_the_log_as_it_was(tmp_path, monkeypatch):
    """The segment number moved on at each failed open: the next append wrote segment 2, and readers
    called the never-written segment 1 missing."""
    import builtins

    real_open = builtins.open
    log = SegmentLog(tmp_path, segment_bytes=100, fsync="never")
    log.append(b"a" * 40)
    log.append(b"b" * 40)

    def no_handles(path, *args, **kw):
        if str(path).endswith(segments.segment_name(1)):
            raise OSError(24, "Too many open files")
        return real_open(path, *args, **kw)

    monkeypatch.setattr(builtins, "open", no_handles)
    with pytest.raises(OSError):
        log.append(b"c" * 40)
    monkeypatch.setattr(builtins, "open", real_open)
    assert log.append(b"c" * 40) == Position(1, 0)
    log.close()
    report = segments.ReadReport()
    assert [p for _, p in segments.read_records(tmp_path, report=report)] == [b"a" * 40, b"b" * 40, b"c" * 40]
    assert report.damage == []


def test_record_larger_than_segment_gets_its_own_segment(tmp_path):
    with SegmentLog(tmp_path, segment_bytes=16) as log:
        assert log.append(b"a" * 100) == Position(0, 0)  # an empty segment takes any record
        assert log.append(b"b") == Position(1, 0)
        assert log.append(b"c" * 50) == Position(2, 0)
        assert [p for _, p in log.read()] == [b"a" * 100, b"b", b"c" * 50]


def test_read_from_a_position(tmp_path):
    records = payloads(12, size=30)
    with SegmentLog(tmp_path, segment_bytes=150) as log:
        positions = [log.append(p) for p in records]
        assert len(log.segment_numbers()) > 2
        for i in (0, 1, 4, 5, 11):
            got = read_all(log, positions[i])
            assert got == list(zip(positions[i:], records[i:], strict=True))
        assert read_all(log, log.position) == []
        seg = positions[5].segment
        assert [p for _, p in log.read(Position(seg, 0))] == [
            r for pos, r in zip(positions, records, strict=True) if pos.segment >= seg
        ]


def test_oversized_record_is_refused(tmp_path, monkeypatch):
    monkeypatch.setattr(segments, "MAX_RECORD", 64)
    with SegmentLog(tmp_path) as log:
        log.append(b"x" * 64)
        with pytest.raises(LogError):
            log.append(b"x" * 65)
        assert [p for _, p in log.read()] == [b"x" * 64]


# --------------------------------------------------------------------------- torn tails (the owner)
def quarantined(directory):
    return sorted((directory / segments.QUARANTINE).glob("*.torn"))


@pytest.mark.parametrize("torn", [1, 3, RECORD.size - 1, RECORD.size, RECORD.size + 5])
def test_torn_partial_record_is_moved_to_quarantine_at_reopen(tmp_path, torn):
    records = payloads(5)
    with SegmentLog(tmp_path, fsync="always") as log:
        for p in records:
            log.append(p)
        intact_size = log.position.offset
    partial = (RECORD.pack(30, crc32c(b"z" * 30)) + b"z" * 30)[:torn]
    with open(seg_path(tmp_path, 0), "ab") as f:
        f.write(partial)
    with SegmentLog(tmp_path, fsync="always") as log:
        assert log.recovery.torn_bytes_cut == torn
        assert seg_path(tmp_path, 0).stat().st_size == intact_size
        # The cut bytes are kept beside the log, named after the segment and the offset.
        [kept] = quarantined(tmp_path)
        assert kept.name == f"00000000-{intact_size:010d}.torn" and kept.read_bytes() == partial
        assert log.recovery.quarantined == [kept]
        assert log.position == Position(0, intact_size)
        assert [p for _, p in log.read()] == records
        assert log.append(b"after") == Position(0, intact_size)
        assert [p for _, p in log.read()] == [*records, b"after"]
    with SegmentLog(tmp_path) as log:
        assert log.recovery.torn_bytes_cut == 0
        assert [p for _, p in log.read()] == [*records, b"after"]
    assert len(quarantined(tmp_path)) == 1


def test_file_truncated_mid_record_is_cut_at_reopen(tmp_path):
    records = payloads(6, size=50)
    with SegmentLog(tmp_path, segment_bytes=200, fsync="always") as log:
        positions = [log.append(p) for p in records]
    last = positions[-1]
    assert last.segment > 0 and last.offset > 0
    full = seg_path(tmp_path, last.segment).stat().st_size
    with open(seg_path(tmp_path, last.segment), "r+b") as f:
        f.truncate(full - 7)
    with SegmentLog(tmp_path, segment_bytes=200) as log:
        assert log.recovery.torn_bytes_cut == full - 7 - last.offset
        assert seg_path(tmp_path, last.segment).stat().st_size == last.offset
        assert [p for _, p in log.read()] == records[:-1]
        log.append(b"new")
        assert [p for _, p in log.read()] == [*records[:-1], b"new"]


def test_torn_record_with_bad_crc_is_cut(tmp_path):
    with SegmentLog(tmp_path) as log:
        log.append(b"first")
        log.append(b"second")
        size = log.position.offset
    data = bytearray(seg_path(tmp_path, 0).read_bytes())
    data[-1] ^= 0xFF  # the last record's payload no longer matches its CRC
    seg_path(tmp_path, 0).write_bytes(bytes(data))
    with SegmentLog(tmp_path) as log:
        assert log.recovery.torn_bytes_cut == RECORD.size + len(b"second")
        assert [p for _, p in log.read()] == [b"first"]
        assert log.position.offset == size - RECORD.size - len(b"second")
    assert quarantined(tmp_path)[0].read_bytes() == bytes(data[size - RECORD.size - len(b"second") :])


def test_absurd_length_in_tail_is_cut(tmp_path):
    with SegmentLog(tmp_path) as log:
        log.append(b"ok")
    with open(seg_path(tmp_path, 0), "ab") as f:
        f.write(RECORD.pack(0xFFFFFFFF, 0) + b"junk")
    with SegmentLog(tmp_path) as log:
        assert log.recovery.torn_bytes_cut == RECORD.size + 4
        assert [p for _, p in log.read()] == [b"ok"]


def test_zero_filled_tail_is_not_read_as_records(tmp_path):
    with SegmentLog(tmp_path) as log:
        log.append(b"ok")
    with open(seg_path(tmp_path, 0), "ab") as f:
        f.write(b"\0" * 4096)
    assert [p for _, p in segments.read_records(tmp_path)] == [b"ok"]
    with SegmentLog(tmp_path) as log:
        assert [p for _, p in log.read()] == [b"ok"]


# --------------------------------------------------------------------------- damage in the middle
def damage(path, offset, xor=0x01):
    data = bytearray(path.read_bytes())
    data[offset] ^= xor
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("marker", [b"", b"r"])
def test_a_damaged_record_in_the_middle_is_skipped_and_the_next_ones_read(tmp_path, marker):
    records = payloads(9, size=40)
    with SegmentLog(tmp_path, segment_bytes=160, fsync="always") as log:
        positions = [log.append(p) for p in records]
    by_segment = {}
    for pos, p in zip(positions, records, strict=True):
        by_segment.setdefault(pos.segment, []).append((pos, p))
    assert len(by_segment) >= 3 and len(by_segment[1]) == 3
    victim = by_segment[1][1][0]  # the middle record of segment 1
    damage(seg_path(tmp_path, 1), victim.offset + RECORD.size + 3)
    expected = [p for pos, p in zip(positions, records, strict=True) if pos != victim]

    report = segments.ReadReport()
    assert [p for _, p in segments.read_records(tmp_path, report=report, marker=marker)] == expected
    length = RECORD.size + len(by_segment[1][1][1])
    assert report.damage == [segments.Damage(1, victim.offset, length, "corrupt")]
    assert report.records == len(expected) and report.skipped_bytes == length

    with SegmentLog(tmp_path, segment_bytes=160, marker=marker) as log:
        assert log.recovery.torn_bytes_cut == 0 and log.recovery.corrupt_spans == 0  # not its last segment
        assert [p for _, p in log.read()] == expected
        after = [p for pos, p in zip(positions, records, strict=True) if pos > victim]
        assert [p for _, p in log.read(victim)] == after
        log.append(b"more")
        assert [p for _, p in log.read()] == [*expected, b"more"]


def test_damage_in_the_middle_of_the_last_segment_is_left_for_readers(tmp_path):
    records = payloads(5)
    with SegmentLog(tmp_path) as log:
        positions = [log.append(p) for p in records]
    size = seg_path(tmp_path, 0).stat().st_size
    damage(seg_path(tmp_path, 0), positions[1].offset + 1)  # the length field of record 1
    with SegmentLog(tmp_path) as log:
        assert log.recovery.torn_bytes_cut == 0 and log.recovery.corrupt_spans == 1
        assert seg_path(tmp_path, 0).stat().st_size == size and not quarantined(tmp_path)
        assert [p for _, p in log.read()] == [records[0], *records[2:]]
        assert log.append(b"next") == Position(0, size)


def test_two_damaged_records_are_reported_separately(tmp_path):
    with SegmentLog(tmp_path, segment_bytes=40) as log:
        positions = [log.append(bytes([i]) * 20) for i in range(4)]
    assert [p.segment for p in positions] == [0, 1, 2, 3]
    for n in (0, 2):
        damage(seg_path(tmp_path, n), 27, 0x80)
    report = segments.ReadReport()
    read = [p for _, p in segments.read_records(tmp_path, report=report)]
    assert read == [bytes([1]) * 20, bytes([3]) * 20]
    assert [(d.segment, d.offset, d.length) for d in report.damage] == [(0, 0, 28), (2, 0, 28)]


def test_read_at_returns_a_record_or_none(tmp_path):
    with SegmentLog(tmp_path) as log:
        first = log.append(b"one")
        second = log.append(b"two")
        assert log.read_at(first) == b"one" and log.read_at(second) == b"two"
        assert log.read_at(Position(0, 1)) is None and log.read_at(Position(7, 0)) is None
        damage(seg_path(tmp_path, 0), second.offset + RECORD.size)
        assert log.read_at(second) is None


# --------------------------------------------------------------------------- reading never writes
def snapshot(directory):
    return {p.relative_to(directory): (p.read_bytes(), p.stat().st_mtime_ns)
            for p in sorted(directory.rglob("*")) if p.is_file()}  # fmt: skip


def test_reading_changes_no_file_whatever_the_damage(tmp_path):
    with SegmentLog(tmp_path, segment_bytes=100) as log:
        positions = [log.append(p) for p in payloads(8, size=30)]
    damage(seg_path(tmp_path, 1), 10)
    with open(seg_path(tmp_path, positions[-1].segment), "ab") as f:
        f.write(b"torn tail")
    before = snapshot(tmp_path)
    report = segments.ReadReport()
    assert len(list(segments.read_records(tmp_path, report=report))) == 7
    assert [d.kind for d in report.damage] == ["corrupt", "tail"]
    assert snapshot(tmp_path) == before


def test_damage_at_the_end_of_a_segment_before_the_last_is_corrupt_not_a_torn_tail(tmp_path):
    """Only the last segment can end in a torn write: a segment is synced before the next begins."""
    with SegmentLog(tmp_path, segment_bytes=40) as log:  # one record per segment
        positions = [log.append(p) for p in payloads(4)]
    assert [p.segment for p in positions] == [0, 1, 2, 3]
    damaged = bytearray(seg_path(tmp_path, 1).read_bytes())
    damaged[-1] ^= 1
    seg_path(tmp_path, 1).write_bytes(bytes(damaged))
    report = segments.ReadReport()
    assert len(list(segments.read_records(tmp_path, report=report))) == 3
    assert [(d.segment, d.kind) for d in report.damage] == [(1, "corrupt")]


def test_reading_works_without_write_permission(tmp_path):
    import os
    import stat

    with SegmentLog(tmp_path / "log") as log:
        log.append(b"a")
        log.append(b"b")
    for path in [tmp_path / "log", *(tmp_path / "log").iterdir()]:
        path.chmod(stat.S_IRUSR | stat.S_IXUSR if path.is_dir() else stat.S_IRUSR)
    try:
        if os.access(seg_path(tmp_path / "log", 0), os.W_OK):
            pytest.skip("running as root: permissions do not stop writes here")
        assert [p for _, p in segments.read_records(tmp_path / "log")] == [b"a", b"b"]
    finally:
        for path in [tmp_path / "log", *(tmp_path / "log").iterdir()]:
            path.chmod(stat.S_IRWXU)


# --------------------------------------------------------------------------- fsync policies
def test_always_leaves_nothing_to_sync(tmp_path, clock):
    with SegmentLog(tmp_path, fsync="always", fsync_interval_s=0.0) as log:
        log.append(b"a")
        assert not log.due()
        clock.now += 100
        assert not log.due()
        log.append(b"b")
        assert not log.due()


def test_interval_due_only_after_the_interval(tmp_path, clock):
    with SegmentLog(tmp_path, fsync="interval", fsync_interval_s=0.5) as log:
        log.append(b"a")
        assert not log.due()
        clock.now += 0.4375
        assert not log.due()
        clock.now += 0.0625
        assert log.due()
        log.sync()
        assert not log.due()
        clock.now += 0.25
        log.append(b"b")
        assert not log.due()  # the interval counts from the last sync
        clock.now += 0.25
        assert log.due()


def test_interval_with_nothing_appended_is_never_due(tmp_path, clock):
    with SegmentLog(tmp_path, fsync="interval", fsync_interval_s=0.5) as log:
        clock.now += 10
        assert not log.due()


def test_never_is_due_whenever_records_wait(tmp_path, clock):
    with SegmentLog(tmp_path, fsync="never", fsync_interval_s=100.0) as log:
        assert not log.due()
        log.append(b"a")
        assert log.due()
        log.sync()
        assert not log.due()


def test_appends_reach_the_file_before_any_sync(tmp_path):
    with SegmentLog(tmp_path, fsync="never") as log:
        log.append(b"a")
        log.append(b"bc")
        assert log.due()
        data = seg_path(tmp_path, 0).read_bytes()
        assert data == RECORD.pack(1, crc32c(b"a")) + b"a" + RECORD.pack(2, crc32c(b"bc")) + b"bc"


@pytest.mark.parametrize("policy", ["sometimes", "", "ALWAYS", None])
def test_invalid_fsync_policy_is_refused(tmp_path, policy):
    with pytest.raises(ValueError, match="fsync"):
        SegmentLog(tmp_path / "x", fsync=policy)
    assert not (tmp_path / "x").exists()


def test_a_second_writer_of_one_log_is_refused_until_the_first_closes(tmp_path):
    import subprocess
    import sys

    first = SegmentLog(tmp_path / "log", fsync="never")
    first.append(b"one")
    with pytest.raises(LogError, match="in use"):
        SegmentLog(tmp_path / "log", fsync="never")
    # Another process too (two clients given one --out, two servers one --data-dir).
    probe = (
        "import sys; from wfnn_io.segments import SegmentLog, LogError\n"
        "try:\n    SegmentLog(sys.argv[1], fsync='never')\nexcept LogError:\n    sys.exit(3)\n"
    )
    second = subprocess.run([sys.executable, "-c", probe, str(tmp_path / "log")], timeout=60)
    assert second.returncode == 3
    first.close()
    again = SegmentLog(tmp_path / "log", fsync="never")  # the lock went with the first writer
    assert [bytes(p) for _, p in again.read()] == [b"one"]
    again.close()


def test_a_tail_torn_twice_at_the_same_place_keeps_both_in_quarantine(tmp_path):
    with SegmentLog(tmp_path, fsync="always") as log:
        log.append(b"kept")
    tails = [b"\x05\x00\x00\x00first-torn", b"\x07\x00\x00\x00second"]
    for tail in tails:  # each start's first append torn at the same offset
        with open(seg_path(tmp_path, 0), "ab") as f:
            f.write(tail)
        with SegmentLog(tmp_path, fsync="always") as log:
            assert [p for _, p in log.read()] == [b"kept"]
    assert sorted(p.read_bytes() for p in quarantined(tmp_path)) == sorted(tails)


def test_only_segment_names_as_the_log_writes_them_count(tmp_path):
    with SegmentLog(tmp_path, segment_bytes=40) as log:
        for p in payloads(3):
            log.append(p)
    (tmp_path / "1.seg").write_bytes(seg_path(tmp_path, 1).read_bytes())  # a copy under another name
    (tmp_path / "\u00b2.seg").write_bytes(b"")  # a digit to str.isdigit, not to int()
    assert segments.segment_numbers(tmp_path) == [0, 1, 2]
    assert [p for _, p in segments.read_records(tmp_path)] == payloads(3)


def test_files_named_like_segments_that_are_not_read_are_told(tmp_path, caplog):
    """A segment renamed by hand (a leading zero, a number beyond any a writer reaches) was read
    past without a word, and a number of 2^63 or more stopped every start of a client."""
    with SegmentLog(tmp_path, segment_bytes=40) as log:
        for p in payloads(4):
            log.append(p)
    seg_path(tmp_path, 3).rename(tmp_path / "100000000000000000000.seg")
    (tmp_path / "000000002.seg").write_bytes(seg_path(tmp_path, 2).read_bytes())
    (tmp_path / "1.seg").write_bytes(b"")
    (tmp_path / f"{segments.MAX_SEGMENT_NUMBER}.seg").write_bytes(b"")
    assert segments.segment_numbers(tmp_path) == [0, 1, 2]
    report = segments.ReadReport()
    assert [p for _, p in segments.read_records(tmp_path, report=report)] == payloads(3)
    assert report.strays == ["000000002.seg", "1.seg", "1000000000000.seg", "100000000000000000000.seg"]
    assert "4 files named like segments" in caplog.text and "100000000000000000000.seg" in caplog.text
    with SegmentLog(tmp_path, segment_bytes=40) as log:  # its owner goes on from its last segment
        log.append(b"more")
    assert segments.segment_numbers(tmp_path)[-1] == 3


@pytest.mark.parametrize("kind", ["fifo", "directory", "link"])
def test_a_segment_that_is_not_a_regular_file_is_refused_in_one_line(tmp_path, kind):
    import os

    directory, outside = tmp_path / "log", tmp_path / "outside.txt"
    with SegmentLog(directory) as log:
        log.append(b"kept")
    outside.write_bytes(b"not a segment")
    odd = seg_path(directory, 1)
    if kind == "fifo":  # opening it would wait forever for a writer
        os.mkfifo(odd)
    elif kind == "directory":
        odd.mkdir()
    else:  # the owner would truncate and append to the file it points to
        odd.symlink_to(outside)
    with pytest.raises(LogError, match=r"00000001\.seg: a segment of this log is"):
        SegmentLog(directory)
    assert outside.read_bytes() == b"not a segment"
    if kind != "link":  # a reader follows a link to a regular file (read-only); nothing else
        with pytest.raises(LogError, match="not a regular file"):
            list(segments.read_records(directory))


def test_new_directory_entries_are_made_durable_before_they_are_relied_on(tmp_path, monkeypatch):
    """The first segment's entry (what a store acknowledges from) and quarantine's (before a cut)."""
    synced = []
    real = segments.sync_dir
    monkeypatch.setattr(segments, "sync_dir", lambda d: (synced.append(d), real(d)))
    log = SegmentLog(tmp_path / "log", fsync="always")
    assert synced == [tmp_path / "log"]
    log.append(b"x" * 100)
    log.close()
    with open(tmp_path / "log" / segments.segment_name(0), "ab") as f:
        f.write(b"torn")
    synced.clear()
    SegmentLog(tmp_path / "log", fsync="always").close()
    assert synced[0] == tmp_path / "log" and tmp_path / "log" / segments.QUARANTINE in synced
    synced.clear()
    SegmentLog(tmp_path / "never", fsync="never").close()
    assert synced == []


# --------------------------------------------------------------------------- crafted and huge segments
@pytest.mark.parametrize("valid_between", [False, True])
def test_false_record_headers_crafted_everywhere_cost_a_bounded_checksum_work(
    tmp_path, monkeypatch, valid_between
):
    """Every 16 bytes a header claiming half the segment, then the marker (with or without a
    valid record between): each try checksummed half the file, so reading took quadratic time
    (a 1 MiB segment did not finish in 25 s)."""
    size = 512 << 10
    unit = RECORD.pack(size // 2, 0) + b"WFNN" + b"\0" * 4
    if valid_between:
        unit = RECORD.pack(size // 2, 0) + b"WFNN" + RECORD.pack(4, crc32c(b"WFNN")) + b"WFNN"
    tmp_path.joinpath(segments.segment_name(0)).write_bytes(unit * (size // len(unit)))
    checked = [0]

    def counting(data):
        checked[0] += len(data)
        return crc32c(data)

    monkeypatch.setattr(segments, "crc32c", counting)
    report = segments.ReadReport()
    records = list(segments.read_records(tmp_path, report=report, marker=b"WFNN"))
    assert all(p == b"WFNN" for _, p in records) and (valid_between or not records)
    assert sum(d.length for d in report.damage) + len(records) * 12 == len(unit * (size // len(unit)))
    assert checked[0] <= (segments.RESYNC_WORK + 1) * size + 2 * segments.MAX_RECORD


def test_a_segment_longer_than_any_written_is_read_only_so_far_and_the_rest_reported(tmp_path, monkeypatch):
    monkeypatch.setattr(segments, "MAX_SEGMENT", 200)
    with SegmentLog(tmp_path) as log:
        for p in payloads(5, size=40):  # 5 records of 50 bytes: the last ends past 200
            log.append(p)
    path = seg_path(tmp_path, 0)
    size = path.stat().st_size
    report = segments.ReadReport()
    assert [p for _, p in segments.read_records(tmp_path, report=report)] == payloads(4, size=40)
    assert [(d.offset, d.offset + d.length) for d in report.damage][-1][1] == size
    assert report.damage[-1].kind == "tail"


def test_the_store_refuses_a_segment_size_readers_would_not_read_whole():
    from wfnn_server.config import ServerConfig

    with pytest.raises(ValueError, match="segment_bytes"):
        ServerConfig(
            controller="t", server_id="s", data_dir="d", segment_bytes=segments.MAX_SEGMENT_BYTES + 1
        )


def test_a_repair_the_disk_cannot_take_leaves_no_empty_tail_in_quarantine(tmp_path, monkeypatch):
    with SegmentLog(tmp_path, fsync="always") as log:
        log.append(b"kept")
    tail = b"\x05\x00\x00\x00torn"
    with open(seg_path(tmp_path, 0), "ab") as f:
        f.write(tail)

    real_fdopen = os.fdopen

    class Full:  # the quarantine copy's writes fail
        def __init__(self, fd, mode):
            self.file = real_fdopen(fd, mode)

        def write(self, data):
            raise OSError(28, "No space left on device")

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.file.close()

    monkeypatch.setattr(segments.os, "fdopen", Full)
    with pytest.raises(OSError, match="No space") as failed:
        SegmentLog(tmp_path, fsync="always")
    assert failed.value.filename.endswith(".torn")  # the copy that failed, not the segment
    assert quarantined(tmp_path) == []
    monkeypatch.undo()  # space again: the tail goes to quarantine under its first name
    with SegmentLog(tmp_path, fsync="always") as log:
        assert [p for _, p in log.read()] == [b"kept"]
    assert [(p.name, p.read_bytes()) for p in quarantined(tmp_path)] == [
        (f"00000000-{RECORD.size + 4:010d}.torn", tail)
    ]


@pytest.mark.parametrize("policy, synced", [("interval", True), ("always", True), ("never", False)])
def test_what_a_crashed_writer_left_unsynced_is_synced_before_the_log_counts_it(
    tmp_path, monkeypatch, policy, synced
):
    """A writer killed before its sync left records in the OS only; reopened, the log took them
    for its own durable records (a restarted server acknowledged them) and never synced them."""
    import os

    first = SegmentLog(tmp_path, fsync="interval")
    for p in payloads(3):
        first.append(p)
    first._file.close()  # killed: the records are in the OS, never synced, the lock let go
    os.close(first._lock)
    segment = os.stat(seg_path(tmp_path, 0)).st_ino
    real, synced_files = os.fsync, []

    def spy(fd):
        synced_files.append(os.fstat(fd).st_ino)
        return real(fd)

    monkeypatch.setattr(os, "fsync", spy)
    log = SegmentLog(tmp_path, fsync=policy)
    assert (segment in synced_files) is synced and len(read_all(log)) == 3
    log.close()


def test_a_lock_file_that_is_a_fifo_is_refused_at_once(tmp_path):
    """Opening it waited for a writer that never came, and SIGTERM could not end the wait."""
    import os
    import threading

    os.mkfifo(tmp_path / segments.LOCK)
    outcomes = []

    def open_both():
        for opening in (lambda: segments.check_free(tmp_path), lambda: SegmentLog(tmp_path)):
            try:
                opening()
                outcomes.append("opened")
            except LogError as exc:
                outcomes.append(str(exc))

    worker = threading.Thread(target=open_both, daemon=True)
    worker.start()
    worker.join(10.0)
    assert not worker.is_alive(), "still waiting on the FIFO"
    assert len(outcomes) == 2 and all("is not a regular file" in o for o in outcomes)


def test_segments_a_never_syncing_writer_left_are_all_synced_when_the_log_is_opened(tmp_path, monkeypatch):
    """Under the `never` policy a segment is not synced before the next begins: only the last was
    synced at open, and what the earlier ones held was acknowledged unsynced."""
    import os

    first = SegmentLog(tmp_path, fsync="never", segment_bytes=200)
    for p in payloads(20):
        first.append(p)
    first.close()
    inodes = {os.stat(path).st_ino for path in tmp_path.glob("*.seg")}
    assert len(inodes) > 3
    real, synced_files = os.fsync, set()

    def spy(fd):
        synced_files.add(os.fstat(fd).st_ino)
        return real(fd)

    monkeypatch.setattr(os, "fsync", spy)
    SegmentLog(tmp_path, fsync="interval").close()
    assert inodes <= synced_files


def test_a_write_that_fails_names_the_segment(tmp_path):
    """A full disk failed a record's write, flush or fsync with an error naming no file, and the
    tools' one-line errors ("No space left on device") did not say which of their files it was."""
    import errno

    from wfnn_io.cli_errors import describe

    class Full:
        def __init__(self, file):
            self.file = file

        def write(self, data):
            raise OSError(errno.ENOSPC, "No space left on device")

        def __getattr__(self, name):
            return getattr(self.file, name)

    log = SegmentLog(tmp_path / "log", fsync="always")
    log.append(b"kept")
    log._file = Full(log._file)
    with pytest.raises(OSError) as failed:
        log.append(b"lost")
    segment = str(tmp_path / "log" / "00000000.seg")
    assert failed.value.errno == errno.ENOSPC and failed.value.filename == segment
    assert describe(failed.value) == f"{segment}: No space left on device"
    log._file = log._file.file
    log.close()
    with SegmentLog(tmp_path / "log") as again:
        assert [payload for _, payload in again.read()] == [b"kept"]


def test_a_flush_and_a_torn_tail_that_cannot_be_read_name_their_own_file(tmp_path, monkeypatch):
    """A failed flush named no file; a segment whose torn tail could not be read was reported as
    its quarantine copy, a file just deleted."""
    import errno

    from wfnn_io import segments

    class Failing:
        def __init__(self, file):
            self.file = file

        def flush(self):
            raise OSError(errno.ENOSPC, "No space left on device")

        def seek(self, *args):
            raise OSError(errno.EIO, "Input/output error")

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.file.close()

        def __getattr__(self, name):
            return getattr(self.file, name)

    segment = tmp_path / "log" / "00000000.seg"
    log = SegmentLog(tmp_path / "log", fsync="never")
    log.append(b"kept")
    log._file = Failing(log._file)
    with pytest.raises(OSError) as failed:
        log.flush()
    assert failed.value.filename == str(segment)
    log._file = log._file.file
    log.close()
    with open(segment, "ab") as f:
        f.write(b"torn tail")
    real_open = open

    def failing_open(path, *args, **kwargs):
        return Failing(real_open(path, *args, **kwargs))

    monkeypatch.setattr(segments, "open", failing_open, raising=False)
    with pytest.raises(OSError) as failed:
        SegmentLog(tmp_path / "log")
    assert failed.value.errno == errno.EIO and failed.value.filename == str(segment)
    assert not list((tmp_path / "log" / "quarantine").glob("*.torn"))
    monkeypatch.undo()
    with SegmentLog(tmp_path / "log") as again:
        assert [payload for _, payload in again.read()] == [b"kept"]


def test_a_segment_a_listing_missed_beside_a_live_writer_is_listed_again(tmp_path, monkeypatch):
    """A directory listed while a writer creates segments can miss an earlier one: a reader beside
    a live log skipped a whole segment, with no word of damage."""
    import pathlib

    log = SegmentLog(tmp_path / "log", segment_bytes=64, fsync="never")
    for k in range(6):
        log.append(bytes([k]) * 40)  # a segment each
    log.close()
    real, calls = pathlib.Path.glob, []

    def racing(self, pattern, *args, **kw):  # the first listing misses segment 2
        calls.append(pattern)
        found = list(real(self, pattern, *args, **kw))
        return [p for p in found if p.name != "00000002.seg"] if len(calls) == 1 else found

    monkeypatch.setattr(pathlib.Path, "glob", racing)
    assert segments.segment_numbers(tmp_path / "log") == [0, 1, 2, 3, 4, 5] and len(calls) == 2
    assert [payload[0] for _, payload in segments.read_records(tmp_path / "log")] == list(range(6))
    (tmp_path / "log" / "00000002.seg").unlink()  # really gone: listed as it is, three times at most
    calls.clear()
    assert segments.segment_numbers(tmp_path / "log") == [0, 1, 3, 4, 5] and len(calls) == segments.LISTINGS
