import json
import time

import numpy as np
import pytest

from sims.positioning import PositioningVec
from tests.fakes import Hub, small_config, unchecked_frame
from tests.fakes import wait_for as wait
from tests.unit.wfnn_server.test_server import KEYS, Listener, make_server
from wfnn_client.brain import Experience, LocalBrain
from wfnn_client.link import ServerView
from wfnn_client.remote import RemoteBrain, RemoteConfig
from wfnn_common.config import LearnerConfig
from wfnn_common.learner import WFNN
from wfnn_io.protocol import Codec, MsgType, ServerStatus, WeightSnapshot
from wfnn_io.segments import check_free


def positioning_config(**kw):
    return LearnerConfig.for_task(PositioningVec, **kw)


def remote(tmp_path, hub, cfg, **kw):
    options = {"controller": "t", "journal_dir": tmp_path / "journal", "resend_after_s": 0.2, **kw}
    return RemoteBrain(WFNN(cfg), RemoteConfig(**options), hub.bus())


KEY = b"k" * 32
"""The shared key of the keyed tests (`keyed`)."""


def keyed(tmp_path, hub, cfg, **kw):
    """A started client whose frames carry HMAC tags under KEY, and a bus to reach it -> (brain, bus)."""
    (tmp_path / "key").write_bytes(KEY)
    brain = remote(tmp_path, hub, cfg, key_file=tmp_path / "key", **kw)
    brain.start()
    return brain, hub.bus()


def drive(brain, steps, seed=0, lockstep=True):
    """Act-learn(-sync) on the positioning task; returns the rewards."""
    task = PositioningVec(1)
    rng = np.random.default_rng(seed)
    x = task.reset(rng)[0]
    rewards = []
    for _ in range(steps):
        acted = brain.act(x)
        u = acted.result.action if acted is not None else np.zeros(1)
        tr = task.step(u[None])
        if tr.learnable[0]:
            brain.learn(Experience(x, u, tr.state[0], float(tr.reward[0])), acted)
            if lockstep:
                assert brain.sync(10.0)
        rewards.append(float(tr.reward[0]))
        x = tr.state[0]
    return np.asarray(rewards)


def test_lockstep_client_server_matches_single_process(tmp_path):
    cfg = positioning_config(thinks_per_action=20, seed=3)
    local = LocalBrain(WFNN(cfg), lockstep=True)
    local_rewards = drive(local, 300)
    hub = Hub()
    with make_server(tmp_path, hub, cfg):
        brain = remote(tmp_path, hub, cfg, lockstep=True)
        brain.start()
        assert brain.sync(10.0)  # the first snapshot: the server's initial weights
        remote_rewards = drive(brain, 300)
        brain.stop()
    # Same seed, same experiences, same replays: the C/S learner is the single-process one.
    np.testing.assert_allclose(remote_rewards, local_rewards, rtol=0, atol=1e-9)


def test_no_weights_means_no_action(tmp_path):
    hub, cfg = Hub(), small_config()
    brain = remote(tmp_path, hub, cfg)
    brain.start()
    assert brain.act(np.zeros(3)) is None and brain.following == ""
    brain.stop()


def test_follows_longest_alive_and_fails_over_within_two_seconds(tmp_path):
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    first = make_server(tmp_path, hub, cfg, server_id="s1").start()
    time.sleep(0.01)
    second = make_server(tmp_path, hub, cfg, server_id="s2").start()
    brain = remote(tmp_path, hub, cfg)
    brain.start()
    try:
        assert wait(lambda: brain.following == "s1")
        assert brain.act(np.zeros(3)) is not None
        first.stop()
        first.bus.close()  # its liveliness token disappears
        t0 = time.monotonic()
        assert wait(lambda: brain.following == "s2", timeout=2.0)
        assert time.monotonic() - t0 < 2.0
        assert brain.failovers and brain.failovers[-1]["from"] == "s1"
    finally:
        brain.stop()
        second.stop()


def test_a_server_restarted_with_its_clock_set_back_does_not_take_over(tmp_path, monkeypatch):
    """Longest alive by the uptimes the statuses tell: by the servers' wall-clock starts, s2
    restarted while its clock was an hour behind took over from s1, which kept running."""
    import wfnn_server.server as server_module

    hub, cfg = Hub(), small_config(thinks_per_action=1)
    s1 = make_server(tmp_path, hub, cfg, server_id="s1").start()
    s2 = make_server(tmp_path, hub, cfg, server_id="s2").start()
    brain = remote(tmp_path, hub, cfg)
    brain.start()
    try:
        assert wait(lambda: brain.following == "s1")
        s2.stop()
        s2.bus.close()
        wall = time.time_ns

        class SetBack:  # the server module's clock only: an hour behind
            def __getattr__(self, name):
                return getattr(time, name)

            @staticmethod
            def time_ns():
                return wall() - 3_600 * 10**9

        monkeypatch.setattr(server_module, "time", SetBack())
        s2 = make_server(tmp_path, hub, cfg, server_id="s2").start()
        monkeypatch.undo()
        views = brain.table.views
        assert wait(lambda: "s2" in views and views["s2"].started_ns == s2.started_ns and views["s2"].alive)
        assert s2.started_ns < brain.table.views["s1"].started_ns
        time.sleep(0.5)  # statuses and snapshots of both, several times over
        assert brain.following == "s1" and not brain.failovers
    finally:
        brain.stop()
        s1.stop()
        s2.stop()


def test_a_pinned_server_is_followed(tmp_path):
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    with make_server(tmp_path, hub, cfg, server_id="s1"), make_server(tmp_path, hub, cfg, server_id="s2"):
        brain = remote(tmp_path, hub, cfg, follow="s2")
        brain.start()
        assert wait(lambda: brain.following == "s2")
        time.sleep(0.2)
        assert brain.following == "s2"
        brain.stop()


def test_a_silent_server_is_left_for_a_live_one(tmp_path):
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    with (
        make_server(tmp_path, hub, cfg, server_id="s1") as s1,
        make_server(tmp_path, hub, cfg, server_id="s2"),
    ):
        brain = remote(tmp_path, hub, cfg, snapshot_timeout_s=0.5)
        brain.start()
        assert wait(lambda: brain.following == "s1")
        s1.bus.closed = True  # half-open: the token stays, nothing arrives any more
        assert wait(lambda: brain.following == "s2", timeout=2.0)
        brain.stop()


_CODECS: dict[tuple[str, bytes | None], Codec] = {}


def server_codec(server, key=None):
    """The codec of a pretend server: one per server and key, so that its frames are numbered in
    order as a real server's are (with a key, a client refuses a frame numbered below one it took)."""
    return _CODECS.setdefault((server, key), Codec(server, key, "t"))


def forge(cfg, server="s1", version=10**6, params=None, spec=None, incarnation=1, key=None, diverged=False,
          store="store1", published_ns=None, learned_through=None, started_ns=1, checked=True):  # fmt: skip
    n = WFNN(cfg).params.flat.shape[1] if params is None else params.shape[1]
    snap = WeightSnapshot(
        server=server, incarnation=incarnation, store=store, started_ns=started_ns, version=version,
        spec_hash=spec or cfg.spec_hash(),
        published_ns=published_ns or time.time_ns(), thinks=0, diverged=diverged,
        learned_through=learned_through or {},
        params=np.full((1, n), 0.5) if params is None else params,
    )  # fmt: skip
    codec = server_codec(server, key)
    # Unchecked: a snapshot no receiver takes (as a hostile or broken server sends it)
    return codec.encode(snap) if checked else unchecked_frame(snap, server, next(codec._seq), codec.key)


def test_invalid_snapshots_never_drive_the_robot(tmp_path):
    hub, cfg = Hub(), small_config()
    brain, bus = keyed(tmp_path, hub, cfg)
    announce(bus, "s1", cfg, started_ns=1, key=KEY)  # its heartbeat
    n = WFNN(cfg).params.flat.shape[1]
    bad = {
        "auth": forge(cfg),  # no key
        "spec": forge(cfg, spec="0123456789abcdef", key=KEY),
        "shape": forge(cfg, params=np.zeros((1, n + 1)), key=KEY),
        "non_finite": forge(cfg, params=np.full((1, n), np.nan), key=KEY),
        "misrouted": Codec("s2", KEY, "t").encode(Codec("s1").decode(forge(cfg), WeightSnapshot)[1]),
        "unannounced": forge(cfg, incarnation=7, key=KEY),  # not what s1's status says it is
        "malformed": forge(
            cfg, version=-1, key=KEY, checked=False
        ),  # applied, it stopped the uplink (batches: uint64)
    }
    for reason, frame in bad.items():  # one at a time: the downlink keeps only the newest per server
        bus.put(KEYS.weights("s1"), frame, None)
        assert wait(lambda r=reason: brain.rejected[r] == 1), reason
    assert brain.current is None
    bus.put(KEYS.weights("s1"), forge(cfg, version=5, key=KEY), None)
    assert wait(lambda: brain.current is not None and brain.current.version == 5)
    bus.put(KEYS.weights("s1"), forge(cfg, version=4, params=np.zeros((1, n)), key=KEY), None)
    assert wait(lambda: brain.rejected["stale"] == 1)
    assert brain.current.version == 5
    # A restarted server (next incarnation, as its status says) starts its versions again.
    announce(bus, "s1", cfg, started_ns=2, key=KEY, incarnation=2, token=False)
    bus.put(KEYS.weights("s1"), forge(cfg, version=1, incarnation=2, key=KEY, started_ns=2), None)
    assert wait(lambda: brain.current.incarnation == 2)
    brain.stop()


