"""Nothing forged drives the robot and nothing received stops a thread (in-process bus).

Each test plays an attacker on the controller's keys, or a server restarted the wrong way, and
checks what the robot side and the think server make of it.
"""

import contextlib
import dataclasses
import json
import logging
import math
import threading
import time

import numpy as np
import pytest

from tests.fakes import Hub, small_config
from tests.fakes import wait_for as wait
from tests.unit.wfnn_client.test_remote import announce, forge, remote
from tests.unit.wfnn_server.test_server import KEYS, Listener, batch, make_server, send
from wfnn_client.brain import Experience
from wfnn_common.config import ConfigError, ExplorationConfig, LearnerConfig
from wfnn_common.learners import make_learner
from wfnn_io.bus import NetConfig, check_exposure, endpoints
from wfnn_io.protocol import EXP_NON_FINITE, MAX_SEQ, Ack, ClientStatus, Codec


def feed(brain, n, seed=0):
    rng = np.random.default_rng(seed)
    for _ in range(n):
        x = rng.uniform(-1, 1, 3)
        brain.learn(Experience(x, rng.uniform(-1, 1, 2), x, -0.1), None)


@contextlib.contextmanager
def streaming(tmp_path):
    """A server and a started client (1 think an action) whose first 20 experiences it has stored and
    acknowledged -> (hub, cfg, server, brain); both are stopped after."""
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    with make_server(tmp_path, hub, cfg) as server:
        brain = remote(tmp_path, hub, cfg)
        brain.start()
        try:
            feed(brain, 20)
            assert wait(lambda: server.store.stored_through.get(brain.id) == 19 and brain.all_acked())
            yield hub, cfg, server, brain
        finally:
            brain.stop()


def status_of(client, cfg_json, spec):
    return ClientStatus(client=client, spec_hash=spec, learner_config=cfg_json, following="",
                        weights_version=0, produced_through=-1, acked={}, metrics={})  # fmt: skip


# --------------------------------------------------------------------------- a server restarted empty
def test_a_server_restarted_empty_under_the_same_id_is_sent_everything_and_followed(tmp_path):
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    first = make_server(tmp_path / "a", hub, cfg).start()
    brain = remote(tmp_path, hub, cfg)
    brain.start()
    try:
        feed(brain, 100)
        assert wait(lambda: first.store.stored_through.get(brain.id) == 99 and brain.all_acked())
        assert wait(lambda: brain.current is not None and brain.current.store == first.store.id)
        first.stop()
        first.bus.close()
        # The same id with an empty data directory: the same incarnation number, another store.
        second = make_server(tmp_path / "b", hub, cfg).start()
        assert second.incarnation == first.incarnation and second.store.id != first.store.id
        feed(brain, 20, seed=1)
        assert wait(lambda: second.store.stored_through.get(brain.id) == 119, timeout=10)
        assert second.store.count == 120
        # Its snapshots are not "stale" against the old store's versions: the robot follows them.
        assert wait(lambda: brain.current.store == second.store.id, timeout=5)
        second.stop()
    finally:
        brain.stop()


# --------------------------------------------------------------------------- hostile configs
HOSTILE_CONFIGS = [
    "[" * 20_000 + "]" * 20_000,  # nested past the parser's recursion limit (within the string limit)
    '{"a":' * 5_000 + "1" + "}" * 5_000,
    "[]", '"x"', "null", "{", '{"state_low": 5}', '{"exploration": [1]}', '{"symmetries": {"a": 1}}',
]  # fmt: skip


def ranges(**kw):
    return {"state_low": [-1, -1, -1], "state_high": [1, 1, 1], "action_low": [-1, -1], "action_high": [1, 1],
            "n_hidden": 6, "n_wires": 4, **kw}  # fmt: skip


