"""Nothing acknowledged is lost and reading never destroys: logs, stores and a server's data directory."""

import dataclasses
import logging

import numpy as np
import pytest

from tests.fakes import Hub, small_config
from tests.mounts import files, read_only, tmpfs
from tests.unit.wfnn_server.test_server import Listener, announce, batch, make_server, send
from wfnn_client.journal import Journal
from wfnn_io import logs, segments
from wfnn_io.logs import LogFormatError
from wfnn_io.protocol import Codec
from wfnn_server.server import CHECKPOINT, PREVIOUS_CHECKPOINT

BATCHES, PER_BATCH = 20, 10


def journal(directory, cfg, key=None, client="c1"):
    """A client's journal of BATCHES batches; -> where each batch's record starts."""
    j = Journal(directory, client, fsync="never", learner_config=cfg)
    codec = Codec(client, key)
    for i in range(BATCHES):
        b = batch(cfg, i * PER_BATCH, PER_BATCH, client=client)
        j.append(codec.encode(b), b.last_seq)
    where = [j._index.where(i) for i in range(len(j._index))]
    j.close()
    return where


def seg(directory, n=0):
    return directory / segments.segment_name(n)


def overwrite(path, offset, data):
    raw = bytearray(path.read_bytes())
    raw[offset : offset + len(data)] = data
    path.write_bytes(bytes(raw))


def hit(where, size, start, length):
    """How many records (starting at `where`, the last ending at `size`) a span touches."""
    ends = [p.offset for p in where[1:]] + [size]
    return sum(1 for p, end in zip(where, ends, strict=True) if p.offset < start + length and start < end)