def test_snapshots_that_fail_their_tag_are_told_once_as_other_frames_are(tmp_path, caplog):
    """Statuses and acks refused by the key were told in a warning; snapshots were only counted."""
    import logging

    hub, cfg = Hub(), small_config()
    with caplog.at_level(logging.WARNING):
        brain, bus = keyed(tmp_path, hub, cfg)
        try:
            announce(bus, "s1", cfg, started_ns=1, key=KEY)
            for version in (1, 2, 3):
                bus.put(KEYS.weights("s1"), forge(cfg, version=version), None)  # untagged
                assert wait(lambda v=version: brain.rejected["auth"] == v)
        finally:
            brain.stop()
    told = [r.getMessage() for r in caplog.records if "failed its HMAC tag" in r.getMessage()]
    assert len(told) == 1 and "weight snapshot" in told[0], told


def announce(bus, server, cfg, started_ns, key=None, incarnation=1, store="store1", token=True,
             stored_through=None, weights_version=0):  # fmt: skip
    """A server's liveliness token and heartbeat, as a real one publishes them."""
    if token:
        bus.declare_token(KEYS.server_alive(server))
    status = ServerStatus(
        server=server, incarnation=incarnation, store=store, started_ns=started_ns, spec_hash=cfg.spec_hash(),
        learner_config=cfg.to_json(), weights_version=weights_version, stored_through=stored_through or {},
        rejected={}, metrics={},
    )  # fmt: skip
    bus.put(KEYS.server_status(server), server_codec(server, key).encode(status), None)


def test_with_no_healthy_server_the_weights_relearned_after_a_reset_drive_the_robot(tmp_path):
    hub, cfg = Hub(), small_config()
    n = WFNN(cfg).params.flat.shape[1]
    brain = remote(tmp_path, hub, cfg)
    brain.start()
    bus = hub.bus()
    announce(bus, "s1", cfg, started_ns=1)
    bus.put(KEYS.weights("s1"), forge(cfg, version=1, params=np.full((1, n), 0.1)), None)
    assert wait(lambda: brain.connected and brain.current.version == 1)
    # s1 detects divergence and resets: its relearning weights are flagged. With no other
    # server, they replace the weights that diverged.
    bus.put(KEYS.weights("s1"), forge(cfg, version=2, params=np.full((1, n), 0.2), diverged=True), None)
    assert wait(lambda: brain.current.version == 2)
    assert not brain.connected and brain.following == "s1"
    assert brain.act(np.zeros(3)) is not None
    # A healthy server is preferred to a relearning one, even a younger one.
    announce(bus, "s2", cfg, started_ns=2)
    bus.put(KEYS.weights("s2"), forge(cfg, server="s2", version=7, started_ns=2), None)
    assert wait(lambda: brain.connected and brain.following == "s2" and brain.current.server == "s2")
    bus.put(KEYS.weights("s1"), forge(cfg, version=3, diverged=True), None)
    time.sleep(0.2)
    assert brain.current.server == "s2"
    brain.stop()


def test_a_server_whose_weights_diverged_here_does_not_take_over_from_one_whose_snapshots_pause(tmp_path):
    """s1's weights diverge when acted on, so the robot fails over to s2; s2's snapshots then pause
    (it still heartbeats) while s1 publishes newer weights: the robot stays on s2's, which never
    diverged, and does not go back to s1's for the rest of the hold."""
    hub, cfg = Hub(), small_config(divergence_patience=1)
    n = WFNN(cfg).params.flat.shape[1]
    brain = remote(tmp_path, hub, cfg, snapshot_timeout_s=0.3, status_timeout_s=1.0, diverged_hold_s=30.0)
    brain.start()
    bus = hub.bus()
    try:
        version = {"s1": 0, "s2": 0}

        def heartbeat(s2_snapshots: bool) -> None:
            for server, started, params in (("s1", 1, 1e300), ("s2", 2, 0.1)):
                if server == "s1" or s2_snapshots:
                    version[server] += 1
                    weights = np.full((1, n), params)
                    snapshot = forge(cfg, server=server, version=version[server], started_ns=started,
                                     params=weights)  # fmt: skip
                    bus.put(KEYS.weights(server), snapshot, None)
                announce(bus, server, cfg, started_ns=started, weights_version=version[server])

        diverged, served = 0, []
        for k in range(150):  # 3 s at 20 ms; s2's snapshots stop after 1 s
            if k % 5 == 0:
                heartbeat(s2_snapshots=k < 50)
            acted = brain.act(np.zeros(3))
            if acted is not None:
                diverged += bool(acted.result.diverged)
                served.append((k, brain.current.server))
            time.sleep(0.02)
        assert diverged >= 1  # s1's weights were acted on once, and diverged
        assert [s for k, s in served if k >= 40] == ["s2"] * len([k for k, _ in served if k >= 40])
    finally:
        brain.stop()


def test_lost_frames_are_resent_from_the_journal(tmp_path):
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    rng = np.random.default_rng(0)
    hub.tap = lambda key, data: None if "/exp/live/" in key and rng.random() < 0.4 else data
    with make_server(tmp_path, hub, cfg) as server:
        brain = remote(tmp_path, hub, cfg, batch_max=5)
        brain.start()
        for i in range(200):
            x = rng.uniform(-1, 1, 3)
            brain.learn(Experience(x, rng.uniform(-1, 1, 2), x, -0.1), None)
            if i % 10 == 0:
                time.sleep(0.01)
        assert wait(lambda: server.store.stored_through.get(brain.id) == 199, timeout=20)
        assert brain.counters["uplink/resent_frames"] > 0
        assert wait(brain.all_acked)
        brain.stop()
    assert server.store.count == 200


def test_a_late_server_catches_up_from_the_client(tmp_path):
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    with make_server(tmp_path, hub, cfg, server_id="s1"):
        brain = remote(tmp_path, hub, cfg)
        brain.start()
        rng = np.random.default_rng(1)
        for _ in range(150):
            x = rng.uniform(-1, 1, 3)
            brain.learn(Experience(x, rng.uniform(-1, 1, 2), x, -0.1), None)
        assert wait(brain.all_acked)
        with make_server(tmp_path, hub, cfg, server_id="s2") as late:
            assert wait(lambda: late.store.stored_through.get(brain.id) == 149, timeout=20)
        brain.stop()


def test_the_journal_continues_after_a_client_restart(tmp_path):
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    listener = Listener(hub)
    with make_server(tmp_path, hub, cfg):
        brain = remote(tmp_path, hub, cfg)
        brain.start()
        for _ in range(30):
            brain.learn(Experience(np.zeros(3), np.zeros(2), np.zeros(3), -0.1), None)
        brain.stop()
        again = remote(tmp_path, hub, cfg)
        assert again.id == brain.id and again.produced_through == 29
        again.start()
        for _ in range(5):
            again.learn(Experience(np.zeros(3), np.zeros(2), np.zeros(3), -0.1), None)
        assert wait(lambda: listener.acked(brain.id) == 34)
        again.stop()
    with pytest.raises(ValueError, match="belongs to client"):
        remote(tmp_path, hub, cfg, client_id="someone")


def test_a_new_server_is_asked_for_its_weights(tmp_path):
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    with make_server(tmp_path, hub, cfg, publish_period_s=100.0) as server:
        assert wait(lambda: server.version == 1)  # published once, before the client existed
        brain = remote(tmp_path, hub, cfg)
        brain.start()
        assert wait(lambda: brain.following == "s1", timeout=2.0)
        assert brain.current.version == 1
        brain.stop()


def test_a_server_that_learns_with_other_settings_is_warned_of_and_recorded(tmp_path, caplog):
    """The server has another config and overrides bc_weight: this client learns so, and says so."""
    import json

    hub, cfg = Hub(), small_config(thinks_per_action=1)
    theirs = small_config(thinks_per_action=5)
    with make_server(tmp_path, hub, theirs, server_id="s1", bc_weight=0.5) as server:
        brain = remote(tmp_path, hub, cfg)
        brain.start()
        assert wait(lambda: brain.following == "s1" and "s1" in brain.learned_with)
        brain.stop()
    effective = json.loads(brain.learned_with["s1"])
    assert effective == json.loads(server.learner_config.to_json())
    assert (effective["bc_weight"], effective["thinks_per_action"]) == (0.5, 5)
    warned = [r.getMessage() for r in caplog.records if "not this client's" in r.getMessage()]
    assert len(warned) == 1 and "bc_weight, thinks_per_action" in warned[0]