BAD_VALUES = [
    {"alpha": math.inf}, {"alpha": math.nan}, {"gamma": math.nan}, {"divergence_threshold": math.inf},
    {"n_hidden": 10.5}, {"n_hidden": "10"}, {"n_hidden": True}, {"n_hidden": 10**9},
    {"replay_capacity": 10**12}, {"state_low": [-1, math.nan, -1]}, {"exploration": {"sigma": math.nan}},
    {"exploration": {"tau_steps": math.inf}}, {"thinks_per_action": -1}, {"bc_weight": 1e300},
]  # fmt: skip


@pytest.mark.parametrize("text", HOSTILE_CONFIGS + [json.dumps(ranges(**bad)) for bad in BAD_VALUES])
def test_a_learner_config_that_is_not_valid_is_a_config_error(text):
    with pytest.raises(ConfigError):
        LearnerConfig.from_json(text)


def test_hostile_configs_in_client_statuses_are_counted_and_the_server_goes_on(tmp_path):
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    listener = Listener(hub)
    bus = hub.bus()
    texts = HOSTILE_CONFIGS + [json.dumps(ranges(**bad)) for bad in BAD_VALUES]
    with make_server(tmp_path, hub, None) as server:  # no learner config yet: it adopts a client's
        for text in texts:
            bus.put(
                KEYS.client_status("c1"), Codec("c1").encode(status_of("c1", text, cfg.spec_hash())), None
            )
        assert listener.wait(lambda: server.rejected["config"] == len(texts), timeout=20), dict(
            server.rejected
        )
        assert all(t.is_alive() for t in server._threads) and server.error is None
        assert server.learner is None and not (tmp_path / "s1" / "learner_config.json").exists()
        # Nothing was adopted or persisted; a valid config is adopted as before.
        bus.put(KEYS.client_status("c1"), Codec("c1").encode(status_of("c1", cfg.to_json(), cfg.spec_hash())),
                None)  # fmt: skip
        assert listener.wait(lambda: server.learner is not None)
        assert server.rejected["config"] == len(texts)


def test_a_config_with_infinite_alpha_never_reaches_the_weights(tmp_path):
    hub, cfg = Hub(), small_config(thinks_per_action=2)
    listener = Listener(hub)
    poisoned = json.dumps({**json.loads(cfg.to_json()), "alpha": math.inf})
    with make_server(tmp_path, hub, None) as server:
        poison = Codec("c1").encode(status_of("c1", poisoned, cfg.spec_hash()))
        hub.bus().put(KEYS.client_status("c1"), poison,
                      None)  # fmt: skip
        send(hub, batch(cfg, 0, 10))
        assert listener.wait(lambda: server.rejected["config"] == 1 and server.rejected["no_config"] >= 1)
        assert server.learner is None
    assert not (tmp_path / "s1" / "checkpoint.npz").exists()


@pytest.mark.parametrize(
    "make",
    [
        lambda: ExplorationConfig(sigma=math.nan),
        lambda: small_config(alpha=math.inf),
        lambda: small_config(smoothing_c=math.nan),
        lambda: NetConfig(lease_ms=math.nan),  # type: ignore[arg-type]
    ],
)
def test_every_config_refuses_values_that_are_not_finite(make):
    with pytest.raises(ValueError):
        make()


def test_every_config_class_checks_its_fields():
    """Each config dataclass calls `check_fields` first, so NaN and wrong types are refused everywhere."""
    import dataclasses
    import importlib
    import pkgutil

    import sims
    import wfnn_bench
    import wfnn_client
    import wfnn_common
    import wfnn_io
    import wfnn_server

    unchecked = []
    for package in (wfnn_common, wfnn_io, wfnn_client, wfnn_server, sims, wfnn_bench):
        for info in pkgutil.walk_packages(package.__path__, package.__name__ + "."):
            module = importlib.import_module(info.name)
            for name, obj in vars(module).items():
                if (dataclasses.is_dataclass(obj) and isinstance(obj, type) and name.endswith("Config")
                        and obj.__module__ == module.__name__):  # fmt: skip
                    import inspect

                    post = getattr(obj, "__post_init__", None)
                    if post is None or "check_fields(self)" not in inspect.getsource(post):
                        unchecked.append(f"{module.__name__}.{name}")
    assert unchecked == []