# --------------------------------------------------------------------------- reading never writes
def test_inspecting_a_journal_with_a_torn_tail_changes_no_byte_and_reads_every_whole_batch(tmp_path):
    cfg = small_config()
    journal(tmp_path / "j", cfg)
    frame = Codec("c1").encode(batch(cfg, BATCHES * PER_BATCH, PER_BATCH))
    torn = segments.RECORD.pack(len(frame), segments.crc32c(frame)) + frame
    with open(seg(tmp_path / "j"), "ab") as f:
        f.write(torn[: len(torn) // 2])  # the client died mid-append
    before = files(tmp_path / "j")
    summary = logs.summarise(tmp_path / "j")
    assert files(tmp_path / "j") == before
    assert summary.experiences == BATCHES * PER_BATCH and summary.clients["c1"].gaps == 0
    [damage] = summary.damage
    assert damage.kind == "tail" and damage.length == len(torn) // 2


def test_damage_in_the_middle_is_skipped_reported_and_every_other_batch_recovered(tmp_path):
    cfg = small_config()
    where = journal(tmp_path / "j", cfg)
    size = seg(tmp_path / "j").stat().st_size
    overwrite(seg(tmp_path / "j"), 2000, b"\xa5" * 8)  # 8 bytes overwritten 2,000 bytes in
    lost = hit(where, size, 2000, 8)
    assert lost >= 1
    before = files(tmp_path / "j")
    summary = logs.summarise(tmp_path / "j")
    assert files(tmp_path / "j") == before
    assert summary.experiences == (BATCHES - lost) * PER_BATCH
    assert summary.clients["c1"].gaps == 1
    assert [d.kind for d in summary.damage] == ["corrupt"]
    assert summary.damage[0].offset <= 2000 < summary.damage[0].offset + summary.damage[0].length


def test_a_log_on_a_read_only_file_system_can_be_inspected(tmp_path):
    cfg = small_config()
    with tmpfs(tmp_path / "ro", "2m") as root:
        journal(root / "j", cfg)
        read_only(root)
        summary = logs.summarise(root / "j")
        assert summary.experiences == BATCHES * PER_BATCH


def test_replay_only_changes_no_byte_of_its_logs_and_imports_every_readable_experience(tmp_path, caplog):
    cfg = small_config(thinks_per_action=1)
    where = journal(tmp_path / "j", cfg)
    size = seg(tmp_path / "j").stat().st_size
    overwrite(seg(tmp_path / "j"), 2000, b"\x00" * 8)
    lost = hit(where, size, 2000, 8)
    before = files(tmp_path / "j")
    with caplog.at_level(logging.WARNING, logger="wfnn_io.segments"):
        server = make_server(tmp_path, Hub(), cfg, replay=(tmp_path / "j",), replay_only=True)
    try:
        assert files(tmp_path / "j") == before
        # Told once: the logs are read twice (checked through, then stored), and it was said twice.
        assert sum("damaged bytes" in r.getMessage() for r in caplog.records) == 1
        # The damaged batch is in no log: c1's run goes on after it, and it is a hole, missing
        # (c1 would be asked for it), not given up as lost.
        assert server.imported == server.store.count == (BATCHES - lost) * PER_BATCH
        assert server.store.lost == {}
        assert server.store.missing() == lost * PER_BATCH
        assert server.store.stored_through == {"c1": BATCHES * PER_BATCH - 1}
        first = server.store.holes["c1"][0][0]
        assert server.store.durable_through == {"c1": first - 1}  # the acks stop before the hole
    finally:
        server.store.close()


def test_replay_only_names_the_experiences_of_another_run_under_the_same_numbers(tmp_path, caplog):
    """Two runs' journals under one client id: only the first of each number can be stored, and the
    other run's experiences were left out without a word."""
    cfg = small_config(thinks_per_action=1)
    journal(tmp_path / "j", cfg)
    other = Journal(tmp_path / "k", "c1", fsync="never", learner_config=cfg)
    b = batch(cfg, 0, 30, seed=1000)  # numbers 0-29 again, other values
    other.append(Codec("c1").encode(b), b.last_seq)
    other.close()
    with caplog.at_level(logging.WARNING, logger="wfnn_io.logs"):
        server = make_server(tmp_path, Hub(), cfg, replay=(tmp_path / "j", tmp_path / "k"), replay_only=True)
    try:
        assert server.imported == BATCHES * PER_BATCH
        said = [r.getMessage() for r in caplog.records if "client c1" in r.getMessage()]
        assert len(said) == 1 and "30 experiences are numbered as other experiences" in said[0]
    finally:
        server.store.close()


def test_replay_only_of_logs_with_nothing_readable_is_refused_writing_nothing(tmp_path):
    """It saved a checkpoint of untrained weights and ended as if it had learned."""
    cfg = small_config(thinks_per_action=1)
    Journal(tmp_path / "j", "c1", fsync="never", learner_config=cfg).close()
    with pytest.raises(LogFormatError, match="no readable experience"):
        make_server(tmp_path, Hub(), cfg, replay=(tmp_path / "j",), replay_only=True)
    assert list((tmp_path / "s1").iterdir()) == []  # not even the new, empty store


def _widened(b):
    """A batch of its spec with two state variables more than the spec has."""
    wide = np.concatenate([b.state, b.state[:, :2]], axis=1)
    return dataclasses.replace(b, state=wide, next_state=wide.copy())


def test_a_log_whose_batches_do_not_have_their_specs_widths_is_refused_before_anything_is_stored(tmp_path):
    cfg = small_config(thinks_per_action=1)
    j = Journal(tmp_path / "j", "c1", fsync="never", learner_config=cfg)
    for i in range(4):
        b = batch(cfg, i * 10, 10)
        j.append(Codec("c1").encode(_widened(b) if i == 2 else b), b.last_seq)
    j.close()
    before = files(tmp_path / "j")
    with pytest.raises(LogFormatError, match=r"experiences 20-29 of client 'c1' have 5 state .* has 3 and 2"):
        make_server(tmp_path, Hub(), cfg, replay=(tmp_path / "j",), replay_only=True)
    assert files(tmp_path / "j") == before
    assert not (tmp_path / "s1" / "store").exists()  # nothing stored: the new store is gone
    with pytest.raises(LogFormatError, match="5 state"):
        logs.export([tmp_path / "j"], tmp_path / "out.npz")
    # A store that took such a batch before logs were checked for it still opens: kept, not learned.
    server = make_server(tmp_path, Hub(), cfg, server_id="s2")
    server.store.append(_widened(batch(cfg, 0, 10, client="c2")))
    server.store.close()
    again = make_server(tmp_path, Hub(), cfg, server_id="s2")
    try:
        assert again.counters["store/other_spec"] == 10 and int(again.learner.buffer.count[0]) == 0
    finally:
        again.store.close()


# --------------------------------------------------------------------------- only the owner repairs
def test_reopening_a_journal_moves_its_torn_tail_to_quarantine_and_keeps_every_byte(tmp_path):
    cfg = small_config()
    journal(tmp_path / "j", cfg)
    original = seg(tmp_path / "j").read_bytes()
    with open(seg(tmp_path / "j"), "ab") as f:
        f.write(b"WFNN half a record")
    again = Journal(tmp_path / "j", fsync="never")
    assert again.next_seq == BATCHES * PER_BATCH and again.client_id == "c1"
    [kept] = (tmp_path / "j" / segments.QUARANTINE).glob("*.torn")
    assert kept.read_bytes() == b"WFNN half a record"
    assert seg(tmp_path / "j").read_bytes() == original
    again.close()


def test_a_journal_with_a_damaged_middle_record_continues_after_its_last_batch(tmp_path):
    cfg = small_config()
    where = journal(tmp_path / "j", cfg)
    overwrite(seg(tmp_path / "j"), where[5].offset + 40, b"\xff\xff")
    again = Journal(tmp_path / "j", fsync="never")
    assert again.next_seq == BATCHES * PER_BATCH  # numbering goes on; nothing is cut
    frames, last = again.frames_from(0, 100)
    assert len(frames) == BATCHES - 1 and last == BATCHES * PER_BATCH - 1
    again.close()


def test_a_corrupt_client_json_is_set_aside_and_the_id_recovered_from_the_batches(tmp_path):
    cfg = small_config()
    journal(tmp_path / "j", cfg, client="robot7")
    (tmp_path / "j" / "client.json").write_text("{not json")
    again = Journal(tmp_path / "j", fsync="never")
    assert again.client_id == "robot7"
    assert list((tmp_path / "j").glob("client.json.unreadable-*"))
    again.close()


# --------------------------------------------------------------------------- a server's data directory
def stored_and_checkpointed(tmp_path, hub, cfg, n_first=20, n_second=10):
    """A server that checkpointed twice (the second after more experiences), then stopped."""
    listener = Listener(hub)
    server = make_server(tmp_path, hub, cfg).start()
    send(hub, batch(cfg, 0, n_first))
    assert listener.wait(lambda: any(s.learned_through.get("c1") == n_first - 1 for s in listener.snapshots))
    server.checkpoint()
    first_thinks = int(server.learner.thinks[0])
    send(hub, batch(cfg, n_first, n_second))
    last = n_first + n_second - 1
    assert listener.wait(lambda: any(s.learned_through.get("c1") == last for s in listener.snapshots))
    server.stop()  # the final checkpoint: the previous one is kept beside it
    return server, first_thinks


def test_a_truncated_checkpoint_falls_back_to_the_previous_one_and_re_earns_the_thinks(tmp_path, caplog):
    hub, cfg = Hub(), small_config(thinks_per_action=3)
    first, first_thinks = stored_and_checkpointed(tmp_path, hub, cfg)
    data = tmp_path / "s1"
    assert (data / PREVIOUS_CHECKPOINT).exists()
    newest = (data / CHECKPOINT).read_bytes()
    (data / CHECKPOINT).write_bytes(newest[: len(newest) // 2])
    with caplog.at_level(logging.ERROR):
        again = make_server(tmp_path, hub, cfg)
    assert "cannot be used" in caplog.text
    assert int(again.learner.thinks[0]) == first_thinks
    assert again.budget == 10 * 3  # the 10 experiences stored after the previous checkpoint
    assert again.incarnation == first.incarnation + 1
    [kept] = data.glob(f"{CHECKPOINT}.unreadable-*")
    assert kept.read_bytes() == newest[: len(newest) // 2]
    again.store.close()


def test_with_no_readable_checkpoint_fresh_weights_re_earn_every_experiences_thinks(tmp_path):
    hub, cfg = Hub(), small_config(thinks_per_action=3)
    stored_and_checkpointed(tmp_path, hub, cfg)
    data = tmp_path / "s1"
    for name in (CHECKPOINT, PREVIOUS_CHECKPOINT):
        (data / name).write_bytes(b"PK\x03\x04 not a zip any more")
    before = files(data)
    again = make_server(tmp_path, hub, cfg)
    assert int(again.learner.thinks[0]) == 0 and again.budget == 30 * 3
    again.start()
    again.stop()  # its checkpoints rotate: the unreadable ones were set aside, not rotated over
    after = files(data)
    kept = {content for content, _ in after.values()}
    missing = [name for name, (content, _) in before.items() if content not in kept and name != "incarnation"]
    assert missing == []  # nothing deleted: the unreadable checkpoints too are kept, set aside


@pytest.mark.parametrize(
    "garbage", [b"", b"seven", b"-3", b"\xff\xfe", b"18446744073709551616", b"4611686018427387903"]
)
def test_a_corrupt_incarnation_file_is_set_aside_and_the_count_goes_on(tmp_path, garbage):
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    first, _ = stored_and_checkpointed(tmp_path, hub, cfg, 5, 5)
    (tmp_path / "s1" / "incarnation").write_bytes(garbage)
    again = make_server(tmp_path, hub, cfg)
    assert again.incarnation == first.incarnation + 1  # from the checkpoint's record of it
    [kept] = (tmp_path / "s1").glob("incarnation.unreadable-*")
    assert kept.read_bytes() == garbage
    again.store.close()


def test_a_corrupt_learner_config_json_falls_back_to_the_checkpoints_config(tmp_path):
    hub, cfg = Hub(), small_config(thinks_per_action=2, seed=4)
    stored_and_checkpointed(tmp_path, hub, cfg, 5, 5)
    data = tmp_path / "s1"
    (data / "learner_config.json").write_text('{"state_low": [')
    again = make_server(tmp_path, hub, None)  # no --learner-config: the data directory's own
    assert again.learner is not None and again.learner_config.spec_hash() == cfg.spec_hash()
    assert again.learner_config.seed == 4 and again.store.count == 10
    assert list(data.glob("learner_config.json.unreadable-*"))
    again.store.close()


def test_a_store_damaged_in_the_middle_loads_every_readable_batch(tmp_path):
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    listener = Listener(hub)
    with make_server(tmp_path, hub, cfg):
        for i in range(5):
            send(hub, batch(cfg, 10 * i, 10))
            assert listener.wait(lambda i=i: listener.acked() == 10 * i + 9)
    store = tmp_path / "s1" / "store"
    overwrite(seg(store), seg(store).stat().st_size // 2, b"\x00\x00\x00")
    again = make_server(tmp_path, hub, cfg)
    assert again.store.count == 40 and len(again.store.log.counts.damage) == 1
    assert again.learner.buffer.count[0] == 40
    again.store.close()


def _store_with_a_hole(tmp_path, hub, listener, cfg, thought=False):
    """A server's store of c1's experiences 0-49 (five batches), its middle record then damaged
    (`thought`: after every experience was thought and a checkpoint says so)."""
    sent = [batch(cfg, 10 * i, 10) for i in range(5)]
    with make_server(tmp_path, hub, cfg) as server:
        for b in sent:
            send(hub, b)
            assert listener.wait(lambda b=b: listener.acked() == b.last_seq)
        if thought:
            assert listener.wait(lambda: server.budget == 0 and server.learned_through.get("c1") == 49)
    store = tmp_path / "s1" / "store"
    overwrite(seg(store), seg(store).stat().st_size // 2, b"\x00\x00\x00")
    listener.acks.clear()
    listener.statuses.clear()
    return sent


def test_a_hole_damage_left_in_the_store_is_asked_for_again_filled_and_learned_once(tmp_path):
    """Experiences acknowledged and then damaged on the server's disk were skipped for good; the
    client's journal still holds them. The acks now stop before the hole, so the client re-sends."""
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    listener = Listener(hub)
    sent = _store_with_a_hole(tmp_path, hub, listener, cfg)
    with make_server(tmp_path, hub, cfg) as again:
        [(first, last)] = again.store.holes["c1"]
        assert last - first + 1 == 10 and again.store.missing() == 10
        assert again.store.count == 40 and again.learner.buffer.count[0] == 40  # the rest is learned
        assert again.store.stored_through == {"c1": 49} and again.store.lost == {}
        # Its status (what a client hearing of this start believes) stops before the hole.
        assert listener.wait(lambda: any(s.stored_through.get("c1") == first - 1 for s in listener.statuses))
        send(hub, batch(cfg, 50, 5))  # a live batch is stored after the run, not acknowledged past the hole
        assert listener.wait(lambda: again.store.stored_through["c1"] == 54)
        assert again.store.durable_through == {"c1": first - 1}
        for b in sent:  # the client re-sends from the hole: its part is new, the rest duplicates
            send(hub, b)
        assert listener.wait(lambda: listener.acked() == 54)
        assert again.store.holes == {} and again.store.count == 55
        assert listener.wait(lambda: not again._to_learn)
        assert again.learner.buffer.count[0] == 55 and again.counters["ingest/holes_filled"] == 10
    with make_server(tmp_path, hub, cfg) as third:
        assert third.store.holes == {} and third.store.count == 55 and third.learner.buffer.count[0] == 55
        assert third.store.durable_through == {"c1": 54}
        seqs = sorted(s for b in third.store.batches() for s in range(b.first_seq, b.last_seq + 1))
        assert seqs == list(range(55))  # each stored once


def test_a_hole_filled_before_the_learner_is_built_is_learned_once(tmp_path, monkeypatch):
    import threading

    import wfnn_server.server as server_module

    hub, cfg = Hub(), small_config(thinks_per_action=1)
    listener = Listener(hub)
    sent = _store_with_a_hole(tmp_path, hub, listener, cfg)
    for path in (tmp_path / "s1").iterdir():  # the adopted config and checkpoints: adopted again
        if path.is_file() and path.name != "incarnation":
            path.unlink()
    stored = threading.Event()
    monkeypatch.setattr(server_module, "lower_priority", lambda nice: stored.wait(10.0))
    with make_server(tmp_path, hub, None) as again:
        assert again.learner is None and again.store.missing() == 10
        announce(hub, cfg, produced_through=49)
        assert listener.wait(lambda: again._pending_config is not None)
        for b in sent:
            send(hub, b)
        assert listener.wait(lambda: again.store.count == 50)
        stored.set()  # the learner is built: it loads the fill from the store, not again from its queue
        assert listener.wait(lambda: again.learner is not None and not again._to_learn)
        assert int(again.learner.buffer.count[0]) == 50


def _crash(server):
    """Stop a server's threads as a SIGKILL would: no final checkpoint, the store as it was."""
    server._stop.set()
    server._wake.set()
    for thread in server._threads:
        thread.join()
    server.store.close()


def _thinks_done(server):
    return int(server.learner.thinks[0])


def test_a_hole_filled_after_the_checkpoint_is_owed_its_thinks_after_a_crash(tmp_path):
    """The checkpoint's mark reached past the hole, so a fill stored after it (acknowledged) was
    taken as thought at the next start: learned into the replay, but its thinks were never done."""
    hub, cfg = Hub(), small_config(thinks_per_action=3)
    listener = Listener(hub)
    first = make_server(tmp_path, hub, cfg, checkpoint_period_s=3600.0).start()
    for i in range(5):
        send(hub, batch(cfg, 10 * i, 10))
        assert listener.wait(lambda i=i: listener.acked() == 10 * i + 9)
    _crash(first)  # before any checkpoint
    store = tmp_path / "s1" / "store"
    overwrite(seg(store), seg(store).stat().st_size // 2, b"\x00\x00\x00")  # 20-29 damaged
    second = make_server(tmp_path, hub, cfg, checkpoint_period_s=3600.0).start()
    assert second.store.holes == {"c1": [(20, 29)]}
    assert listener.wait(second.replayed)  # the budget is taken before its thinks are done
    second.checkpoint()  # its mark is 49, beyond the hole
    checkpointed = _thinks_done(second)
    listener.acks.clear()
    send(hub, batch(cfg, 20, 10))  # the fill, and a new batch: both acknowledged after the checkpoint
    send(hub, batch(cfg, 50, 5))
    assert listener.wait(lambda: listener.acked() == 54 and not second._to_learn)
    _crash(second)
    third = make_server(tmp_path, hub, cfg)
    assert third.store.count == 55 and int(third.learner.buffer.count[0]) == 55
    assert _thinks_done(third) == checkpointed and third.budget == 3 * (10 + 5)
    third.store.close()


def test_a_fill_imported_below_the_checkpoints_mark_is_owed_its_thinks(tmp_path):
    hub, cfg = Hub(), small_config(thinks_per_action=3, replay_capacity=1000)
    listener = Listener(hub)
    journal(tmp_path / "j", cfg)  # c1's 0-199, whole
    first = make_server(tmp_path, hub, cfg, checkpoint_period_s=3600.0).start()
    for i in range(5):
        send(hub, batch(cfg, 10 * i, 10))
        assert listener.wait(lambda i=i: listener.acked() == 10 * i + 9)
    _crash(first)
    store = tmp_path / "s1" / "store"
    overwrite(seg(store), seg(store).stat().st_size // 2, b"\x00\x00\x00")
    with make_server(tmp_path, hub, cfg) as second:  # thinks the 40 left; its checkpoint's mark is 49
        assert listener.wait(lambda: second.budget == 0 and not second._to_learn)
    third = make_server(tmp_path, hub, cfg, replay=(tmp_path / "j",))
    assert third.imported == 160 and third.store.holes == {}
    assert third.budget == 3 * 160  # the 10 filling the hole as well as the 150 after 49
    third.store.close()


def test_a_fill_of_experiences_thought_before_their_record_was_damaged_owes_no_thinks(tmp_path):
    hub, cfg = Hub(), small_config(thinks_per_action=3)
    listener = Listener(hub)
    sent = _store_with_a_hole(tmp_path, hub, listener, cfg, thought=True)
    with make_server(tmp_path, hub, cfg) as again:
        assert again.store.holes == {"c1": [(20, 29)]} and again.budget == 0
        before = _thinks_done(again)
        send(hub, sent[2])
        assert listener.wait(lambda: listener.acked() == 49 and not again._to_learn)
        assert int(again.learner.buffer.count[0]) == 50  # in the replay again
        assert again.budget == 0 and _thinks_done(again) == before  # its thinks are in the weights


def test_a_checkpoints_ranges_are_checked():
    from wfnn_io.persist import PersistError
    from wfnn_server.server import _ranges

    assert _ranges({"c1": [[20, 29], [40, 40]]}) == {"c1": [(20, 29), (40, 40)]}
    for bad in ([], {"c1": [[5, 4]]}, {"c1": [[1]]}, {"c1": [[-2, 3]]}, {"c1": [["a", 3]]}, {"c1": 7},
                {"c1": [[True, 3]]}, {"c1": [[5, 6], [1, 2]]}, {"c1": [[1, 5], [5, 6]]}):  # fmt: skip
        with pytest.raises(PersistError, match="unqueued"):
            _ranges(bad)


def test_the_servers_range_sums_agree_with_sets():
    """`_less`, `_in_ranges` and `_overlapping` (bisected: a client declaring losses one by one
    makes thousands of holes) against the same sums done on sets."""
    from wfnn_server.server import _in_ranges, _less, _overlapping
    from wfnn_server.store import without

    rng = np.random.default_rng(0)

    def ordered(n):
        edges = np.sort(rng.choice(60, size=2 * n, replace=False))
        return [(int(a), int(b)) for a, b in edges.reshape(-1, 2)]

    def seqs(ranges):
        return {s for a, b in ranges for s in range(a, b + 1)}

    for _ in range(500):
        ranges, taken = ordered(rng.integers(0, 8)), ordered(rng.integers(0, 8))
        less = _less(ranges, taken)
        assert seqs(less) == seqs(ranges) - seqs(taken) and less == sorted(less)
        first = int(rng.integers(0, 60))
        last = first + int(rng.integers(0, 10))
        inside = _in_ranges(first, last, ranges)
        assert [s for s in range(first, last + 1) if inside[s - first]] == sorted(
            seqs(ranges) & set(range(first, last + 1))
        )
        i, j = _overlapping(ranges, first, last)
        cut = ranges[:i] + without(ranges[i:j], first, last) + ranges[j:]
        assert cut == without(ranges, first, last)


def test_a_checkpoint_from_before_unqueued_was_recorded_owes_every_refill(tmp_path):
    """Such a checkpoint cannot tell a hole it had thought from one it never had (an import's):
    each refill is owed its thinks, as before."""
    from wfnn_io.persist import load_checkpoint, save_weights

    hub, cfg = Hub(), small_config(thinks_per_action=3)
    listener = Listener(hub)
    sent = _store_with_a_hole(tmp_path, hub, listener, cfg, thought=True)
    path = tmp_path / "s1" / CHECKPOINT
    ck_cfg, params, meta, training = load_checkpoint(path)
    del meta["unqueued"]
    save_weights(path, ck_cfg, params, meta, training=training)
    with make_server(tmp_path, hub, cfg) as again:
        assert again.store.holes == {"c1": [(20, 29)]} and again.budget == 0
        before = _thinks_done(again)
        send(hub, sent[2])
        assert listener.wait(lambda: listener.acked() == 49 and not again._to_learn)
        assert listener.wait(lambda: again.budget == 0 and _thinks_done(again) == before + 3 * 10)


# --------------------------------------------------------------------------- what the key protects
def test_a_log_read_with_a_wrong_key_names_a_few_refusals_and_counts_the_rest(tmp_path, caplog):
    journal(tmp_path / "j", small_config(), key=b"k" * 32)
    counts = logs.ReadCounts()
    with caplog.at_level(logging.ERROR):
        assert list(logs.read_batches(tmp_path / "j", b"w" * 32, counts)) == []
    assert counts.refused == {"auth": BATCHES}
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == logs.REFUSALS_TOLD + 1 < BATCHES
    assert f"{BATCHES} records refused in all (auth {BATCHES})" in lines[-1]


def test_a_keyed_server_replays_its_own_store_and_a_keyed_clients_journal(tmp_path):
    cfg = small_config(thinks_per_action=1)
    key = b"k" * 32
    (tmp_path / "key").write_bytes(key)
    journal(tmp_path / "j", cfg, key=key, client="robot1")
    hub = Hub()
    listener = Listener(hub)
    with make_server(tmp_path, hub, cfg, server_id="s0", key_file=tmp_path / "key"):
        send(hub, batch(cfg, 0, 30, client="robot2"), client="robot2", key=key)
        assert listener.wait(lambda: listener.acked("robot2", "s0") == 29)
    server = make_server(tmp_path, hub, cfg, key_file=tmp_path / "key", replay_only=True,
                         replay=(tmp_path / "j", tmp_path / "s0" / "store"))  # fmt: skip
    assert server.imported == BATCHES * PER_BATCH + 30
    server.store.close()
    # Read without a key, the same logs import alike (a log's records are not transport).
    plain = make_server(tmp_path, hub, cfg, server_id="s2", replay_only=True,
                        replay=(tmp_path / "j", tmp_path / "s0" / "store"))  # fmt: skip
    assert plain.imported == BATCHES * PER_BATCH + 30
    plain.store.close()


def test_replay_with_a_wrong_key_imports_nothing_and_says_why(tmp_path):
    cfg = small_config(thinks_per_action=1)
    journal(tmp_path / "j", cfg, key=b"k" * 32)
    (tmp_path / "wrong").write_bytes(b"w" * 32)
    with pytest.raises(LogFormatError, match=r"every record .* refused: 20 auth .*wrong --key-file"):
        make_server(tmp_path, Hub(), cfg, key_file=tmp_path / "wrong", replay=(tmp_path / "j",),
                    replay_only=True)  # fmt: skip
    assert logs.summarise(tmp_path / "j", b"w" * 32).refused == {"auth": BATCHES}


def test_a_journal_reads_alike_with_and_without_its_key(tmp_path):
    cfg = small_config()
    journal(tmp_path / "j", cfg, key=b"k" * 32)
    with_key = logs.summarise(tmp_path / "j", b"k" * 32)
    without = logs.summarise(tmp_path / "j")
    assert with_key.experiences == without.experiences == BATCHES * PER_BATCH
    assert np.isclose(with_key.reward_mean, without.reward_mean)


def test_a_checkpoint_whose_counters_are_not_numbers_is_not_used(tmp_path):
    from wfnn_common.learner import WFNN
    from wfnn_io.persist import save_weights

    hub, cfg = Hub(), small_config(thinks_per_action=2)
    stored_and_checkpointed(tmp_path, hub, cfg, 5, 5)
    data = tmp_path / "s1"
    bad = {"thinks": 10, "learned_through": {"c1": "all"}, "stored_through": {"c1": 9}}
    save_weights(data / CHECKPOINT, cfg, WFNN(cfg).params, bad)
    again = make_server(tmp_path, hub, cfg)  # falls back to the previous one, whose meta is sound
    assert int(again.learner.thinks[0]) > 0 and all(type(v) is int for v in again.learned_through.values())
    again.store.close()


def test_an_atomic_write_keeps_the_files_mode_and_a_new_file_takes_the_umask(tmp_path):
    import os

    from wfnn_io.persist import atomic_savez, atomic_write_text

    mask = os.umask(0o022)
    os.umask(mask)
    atomic_write_text(tmp_path / "new.json", "{}")
    assert (tmp_path / "new.json").stat().st_mode & 0o777 == 0o666 & ~mask
    (tmp_path / "shared.json").write_text("{}")
    for mode in (0o640, 0o604):
        (tmp_path / "shared.json").chmod(mode)
        atomic_write_text(tmp_path / "shared.json", '{"a": 1}')
        assert (tmp_path / "shared.json").stat().st_mode & 0o777 == mode
    assert (tmp_path / "shared.json").read_text() == '{"a": 1}'
    atomic_savez(tmp_path / "w.npz", {"x": np.zeros(3)})
    (tmp_path / "w.npz").chmod(0o600)  # a file kept private stays private
    atomic_savez(tmp_path / "w.npz", {"x": np.ones(3)})
    assert (tmp_path / "w.npz").stat().st_mode & 0o777 == 0o600


@pytest.mark.parametrize("version", [np.float64(np.inf), np.float64(np.nan), np.str_("one"), np.array([1, 1]),
                                     np.float64(1.0), np.bool_(True)])  # fmt: skip
def test_a_newest_checkpoint_with_a_damaged_format_version_falls_back_to_the_previous_one(tmp_path, version):
    hub, cfg = Hub(), small_config(thinks_per_action=3)
    _, first_thinks = stored_and_checkpointed(tmp_path, hub, cfg)
    data = tmp_path / "s1"
    with np.load(data / CHECKPOINT) as npz:
        arrays = {k: npz[k] for k in npz.files}
    with open(data / CHECKPOINT, "wb") as f:
        np.savez(f, **{**arrays, "format_version": version})
    again = make_server(tmp_path, hub, cfg)
    assert int(again.learner.thinks[0]) == first_thinks  # the previous checkpoint's
    assert len(list(data.glob(f"{CHECKPOINT}.unreadable-*"))) == 1
    again.store.close()


def test_a_checkpoints_damaged_incarnation_record_counts_for_nothing(tmp_path):
    from wfnn_io.persist import load_checkpoint, save_weights

    hub, cfg = Hub(), small_config(thinks_per_action=1)
    first, _ = stored_and_checkpointed(tmp_path, hub, cfg, 5, 5)
    data = tmp_path / "s1"
    ck_cfg, params, meta, training = load_checkpoint(data / CHECKPOINT)
    save_weights(data / CHECKPOINT, ck_cfg, params, {**meta, "incarnation": float("inf")}, training=training)
    (data / "incarnation").write_bytes(b"garbage")
    again = make_server(tmp_path, hub, cfg)  # the previous checkpoint's record of it is sound
    assert again.incarnation == first.incarnation + 1
    again.store.close()


@pytest.mark.parametrize("identity", ["\ud800", "x" * 70_000, "a/b", ""])
def test_a_store_whose_log_id_cannot_name_it_on_the_wire_gets_a_new_one(tmp_path, identity):
    """Acks and statuses carry the store's id: one that cannot travel would end the server's threads."""
    import json

    hub, cfg = Hub(), small_config(thinks_per_action=1)
    with make_server(tmp_path, hub, cfg):
        pass
    info_path = tmp_path / "s1" / "store" / logs.LOG_JSON
    info = json.loads(info_path.read_text())
    info["id"] = identity
    info_path.write_text(json.dumps(info))
    listener = Listener(hub)
    with make_server(tmp_path, hub, cfg) as server:
        assert server.store.id != identity
        send(hub, batch(cfg, 0, 5))
        assert listener.wait(lambda: listener.acked() == 4) and server.error is None
    assert list((tmp_path / "s1" / "store").glob(f"{logs.LOG_JSON}.unreadable-*"))  # kept beside it


def test_a_fifo_where_a_sidecar_should_be_is_refused_without_waiting(tmp_path):
    import os
    import threading

    cfg = small_config()
    journal(tmp_path / "j", cfg)
    (tmp_path / "j" / logs.LOG_JSON).unlink()
    os.mkfifo(tmp_path / "j" / logs.LOG_JSON)
    outcome = []

    def read():
        outcome.append(logs.summarise(tmp_path / "j"))

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    reader.join(10.0)
    assert not reader.is_alive()
    assert (
        outcome[0].experiences == BATCHES * PER_BATCH and "not a regular file" in outcome[0].description_error
    )


def test_a_journal_tagged_for_its_controllers_reads_with_the_key_and_refuses_another_key(tmp_path):
    """A reader with the key checks a client's frames with the keys of the controllers it recorded."""
    cfg, key = small_config(), b"k" * 32
    for n, controller in enumerate(("arm", "base")):  # a journal reopened under another controller
        j = Journal(tmp_path / "j", "c1", fsync="never", learner_config=cfg, controller=controller)
        codec = Codec("c1", key, controller)
        b = batch(cfg, n * PER_BATCH, PER_BATCH)
        j.append(codec.encode(b), b.last_seq)
        j.close()
    Journal(tmp_path / "j", "c1", fsync="never", learner_config=cfg).close()  # a local run on it
    assert logs.summarise(tmp_path / "j", key).experiences == 2 * PER_BATCH
    counts = logs.ReadCounts()
    assert not list(logs.read_entries(tmp_path / "j", b"w" * 32, counts))
    assert counts.refused["auth"] == 2


def checkpoint_content(path):
    """What `load_checkpoint` gives, comparable with ==."""
    from wfnn_io.persist import load_checkpoint

    config, params, meta, training = load_checkpoint(path)
    return config.to_json(), params.flat.tobytes(), meta, {k: v.tobytes() for k, v in training.items()}


@pytest.mark.slow
def test_every_bit_flipped_in_a_checkpoints_directory_is_refused_or_loads_what_was_saved(tmp_path):
    """A flip that lengthens a member's comment hid the members after it (the deep learner's
    training state), and the rest loaded without them: a server resumed with reset critics."""
    import struct

    from wfnn_common.learner import RANDOM_STATE
    from wfnn_common.learners import make_learner
    from wfnn_io.persist import PersistError, save_weights

    cfg = small_config(learner="deep")
    learner = make_learner(cfg)
    path = tmp_path / "checkpoint.npz"
    save_weights(path, cfg, learner.params, {"thinks": 3}, training=learner.training_state())
    saved, original = checkpoint_content(path), path.read_bytes()
    assert saved[3].keys() == {"theta", "target", "reward_scale", *RANDOM_STATE}
    directory = struct.unpack_from("<I", original, original.rindex(b"PK\x05\x06") + 16)[0]
    loaded = refused = 0
    for i in range(directory, len(original)):
        for bit in range(8):
            damaged = bytearray(original)
            damaged[i] ^= 1 << bit
            path.write_bytes(bytes(damaged))
            try:
                content = checkpoint_content(path)
            except PersistError:
                refused += 1
                continue
            assert content == saved, (i, bit)
            loaded += 1
    assert refused > 0 and loaded > 0


def test_a_checkpoint_that_is_a_fifo_or_holds_no_network_is_refused_without_waiting(tmp_path):
    import os
    import threading
    import types

    from wfnn_common.learner import WFNN
    from wfnn_io.persist import PersistError, load_checkpoint, save_weights

    os.mkfifo(tmp_path / "fifo.npz")  # opening it to read would wait for a writer for good
    outcome: list[str] = []

    def load():
        try:
            load_checkpoint(tmp_path / "fifo.npz")
        except PersistError as exc:
            outcome.append(str(exc))

    reader = threading.Thread(target=load, daemon=True)
    reader.start()
    reader.join(10.0)
    assert not reader.is_alive() and "not a regular file" in outcome[0]
    (tmp_path / "folder.npz").mkdir()  # told as such, by its name (the refusal named a descriptor)
    with pytest.raises(PersistError, match=r"folder\.npz: is a directory$"):
        load_checkpoint(tmp_path / "folder.npz")
    cfg = small_config()
    no_network = types.SimpleNamespace(flat=WFNN(cfg).params.flat[:0])  # [0, n_params]
    save_weights(tmp_path / "none.npz", cfg, no_network)  # type: ignore[arg-type]
    with pytest.raises(PersistError, match="do not fit"):
        load_checkpoint(tmp_path / "none.npz")


@pytest.mark.parametrize("damage", ["wide_state", "state_3d", "reward_strings", "terminal_floats",
                                    "action_1d"])  # fmt: skip
def test_experiences_that_do_not_fit_their_config_are_refused(tmp_path, damage):
    from wfnn_common.replay import Experiences
    from wfnn_io.persist import PersistError, load_experiences, save_experiences

    cfg, n = small_config(), 10  # S 3, A 2
    rng = np.random.default_rng(0)
    exp = Experiences(rng.normal(size=(n, 3)), rng.normal(size=(n, 2)), rng.normal(size=(n, 3)),
                      rng.normal(size=n), np.zeros(n, dtype=bool))  # fmt: skip
    save_experiences(tmp_path / "good.npz", cfg, exp)
    for config in (cfg, None):
        assert all(np.array_equal(a, b) for a, b in zip(load_experiences(tmp_path / "good.npz", config), exp,
                                                        strict=True))  # fmt: skip
    bad = {
        "wide_state": exp._replace(state=rng.normal(size=(n, 7))),
        "state_3d": exp._replace(state=rng.normal(size=(n, 3, 4))),
        "reward_strings": exp._replace(reward=np.array(["x"] * n)),
        "terminal_floats": exp._replace(terminal=np.full(n, 0.5)),
        "action_1d": exp._replace(action=rng.normal(size=n)),
    }[damage]
    save_experiences(tmp_path / "bad.npz", cfg, bad)
    for config in (cfg, None):
        with pytest.raises(PersistError, match=r"bad\.npz: (state|action|reward|terminal)"):
            load_experiences(tmp_path / "bad.npz", config)


def test_an_output_path_that_is_a_fifo_is_refused_not_replaced(tmp_path):
    """A write renames a new file over its path: a FIFO there would be replaced silently."""
    import os

    from wfnn_io.persist import atomic_savez, atomic_write_text, writable

    os.mkfifo(tmp_path / "out")
    writes = (lambda p: atomic_write_text(p, "{}"), lambda p: atomic_savez(p, {"x": np.zeros(1)}), writable)
    for write in writes:
        with pytest.raises(OSError, match="not a regular file"):
            write(tmp_path / "out")
    assert (tmp_path / "out").is_fifo()


def test_a_comment_is_harmless_where_a_manifest_lists_the_members_and_damage_where_none_does(tmp_path):
    """An archiving tool may add comments; a damaged comment length makes one of the members after it."""
    import zipfile

    from wfnn_common.learner import WFNN
    from wfnn_io.persist import MANIFEST, PersistError, load_weights, save_weights

    cfg = small_config()
    params = WFNN(cfg).params
    save_weights(tmp_path / "w.npz", cfg, params)
    with zipfile.ZipFile(tmp_path / "w.npz", "a") as archive:
        archive.comment = b"archived"
        archive.getinfo("params.npy").comment = b"checked"
    assert np.array_equal(load_weights(tmp_path / "w.npz")[1].flat, params.flat)
    with np.load(tmp_path / "w.npz") as npz:  # as an older version wrote it: no manifest
        members = {name: npz[name] for name in npz.files if name != MANIFEST}
    with open(tmp_path / "old.npz", "wb") as f:
        np.savez(f, **members)
    assert np.array_equal(load_weights(tmp_path / "old.npz")[1].flat, params.flat)
    with zipfile.ZipFile(tmp_path / "old.npz", "a") as archive:
        archive.getinfo("config.npy").comment = b"x"
        archive.comment = b""  # marks the archive changed: its directory is written again
    with pytest.raises(PersistError, match="comment"):
        load_weights(tmp_path / "old.npz")


def test_a_previous_checkpoint_path_that_is_a_fifo_is_refused_not_replaced(tmp_path):
    import os

    from wfnn_common.learner import WFNN
    from wfnn_io.persist import save_weights

    cfg = small_config()
    save_weights(tmp_path / "w.npz", cfg, WFNN(cfg).params)
    os.mkfifo(tmp_path / "w.prev.npz")
    with pytest.raises(OSError, match=r"not a regular file.*w\.prev\.npz"):
        save_weights(tmp_path / "w.npz", cfg, WFNN(cfg).params, keep_previous=tmp_path / "w.prev.npz")
    assert (tmp_path / "w.prev.npz").is_fifo() and (tmp_path / "w.npz").is_file()


def test_reading_a_small_file_under_a_large_limit_reserves_no_more_memory_than_it_holds(tmp_path):
    """`wfnn report` reads metrics.json with a 4 GiB limit: the read reserved the whole limit first,
    so on a machine without that much to spare every report failed with MemoryError."""
    import subprocess
    import sys

    (tmp_path / "small.json").write_text('{"scores": [1, 2, 3]}')
    child = (
        "import resource, sys\n"
        "from wfnn_io.persist import read_regular_bytes\n"
        "resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))\n"
        f"data = read_regular_bytes({str(tmp_path / 'small.json')!r}, 4 << 30)\n"
        "assert data == b'{\"scores\": [1, 2, 3]}'\n"
    )
    proc = subprocess.run([sys.executable, "-c", child], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]


def test_a_file_that_grows_while_read_is_read_on_up_to_the_limit(tmp_path, monkeypatch):
    from wfnn_io import persist

    path = tmp_path / "growing"
    path.write_bytes(b"a" * 10)
    real_fstat = persist.os.fstat

    def stale_fstat(fd):  # as if the file grew by 90 bytes after its size was taken
        info = real_fstat(fd)
        path.write_bytes(b"a" * 100)
        return info

    monkeypatch.setattr(persist.os, "fstat", stale_fstat)
    assert persist.read_regular_bytes(path, limit=1000) == b"a" * 100
    path.write_bytes(b"a" * 10)
    with pytest.raises(OSError, match="larger than 50"):
        persist.read_regular_bytes(path, limit=50)


def test_a_damaged_client_json_is_named_when_a_keyed_journals_frames_fail_their_check(tmp_path, caplog):
    """The journal's controllers are recorded only there: without them its frames fail the key's
    check, and the user was told only that the key did not verify."""
    from wfnn_io.protocol import controller_key

    cfg, key = small_config(), b"k" * 32
    j = Journal(tmp_path / "j", "c1", fsync="never", learner_config=cfg, controller="rv")
    codec = Codec("c1", controller_key(key, "rv"))
    b = batch(cfg, 0, PER_BATCH)
    j.append(codec.encode(b), b.last_seq)
    j.close()
    assert logs.summarise(tmp_path / "j", key).experiences == PER_BATCH
    (tmp_path / "j" / "client.json").write_bytes(b"\xff\xfe")
    with caplog.at_level(logging.WARNING):
        summary = logs.summarise(tmp_path / "j", key)
    assert summary.experiences == 0 and summary.refused["auth"] == 1
    assert any("client.json cannot be read" in r.getMessage() for r in caplog.records)
    assert (tmp_path / "j" / "client.json").read_bytes() == b"\xff\xfe"  # reading changed nothing


# --------------------------------------------------------------------------- figures and output checks
def test_a_figure_that_fails_while_written_leaves_the_old_picture(tmp_path):
    """Pictures were written in place: a full disk left a torn PNG where a good one was."""
    from wfnn_io.persist import save_figure

    class Failing:
        def savefig(self, out, format, dpi):
            out.write(b"\x89PNG half a picture")
            raise OSError(27, "File too large")

    (tmp_path / "plot.png").write_bytes(b"the old picture")
    with pytest.raises(OSError, match="File too large"):
        save_figure(Failing(), tmp_path / "plot.png", dpi=100)
    assert (tmp_path / "plot.png").read_bytes() == b"the old picture"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["plot.png"]


def test_checking_that_an_output_can_be_written_makes_nothing(tmp_path):
    """A run refused after the check (a bad option) left the output's folders behind."""
    from wfnn_io.persist import writable

    writable(tmp_path / "a" / "b" / "x.json")
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "afile").write_text("x")
    with pytest.raises(FileExistsError, match="a file is in the way"):
        writable(tmp_path / "afile" / "b" / "x.json")
    # A link to a folder that is not there (a disk not mounted): refused now, not after the run.
    (tmp_path / "results").symlink_to(tmp_path / "not_mounted" / "results")
    with pytest.raises(FileExistsError, match="a file is in the way"):
        writable(tmp_path / "results" / "x.json")


def test_a_replay_only_start_whose_flags_the_logs_config_refuses_stores_nothing(tmp_path):
    """`--alpha 5` (a thesis rate) over a deep learner's logs was refused only after the logs were
    stored: a data directory left holding them, with no learner config, which a later start on it
    would fill from whatever client came first."""
    from wfnn_common.config import ConfigError

    cfg = small_config(learner="deep")
    journal(tmp_path / "j", cfg)
    with pytest.raises(ConfigError, match="lr"):
        make_server(tmp_path, Hub(), None, replay=(tmp_path / "j",), replay_only=True, alpha=5.0)
    store = tmp_path / "s1" / "store"
    assert not store.exists() or not any(p.stat().st_size for p in store.glob("*.seg"))