def test_a_server_with_this_clients_config_is_not_warned_of(tmp_path, caplog):
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    with make_server(tmp_path, hub, cfg, server_id="s1"):
        brain = remote(tmp_path, hub, cfg)
        brain.start()
        assert wait(lambda: "s1" in brain.learned_with)
        brain.stop()
    assert not [r for r in caplog.records if "not this client's" in r.getMessage()]


def test_a_server_of_another_spec_is_not_said_to_learn_for_this_client(tmp_path, caplog):
    """Its snapshots are ignored (said once): its config neither applies nor is recorded."""
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    other = small_config(state_dim=2, thinks_per_action=1)
    brain = remote(tmp_path, hub, cfg)
    brain.start()
    announce(hub.bus(), "s9", other, started_ns=1)
    assert wait(lambda: "s9" in brain.servers and brain.servers["s9"].learner_config != "")
    announce(hub.bus(), "s9", other, started_ns=1, token=False)  # its next heartbeat: said once only
    assert wait(lambda: brain.servers["s9"].heard > 0)
    brain.stop()
    assert not [r for r in caplog.records if "not this client's" in r.getMessage()]
    # Said from its status alone, no snapshot read: a snapshot larger than this client's network
    # (a deep learner's to a thesis client) never reaches the client to be refused.
    said = [r.getMessage() for r in caplog.records if "learns for spec" in r.getMessage()]
    assert said == [f"server s9 learns for spec {other.spec_hash()}; this client is spec {cfg.spec_hash()} "
                    "(another task, ranges or learner): its weights are ignored"]  # fmt: skip
    # A lock-step run's "no weights" names it (it said only "no weights from ..." after 30 s).
    assert brain.why_no_weights() == (f"the servers heard learn for another spec than this client's "
                                      f"{cfg.spec_hash()}: s9 (spec {other.spec_hash()})")  # fmt: skip


def test_a_status_with_an_unreadable_config_is_counted_and_never_recorded(tmp_path):
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    brain = remote(tmp_path, hub, cfg)
    brain.start()
    for text in ("[1, 2]", "{not json"):
        status = ServerStatus(server="s9", incarnation=1, store="st", started_ns=1, spec_hash=cfg.spec_hash(),
                              learner_config=text, weights_version=0, stored_through={}, rejected={},
                              metrics={})  # fmt: skip
        hub.bus().put(KEYS.server_status("s9"), Codec("s9").encode(status), None)
    assert wait(lambda: brain.rejected["status_config"] == 2)
    brain.stop()
    assert brain.servers["s9"].learner_config == "" and brain.learned_with == {}


def test_config_differences_name_dotted_fields_and_leave_out_where_updates_run():
    import dataclasses

    from wfnn_client.remote import config_differences

    mine = small_config(learner="deep")
    theirs = dataclasses.replace(mine, gamma=0.5, deep=dataclasses.replace(mine.deep, lr=0.1, compile=True))
    assert config_differences(mine.to_json(), theirs.to_json()) == ["deep.lr", "gamma"]
    assert config_differences(mine.to_json(), mine.to_json()) == []
    with pytest.raises(ValueError):
        config_differences(mine.to_json(), "[]")


def test_a_store_announced_during_a_resend_keeps_its_restarted_window(tmp_path):
    # The downlink may hear of a new store (a server restarted empty) while the uplink re-sends to
    # the old one; the re-send's bookkeeping must not overwrite the restarted window, or the new
    # store waits a whole resend period for what it lacks.
    hub, cfg = Hub(), small_config()
    brain = remote(tmp_path, hub, cfg, resend_after_s=0.05)
    uplink = brain.uplink
    for _ in range(3):
        brain.learn(Experience(np.zeros(3), np.zeros(2), np.zeros(3), -0.1), None)
    while uplink.queued:
        uplink._send_batch()
    time.sleep(0.1)  # the batches are overdue
    view = uplink.table.views.setdefault("s1", ServerView("s1"))
    view.alive, view.spec_hash, view.store = True, brain.spec_hash, "old"
    frames_from = uplink.journal.frames_from

    def announced_meanwhile(first, count):
        with uplink.table.lock:
            uplink.table.announced(view, "new", 1, 1)
        return frames_from(first, count)

    uplink.journal.frames_from = announced_meanwhile
    uplink._resend()
    assert brain.counters["uplink/resent_frames"] > 0
    assert (view.store, view.acked, view.window_end, view.last_resend) == ("new", -1, -1, 0.0)
    uplink.journal.frames_from = frames_from
    uplink._resend()  # without a new store, the window advances as before
    assert view.window_end == 2 and view.last_resend > 0.0
    brain.stop()


def test_a_local_brain_counts_the_experiences_its_learner_refused():
    cfg = small_config(state_dim=1, action_dim=1)
    brain = LocalBrain(WFNN(cfg), lockstep=True)
    z = np.zeros(1)
    for reward in (-1.0, np.nan, 1e39, -0.5):
        brain.learn(Experience(z, z, z, reward), None)
    figures = brain.metrics()
    assert figures["learn/experiences"] == 2.0 and figures["learn/rejected"] == 2.0


def test_an_earlier_start_replayed_while_the_server_is_alive_is_refused(tmp_path):
    hub, cfg = Hub(), small_config()
    brain, bus = keyed(tmp_path, hub, cfg)
    announce(bus, "s1", cfg, started_ns=1, key=KEY)
    old_snapshot = forge(cfg, version=9, key=KEY)
    old = Codec("s1", KEY, "t").encode(
        ServerStatus(server="s1", incarnation=1, store="store1", started_ns=1, spec_hash=cfg.spec_hash(),
                     learner_config=cfg.to_json(), weights_version=0, stored_through={}, rejected={},
                     metrics={})
    )  # fmt: skip
    announce(bus, "s1", cfg, started_ns=2, key=KEY, incarnation=2, token=False)  # s1 restarted
    bus.put(KEYS.weights("s1"), forge(cfg, version=1, incarnation=2, key=KEY, started_ns=2), None)
    assert wait(lambda: brain.current is not None and brain.current.incarnation == 2)
    # MAC-valid frames of s1's first start, replayed (one at a time: the downlink keeps the newest)
    for n in range(1, 4):
        bus.put(KEYS.server_status("s1"), old, None)
        assert wait(lambda n=n: brain.rejected["status_stale"] == n)
        bus.put(KEYS.weights("s1"), old_snapshot, None)
        assert wait(lambda n=n: brain.rejected["unannounced"] == n)
    assert brain.current.incarnation == 2 and brain.servers["s1"].incarnation == 2
    brain.stop()


def test_a_lost_later_incarnation_replayed_while_the_restored_server_is_alive_is_refused(tmp_path):
    """Incarnations 2 and 3 lost with the disk, the backup of incarnation 1 restored: the live
    server is incarnation 2 again, started later. Frames of the lost incarnation 3 (higher, and
    started before it) replayed while it is alive were taken, and its own refused as stale."""
    hub, cfg = Hub(), small_config()
    brain, bus = keyed(tmp_path, hub, cfg)
    codec = server_codec("s1", KEY)

    def status(incarnation, started_ns):
        return codec.encode(ServerStatus(
            server="s1", incarnation=incarnation, store="store1", started_ns=started_ns,
            spec_hash=cfg.spec_hash(), learner_config=cfg.to_json(), weights_version=0, stored_through={},
            rejected={}, metrics={},
        ))  # fmt: skip

    lost = status(3, 30)  # recorded before the disk was lost
    bus.declare_token(KEYS.server_alive("s1"))
    bus.put(KEYS.server_status("s1"), status(2, 40), None)  # the restored server's start
    bus.put(KEYS.weights("s1"), forge(cfg, version=1, incarnation=2, key=KEY, started_ns=40), None)
    assert wait(lambda: brain.current is not None and brain.current.incarnation == 2)
    for n in range(1, 4):
        bus.put(KEYS.server_status("s1"), lost, None)
        assert wait(lambda n=n: brain.rejected["status_stale"] == n)
    view = brain.servers["s1"]
    assert (view.incarnation, view.started_ns) == (2, 40) and brain.current.incarnation == 2
    brain.stop()


def status_frame(cfg, server="s1", started_ns=1, incarnation=1, store="store1", weights_version=0, key=KEY):
    """A server's status as its codec frames it (numbered after its earlier frames)."""
    status = ServerStatus(
        server=server, incarnation=incarnation, store=store, started_ns=started_ns, spec_hash=cfg.spec_hash(),
        learner_config=cfg.to_json(), weights_version=weights_version, stored_through={}, rejected={},
        metrics={},
    )  # fmt: skip
    return server_codec(server, key).encode(status)