# --------------------------------------------------------------------------- forged weights, no key
def test_forged_snapshots_of_a_huge_incarnation_do_not_capture_the_robot(tmp_path):
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    with make_server(tmp_path, hub, cfg) as server:
        brain = remote(tmp_path, hub, cfg)
        brain.start()
        try:
            assert wait(lambda: brain.following == "s1")
            rogue = hub.bus()
            stop = threading.Event()

            def attack():
                version = 10**9
                while not stop.is_set():
                    version += 1
                    # The genuine server's name, an incarnation it never had, its status forged too.
                    announce(rogue, "s1", cfg, started_ns=1, incarnation=10**6, store="fake", token=False)
                    rogue.put(
                        KEYS.weights("s1"), forge(cfg, version=version, incarnation=10**6, store="fake"), None
                    )
                    time.sleep(0.01)

            thread = threading.Thread(target=attack)
            thread.start()
            time.sleep(1.0)
            stop.set()
            thread.join()
            # Within a second or so of the attacker stopping, the robot acts on genuine weights again.
            assert wait(lambda: brain.current.store == server.store.id, timeout=3.0)
            time.sleep(0.5)
            acted = brain.act(np.zeros(3))
            assert acted.source == f"s1:{server.incarnation}" and brain.current.store == server.store.id
            assert not np.allclose(brain.current.params.flat, 0.5)
        finally:
            brain.stop()


def test_one_forged_snapshot_of_a_huge_version_stops_driving_the_robot(tmp_path):
    """The genuine start (store, incarnation and start are public in its status), a version its
    statuses never reach: dropped status_timeout_s after it arrived, and genuine weights return."""
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    with make_server(tmp_path, hub, cfg) as server:
        brain = remote(tmp_path, hub, cfg, status_timeout_s=0.5)
        brain.start()
        try:
            assert wait(lambda: brain.following == "s1" and brain.current is not None)
            forged = forge(cfg, version=2**63, incarnation=server.incarnation, store=server.store.id,
                           started_ns=server.started_ns)  # fmt: skip
            hub.bus().put(KEYS.weights("s1"), forged, None)  # one frame, then the forger stops
            assert wait(lambda: brain.current.version == 2**63)
            assert wait(lambda: brain.current.version < 2**63, timeout=3.0)
            assert brain.rejected["unconfirmed"] >= 1 and not np.allclose(brain.current.params.flat, 0.5)
        finally:
            brain.stop()


@pytest.mark.parametrize("frame", ["status", "ack"])
def test_one_forged_later_start_of_the_genuine_store_does_not_shut_the_server_out(tmp_path, frame):
    """Without a key, a start later by both incarnation and clock, of the store the server's status
    names (public), once: the robot follows the genuine server again soon after, and its acks go on."""
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    with make_server(tmp_path, hub, cfg) as server:
        brain = remote(tmp_path, hub, cfg, status_timeout_s=0.5)
        brain.start()
        try:
            feed(brain, 10)
            assert wait(lambda: brain.following == "s1" and brain.current is not None and brain.all_acked())
            later = {"incarnation": server.incarnation + 1, "started_ns": server.started_ns + 3600 * 10**9}
            rogue = hub.bus()
            if frame == "status":
                announce(rogue, "s1", cfg, store=server.store.id, token=False, **later)
            else:
                forged = Ack(client=brain.id, server="s1", store=server.store.id, stored_through=-1, **later)
                rogue.put(KEYS.ack(brain.id, "s1"), Codec("s1").encode(forged), None)
            assert wait(lambda: brain.rejected["status_stale"] + brain.rejected["ack_stale"] > 0)
            feed(brain, 10, seed=1)
            assert wait(lambda: brain.current.source == f"s1:{server.incarnation}" and brain.all_acked(),
                        timeout=5.0)  # fmt: skip
            assert server.store.stored_through[brain.id] == 19
        finally:
            brain.stop()