def test_a_status_and_snapshot_of_the_same_start_replayed_are_refused(tmp_path):
    """Recorded while s1 was at version 1 and replayed once it fell silent at version 5: the old
    status would otherwise drop version 5 as one its statuses never confirm, mark s1 alive again,
    and let the old snapshot back in."""
    hub, cfg = Hub(), small_config()
    brain, bus = keyed(tmp_path, hub, cfg, status_timeout_s=0.3)
    old_status, old_snapshot = status_frame(cfg, weights_version=1), forge(cfg, version=1, key=KEY)
    bus.put(KEYS.server_status("s1"), old_status, None)
    bus.put(KEYS.weights("s1"), old_snapshot, None)
    assert wait(lambda: brain.current is not None and brain.current.version == 1)
    bus.put(KEYS.server_status("s1"), status_frame(cfg, weights_version=5), None)
    bus.put(KEYS.weights("s1"), forge(cfg, version=5, key=KEY), None)
    assert wait(lambda: brain.current.version == 5)
    assert wait(lambda: not brain.table.views["s1"].alive)  # silent longer than status_timeout_s
    bus.put(KEYS.server_status("s1"), old_status, None)
    assert wait(lambda: brain.rejected["status_replayed"] == 1)
    bus.put(KEYS.weights("s1"), old_snapshot, None)
    assert wait(lambda: brain.rejected["stale"] + brain.rejected["replayed"] == 1)
    time.sleep(0.1)
    view = brain.table.views["s1"]
    assert brain.current.version == 5 and view.latest.version == 5 and not view.alive
    assert brain.rejected["unconfirmed"] == 0
    # Its next status (numbered after both) is taken: the server is back.
    bus.put(KEYS.server_status("s1"), status_frame(cfg, weights_version=5), None)
    assert wait(lambda: brain.table.views["s1"].alive)
    brain.stop()


@pytest.mark.parametrize(("key", "silent"), [(KEY, False), (KEY, True), (None, False)],
                         ids=["key-alive", "key-silent", "no_key-alive"])  # fmt: skip
def test_another_stores_earlier_start_replayed_is_refused(tmp_path, key, silent):
    """s1 restarted on another data directory (a later start): frames of its first store, recorded
    and replayed, neither switch the client back (to that store's weights) nor make it re-send its
    journal from the start; with a key also once s1 has fallen silent (without one, a silent
    server's next store is taken: a forged later start must not shut the real one out for good)."""
    hub, cfg = Hub(), small_config()
    if key:
        brain, bus = keyed(tmp_path, hub, cfg, status_timeout_s=0.3 if silent else 2.0)
    else:
        brain = remote(tmp_path, hub, cfg, status_timeout_s=0.3 if silent else 2.0)
        brain.start()
        bus = hub.bus()
    old_status = status_frame(cfg, store="storeA", started_ns=1, key=key)
    old_snapshot = forge(cfg, version=9, key=key, store="storeA", started_ns=1)
    bus.put(KEYS.server_status("s1"), old_status, None)
    assert wait(lambda: "s1" in brain.table.views and brain.table.views["s1"].store == "storeA")
    bus.put(KEYS.server_status("s1"), status_frame(cfg, store="storeB", started_ns=2, key=key), None)
    bus.put(KEYS.weights("s1"), forge(cfg, version=3, key=key, store="storeB", started_ns=2), None)
    assert wait(lambda: brain.current is not None and brain.current.store == "storeB")
    if silent:
        assert wait(lambda: not brain.table.views["s1"].alive)
    for n in range(1, 3):
        bus.put(KEYS.server_status("s1"), old_status, None)
        assert wait(lambda n=n: brain.rejected["status_stale"] == n)
        bus.put(KEYS.weights("s1"), old_snapshot, None)
        assert wait(lambda n=n: brain.rejected["unannounced"] == n)
    view = brain.table.views["s1"]
    assert view.store == "storeB" and brain.current.store == "storeB" and brain.current.version == 3
    brain.stop()


def test_a_replayed_snapshot_does_not_push_out_a_newer_one_waiting_to_be_read(tmp_path):
    """The downlink keeps one snapshot per server until its thread reads it: with a key, a recorded
    one (numbered lower) arriving meanwhile must not take the genuine one's place."""
    hub, cfg = Hub(), small_config()
    (tmp_path / "key").write_bytes(KEY)
    brain = remote(tmp_path, hub, cfg, key_file=tmp_path / "key")  # not started: its rounds run here
    downlink = brain.downlink

    def one_round():
        for frame in downlink._statuses.drained():
            downlink._take_status(frame)
        downlink._refresh()
        for server in list(downlink._snapshots):
            lower = downlink._lower.pop(server, None)
            for data in (lower, downlink._snapshots.pop(server)[1]):
                if data is not None:
                    downlink._take_snapshot(data)
        downlink._choose()

    downlink._on_status(KEYS.server_status("s1"), status_frame(cfg, weights_version=1))
    recorded = forge(cfg, version=1, key=KEY)
    downlink._on_snapshot(KEYS.weights("s1"), recorded)
    one_round()
    assert downlink.current.version == 1
    downlink._on_status(KEYS.server_status("s1"), status_frame(cfg, weights_version=2))
    downlink._on_snapshot(KEYS.weights("s1"), forge(cfg, version=2, key=KEY))
    downlink._on_snapshot(KEYS.weights("s1"), recorded)  # replayed before the thread reads the genuine one
    one_round()
    assert downlink.current.version == 2 and brain.rejected["stale"] == 1
    brain.stop(flush_timeout_s=0.0)


def test_a_forged_later_start_without_a_key_shuts_the_real_server_out_only_while_it_is_sent(tmp_path):
    """Without a key a start "later" than every real one can be forged: once the forger stops, the
    real server is taken back (with a key, where a start cannot be forged, an earlier one stays out)."""
    hub, cfg = Hub(), small_config()
    brain = remote(tmp_path, hub, cfg, status_timeout_s=0.3)
    brain.start()
    bus = hub.bus()
    bus.put(KEYS.server_status("s1"), status_frame(cfg, store="real", started_ns=5, key=None), None)
    assert wait(lambda: "s1" in brain.table.views and brain.table.views["s1"].store == "real")
    forged = Codec("s1").encode(ServerStatus(
        server="s1", incarnation=1, store="forged", started_ns=2**62, spec_hash=cfg.spec_hash(),
        learner_config=cfg.to_json(), weights_version=0, stored_through={}, rejected={}, metrics={},
    ))  # fmt: skip
    bus.put(KEYS.server_status("s1"), forged, None)
    assert wait(lambda: brain.table.views["s1"].store == "forged")
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline and brain.table.views["s1"].store != "real":
        bus.put(KEYS.server_status("s1"), status_frame(cfg, store="real", started_ns=5, key=None), None)
        time.sleep(0.1)
    assert brain.table.views["s1"].store == "real" and brain.table.views["s1"].alive
    brain.stop()


def test_the_first_snapshot_of_a_restarted_server_is_read_beside_a_higher_numbered_one_waiting(tmp_path):
    """A server numbers its frames from 0 each start: its next start's first snapshot is numbered
    below the last one of the start before, which may still wait to be read."""
    hub, cfg = Hub(), small_config()
    (tmp_path / "key").write_bytes(KEY)
    brain = remote(tmp_path, hub, cfg, key_file=tmp_path / "key")  # not started: its rounds run here
    downlink = brain.downlink
    old_start = Codec("s1", KEY, "t")
    for _ in range(500):  # a start that has published for a while
        old_start.encode(ServerStatus(server="s1", incarnation=1, store="store1", started_ns=1,
                                      spec_hash="", learner_config="", weights_version=0, stored_through={},
                                      rejected={}, metrics={}))  # fmt: skip
    old_frame = old_start.encode(Codec("s1").decode(forge(cfg, version=90, started_ns=1), WeightSnapshot)[1])
    new_start = Codec("s1", KEY, "t")
    downlink._on_status(KEYS.server_status("s1"), new_start.encode(ServerStatus(
        server="s1", incarnation=2, store="store1", started_ns=2, spec_hash=cfg.spec_hash(),
        learner_config=cfg.to_json(), weights_version=1, stored_through={}, rejected={}, metrics={},
    )))  # fmt: skip
    new_frame = new_start.encode(Codec("s1").decode(forge(cfg, version=1, incarnation=2, started_ns=2),
                                                    WeightSnapshot)[1])  # fmt: skip
    downlink._on_snapshot(KEYS.weights("s1"), old_frame)  # still waiting when the restart's arrives
    downlink._on_snapshot(KEYS.weights("s1"), new_frame)
    for frame in downlink._statuses.drained():
        downlink._take_status(frame)
    downlink._refresh()
    for server in set(downlink._snapshots) | set(downlink._lower):
        for data in (downlink._lower.pop(server, None), downlink._snapshots.pop(server)[1]):
            if data is not None:
                downlink._take_snapshot(data)
    downlink._choose()
    assert downlink.current is not None and (downlink.current.incarnation, downlink.current.version) == (2, 1)
    assert brain.rejected["unannounced"] == 1
    brain.stop(flush_timeout_s=0.0)