def test_one_forged_snapshot_that_diverges_on_the_robot_stops_driving_it(tmp_path, caplog):
    """Acting on it diverges, which passes the server over: the robot must not stay on the weights
    that diverged once they are dropped as unconfirmed and genuine ones come."""
    hub, cfg = Hub(), small_config(thinks_per_action=1, divergence_patience=1)
    with make_server(tmp_path, hub, cfg) as server:
        brain = remote(tmp_path, hub, cfg, status_timeout_s=0.5)
        brain.start()
        try:
            assert wait(lambda: brain.following == "s1" and brain.current is not None)
            n = brain.current.params.flat.shape[1]
            forged = forge(cfg, version=2**63, incarnation=server.incarnation, store=server.store.id,
                           started_ns=server.started_ns, params=np.full((1, n), 1e300))  # fmt: skip
            hub.bus().put(KEYS.weights("s1"), forged, None)  # one frame, then the forger stops
            assert wait(lambda: brain.current.version == 2**63)
            diverged, deadline = 0, time.monotonic() + 5.0
            while brain.current.version == 2**63 and time.monotonic() < deadline:
                acted = brain.act(np.zeros(3))  # the tick: each act on the forged weights diverges
                diverged += bool(acted.result.diverged)
                feed(brain, 1, seed=diverged)
                time.sleep(0.02)
            assert diverged > 0 and brain.current.version < 2**63
            assert brain.current.source == f"s1:{server.incarnation}"
            assert "acting on newer weights" in caplog.text and "of server s1, whose weights" in caplog.text
            assert not brain.act(np.zeros(3)).result.diverged
        finally:
            brain.stop()


def lose_one_live_batch(hub, brain):
    """One experience fed to `brain` whose live batch is lost on the way (the journal keeps it)."""
    lost = {"n": 1}

    def tap(key, payload):
        if "/exp/live/" in key and lost["n"]:
            lost["n"] -= 1
            return None
        return payload

    hub.tap = tap
    feed(brain, 1, seed=1)
    assert wait(lambda: lost["n"] == 0)
    hub.tap = None


def test_one_forged_ack_of_a_huge_number_does_not_stop_resends(tmp_path):
    with streaming(tmp_path) as (hub, _, server, brain):
        forged = Ack(client=brain.id, server="s1", incarnation=server.incarnation, store=server.store.id,
                     started_ns=server.started_ns, stored_through=MAX_SEQ)  # fmt: skip
        hub.bus().put(KEYS.ack(brain.id, "s1"), Codec("s1").encode(forged), None)
        assert wait(lambda: brain.rejected["ack_beyond"] == 1)
        lose_one_live_batch(hub, brain)
        feed(brain, 40, seed=2)
        assert wait(lambda: server.store.stored_through.get(brain.id) == 60, timeout=10.0)
        assert wait(brain.all_acked)


def test_a_session_listens_on_loopback_unless_told_otherwise():
    assert endpoints(NetConfig(mode="peer"))[0] == ["tcp/127.0.0.1:0"]
    assert endpoints(NetConfig(mode="router"))[0] == ["tcp/127.0.0.1:7447"]
    assert check_exposure(NetConfig(mode="peer", connect=("tcp/127.0.0.1:7447",)), False, False) == []


@pytest.mark.parametrize("where", ["listen", "connect"])
@pytest.mark.parametrize("endpoint", ["tcp/0.0.0.0:7447", "tcp/10.1.2.3:7447", "tls/robot.lab:7447",
                                      "tcp/[::]:7447"])  # fmt: skip
def test_a_non_loopback_endpoint_needs_a_key_or_insecure(where, endpoint):
    net = NetConfig(mode="peer", **{where: (endpoint,)})
    with pytest.raises(ValueError, match=r"--key-file.*--insecure"):
        check_exposure(net, keyed=False, insecure=False)
    assert "insecure" in check_exposure(net, keyed=False, insecure=True)[0]
    assert "not encrypted" in check_exposure(net, keyed=True, insecure=False)[0]


def test_a_client_refuses_to_reach_beyond_loopback_without_a_key(tmp_path):
    from wfnn_client.config import ClientConfig
    from wfnn_client.run import prepare

    config = ClientConfig(sim="boat", server=("tcp/192.168.1.20:7447",), out=tmp_path / "run")
    with pytest.raises(ValueError, match="no --key-file"):
        prepare(config)
    (tmp_path / "key").write_text("k" * 32)
    keyed = ClientConfig(sim="boat", server=("tcp/192.168.1.20:7447",), out=tmp_path / "run",
                         key_file=tmp_path / "key")  # fmt: skip
    assert prepare(keyed)


# --------------------------------------------------------------------------- tokens and queries, key on
def test_fake_tokens_and_a_silent_queryable_do_not_freeze_the_weights(tmp_path, caplog):
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    (tmp_path / "key").write_bytes(b"k" * 32)
    with make_server(tmp_path, hub, cfg, key_file=tmp_path / "key") as server:
        brain = remote(tmp_path, hub, cfg, key_file=tmp_path / "key")
        brain.start()
        try:
            assert wait(lambda: brain.following == "s1")
            rogue = hub.bus()
            release = threading.Event()
            rogue.queryable(KEYS.weights("**"), lambda: release.wait(30) and None)  # never answers in time
            for i in range(30):
                rogue.declare_token(KEYS.server_alive(f"fake{i:02d}"))
            announce(rogue, "fake00", cfg, started_ns=1, token=False)  # no tag: not believed
            feed(brain, 50)
            start = brain.current.version
            time.sleep(3.0)
            assert brain.current.version > start + 5  # new weights kept coming
            assert brain.longest_without_weights_s <= 1.0
            assert brain.rejected["status_auth"] >= 1 and "fake00" not in [
                v.server for v in brain.servers.values() if v.alive
            ]
            assert not [k for k, _ in hub.puts if "/exp/to/fake" in k]  # nothing re-sent to fakes
            assert brain.following == "s1"
            # A stretch without new weights is logged and counted.
            with caplog.at_level(logging.WARNING):
                server.stop()
                server.bus.close()
                assert wait(lambda: brain.counters["downlink/weightless_stretches"] == 1, timeout=5)
            assert "no new weights applied" in caplog.text
            release.set()
        finally:
            brain.stop()


# --------------------------------------------------------------------------- large frames
def test_frames_larger_than_a_snapshot_are_dropped_uncopied(tmp_path):
    hub, cfg = Hub(), small_config()
    brain = remote(tmp_path, hub, cfg)
    brain.start()
    try:
        big = b"WFNN" + bytes(40 << 20)
        for _ in range(3):
            hub.bus().put(KEYS.weights("s1"), big, None)
        assert brain.bus.oversized[KEYS.weights("s1").rsplit("/", 1)[0]] == 3
        assert brain.metrics()["downlink/oversized_weights"] == 3
        assert sum(brain.rejected.values()) == 0  # never reached decoding
    finally:
        brain.stop()


# --------------------------------------------------------------------------- non-finite experiences
def test_non_finite_experiences_are_stored_flagged_and_never_learned(tmp_path):
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    listener = Listener(hub)
    b = batch(cfg, 0, 10, client="made-up")
    b.state[2, 0] = np.nan
    b.reward[5] = np.inf
    b.next_state[7, 1] = -np.inf
    # A failure the task reports with a state it cannot measure: no value follows a terminal, so
    # its reward is learned, as a local learner learns it (the server refused it).
    b.next_state[8, :], b.terminal[8] = np.nan, True
    with make_server(tmp_path, hub, cfg) as server:
        send(hub, b, client="made-up")
        assert listener.wait(lambda: listener.acked("made-up") == 9)
        assert server.counters["ingest/non_finite"] == 3
        assert listener.wait(lambda: server.learner.buffer.count[0] == 7)
        [stored] = list(server.store.batches())
        assert (np.flatnonzero(stored.flags & EXP_NON_FINITE) == [2, 5, 7]).all()
        assert server.budget + int(server.learner.thinks[0]) <= 7  # thinks owed only for the learnable
    local = make_learner(cfg)
    assert local.learn_many(b.state, b.action, b.next_state, b.reward, b.terminal).tolist() == [
        k not in (2, 5, 7) for k in range(10)
    ]