def test_a_snapshot_is_checked_again_against_a_start_taken_while_it_was_read(tmp_path, monkeypatch):
    """The uplink (an ack of s1's next start) may change s1's view while the downlink reads a
    snapshot of the start before: that snapshot must not be kept as the new start's."""
    import wfnn_client.downlink as downlink

    hub, cfg = Hub(), small_config()
    brain, bus = keyed(tmp_path, hub, cfg)
    bus.put(KEYS.server_status("s1"), status_frame(cfg, started_ns=1), None)
    assert wait(lambda: "s1" in brain.table.views and brain.table.views["s1"].alive)
    table, read = brain.table, downlink.weights_from_flat

    def read_while_the_server_restarts(*args, **kwargs):
        with table.lock:  # what the uplink does with an ack of the next start
            table.announced(table.views["s1"], "store1", 2, 2)
        return read(*args, **kwargs)

    monkeypatch.setattr(downlink, "weights_from_flat", read_while_the_server_restarts)
    bus.put(KEYS.weights("s1"), forge(cfg, version=500, key=KEY, started_ns=1), None)
    assert wait(lambda: brain.rejected["unannounced"] == 1)
    monkeypatch.setattr(downlink, "weights_from_flat", read)
    assert brain.table.views["s1"].latest is None and brain.current is None
    # The new start's own first snapshot is followed, not refused as older than version 500.
    bus.put(KEYS.server_status("s1"), status_frame(cfg, started_ns=2, incarnation=2), None)
    bus.put(KEYS.weights("s1"), forge(cfg, version=1, key=KEY, started_ns=2, incarnation=2), None)
    assert wait(lambda: brain.current is not None and brain.current.version == 1)
    assert brain.current.incarnation == 2
    brain.stop()


@pytest.mark.parametrize("restart", ["next_incarnation", "restored_backup"])
def test_a_restarted_server_holding_less_than_it_acknowledged_is_sent_the_rest(tmp_path, restart):
    """A store restored from a backup, or whose last records were damaged, holds less after a restart."""
    hub, cfg = Hub(), small_config()
    brain = remote(tmp_path, hub, cfg)
    brain.start()
    bus = hub.bus()
    announce(bus, "s1", cfg, started_ns=1, stored_through={brain.id: 99})
    assert wait(lambda: "s1" in brain.servers and brain.servers["s1"].acked == 99)
    # The restored backup counts its incarnations again: the same one, a later start.
    incarnation = 2 if restart == "next_incarnation" else 1
    held = {brain.id: 49}
    announce(bus, "s1", cfg, started_ns=2, incarnation=incarnation, token=False, stored_through=held)
    assert wait(lambda: brain.servers["s1"].acked == 49)  # what it holds now: the journal re-sends from 50
    brain.stop()


def a_run_that_ended(tmp_path, hub, cfg, n):
    """Client robot1's run of n experiences (reward -0.1) in journal run1, all stored, then stopped."""
    first = remote(tmp_path, hub, cfg, client_id="robot1", journal_dir=tmp_path / "run1")
    first.start()
    for _ in range(n):
        first.learn(Experience(np.zeros(3), np.zeros(2), np.zeros(3), -0.1), None)
    assert wait(first.all_acked)
    first.stop()


def test_new_experiences_are_numbered_past_what_the_servers_hold(tmp_path):
    """A journal that lost its newest records (or a new one with an old client id) never numbers
    new experiences as ones a server stored already: it would drop them as re-sends, and ack them."""
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    with make_server(tmp_path, hub, cfg) as server:
        a_run_that_ended(tmp_path, hub, cfg, 50)
        again = remote(tmp_path, hub, cfg, client_id="robot1", journal_dir=tmp_path / "run2",
                       status_timeout_s=0.5)  # fmt: skip
        time.sleep(0.7)  # built long before it starts (a learner compiling): the wait counts from the start
        again.start()
        for _ in range(40):  # queued at once, before any server was heard
            again.learn(Experience(np.zeros(3), np.zeros(2), np.zeros(3), -0.7), None)
        assert wait(lambda: again.all_acked() and server.store.count == 90)
        assert again.produced_through == 89 and again.counters["uplink/numbers_skipped"] == 50
        new = [b for b in server.store.batches() if b.client == "robot1" and b.first_seq >= 50]
        assert sum(len(b) for b in new) == 40 and all((b.reward == -0.7).all() for b in new)
        again.stop()


def test_a_snapshot_of_a_restored_stores_earlier_start_is_refused(tmp_path):
    """A data directory restored from a backup counts its incarnations again: an earlier start's
    snapshot has the same store and incarnation, but not the start announced."""
    hub, cfg = Hub(), small_config()
    brain, bus = keyed(tmp_path, hub, cfg)
    earlier = forge(cfg, version=9, key=KEY, started_ns=100)  # recorded from the first start
    announce(bus, "s1", cfg, started_ns=200, key=KEY)  # the restored start
    bus.put(KEYS.weights("s1"), earlier, None)
    assert wait(lambda: brain.rejected["unannounced"] == 1)
    bus.put(KEYS.weights("s1"), forge(cfg, version=1, key=KEY, started_ns=200), None)  # its own
    assert wait(lambda: brain.current is not None and brain.current.version == 1)
    brain.stop()


def test_a_server_whose_clock_was_set_back_is_still_followed(tmp_path):
    """Its snapshots are published "before" its start by its own clock: they are still its start's."""
    hub, cfg = Hub(), small_config()
    brain, bus = keyed(tmp_path, hub, cfg)
    start = time.time_ns()
    announce(bus, "s1", cfg, started_ns=start, key=KEY)
    for version in (1, 2):
        set_back = start - 3_600 * 10**9 + version  # an hour back, as NTP or an RTC might set it
        frame = forge(cfg, version=version, key=KEY, started_ns=start, published_ns=set_back)
        bus.put(KEYS.weights("s1"), frame, None)
        assert wait(lambda v=version: brain.current is not None and brain.current.version == v)
    assert brain.connected and not brain.rejected
    brain.stop()


def test_an_earlier_start_replayed_after_the_server_fell_silent_is_refused(tmp_path):
    """Known at incarnation 2, then silent: its incarnation 1 (started before) is not taken back."""
    hub, cfg = Hub(), small_config()
    brain, bus = keyed(tmp_path, hub, cfg, status_timeout_s=0.3)
    announce(bus, "s1", cfg, started_ns=2, key=KEY, incarnation=2)
    bus.put(KEYS.weights("s1"), forge(cfg, version=1, incarnation=2, key=KEY, started_ns=2), None)
    assert wait(lambda: brain.current is not None and brain.current.incarnation == 2)
    assert wait(lambda: not brain.table.views["s1"].alive)
    announce(bus, "s1", cfg, started_ns=1, key=KEY, incarnation=1, token=False)  # recorded, replayed
    assert wait(lambda: brain.rejected["status_stale"] == 1)
    bus.put(KEYS.weights("s1"), forge(cfg, version=9, incarnation=1, key=KEY, started_ns=1), None)
    assert wait(lambda: brain.rejected["unannounced"] == 1)
    assert brain.current.incarnation == 2 and brain.table.views["s1"].incarnation == 2
    # A store restored from a backup (a lower incarnation that started later) is taken.
    announce(bus, "s1", cfg, started_ns=3, key=KEY, incarnation=1, token=False)
    bus.put(KEYS.weights("s1"), forge(cfg, version=1, incarnation=1, key=KEY, started_ns=3), None)
    assert wait(lambda: brain.current.incarnation == 1 and brain.current.version == 1)
    brain.stop()


def test_a_server_restored_from_a_backup_is_sent_what_it_lost(tmp_path):
    """Its data directory restored (the same store, less than it acknowledged, its incarnations
    counted again): the client re-sends from what it now holds, and the stream goes on."""
    import shutil

    hub, cfg = Hub(), small_config(thinks_per_action=1)

    def feed(brain, n):
        for _ in range(n):
            brain.learn(Experience(np.zeros(3), np.zeros(2), np.zeros(3), -0.1), None)

    server = make_server(tmp_path, hub, cfg).start()
    brain = remote(tmp_path, hub, cfg, batch_max=10)
    brain.start()
    feed(brain, 50)
    assert wait(brain.all_acked)
    server.stop()
    shutil.copytree(tmp_path / "s1", tmp_path / "backup")
    server = make_server(tmp_path, hub, cfg).start()
    feed(brain, 50)
    assert wait(lambda: brain.all_acked() and server.store.count == 100)
    server.stop()
    shutil.rmtree(tmp_path / "s1")
    shutil.copytree(tmp_path / "backup", tmp_path / "s1")  # the disk lost, the backup restored
    with make_server(tmp_path, hub, cfg) as restored:
        assert restored.store.count == 50
        feed(brain, 20)
        assert wait(lambda: restored.store.stored_through.get(brain.id) == 119 and brain.all_acked())
        assert restored.store.count == 120 and brain.counters["uplink/resent_frames"] > 0
    brain.stop()