def test_allow_client_takes_only_the_named_clients(tmp_path):
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    listener = Listener(hub)
    with make_server(tmp_path, hub, cfg, allow_clients=("robot1",)) as server:
        send(hub, batch(cfg, 0, 5, client="intruder"), client="intruder")
        hub.bus().put(
            KEYS.client_status("intruder"),
            Codec("intruder").encode(status_of("intruder", cfg.to_json(), cfg.spec_hash())),
            None,
        )
        send(hub, batch(cfg, 0, 5, client="robot1"), client="robot1")
        assert listener.wait(lambda: listener.acked("robot1") == 4)
        assert server.rejected["client_not_allowed"] == 2
        assert server.store.stored_through == {"robot1": 4} and "intruder" not in server.view.clients


def test_experience_numbers_past_an_int64_are_refused():
    from tests.unit.wfnn_io.test_protocol import make_batch
    from wfnn_io.protocol import MAX_SEQ, MalformedBody, decode

    with pytest.raises(MalformedBody):
        make_batch(n=5, first_seq=MAX_SEQ - 3).validate()
    frame = Codec("robot1").encode(make_batch(n=5, first_seq=MAX_SEQ - 4))
    assert decode(frame).message.last_seq == MAX_SEQ


def test_junk_on_the_weights_key_never_pushes_out_a_genuine_snapshot(tmp_path):
    """The client keeps one frame per server until it decodes it: only a frame that checks out."""
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    with make_server(tmp_path, hub, cfg) as server:
        brain = remote(tmp_path, hub, cfg)
        rogue = hub.bus()
        real_put = server.bus.put

        def put_then_junk(key, data, channel):  # every snapshot chased at once by 4 junk bytes
            real_put(key, data, channel)
            if "/weights/" in key:
                rogue.put(key, b"junk", None)

        server.bus.put = put_then_junk
        brain.start()
        try:
            assert wait(lambda: brain.current is not None and brain.current.version >= 5, timeout=5.0)
            assert brain.rejected["truncated"] >= 3
        finally:
            brain.stop()


def test_a_journal_written_without_a_key_is_resent_tagged_once_the_client_has_one(tmp_path):
    """Also where its numbers have a gap that must be declared lost (a decode with the key)."""
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    (tmp_path / "key").write_bytes(b"k" * 32)
    first = remote(tmp_path, hub, cfg, status_timeout_s=0.3)
    first.start()
    bus = hub.bus()
    announce(
        bus, "old", cfg, started_ns=1, stored_through={first.id: 4}, token=False
    )  # the journal starts at 5
    feed(first, 20)
    assert wait(lambda: first.journal.next_seq == 25)
    first.stop()
    keyed_hub = Hub()
    with make_server(tmp_path, keyed_hub, cfg, key_file=tmp_path / "key") as server:
        brain = remote(tmp_path, keyed_hub, cfg, key_file=tmp_path / "key")
        brain.start()
        try:
            feed(brain, 10, seed=3)
            assert wait(lambda: server.store.stored_through.get(brain.id) == 34, timeout=10.0)
            assert not server.rejected.get("auth") and brain.counters["uplink/retagged_frames"] > 0
            assert brain.error is None
        finally:
            brain.stop()