def test_the_servers_a_client_knows_are_bounded_and_idle_ones_make_room(tmp_path):
    """Statuses of many server ids (forged, without a key) neither grow the table nor displace live ones."""
    from wfnn_client.link import MAX_SERVERS

    hub, cfg = Hub(), small_config()
    brain = remote(tmp_path, hub, cfg, status_timeout_s=0.5)
    brain.start()
    bus = hub.bus()
    for i in range(MAX_SERVERS + 8):
        announce(bus, f"f{i}", cfg, started_ns=1, token=False)
    assert wait(lambda: brain.metrics().get("downlink/rejected_status_servers_full", 0) >= 8)
    assert len(brain.table.views) == MAX_SERVERS
    assert wait(lambda: not brain.table.any_alive(), timeout=3.0)  # silent now: their places are free
    announce(bus, "s1", cfg, started_ns=1, token=False)
    assert wait(lambda: "s1" in brain.table.views)
    assert len(brain.table.views) == MAX_SERVERS
    brain.stop()


@pytest.mark.parametrize("learned, warming_up", [({}, True), ({"r1": 2999, "r2": 1999}, False)])
def test_a_deep_client_new_to_trained_weights_acts_on_them_past_its_warm_up(tmp_path, learned, warming_up):
    """Weights that learned from 5,000 experiences (of other robots) are acted on, with exploration
    noise, by a robot that has taken no action yet; fresh ones (none learned) get random actions."""
    from wfnn_common.config import DeepConfig, ExplorationConfig
    from wfnn_common.learners import make_learner

    hub = Hub()
    noise = ExplorationConfig(kind="gaussian", sigma=0.1)
    deep = DeepConfig(hidden=(8, 8), value_hidden=4, warmup=1000)
    cfg = small_config(learner="deep", deep=deep, thinks_per_action=1, exploration=noise)
    trained = make_learner(cfg)
    brain = RemoteBrain(
        make_learner(cfg), RemoteConfig(controller="t", journal_dir=tmp_path / "j"), hub.bus()
    )
    brain.start()
    bus = hub.bus()
    announce(bus, "s1", cfg, started_ns=1, token=False)
    bus.put(
        KEYS.weights("s1"), forge(cfg, version=1, params=trained.params.flat, learned_through=learned), None
    )
    assert wait(lambda: brain.current is not None)
    x = np.zeros(cfg.state_dim)
    greedy = trained.act(x, explore=False).action
    off = np.mean([np.abs(brain.act(x).result.action - greedy).mean() for _ in range(300)])
    brain.stop()
    assert (off > 0.3) == warming_up, off  # uniform in [-1, 1]: 0.5 off on average; sigma 0.1: 0.08


def test_a_restarted_client_resends_what_its_last_run_journaled_unacknowledged(tmp_path):
    """Before it produces anything new (an idle robot, or a lock-step run's first sync)."""
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    with make_server(tmp_path, hub, cfg) as server:
        hub.tap = lambda key, data: None if "/exp/" in key or "/ack/" in key else data  # nothing gets through
        first = remote(tmp_path, hub, cfg)
        first.start()
        for _ in range(30):
            first.learn(Experience(np.zeros(3), np.zeros(2), np.zeros(3), -0.1), None)
        assert wait(lambda: first.uplink.queued == 0 and first.produced_through == 29)
        first.stop()
        assert server.store.count == 0
        hub.tap = None
        again = remote(tmp_path, hub, cfg, lockstep=True)
        again.start()
        assert again.sync(5.0)  # every journaled experience re-sent and thought about
        # The acknowledgement comes from the server's ingest thread, the snapshot from its learner
        # thread: under load the snapshot can arrive first.
        assert server.store.count == 30 and wait(again.all_acked)
        again.stop()


def _journal_after_a_power_cut(tmp_path, hub, cfg, server):
    """A client that sent 100 experiences, all acknowledged by `server`, and stopped -> that client.

    Its journal as a power cut leaves it is in tmp_path / "crashed": not closed, and its newest
    records never synced (cut to 60% of its bytes).
    """
    import shutil

    first = remote(tmp_path, hub, cfg, batch_max=10)
    first.start()
    for _ in range(100):
        first.learn(Experience(np.zeros(3), np.zeros(2), np.zeros(3), -0.1), None)
    assert wait(first.all_acked) and server.store.stored_through[first.id] == 99
    shutil.copytree(tmp_path / "journal", tmp_path / "crashed")
    first.stop()
    seg = tmp_path / "crashed" / "00000000.seg"
    seg.write_bytes(seg.read_bytes()[: seg.stat().st_size * 6 // 10])
    return first


def test_a_journal_that_lost_its_tail_in_a_crash_never_reuses_numbers_its_servers_hold(tmp_path):
    """Even when no server is heard at the restart: the numbers reserved before publishing are skipped."""
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    with make_server(tmp_path, hub, cfg) as server:
        first = _journal_after_a_power_cut(tmp_path, hub, cfg, server)
        hub.tap = lambda key, data: None  # and the server is out of reach at the restart
        again = remote(
            tmp_path, hub, cfg, journal_dir=tmp_path / "crashed", batch_max=10, status_timeout_s=0.3
        )
        assert again.journal.next_seq > 99  # past what was reserved, not inside what the server holds
        again.start()
        for _ in range(50):
            again.learn(Experience(np.zeros(3), np.zeros(2), np.zeros(3), -0.7), None)
        time.sleep(0.5)  # numbered while nothing is heard
        hub.tap = None
        assert wait(again.all_acked, timeout=10.0)
        new = sum(int((b.reward == -0.7).sum()) for b in server.store.batches() if b.client == first.id)
        assert new == 50
        again.stop()
    meta = json.loads((tmp_path / "crashed" / "client.json").read_text())
    assert meta["reserved_through"] == again.produced_through and meta["closed"] is True
    assert again.counters["uplink/numbers_reserved_skipped"] > 0


def test_a_lockstep_client_restarted_after_a_crash_syncs_past_the_numbers_it_reserved(tmp_path, caplog):
    """Its first sync waited for the server to learn the numbers the crashed run reserved and never
    used, which only its first batch declares lost: every lock-step restart timed out. Declaring
    them lost is the expected end of a crash: a warning, not the error that damage is."""
    import logging
    import shutil

    hub, cfg = Hub(), small_config(thinks_per_action=1)
    with make_server(tmp_path, hub, cfg) as server:
        first = remote(tmp_path, hub, cfg)
        first.start()
        for _ in range(30):
            first.learn(Experience(np.zeros(3), np.zeros(2), np.zeros(3), -0.1), None)
        assert wait(first.all_acked) and server.store.stored_through[first.id] == 29
        shutil.copytree(tmp_path / "journal", tmp_path / "crashed")  # as a kill -9 leaves it: not closed
        first.stop()
        again = remote(tmp_path, hub, cfg, journal_dir=tmp_path / "crashed", lockstep=True)
        assert again.produced_through > 29 and again.uplink.experiences_through(server.id) is None  # unheard
        again.start()
        assert again.sync(5.0) and again.uplink.experiences_through(server.id) == 29
        caplog.set_level(logging.WARNING, logger="wfnn_client.uplink")
        again.learn(Experience(np.zeros(3), np.zeros(2), np.zeros(3), -0.7), None)
        assert again.sync(5.0)  # the first batch declared the reserved numbers lost, and was learned
        assert wait(again.all_acked)
        again.stop()
    told = [r for r in caplog.records if r.name == "wfnn_client.uplink" and "told they are lost" in r.message]
    assert told and {r.levelno for r in told} == {logging.WARNING}, [r.message for r in told]
    assert "a run that did not close its journal reserved" in told[0].message


def test_numbers_an_earlier_crash_reserved_are_declared_to_a_new_server_as_a_crash_not_as_damage(
    tmp_path, caplog
):
    """A run after the one that restarted from a crash re-sent its journal to an empty server, and
    called the crash's gap damage (an error) where the run just after the crash called it a warning."""
    import logging
    import shutil

    hub, cfg = Hub(), small_config(thinks_per_action=1)
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    with make_server(tmp_path / "a", hub, cfg):
        first = remote(tmp_path, hub, cfg)
        first.start()
        for _ in range(30):
            first.learn(Experience(np.zeros(3), np.zeros(2), np.zeros(3), -0.1), None)
        assert wait(first.all_acked)
        shutil.copytree(tmp_path / "journal", tmp_path / "crashed")  # as a kill -9 leaves it: not closed
        first.stop()
        second = remote(tmp_path, hub, cfg, journal_dir=tmp_path / "crashed")
        second.start()
        second.learn(Experience(np.zeros(3), np.zeros(2), np.zeros(3), -0.7), None)
        assert wait(second.all_acked)
        second.stop()
    hub = Hub()
    with make_server(tmp_path / "b", hub, cfg) as empty:  # another store: everything is sent again
        caplog.set_level(logging.WARNING, logger="wfnn_client.uplink")
        third = remote(tmp_path, hub, cfg, journal_dir=tmp_path / "crashed")
        third.start()
        assert wait(third.all_acked, timeout=10.0) and empty.store.count == 31
        third.stop()
    told = [r for r in caplog.records if r.name == "wfnn_client.uplink" and "told they are lost" in r.message]
    assert told and {r.levelno for r in told} == {logging.WARNING}, [r.message for r in told]


def test_a_lockstep_restart_after_a_power_cut_waits_for_what_the_server_holds_beyond_the_journal(tmp_path):
    """The journal's newest records lost (not synced), its first sync waited only for what the
    journal kept: it acted on weights that had not learned experiences the server holds."""
    hub, cfg = Hub(), small_config(thinks_per_action=400)  # the server learns slowly
    with make_server(tmp_path, hub, cfg) as server:
        first = _journal_after_a_power_cut(tmp_path, hub, cfg, server)
        again = remote(tmp_path, hub, cfg, journal_dir=tmp_path / "crashed", batch_max=10, lockstep=True)
        assert again.journal.last_held < 99 and again.uplink.experiences_through(server.id) is None
        again.start()
        assert again.sync(30.0)
        assert again.downlink.current.learned_through[first.id] >= 99
        assert again.uplink.experiences_through(server.id) == 99
        again.stop()
        # Followed, a server holding only what the journal kept is not waited on for what another
        # holds, which cannot be sent to it before the first batch declares it lost.
        with make_server(tmp_path, hub, cfg, server_id="s2") as s2:
            pinned = remote(tmp_path, hub, cfg, journal_dir=tmp_path / "crashed", batch_max=10, lockstep=True,
                            follow="s2")  # fmt: skip
            pinned.start()
            assert pinned.sync(10.0) and pinned.uplink.experiences_through(s2.id) == pinned.journal.last_held
            pinned.stop()


def test_a_journal_closed_cleanly_continues_where_it_was_and_says_nothing(tmp_path, caplog):
    from wfnn_client.journal import Journal

    cfg = small_config()
    journal = Journal(tmp_path / "j", "c1", learner_config=cfg)
    journal.reserve(9)  # as the uplink does before publishing 0-9
    journal.skip_to(10)  # (what it published is not needed here)
    journal.close()
    for _ in range(2):
        again = Journal(tmp_path / "j", "c1", learner_config=cfg)
        assert again.next_seq == 10 and again.skipped_at_open == 10
        again.close()
    assert "was not closed" not in caplog.text


def test_a_robot_acting_on_snapshots_judges_their_values_by_the_rewards_it_meets(tmp_path):
    """The server's deep learner scales its divergence threshold with the rewards it learns; the
    robot's learner learns nothing, so its threshold stayed the config's, and it judged a healthy
    server's values (rewards of 1e5 a step) diverged and stopped following its weights."""
    from wfnn_common.learners import make_learner

    cfg = small_config(learner="deep", gamma=0.99, squash_reward=False, divergence_threshold=1e4)
    server_side = make_learner(cfg)
    z3, z2 = np.zeros(3), np.zeros(2)
    server_side.learn(z3, z2, z3, 1e5)
    assert server_side.monitor.threshold == pytest.approx(1e8)
    brain = RemoteBrain(
        make_learner(cfg), RemoteConfig(controller="t", journal_dir=tmp_path / "j"), Hub().bus()
    )
    try:
        assert brain.learner.monitor.threshold == 1e4
        brain.learn(Experience(z3, z2, z3, -1e5), None)
        assert brain.learner.monitor.threshold == server_side.monitor.threshold
        brain.learn(Experience(z3, z2, z3, float("nan")), None)  # refused by a learner: says nothing
        assert brain.learner.monitor.threshold == server_side.monitor.threshold
    finally:
        brain.stop()


def test_a_stop_interrupted_while_waiting_for_acks_still_closes_the_journal_and_session(tmp_path):
    hub, cfg = Hub(), small_config()
    brain = remote(tmp_path, hub, cfg)
    brain.start()

    def interrupted():
        raise KeyboardInterrupt  # a second Ctrl-C while waiting for a silent server's acks

    brain.uplink.all_acked = interrupted
    brain.table.any_alive = lambda: True
    with pytest.raises(KeyboardInterrupt):
        brain.stop()
    check_free(tmp_path / "journal")  # closed: no writer holds it
    assert not brain._threads


def test_a_declared_loss_names_from_where_it_declares(tmp_path):
    """From the acknowledged point the re-send began at: a server restarted since with a hole this
    journal still holds gives up only what the declaration names."""
    from tests.unit.wfnn_server.test_server import batch
    from wfnn_io.protocol import EXP_AFTER_LOSS, ExperienceBatch, decode

    hub, cfg = Hub(), small_config()
    brain = remote(tmp_path, hub, cfg)
    try:
        frame = Codec(brain.id).encode(batch(cfg, 10, 5, client=brain.id))
        declared = decode(brain.uplink._declare_loss(frame, "s1", acked=4), expect=ExperienceBatch).message
        assert declared.flags[0] & EXP_AFTER_LOSS and declared.lost_from == 5 and declared.first_seq == 10
    finally:
        brain.stop()


def test_what_a_server_acknowledged_is_counted_after_it_is_gone(tmp_path):
    """Counted over live servers only, a run whose server acknowledged everything, then stopped,
    ended saying that no server acknowledged any experience."""
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    server = make_server(tmp_path, hub, cfg).start()
    brain = remote(tmp_path, hub, cfg, status_timeout_s=0.5)
    brain.start()
    try:
        assert wait(lambda: brain.following == "s1")
        rng = np.random.default_rng(0)
        for _ in range(20):
            x = rng.uniform(-1, 1, 3)
            acted = brain.act(x)
            brain.learn(Experience(x, acted.result.action, rng.uniform(-1, 1, 3), -0.5), acted)
        assert wait(lambda: brain.all_acked(), timeout=10)
    finally:
        server.stop()
    assert wait(lambda: brain.metrics()["uplink/acked_through_max"] == -1.0)  # no live server
    brain.stop()
    assert brain.metrics()["uplink/acked_by_any"] == 19.0


def test_the_longest_alive_is_the_earliest_start_on_a_clock_that_agrees_with_the_uptimes():
    """Servers whose clocks agree with their uptimes are ordered by their exact announced starts
    (servers started moments apart on one host, as they started, whatever the statuses' delays);
    a server whose clock does not (set back since its restart, or another host's) by its uptime.
    One number per server: a server not chosen changes nothing by coming or going."""
    from wfnn_client.downlink import CLOCK_TOLERANCE_S, _longest_alive

    wall, now = time.time_ns(), time.monotonic()

    def view(server: str, started_s_ago: float, delay_s: float = 0.0, clock_s: float = 0.0) -> ServerView:
        """A server started `started_s_ago`, its uptime heard `delay_s` late, its clock `clock_s` off."""
        started_ns = wall - int(started_s_ago * 1e9) + int(clock_s * 1e9)
        return ServerView(server=server, started_ns=started_ns, born=now - started_s_ago + delay_s)

    a, b = view("a", 100.00, delay_s=0.3), view("b", 99.99)  # a 10 ms earlier, heard 0.3 s late
    assert _longest_alive([b, a]) is a and _longest_alive([]) is None
    restarted = view("c", 5.0, clock_s=-3_600.0)  # restarted 5 s ago, its clock an hour behind
    assert _longest_alive([a, b, restarted]) is a and _longest_alive([b, restarted]) is b
    ahead = view("d", 100.5, clock_s=2 * CLOCK_TOLERANCE_S)  # the earliest, its clock ahead
    assert _longest_alive([a, b, restarted, ahead]) is ahead
    assert _longest_alive([a, ahead]) is ahead and _longest_alive([b, restarted, ahead]) is ahead
    # A new start known from an ack, its status not yet heard: its clock is unchecked.
    unheard = ServerView(server="e", started_ns=wall - 3_600 * 10**9)
    assert _longest_alive([b, unheard]) is b


def test_a_followed_servers_figures_never_make_this_clients_status_one_the_protocol_refuses(tmp_path):
    """A server's status may hold as many figures, of keys as long, as the protocol allows; a client
    repeats them as server/<name> beside its own, and its status must still be one servers take."""
    from wfnn_io.protocol import MAX_KEY_CHARS, MAX_MAP_ENTRIES, ClientStatus

    hub, cfg = Hub(), small_config()
    server = make_server(tmp_path, hub, cfg).start()
    brain = remote(tmp_path, hub, cfg)
    brain.start()
    figures = {f"m{i:04d}".ljust(MAX_KEY_CHARS, "x"): float(i) for i in range(MAX_MAP_ENTRIES - 1)}
    figures["think/thinks_per_s"] = -5.0
    codec = Codec("robot1")
    try:
        assert wait(lambda: brain.following == "s1")
        for _ in range(100):  # the server's own statuses replace these figures now and then
            with brain.table.lock:
                brain.table.views["s1"].metrics = figures  # as the downlink keeps a status's
            status = codec.decode(codec.encode(brain._status()), ClientStatus)[1]
            if status.metrics.get("server/think/thinks_per_s") == -5.0:
                break
        else:
            raise AssertionError("the figures were always replaced before the status was made")
        assert not any(k.startswith("server/m") for k in status.metrics)  # too long with the prefix
        # Several behaviours: the loop's figures hold each brain's under <behaviour>/, with what each
        # repeats of its server, and every brain is told them all.
        with brain.table.lock:
            brain.table.views["s1"].metrics = {f"f{i}": float(i) for i in range(600)}  # short names
        behaviours = {f"{b}/{k}": v for b in ("servo", "wander") for k, v in brain.metrics().items()}
        assert len(behaviours) > MAX_MAP_ENTRIES
        brain.report({"client/reward_mean": -0.5, **behaviours, "servo/" + "k" * MAX_KEY_CHARS: 1.0})
        status = codec.decode(codec.encode(brain._status()), ClientStatus)[1]
        assert len(status.metrics) == MAX_MAP_ENTRIES and status.metrics["client/reward_mean"] == -0.5
        assert {"uplink/produced_through", "weights/version", "downlink/failovers"} <= status.metrics.keys()
    finally:
        brain.stop()
        server.stop()


def test_a_client_keeps_its_first_thread_failure_as_its_error(tmp_path):
    """As a server does: the cause, not the symptoms that follow it in other threads."""
    brain = remote(tmp_path, Hub(), small_config())
    first = OSError(28, "No space left on device", str(tmp_path / "journal" / "00000000.seg"))
    brain._failed(first)
    brain._failed(RuntimeError("the downlink's bus is closed"))
    assert brain.error is first
    with pytest.raises(RuntimeError, match="client thread failed") as failed:
        brain.check()
    assert failed.value.__cause__ is first
    brain.journal.close()


def test_a_deep_learners_snapshot_is_made_ready_to_act_before_the_tick_gets_it(tmp_path):
    """Its act layout was made in the tick's first act on new weights: 30 ms for a network of
    1,024 x 1,024, a late tick at every new snapshot. The downlink's thread makes it now."""
    hub, cfg = Hub(), small_config(learner="deep", thinks_per_action=1)
    with make_server(tmp_path, hub, cfg):
        brain = remote(tmp_path, hub, cfg)
        brain.start()
        try:
            assert wait(lambda: brain.following == "s1" and brain.current is not None)
            assert "act_layout" in vars(brain.current.params)  # made (a cached property) before the tick acts
        finally:
            brain.stop()


def test_a_snapshot_is_crc_checked_once_on_its_way_to_the_tick(tmp_path, monkeypatch):
    """The bus's thread checked its CRC and the downlink's decoded it and computed it again: a
    second pass over a large snapshot, holding the interpreter's lock from the tick."""
    from wfnn_io import protocol

    hub, cfg = Hub(), small_config()
    n = WFNN(cfg).params.flat.shape[1]
    brain = remote(tmp_path, hub, cfg)
    brain.start()
    try:
        bus = hub.bus()
        announce(bus, "s1", cfg, started_ns=1)
        frame = forge(cfg, version=1, params=np.full((1, n), 0.1))
        passes: list[int] = []
        real = protocol.crc32c
        monkeypatch.setattr(protocol, "crc32c", lambda data: passes.append(len(data)) or real(data))
        bus.put(KEYS.weights("s1"), frame, None)
        assert wait(lambda: brain.current is not None and brain.current.version == 1)
        assert passes.count(len(frame) - 4) == 1  # one pass, over all but the CRC itself
    finally:
        brain.stop()


def test_two_clients_given_one_client_id_are_not_mixed_in_a_store(tmp_path, caplog):
    """Both numbered alike: the store took each one's experiences under numbers the other had not
    sent yet, dropped the rest as copies, and both clients were told all of theirs were stored."""
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    with make_server(tmp_path, hub, cfg) as server:
        first = remote(tmp_path, hub, cfg, client_id="twin", journal_dir=tmp_path / "a")
        second = remote(tmp_path, hub, cfg, client_id="twin", journal_dir=tmp_path / "b")
        first.start()
        second.start()
        try:
            for _ in range(20):  # both stream at once, each its own rewards
                for brain, reward in ((first, -0.1), (second, -0.9)):
                    for _ in range(5):
                        brain.learn(Experience(np.zeros(3), np.zeros(2), np.zeros(3), reward), None)
                time.sleep(0.05)
            assert wait(lambda: first.all_acked() or second.all_acked())
            taken, refused = (first, second) if first.all_acked() else (second, first)
            reward = -0.1 if taken is first else -0.9
            assert wait(lambda: server.store.count == taken.produced_through + 1)
            stored = [b for b in server.store.batches() if b.client == "twin"]
            assert all((b.reward == reward).all() for b in stored), "two runs mixed in one store"
            assert wait(lambda: server.rejected["journal_in_use"] > 0)  # its numbering waits for the servers
            assert wait(lambda: refused.rejected["ack_other_journal"] > 0) and not refused.all_acked()
            # Nothing is re-sent there to be refused, nor the numbers it skipped past the other's
            # declared lost, once the server's status says it takes the other journal.
            assert wait(lambda: refused.table.views["s1"].taken_journal == taken.table.journal)
            before = refused.counters["uplink/declared_lost"], refused.counters["uplink/resent_frames"]
            time.sleep(1.0)  # five re-send periods
            after = refused.counters["uplink/declared_lost"], refused.counters["uplink/resent_frames"]
            assert after == before

            def said():
                return [r.getMessage() for r in caplog.records if "another journal" in r.getMessage()]

            assert wait(lambda: said()) and len(said()) == 1 and "its own --client-id" in said()[0]
        finally:
            first.stop()
            second.stop()


def test_a_run_under_the_client_id_of_one_that_ended_is_taken_without_a_word(tmp_path, caplog, monkeypatch):
    """A fresh journal under an old client id, after its run ended: not refused, nothing declared lost."""
    import wfnn_server.server as server_module

    monkeypatch.setattr(server_module, "JOURNAL_HOLD_S", 0.5)
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    with make_server(tmp_path, hub, cfg) as server:
        a_run_that_ended(tmp_path, hub, cfg, 30)
        time.sleep(1.0)
        again = remote(tmp_path, hub, cfg, client_id="robot1", journal_dir=tmp_path / "run2")
        again.start()
        try:
            for _ in range(20):
                again.learn(Experience(np.zeros(3), np.zeros(2), np.zeros(3), -0.7), None)
            assert wait(lambda: again.all_acked() and server.store.count == 50)
            assert again.counters["uplink/declared_lost"] == 0 and server.rejected["journal_in_use"] == 0
            assert not [r for r in caplog.records if "takes the experiences of another" in r.getMessage()]
        finally:
            again.stop()


def test_a_journal_given_a_new_identity_still_fills_a_server_with_its_earlier_frames(tmp_path):
    """A damaged log.json gives a journal a new identity; its frames kept the old one, and a server
    taking the new one refused them as another journal's, for good."""
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    alone = remote(tmp_path, hub, cfg, client_id="robot1", batch_max=1, status_timeout_s=0.3)
    alone.start()
    for _ in range(100):  # no server: journaled only, 100 frames
        alone.learn(Experience(np.zeros(3), np.zeros(2), np.zeros(3), -0.1), None)
    assert wait(lambda: alone.produced_through == 99 and alone.uplink.queued == 0)
    alone.stop()
    (tmp_path / "journal" / "log.json").write_text("{not json")
    with make_server(tmp_path, hub, cfg) as server:
        again = remote(tmp_path, hub, cfg, client_id="robot1", batch_max=1)
        again.start()
        try:
            assert again.table.journal != alone.table.journal
            for _ in range(20):
                again.learn(Experience(np.zeros(3), np.zeros(2), np.zeros(3), -0.7), None)
                time.sleep(0.02)
            assert wait(lambda: again.all_acked() and server.store.count == 120, timeout=20.0)
            assert server.rejected["journal_in_use"] == 0
        finally:
            again.stop()


def test_statuses_failing_their_checks_are_refused_before_they_can_crowd_out_a_genuine_one(tmp_path):
    """With a key, frames failing the tag were queued unchecked: a flood of them filled the status
    inbox, and the genuine statuses behind it were dropped (a client then left a healthy server)."""
    from wfnn_client.downlink import STATUS_INBOX_BYTES
    from wfnn_io.protocol import _framed

    hub, cfg = Hub(), small_config()
    (tmp_path / "key").write_bytes(KEY)
    brain = remote(tmp_path, hub, cfg, key_file=tmp_path / "key")  # not started: its rounds run here
    downlink = brain.downlink
    genuine = status_frame(cfg, weights_version=1)
    junk = _framed(MsgType.SERVER_STATUS, b"\x80" * (1 << 20), "s1", 0, b"another key of 32 bytes........")
    for _ in range(2 * STATUS_INBOX_BYTES // len(junk)):
        downlink._on_status(KEYS.server_status("s1"), junk)
    downlink._on_status(KEYS.server_status("s2"), genuine)  # another server's key: misrouted
    downlink._on_status(KEYS.server_status("s1"), genuine)
    assert brain.rejected["status_auth"] == 2 * STATUS_INBOX_BYTES // len(junk)
    assert brain.rejected["status_misrouted"] == 1 and brain.rejected["status_inbox_full"] == 0
    assert list(downlink._statuses.drained()) == [genuine]
    brain.stop(flush_timeout_s=0.0)