def test_a_flood_faster_than_the_server_handles_is_held_in_bounded_memory_and_resent(tmp_path):
    """Frames beyond the inbox's bytes are dropped and counted; experiences then come from the journal."""
    from wfnn_io.bus import ITEM_OVERHEAD, Inbox

    inbox: Inbox[bytes] = Inbox(max_bytes=10 * (100 + ITEM_OVERHEAD))
    assert all(inbox.put(b"x" * 100, 100) for _ in range(10)) and not inbox.put(b"y", 1)
    assert inbox.dropped == 1 and inbox.get(timeout=0) == b"x" * 100 and inbox.put(b"z" * 100, 100)
    assert len(list(inbox.drained())) == 10 and inbox.put(b"w" * 1000, 1000)
    empty: Inbox[bytes] = Inbox(max_bytes=10 * ITEM_OVERHEAD)  # empty frames cost memory too
    assert all(empty.put(b"", 0) for _ in range(10)) and not empty.put(b"", 0) and empty.dropped == 1
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    with make_server(tmp_path, hub, cfg) as server:
        server._inbox.max_bytes = 1  # as full as a flood leaves it: every frame is dropped
        brain = remote(tmp_path, hub, cfg)
        brain.start()
        try:
            feed(brain, 30)
            assert wait(lambda: server._inbox.dropped >= 2)
            assert server.store.count == 0 and not brain.all_acked()
            server._inbox.max_bytes = 1 << 20  # the flood is over
            assert wait(lambda: brain.all_acked() and server.store.count == 30, timeout=10.0)
        finally:
            brain.stop()


def test_an_ack_within_what_was_produced_does_not_hold_back_resends_past_the_next_status(tmp_path):
    """A status of the server's start says what it holds: a forged ack that says more is corrected."""
    with streaming(tmp_path) as (hub, _, server, brain):
        lose_one_live_batch(hub, brain)
        forged = Ack(client=brain.id, server="s1", incarnation=server.incarnation, store=server.store.id,
                     started_ns=server.started_ns, stored_through=brain.produced_through)  # fmt: skip
        hub.bus().put(KEYS.ack(brain.id, "s1"), Codec("s1").encode(forged), None)
        feed(brain, 40, seed=2)
        assert wait(lambda: server.store.stored_through.get(brain.id) == 60, timeout=10.0)


def test_a_forged_status_and_loss_declaration_neither_swallow_experiences_nor_stop_resends(tmp_path):
    """Without a key, a client status claiming MAX_SEQ - 1 experiences produced lifted the bound on
    declared losses; one batch then declared everything below it lost, and the server took every
    later genuine batch as a duplicate (0 of 40 stored), while the client took the server's status
    (stored through 4.6e18) as its acknowledgement and stopped re-sending: all_acked() was True."""
    from wfnn_io.protocol import EXP_AFTER_LOSS, MAX_PRODUCED

    with streaming(tmp_path) as (hub, cfg, server, brain):
        c = brain.id
        claim = dataclasses.replace(
            status_of(c, cfg.to_json(), cfg.spec_hash()), produced_through=MAX_SEQ - 1
        )
        hub.bus().put(KEYS.client_status(c), Codec(c).encode(claim), None)
        assert wait(lambda: server.rejected["status_beyond_produced"] == 1)
        forged = batch(cfg, MAX_SEQ - 1, 1, client=c)
        forged.flags[:] = EXP_AFTER_LOSS
        send(hub, forged, client=c)
        assert wait(lambda: server.rejected["declared_beyond_produced"] >= 1)
        feed(brain, 40, seed=2)
        assert wait(lambda: server.store.stored_through.get(c) == 59 and brain.all_acked(), timeout=10.0)
        assert server.counters["ingest/declared_lost"] == 0
    # A client never takes a server's status beyond what any client numbers as its acknowledgement.
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    brain = remote(tmp_path / "forged", hub, cfg)
    brain.start()
    try:
        feed(brain, 5)
        bus = hub.bus()
        for _ in range(20):
            announce(bus, "s9", cfg, started_ns=1, stored_through={brain.id: MAX_PRODUCED + 1})
            time.sleep(0.05)
        assert wait(lambda: brain.rejected["status_beyond"] >= 1)
        assert not brain.all_acked()
    finally:
        brain.stop()


def test_peers_with_different_keys_each_say_so_once_and_a_follow_of_an_unheard_server_is_told(
    tmp_path, caplog
):
    """Each side only counted the other's refused frames: the robot acted on its safe action for
    the whole run, told nothing but "none acknowledged" and "following -". A --follow naming a
    server never heard, while another stored everything, was told nothing at all."""
    (tmp_path / "ka").write_bytes(b"a" * 32)
    (tmp_path / "kb").write_bytes(b"b" * 32)
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    with caplog.at_level(logging.WARNING):
        with make_server(tmp_path, hub, cfg, key_file=tmp_path / "kb") as server:
            brain = remote(tmp_path, hub, cfg, key_file=tmp_path / "ka")
            brain.start()
            try:
                feed(brain, 20)
                assert wait(lambda: brain.rejected["status_auth"] >= 3 and server.rejected["auth"] >= 3)
            finally:
                brain.stop()
    told = [r.getMessage() for r in caplog.records if "failed its HMAC tag" in r.getMessage()]
    # One a kind each side: the server's of client statuses or batches, the client's of server statuses
    # and of snapshots (where one came before the stop).
    assert 2 <= len(told) <= 4 and any("server status" in t for t in told), told
    assert len(told) == len(set(t.split(" failed")[0] for t in told)), told
    caplog.clear()
    hub = Hub()
    (tmp_path / "f").mkdir()
    with caplog.at_level(logging.WARNING), make_server(tmp_path / "f", hub, cfg):
        brain = remote(tmp_path / "f", hub, cfg, follow="s9", status_timeout_s=0.5)
        brain.start()
        try:
            feed(brain, 5)
            assert wait(lambda: "--follow s9: no status from it" in caplog.text)
            assert "while s1 is alive: acting on the safe action" in caplog.text
        finally:
            brain.stop()


@pytest.mark.parametrize("mode, default", [("peer", "tcp/127.0.0.1:0"), ("router", "tcp/127.0.0.1:7447")])
def test_a_zenoh_file_naming_no_listen_endpoint_listens_on_loopback_and_one_naming_some_is_kept(
    tmp_path, mode, default
):
    """A file without a listen section took Zenoh's default, every interface; one with endpoints
    had a router-mode server listen on 7447 instead."""
    bare, named = tmp_path / "bare.json5", tmp_path / "named.json5"
    bare.write_text("{ transport: { link: { tx: { lease: 3000 } } } }")
    named.write_text('{ listen: { endpoints: ["tcp/127.0.0.1:46174"] } }')
    assert endpoints(NetConfig(mode=mode, zenoh_config=str(bare)))[0] == [default]
    assert check_exposure(NetConfig(mode=mode, zenoh_config=str(bare)), False, False) == []
    assert endpoints(NetConfig(mode=mode, zenoh_config=str(named)))[0] == ["tcp/127.0.0.1:46174"]
    # Zenoh's default written out is a word to listen there; an empty list, to listen nowhere.
    spelled, empty = tmp_path / "spelled.json5", tmp_path / "empty.json5"
    spelled.write_text('{ listen: { endpoints: { peer: ["tcp/[::]:0"], router: ["tcp/[::]:7447"] } } }')
    empty.write_text("{ listen: { endpoints: [] } }")
    assert endpoints(NetConfig(mode=mode, zenoh_config=str(spelled)))[0] == [
        {"peer": "tcp/[::]:0", "router": "tcp/[::]:7447"}[mode]
    ]
    assert endpoints(NetConfig(mode=mode, zenoh_config=str(empty)))[0] == []


def test_a_router_mode_servers_cli_keeps_its_zenoh_files_endpoints(tmp_path, monkeypatch):
    from typer.testing import CliRunner

    import wfnn_server.cli as server_cli

    named = tmp_path / "named.json5"
    named.write_text('{ listen: { endpoints: ["tcp/127.0.0.1:46174"] } }')
    seen = []
    monkeypatch.setattr(server_cli, "run", lambda config, **_: seen.append(config) or {})
    for extra in ([], ["--zenoh-config", str(named)]):
        CliRunner().invoke(server_cli.app, ["--data-dir", str(tmp_path / "d"), "--quiet", *extra])
    assert [endpoints(c.net)[0] for c in seen] == [["tcp/127.0.0.1:7447"], ["tcp/127.0.0.1:46174"]]
    assert "endpoints as" in seen[1].summary() and "listen tcp/127.0.0.1:7447" in seen[0].summary()
