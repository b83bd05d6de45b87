import dataclasses
import json
import logging
import time

import numpy as np
import pytest

from tests.fakes import Hub, small_config, wait_for
from wfnn_common.config import LEARNERS, ConfigError, LearnerConfig
from wfnn_io.protocol import (
    Ack,
    ClientStatus,
    Codec,
    ExperienceBatch,
    Keys,
    ServerStatus,
    WeightSnapshot,
)
from wfnn_server.config import ServerConfig
from wfnn_server.server import CHECKPOINT, ThinkServer

KEYS = Keys("t")


def batch(cfg, first, n, client="c1", seed=0, spec=None):
    rng = np.random.default_rng(seed + first)
    s, a = cfg.state_dim, cfg.action_dim
    return ExperienceBatch(
        client=client, spec_hash=spec or cfg.spec_hash(), first_seq=first, weights_source="",
        state=rng.uniform(-1, 1, (n, s)), action=rng.uniform(-1, 1, (n, a)),
        next_state=rng.uniform(-1, 1, (n, s)), reward=rng.uniform(-1, 0, n),
        terminal=np.zeros(n, dtype=np.bool_), weights_version=np.zeros(n, dtype=np.uint64),
        flags=np.zeros(n, dtype=np.uint8),
    )  # fmt: skip


class Listener:
    """Collects what servers publish."""

    def __init__(self, hub):
        self.bus = hub.bus()
        self.codec = Codec("listener")
        self.acks, self.snapshots, self.statuses = [], [], []
        self.bus.subscribe(KEYS.ack("*", "*"), lambda k, d: self.acks.append(self.codec.decode(d, Ack)[1]))
        self.bus.subscribe(
            KEYS.weights(), lambda k, d: self.snapshots.append(self.codec.decode(d, WeightSnapshot)[1])
        )
        self.bus.subscribe(
            KEYS.server_status(), lambda k, d: self.statuses.append(self.codec.decode(d, ServerStatus)[1])
        )

    @staticmethod
    def wait(predicate, timeout=10.0):
        return wait_for(predicate, timeout)

    def acked(self, client="c1", server="s1"):
        values = [a.stored_through for a in self.acks if a.client == client and a.server == server]
        return max(values, default=-1)


def make_server(tmp_path, hub, cfg=None, server_id="s1", **kw):
    config_path = None
    if cfg is not None:
        config_path = tmp_path / f"{server_id}-learner.json"
        config_path.write_text(cfg.to_json())
    options = {
        "controller": "t", "server_id": server_id, "data_dir": tmp_path / server_id,
        "learner_config": config_path, "publish_period_s": 0.05, "status_period_s": 0.05, "fsync": "never",
    }  # fmt: skip
    options.update(kw)
    return ThinkServer(ServerConfig(**options), hub.bus())


def announce(hub, cfg, client="c1", produced_through=-1, metrics=None):
    """A client's status heartbeat, announcing its learner config (as a running client sends it)."""
    status = ClientStatus(
        client=client, spec_hash=cfg.spec_hash(), learner_config=cfg.to_json(), following="",
        weights_version=0, produced_through=produced_through, acked={}, metrics=metrics or {},
    )  # fmt: skip
    hub.bus().put(KEYS.client_status(client), Codec(client).encode(status), None)


def send(hub, b, client="c1", key=None):
    hub.bus().put(KEYS.experiences(client), Codec(client, key, "t").encode(b), None)


@pytest.mark.parametrize("learner", LEARNERS)
def test_stores_acknowledges_and_learns(tmp_path, learner):
    hub, cfg = Hub(), small_config(thinks_per_action=7, learner=learner)
    listener = Listener(hub)
    with make_server(tmp_path, hub, cfg) as server:
        send(hub, batch(cfg, 0, 10))
        assert listener.wait(lambda: listener.acked() == 9)
        assert listener.wait(lambda: any(s.learned_through.get("c1") == 9 for s in listener.snapshots)), (
            "no snapshot covering the batch"
        )
        snap = next(s for s in listener.snapshots if s.learned_through.get("c1") == 9)
        assert snap.thinks == 70 and snap.server == "s1" and snap.spec_hash == cfg.spec_hash()
        assert snap.params.shape == (1, server.learner.params.flat.shape[1])
        assert server.store.count == 10 and server.learner.buffer.count[0] == 10
        versions = [s.version for s in listener.snapshots]
        assert versions == sorted(versions) and len(set(versions)) == len(versions)


def test_duplicates_overlaps_and_gaps(tmp_path):
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    listener = Listener(hub)
    with make_server(tmp_path, hub, cfg) as server:
        send(hub, batch(cfg, 0, 10))
        assert listener.wait(lambda: listener.acked() == 9)
        send(hub, batch(cfg, 0, 10))  # a re-send: dropped, acked again
        send(hub, batch(cfg, 15, 5))  # a gap: refused, the ack says where to resume
        assert listener.wait(
            lambda: server.counters["ingest/gaps"] == 1 and server.counters["ingest/duplicates"] == 1
        )
        assert server.store.count == 10
        send(hub, batch(cfg, 5, 10))  # overlaps 5..9: only 10..14 is new
        assert listener.wait(lambda: listener.acked() == 14)
        assert server.store.count == 15
        assert listener.wait(lambda: server.learner.buffer.count[0] == 15)


def test_corrupt_and_misrouted_frames_are_counted_never_learned(tmp_path):
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    listener = Listener(hub)
    rng = np.random.default_rng(1)
    with make_server(tmp_path, hub, cfg) as server:
        good = Codec("c1").encode(batch(cfg, 0, 4))
        n = 300
        for _ in range(n):
            bad = bytearray(good)
            bad[int(rng.integers(len(bad)))] ^= 1 << int(rng.integers(8))
            hub.bus().put(KEYS.experiences("c1"), bytes(bad), None)
        # A frame whose sender is not the client it carries experiences of.
        hub.bus().put(KEYS.experiences("c1"), Codec("c2").encode(batch(cfg, 0, 4)), None)
        # Experiences for a network of another shape.
        send(hub, batch(cfg, 0, 4, spec="0123456789abcdef"))
        assert listener.wait(lambda: sum(server.rejected.values()) == n + 2)
        assert server.rejected["spec"] == 1 and server.rejected["sender"] == 1
        assert server.store.count == 0 and server.learner.buffer.count[0] == 0
        send(hub, batch(cfg, 0, 4))
        assert listener.wait(lambda: listener.acked() == 3)


def test_keyed_server_rejects_unauthenticated_frames(tmp_path):
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    key_file = tmp_path / "key"
    key_file.write_text("k" * 32)
    listener = Listener(hub)
    with make_server(tmp_path, hub, cfg, key_file=key_file) as server:
        send(hub, batch(cfg, 0, 4))
        send(hub, batch(cfg, 0, 4), key=b"x" * 32)
        assert listener.wait(lambda: server.rejected["auth"] == 2)
        assert server.store.count == 0
        send(hub, batch(cfg, 0, 4), key=b"k" * 32)
        assert listener.wait(lambda: server.store.count == 4)


def test_a_keyed_server_refuses_frames_failing_the_tag_before_they_take_room_in_its_inbox(tmp_path):
    """They were queued unchecked: a flood of them filled the inbox, and genuine frames behind it
    were dropped (sent again by their clients, late)."""
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    key_file = tmp_path / "key"
    key_file.write_text("k" * 32)
    listener = Listener(hub)
    with make_server(tmp_path, hub, cfg, key_file=key_file) as server:
        queued, put = [], server._inbox.put
        server._inbox.put = lambda item, size: queued.append(item[0]) or put(item, size)
        for _ in range(5):
            send(hub, batch(cfg, 0, 4), key=b"x" * 32)
        assert listener.wait(lambda: server.rejected["auth"] == 5)
        assert queued == []
        send(hub, batch(cfg, 0, 4), key=b"k" * 32)
        assert listener.wait(lambda: server.store.count == 4)
        assert queued == ["exp"]


def test_adopts_the_first_clients_config(tmp_path):
    hub, cfg = Hub(), small_config(thinks_per_action=3, seed=5)
    listener = Listener(hub)
    with make_server(tmp_path, hub, None, seed=11, bc_weight=0.25, alpha=0.05) as server:
        send(hub, batch(cfg, 0, 4))
        assert listener.wait(lambda: server.rejected["no_config"] == 1)
        announce(hub, cfg, produced_through=3)
        assert listener.wait(lambda: server.learner is not None)
        assert server.learner_config.seed == 11 and server.learner_config.thinks_per_action == 3
        assert (server.learner_config.bc_weight, server.learner_config.alpha) == (0.25, 0.05)
        assert (cfg.bc_weight, cfg.alpha) == (0.0, 0.25)
        send(hub, batch(cfg, 0, 4))
        assert listener.wait(lambda: listener.acked() == 3)
    # The adopted config is saved as it came: the overrides are this server's flags, applied at each start.
    saved = json.loads((tmp_path / "s1" / "learner_config.json").read_text())
    assert (saved["seed"], saved["bc_weight"], saved["alpha"]) == (cfg.seed, 0.0, 0.25)
    with make_server(tmp_path, hub, None, bc_weight=0.5) as server:  # a restart with other flags
        assert server.learner_config.seed == cfg.seed and server.learner_config.thinks_per_action == 3
        assert (server.learner_config.bc_weight, server.learner_config.alpha) == (0.5, 0.25)
    with make_server(tmp_path, hub, None) as server:  # and without any: the adopted config itself
        assert server.learner_config == LearnerConfig.from_json(cfg.to_json())


def test_experiences_stored_before_the_learner_is_built_are_learned_once(tmp_path, monkeypatch):
    import threading

    import wfnn_server.server as server_module

    hub, cfg = Hub(), small_config(thinks_per_action=3)
    listener = Listener(hub)
    stored = threading.Event()
    # The learner thread starts late: the config is adopted and batches stored and queued before
    # it builds the learner, which loads them from the store.
    monkeypatch.setattr(server_module, "lower_priority", lambda nice: stored.wait(10.0))
    with make_server(tmp_path, hub, None) as server:
        announce(hub, cfg, produced_through=49)
        for first in range(0, 50, 10):
            send(hub, batch(cfg, first, 10))
        assert listener.wait(lambda: server.store.count == 50)
        stored.set()
        assert listener.wait(lambda: server.learner is not None and not server._to_learn)
        assert int(server.learner.buffer.count[0]) == 50  # each stored experience in the replay once
        assert listener.wait(server.replayed)  # the budget is taken before its thinks are done
        assert int(server.learner.thinks[0]) == 3 * 50  # and its thinks owed once
        assert listener.wait(lambda: server.learned_through.get("c1") == 49)  # and reported learned
        server.checkpoint()
    with make_server(tmp_path, hub, None) as again:  # and not owed again after a restart
        assert again.budget == 0


def test_no_other_config_is_adopted_while_the_adopted_ones_learner_is_built(tmp_path, monkeypatch):
    """Building takes seconds (torch): a client of another task heard meanwhile had its config
    adopted, its experiences stored, acknowledged and handed to the learner of the first."""
    import threading

    building, release = threading.Event(), threading.Event()
    real_start = ThinkServer._start_learner

    def slow_start(self, adopted):
        building.set()
        release.wait(10)
        real_start(self, adopted)

    monkeypatch.setattr(ThinkServer, "_start_learner", slow_start)
    hub = Hub()
    cfg_a, cfg_b = small_config(3, 1, thinks_per_action=1), small_config(2, 1, thinks_per_action=1)
    listener = Listener(hub)
    with make_server(tmp_path, hub) as server:
        announce(hub, cfg_a, client="A")
        assert building.wait(10)
        announce(hub, cfg_b, client="B")
        send(hub, batch(cfg_b, 0, 10, client="B"), client="B")
        send(hub, batch(cfg_a, 0, 10, client="A"), client="A")
        assert listener.wait(lambda: listener.acked("A") == 9)
        release.set()
        assert listener.wait(lambda: server.learner is not None and int(server.learner.buffer.count[0]) == 10)
        assert server.spec_hash == cfg_a.spec_hash() and server.error is None
        assert listener.acked("B") == -1 and "B" not in server.store.stored_through
        assert server.rejected["spec"] >= 1


def test_experiences_of_a_config_that_made_no_learner_do_not_stop_the_next(tmp_path, monkeypatch):
    import threading

    import wfnn_server.server as server_module

    hub, first, other = Hub(), small_config(seed=5), small_config(seed=6, n_wires=5)
    listener = Listener(hub)
    real = server_module.make_learner

    def make_learner(config, **kw):  # the first config passes its checks but fails to build
        if config.seed == 5:
            raise RuntimeError("CUDA out of memory")
        return real(config, **kw)

    monkeypatch.setattr(server_module, "make_learner", make_learner)
    stored = threading.Event()
    monkeypatch.setattr(server_module, "lower_priority", lambda nice: stored.wait(10.0))
    with make_server(tmp_path, hub, None) as server:
        announce(hub, first, produced_through=9)
        send(hub, batch(first, 0, 10))  # adopted: its experiences are stored before the build fails
        assert listener.wait(lambda: server.store.count == 10)
        stored.set()
        assert listener.wait(lambda: server.rejected["config"] == 1 and server._pending_config is None)
        announce(hub, other, client="c2")
        assert listener.wait(lambda: server.learner is not None), (server.rejected, server.counters)
        assert listener.wait(lambda: not server._to_learn)
        assert server.counters["store/other_spec"] == 10
        assert int(server.learner.buffer.count[0]) == 0  # the queued copies were not learned either


def test_a_client_config_no_learner_can_be_made_from_is_refused_and_not_saved(tmp_path, monkeypatch):
    import wfnn_server.server as server_module

    hub, cfg, good = Hub(), small_config(seed=5), small_config(seed=6)
    listener = Listener(hub)
    real = server_module.make_learner

    def make_learner(config, **kw):  # as a config that passes its checks but fails to build would
        if config.seed == 5:
            raise RuntimeError("can't allocate memory: you tried to allocate 34359738368 bytes\nmore")
        return real(config, **kw)

    monkeypatch.setattr(server_module, "make_learner", make_learner)

    with make_server(tmp_path, hub, None) as server:
        for _ in range(200):  # announced again and again, as a client does: refused, and the server stays up
            announce(hub, cfg)
            if listener.wait(lambda: server.rejected["config"] >= 3, timeout=0.05):
                break
        assert server.rejected["config"] >= 3
        assert server.learner is None and server.error is None
        assert not (tmp_path / "s1" / "learner_config.json").exists()  # a restart does not adopt it again
        announce(hub, good)
        assert listener.wait(lambda: server.learner is not None), (server.rejected, server.counters)
        assert server.learner_config.seed == 6


@pytest.mark.parametrize("learner", LEARNERS)
def test_restart_resumes_checkpoint_and_store(tmp_path, learner):
    hub, cfg = Hub(), small_config(thinks_per_action=5, learner=learner)
    listener = Listener(hub)
    with make_server(tmp_path, hub, cfg) as server:
        send(hub, batch(cfg, 0, 20))
        assert listener.wait(lambda: any(s.learned_through.get("c1") == 19 for s in listener.snapshots))
        first_params = None
    first_params = server.learner.params.flat.copy()
    training = server.learner.training_state()
    version, thinks = server.version, int(server.learner.thinks[0])
    listener.snapshots.clear()
    listener.statuses.clear()
    with make_server(tmp_path, hub, cfg) as again:
        assert listener.wait(lambda: len(listener.statuses) >= 2)
        # The restored thinks were not thought since the start: the first statuses said millions a
        # second (the restored count over the first status period).
        rates = [s.metrics["think/thinks_per_s"] for s in listener.statuses[:2]]
        assert rates == [0.0, 0.0] and listener.statuses[0].metrics["think/thinks"] == thinks
        assert again.incarnation == server.incarnation + 1
        assert again.store.count == 20 and again.learner.buffer.count[0] == 20
        assert int(again.learner.thinks[0]) == thinks and again.budget == 0
        np.testing.assert_array_equal(again.learner.params.flat, first_params)
        # The whole training state is resumed (the deep learner's critics, targets and Adam).
        assert set(again.learner.training_state()) == set(training)
        for key, value in training.items():
            np.testing.assert_array_equal(again.learner.training_state()[key], value)
        assert listener.wait(lambda: bool(listener.snapshots))
        assert listener.snapshots[0].version > version
        assert listener.snapshots[0].learned_through["c1"] == 19
        send(hub, batch(cfg, 20, 5))
        assert listener.wait(lambda: listener.acked() == 24)


@pytest.mark.parametrize("learner", LEARNERS)
def test_experiences_stored_after_the_checkpoint_are_owed_their_thinks(tmp_path, learner):
    hub, cfg = Hub(), small_config(thinks_per_action=4, learner=learner)
    listener = Listener(hub)
    server = make_server(tmp_path, hub, cfg).start()
    send(hub, batch(cfg, 0, 10))
    assert listener.wait(lambda: any(s.learned_through.get("c1") == 9 for s in listener.snapshots))
    server.checkpoint()
    thinks = int(server.learner.thinks[0])
    server._stop.set()  # stop the threads as a crash would: no final checkpoint
    for thread in server._threads:
        thread.join()
    # Experiences that reached the store after the checkpoint, then the process died.
    server.store.append(batch(cfg, 10, 6))
    server.store.close()
    again = make_server(tmp_path, hub, cfg)
    assert again.store.count == 16
    assert int(again.learner.thinks[0]) == thinks and again.budget == 6 * 4


@pytest.mark.parametrize("learner", LEARNERS)
def test_divergence_resets_and_flags_snapshots(tmp_path, learner):
    hub = Hub()
    cfg = small_config(thinks_per_action=1, divergence_threshold=-2.0, divergence_patience=3, learner=learner)
    listener = Listener(hub)
    with make_server(tmp_path, hub, cfg) as server:
        send(hub, batch(cfg, 0, 10))
        assert listener.wait(lambda: server.learner.resets[0] >= 1)
        assert listener.wait(lambda: any(s.diverged for s in listener.snapshots))
        assert listener.wait(
            lambda: any(st.metrics.get("learn/divergence_resets", 0) >= 1 for st in listener.statuses)
        )


def test_weights_gone_non_finite_while_thinking_on_stored_experiences_are_reset(tmp_path, monkeypatch):
    """No new states arrive for the values' monitor: the weights themselves are checked."""
    from wfnn_common.learner import WFNN
    from wfnn_io.persist import load_weights

    original, poisoned = WFNN.think, []

    def think(self, n=None):
        stats = original(self, n)
        if not poisoned:  # as an update that overflows would leave them
            poisoned.append(True)
            self.params.flat[:] = np.nan
        return stats

    monkeypatch.setattr(WFNN, "think", think)
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    listener = Listener(hub)
    with make_server(tmp_path, hub, cfg, think="continuous") as server:
        send(hub, batch(cfg, 0, 10))
        assert listener.wait(lambda: server.learner.resets[0] == 1)
        assert listener.wait(lambda: any(s.diverged for s in listener.snapshots))
        assert listener.wait(lambda: listener.snapshots[-1].thinks > 20)
    assert all(np.isfinite(s.params).all() for s in listener.snapshots if s.thinks > 1)
    assert np.isfinite(load_weights(tmp_path / "s1" / CHECKPOINT)[1].flat).all()


@pytest.mark.parametrize(
    "bad",
    [{"publish_period_s": 0}, {"server_id": "a/b"}, {"fsync": "sometimes"}, {"bc_weight": -1}, {"alpha": 0},
     {"publish_period_s": 1e-300}, {"checkpoint_period_s": float("nan")}],
)  # fmt: skip
def test_server_config_is_checked(tmp_path, bad):
    with pytest.raises(ValueError):
        ServerConfig(**{"data_dir": tmp_path, **bad})


def test_silent_clients_are_reported(tmp_path, monkeypatch):
    import wfnn_server.server as server_module

    monkeypatch.setattr(server_module, "CLIENT_TIMEOUT_S", 0.3)
    hub, cfg = Hub(), small_config()
    listener = Listener(hub)
    with make_server(tmp_path, hub, cfg):
        announce(hub, cfg)
        assert listener.wait(lambda: any(s.metrics.get("clients/heard") == 1 for s in listener.statuses))
        assert listener.wait(lambda: listener.statuses[-1].metrics.get("clients/silent") == 1)
        announce(hub, cfg)
        assert listener.wait(lambda: listener.statuses[-1].metrics.get("clients/silent") == 0)


def test_a_deep_learner_trains_on_the_servers_device_and_compiler_not_the_clients(tmp_path):
    hub = Hub()
    cfg = small_config(learner="deep")
    cfg = type(cfg).from_dict({**cfg.to_dict(), "deep": {**cfg.to_dict()["deep"], "device": "cuda:7"}})
    cfg = type(cfg).from_dict({**cfg.to_dict(), "deep": {**cfg.to_dict()["deep"], "compile": True}})
    server = make_server(tmp_path, hub, cfg)
    assert server.learner_config.deep.device == "cpu" and not server.learner_config.deep.compile
    assert server.learner_config.spec_hash() == cfg.spec_hash()  # the same learner to its clients
    server.store.close()
    compiling = make_server(tmp_path, hub, small_config(learner="deep"), server_id="s3", compile=True)
    assert compiling.learner_config.deep.compile
    compiling.store.close()
    if not __import__("torch").cuda.is_available():
        with pytest.raises(ValueError, match="no such CUDA device"):
            ServerConfig(controller="t", server_id="s2", data_dir=tmp_path / "s2", device="cuda")


def test_snapshots_and_statuses_list_only_the_most_recently_heard_clients(tmp_path, monkeypatch):
    import wfnn_server.server as server_module

    # Every client a long-lived store ever held would outgrow the frames a robot accepts.
    monkeypatch.setattr(server_module, "MAX_LISTED", 4)
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    listener = Listener(hub)
    with make_server(tmp_path, hub, cfg) as server:
        for k in range(12):
            send(hub, batch(cfg, 0, 2, client=f"c{k}"), client=f"c{k}")
        assert listener.wait(lambda: server.store.count == 24)
        assert listener.wait(lambda: any("c11" in s.learned_through for s in listener.snapshots))
        assert listener.wait(lambda: any("c11" in s.stored_through for s in listener.statuses))
        assert max(len(s.learned_through) for s in listener.snapshots) <= 8  # never every client
        assert max(len(s.stored_through) for s in listener.statuses) <= 8
        newest = listener.snapshots[-1].learned_through
        assert len(newest) == 4 and "c11" in newest


def test_only_learnable_rows_feed_the_figures_and_the_state_the_dashboard_draws(tmp_path):
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    listener = Listener(hub)
    b = batch(cfg, 0, 3)
    b.next_state[2, 0] = np.nan
    b.reward[1] = -1e300
    b.next_state[1, 0] = np.inf
    with make_server(tmp_path, hub, cfg) as server:
        send(hub, b)
        assert listener.wait(lambda: "c1" in server.view.latest_state)
        np.testing.assert_array_equal(server.view.latest_state["c1"], b.next_state[0])
        assert listener.wait(lambda: any("learn/reward_mean" in s.metrics for s in listener.statuses))
        means = [
            s.metrics["learn/reward_mean"] for s in listener.statuses if "learn/reward_mean" in s.metrics
        ]
        assert means[0] == pytest.approx(b.reward[0])
        # Finite experiences the learner's sanity limits refuse (a state far outside its range, a
        # reward beyond 1e30) count no more than non-finite ones; a terminal experience's reward
        # counts, but its next state, which need not be one (NaN), is neither valued nor drawn.
        listener.statuses.clear()
        late = batch(cfg, 3, 4)
        late.reward[:] = [-0.5, 1e300, -0.25, -0.75]
        late.state[0, 0] = 50.0
        late.next_state[3], late.terminal[3] = np.nan, True
        send(hub, late)
        assert listener.wait(lambda: server.learner.buffer.count[0] == 3)  # rows 2 and 3, and row 0 before
        assert listener.wait(lambda: any("learn/reward_mean" in s.metrics for s in listener.statuses))
        means = [s.metrics.get("learn/reward_mean") for s in listener.statuses]
        assert next(m for m in means if m is not None) == pytest.approx(-0.5)
        np.testing.assert_array_equal(server.view.latest_state["c1"], late.next_state[2])


def test_a_refused_start_leaves_the_last_server_config_as_it_was(tmp_path):
    from wfnn_server.config import DashboardConfig, ServerConfig
    from wfnn_server.server import SERVER_JSON, prepare, record

    data = tmp_path / "s1"
    prepare(ServerConfig(controller="t", server_id="s1", data_dir=data))
    assert not (data / SERVER_JSON).exists()  # written by `record`, once the server is built
    record(ServerConfig(controller="t", server_id="s1", data_dir=data))
    before = (data / SERVER_JSON).read_bytes()
    (tmp_path / "empty.key").write_bytes(b"")
    with pytest.raises(ValueError):
        prepare(
            ServerConfig(controller="other", server_id="s1", data_dir=data, key_file=tmp_path / "empty.key")
        )
    assert (data / SERVER_JSON).read_bytes() == before
    from wfnn_io.segments import LogError, SegmentLog

    with SegmentLog(data / "store"), pytest.raises(LogError, match="in use"):  # a server running on it
        prepare(ServerConfig(controller="other", server_id="s1", data_dir=data))
    assert (data / SERVER_JSON).read_bytes() == before
    (tmp_path / "s2" / SERVER_JSON).mkdir(parents=True)  # found before it serves, not once it has
    with pytest.raises(IsADirectoryError, match="is a directory"):
        prepare(ServerConfig(controller="t", server_id="s2", data_dir=tmp_path / "s2"))
    with pytest.raises(ValueError, match="dashboard host"):
        DashboardConfig(port=0, host="")
    exposed = ServerConfig(
        controller="t", server_id="s1", data_dir=data, dashboard=DashboardConfig(port=0, host="0.0.0.0")
    )
    assert any("dashboard" in w for w in prepare(exposed))
    local = ServerConfig(controller="t", server_id="s1", data_dir=data, dashboard=DashboardConfig(port=0))
    assert not any("dashboard" in w for w in prepare(local))


def test_the_views_states_come_newest_last(tmp_path):
    # The dashboard draws the last one: the client heard from last.
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    listener = Listener(hub)
    with make_server(tmp_path, hub, cfg) as server:
        for client, first in (("c1", 0), ("c2", 0), ("c1", 2)):
            b = batch(cfg, first, 2, client=client)
            send(hub, b, client=client)
            assert listener.wait(
                lambda c=client, b=b: np.array_equal(server.view.latest_state.get(c), b.next_state[-1])
            )
        assert list(server.view.latest_state) == ["c2", "c1"]


def test_what_a_crash_left_of_an_atomic_write_is_deleted_at_the_next_start(tmp_path):
    import os
    import tempfile

    data = tmp_path / "s1"
    data.mkdir()
    fd, left = tempfile.mkstemp(dir=data, prefix="checkpoint.npz", suffix=".tmp")  # as a write names it
    os.write(fd, b"\0" * 1000)  # a checkpoint write never renamed
    os.close(fd)
    users = ["notes.tmp", "checkpoint.npz.before-upgrade.tmp", "checkpoint.npzk3j2x9.tmp", "incarnation.tmp"]
    for name in users:  # named alike, but no write's: a user's own
        (data / name).write_text("the user's")
    with make_server(tmp_path, Hub(), small_config()):
        pass
    assert not os.path.exists(left)
    assert all((data / name).read_text() == "the user's" for name in users)


def test_a_second_server_on_one_data_directory_is_refused_before_it_counts_a_start(tmp_path):
    from wfnn_io.segments import LogError

    hub, cfg = Hub(), small_config()
    with make_server(tmp_path, hub, cfg) as first:
        with pytest.raises(LogError, match="in use by another writer"):
            make_server(tmp_path, hub, cfg)
        assert (tmp_path / "s1" / "incarnation").read_text() == str(first.incarnation)


def test_a_learner_config_that_is_not_text_is_refused_naming_it_or_set_aside(tmp_path):

    binary = tmp_path / "binary.json"
    binary.write_bytes(b"\xff\xfe\x00{")
    with pytest.raises(ConfigError, match=r"binary\.json: not text"):
        ThinkServer(ServerConfig(controller="t", server_id="s1", data_dir=tmp_path / "a",
                                 learner_config=binary), Hub().bus())  # fmt: skip
    with ThinkServer(ServerConfig(controller="t", server_id="s1", data_dir=tmp_path / "a"), Hub().bus()):
        pass  # the refused start left the store unlocked
    # The data directory's own copy gone bad: set aside, and the server starts (and adopts again).
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "learner_config.json").write_bytes(b"\xff\xfe\x00{")
    with ThinkServer(ServerConfig(controller="t", server_id="s1", data_dir=tmp_path / "b"), Hub().bus()) as s:
        assert s.learner_config is None
    assert list((tmp_path / "b").glob("learner_config.json.unreadable-*"))


def test_the_server_keeps_of_each_clients_status_only_what_its_views_show(tmp_path):
    """Thousands of heard clients (forged ids, without a key), a megabyte of figures each, would not fit."""
    from wfnn_server.view import CLIENT_SERIES

    hub, cfg = Hub(), small_config()
    with make_server(tmp_path, hub, cfg) as server:
        figures = {f"junk/{i}": float(i) for i in range(1000)} | {"client/reward_mean": -0.5}
        announce(hub, cfg, metrics=figures)
        assert wait_for(lambda: "c1" in server.view.clients)
        kept = server.view.clients["c1"]
        assert kept.metrics == {"client/reward_mean": -0.5} and set(kept.metrics) <= set(
            CLIENT_SERIES.values()
        )
        assert kept.learner_config == "" and kept.acked == {}
        assert server.learner_config == cfg  # what the status said was used before it was trimmed


def _statuses_while_thinking(tmp_path, think_batch, delay, watch_s):
    """The statuses a server sends over `watch_s` seconds while each think call of it first sleeps
    `delay(n)` (n thinks a call), and the server's counters."""
    hub, cfg = Hub(), small_config(thinks_per_action=1000)
    listener = Listener(hub)
    options = {"think": "continuous", "think_batch": think_batch, "status_period_s": 0.05}
    with make_server(tmp_path, hub, cfg, **options) as server:
        assert listener.wait(lambda: server.learner is not None)
        learner = server.learner
        real = learner.think

        def slow(n=None):
            time.sleep(delay(n or 1))
            return real(n)

        learner.think = slow
        send(hub, batch(cfg, 0, 5))
        assert listener.wait(lambda: listener.acked() == 4)
        time.sleep(0.3)  # thinking now
        before = len(listener.statuses)
        time.sleep(watch_s)
        return listener.statuses[before:], server.counters


def test_a_slow_learner_keeps_the_heartbeat_going(tmp_path):
    """Thinks of 50 ms, 50 a call: the status still goes out about every status period, not every 2.5 s."""
    statuses, _ = _statuses_while_thinking(tmp_path, 50, lambda n: 0.05 * n, 1.5)
    assert len(statuses) >= 6


def test_one_update_longer_than_the_clients_patience_keeps_the_heartbeat_going(tmp_path):
    """A client's config may ask for a network whose one update takes seconds (within the memory
    limits): the statuses came only between updates, and every client dropped the server as silent."""
    statuses, counters = _statuses_while_thinking(tmp_path, 1, lambda n: 1.5, 2.0)  # 1.5 s an update
    assert len(statuses) >= 8
    assert all(s.stored_through.get("c1") == 4 for s in statuses)
    assert counters["publish/status_relayed"] > 0


def test_a_stop_while_a_think_is_in_flight_writes_no_checkpoint_beside_it(tmp_path, monkeypatch, caplog):
    """The budget is taken before its thinks are done: a checkpoint written beside a think in
    flight counted them as paid, and a restart from it never did them."""
    import threading

    import wfnn_server.server as server_module

    hub, cfg = Hub(), small_config(thinks_per_action=1)
    monkeypatch.setattr(server_module, "STOP_JOIN_S", 0.2)
    server = make_server(tmp_path, hub, cfg, checkpoint_period_s=0.05).start()
    release, thinking = threading.Event(), threading.Event()
    think = server.learner.think

    def slow(n):
        thinking.set()
        release.wait(10.0)
        return think(n)

    monkeypatch.setattr(server.learner, "think", slow)
    send(hub, batch(cfg, 0, 10))
    assert thinking.wait(10.0)
    path, threads = tmp_path / "s1" / CHECKPOINT, list(server._threads)
    before = path.read_bytes() if path.exists() else None
    with caplog.at_level(logging.WARNING):
        server.stop()
    release.set()
    for thread in threads:  # the late think ends; nothing is written after the stop either
        thread.join(10.0)
    assert "no final checkpoint" in caplog.text
    assert (path.read_bytes() if path.exists() else None) == before
    again = make_server(tmp_path, hub, cfg)
    assert again.budget == 10  # owed again
    again.store.close()


def test_a_batch_being_stored_or_learned_is_not_replayed_yet(tmp_path, monkeypatch):
    """`replayed` ends a --replay-only run: it read an empty queue as done while the batch taken
    from it was still being learned, before its thinks were owed, and while a batch stored was
    not queued yet."""
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    seen = []
    learn_batch = ThinkServer._learn_batch

    def learning(learner, b):
        seen.append(("learning", server.replayed()))
        return learn_batch(learner, b)

    monkeypatch.setattr(ThinkServer, "_learn_batch", staticmethod(learning))
    with make_server(tmp_path, hub, cfg) as server:
        append = server.store.append

        def storing(*args, **kwargs):
            append(*args, **kwargs)
            seen.append(("stored", server.replayed()))

        monkeypatch.setattr(server.store, "append", storing)
        send(hub, batch(cfg, 0, 10))
        assert Listener(hub).wait(lambda: server.store.count == 10 and server.replayed())
        assert int(server.learner.buffer.count[0]) == 10 and int(server.learner.thinks[0]) == 10
    assert seen == [("stored", False), ("learning", False)]


@pytest.mark.parametrize("saved_copy", ["kept", "unreadable", "missing"])
def test_a_learner_config_of_another_spec_than_the_data_directorys_is_refused(tmp_path, saved_copy):
    """A mistaken --learner-config neither sets the checkpoints aside nor replaces the saved config,
    also where the saved copy cannot be read (the checkpoints then say what the directory holds)."""
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    with make_server(tmp_path, hub, cfg) as server:
        send(hub, batch(cfg, 0, 10))
        assert Listener(hub).wait(lambda: server.store.count == 10 and server.replayed())
    data = tmp_path / "s1"
    if saved_copy == "unreadable":
        (data / "learner_config.json").write_text("{corrupt")
    elif saved_copy == "missing":
        (data / "learner_config.json").unlink()
    before = {p.name: p.read_bytes() for p in data.iterdir() if p.is_file()}
    assert "checkpoint.npz" in before
    other = small_config(state_dim=4)
    with pytest.raises(ConfigError, match="holds a learner of spec"):
        make_server(tmp_path, hub, other).start()
    assert {p.name: p.read_bytes() for p in data.iterdir() if p.is_file()} == before  # incarnation too
    with make_server(tmp_path, hub, cfg) as again:  # the right one resumes the training
        assert again.learner is not None and int(again.learner.thinks[0]) == int(server.learner.thinks[0])


def test_a_saved_learner_config_edited_into_another_spec_is_refused_and_changes_nothing(tmp_path):
    """It set the checkpoints aside (the training lost) and left the stored experiences unlearned."""
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    with make_server(tmp_path, hub, cfg) as server:
        send(hub, batch(cfg, 0, 10))
        assert Listener(hub).wait(lambda: server.store.count == 10 and server.replayed())
    data = tmp_path / "s1"
    (data / "learner_config.json").write_text(small_config(state_dim=4).to_json())
    before = {p.name: p.read_bytes() for p in data.iterdir() if p.is_file()}
    with pytest.raises(ConfigError, match=r"learner_config\.json is spec .* its checkpoint\.npz spec"):
        make_server(tmp_path, hub).start()
    assert {p.name: p.read_bytes() for p in data.iterdir() if p.is_file()} == before
    (data / "learner_config.json").write_text(cfg.to_json())  # put back: the training resumes
    with make_server(tmp_path, hub) as again:
        assert again.learner is not None and int(again.learner.thinks[0]) == int(server.learner.thinks[0])


def test_a_start_refused_at_its_dashboard_port_leaves_the_count_of_starts_as_it_was(tmp_path):
    import socket

    from wfnn_server.config import DashboardConfig

    hub, cfg = Hub(), small_config()
    with make_server(tmp_path, hub, cfg) as first:
        pass
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        server = make_server(tmp_path, hub, cfg, dashboard=DashboardConfig(port=taken.getsockname()[1]))
        with pytest.raises(OSError):
            server.start()
        server.stop()
    assert (tmp_path / "s1" / "incarnation").read_text() == str(first.incarnation)


def test_a_start_that_fails_after_binding_its_dashboard_stops_cleanly_and_says_why(tmp_path, monkeypatch):
    """The failure is what is raised, and stopping still closes the store (its lock)."""
    from wfnn_server import server as server_module
    from wfnn_server.config import DashboardConfig

    hub, cfg = Hub(), small_config()
    server = make_server(tmp_path, hub, cfg, dashboard=DashboardConfig(port=0))

    def full(path, text):
        raise OSError(28, "No space left on device", str(path))

    monkeypatch.setattr(server_module, "atomic_write_text", full)
    with pytest.raises(OSError, match="No space left"):
        server.start()
    monkeypatch.undo()
    server.stop()
    with make_server(tmp_path, hub, cfg):  # the store's lock was released
        pass


def test_a_loss_declared_beyond_what_the_client_announced_is_refused(tmp_path):
    """One frame declaring everything up to a huge number lost would make every later batch of that
    client a duplicate, for good (and its acks would tell the client all was stored)."""
    from wfnn_io.protocol import EXP_AFTER_LOSS, MAX_SEQ

    hub, cfg = Hub(), small_config(thinks_per_action=1)
    listener = Listener(hub)
    with make_server(tmp_path, hub, cfg) as server:
        send(hub, batch(cfg, 0, 5))
        assert listener.wait(lambda: listener.acked() == 4)
        forged = batch(cfg, MAX_SEQ, 1)
        forged.flags[:] = EXP_AFTER_LOSS
        send(hub, forged)
        assert listener.wait(lambda: server.rejected["declared_beyond_produced"] == 1)
        announce(hub, cfg, produced_through=19)  # what the client says it has produced
        for first in (5, 10):
            send(hub, batch(cfg, first, 5))
        assert listener.wait(lambda: listener.acked() == 14)
        declared = batch(cfg, 17, 3)  # 15-16 lost from its journal, as a re-send declares
        declared.flags[:] = EXP_AFTER_LOSS
        send(hub, declared)
        assert listener.wait(lambda: listener.acked() == 19)
        assert server.store.stored_through["c1"] == 19 and server.store.lost["c1"] == 2
        assert server.store.count == 18


def test_a_replayed_older_status_does_not_lower_the_bound_on_declared_losses(tmp_path):
    from wfnn_io.protocol import EXP_AFTER_LOSS

    hub, cfg = Hub(), small_config(thinks_per_action=1)
    listener = Listener(hub)
    with make_server(tmp_path, hub, cfg) as server:
        announce(hub, cfg, produced_through=19)
        send(hub, batch(cfg, 0, 15))
        assert listener.wait(lambda: listener.acked() == 14)
        announce(hub, cfg, produced_through=9)  # an old status, recorded and sent again
        assert listener.wait(lambda: server.counters["ingest/client_status"] == 2)
        declared = batch(cfg, 17, 3)  # 15-16 lost from its journal, as a re-send declares
        declared.flags[:] = EXP_AFTER_LOSS
        send(hub, declared)
        assert listener.wait(lambda: listener.acked() == 19)
        assert server.rejected["declared_beyond_produced"] == 0 and server.store.lost["c1"] == 2


def test_declared_losses_are_counted_each_and_logged_once_per_client_in_a_while(tmp_path, caplog):
    """Without a key anyone can declare losses as fast as frames go: the log is not theirs to fill."""
    from wfnn_io.protocol import EXP_AFTER_LOSS

    hub, cfg = Hub(), small_config(thinks_per_action=1)
    listener = Listener(hub)
    with caplog.at_level(logging.WARNING, "wfnn_server.server"), make_server(tmp_path, hub, cfg) as server:
        announce(hub, cfg, produced_through=999)
        send(hub, batch(cfg, 0, 5))
        assert listener.wait(lambda: listener.acked() == 4)
        for first in range(7, 100, 3):  # each declares the two before it lost
            declared = batch(cfg, first, 1)
            declared.flags[:] = EXP_AFTER_LOSS
            send(hub, declared)
        assert listener.wait(lambda: server.counters["ingest/declared_lost"] == 2 * 31)
    assert len([r for r in caplog.records if "declares" in r.getMessage()]) == 1


def test_relearning_after_a_divergence_reset_goes_on_after_a_restart(tmp_path):
    """The relearning still to do is checkpointed: a restart would otherwise publish weights that
    were just reset as healthy, and stop relearning them."""
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    server = make_server(tmp_path, hub, cfg)
    thinks = int(server.learner.thinks[0])
    server.schedule.recover(thinks, 5_000)  # as a reset does
    server.checkpoint()
    server.store.close()
    again = make_server(tmp_path, hub, cfg)
    resumed = int(again.learner.thinks[0])
    assert resumed == thinks and again.schedule.recovering(resumed)
    assert again.schedule.recover_until == resumed + 5_000
    again.checkpoint()  # nothing relearned meanwhile: the same still to do
    again.store.close()
    third = make_server(tmp_path, hub, cfg)
    assert third.schedule.recover_until == int(third.learner.thinks[0]) + 5_000
    third.schedule.recover_until = 0  # relearned
    third.checkpoint()
    third.store.close()
    last = make_server(tmp_path, hub, cfg)
    assert not last.schedule.recovering(thinks)
    last.store.close()


def test_many_clients_falling_silent_at_once_are_logged_in_bounded_lines(tmp_path, monkeypatch, caplog):
    """Thousands of forged ids falling silent, a line each under the lock the ingest waits on, held
    up the status heartbeat past the clients' timeout."""
    import logging

    import wfnn_server.server as server_module

    hub, cfg = Hub(), small_config()
    listener = Listener(hub)
    with caplog.at_level(logging.INFO), make_server(tmp_path, hub, cfg) as server:
        for n in range(100):
            announce(hub, cfg, client=f"c{n}")
        # All heard, and each heard longer ago than the timeout set next, so that all fall silent
        # at one check (on a busy machine, hearing 100 took longer than the timeout, and they fell
        # silent in two waves of lines).
        assert listener.wait(lambda: server.counters["ingest/client_status"] == 100)
        time.sleep(0.5)
        monkeypatch.setattr(server_module, "CLIENT_TIMEOUT_S", 0.3)
        assert listener.wait(
            lambda: bool(listener.statuses) and listener.statuses[-1].metrics.get("clients/silent") == 100
        )
    named = [r for r in caplog.records if "silent for" in r.getMessage()]
    assert len(named) == server_module.LOGGED_CLIENTS
    assert any("84 more silent" in r.getMessage() for r in caplog.records)


def test_a_full_disk_stops_the_server_with_one_line_not_a_traceback(tmp_path, caplog):
    import errno

    hub, cfg = Hub(), small_config()
    server = make_server(tmp_path, hub, cfg)

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    server.store.append = full
    with caplog.at_level(logging.INFO), server:
        send(hub, batch(cfg, 0, 5))
        assert Listener.wait(lambda: server.error is not None)
    assert isinstance(server.error, OSError)
    [failed] = [r for r in caplog.records if "server thread failed" in r.getMessage()]
    assert "No space left on device" in failed.getMessage() and failed.exc_info is None


def test_a_relayed_status_announces_the_weights_version_published_since(tmp_path):
    """Snapshots go out more often than statuses: a relay of the last status said an older version
    than the newest snapshot, and clients dropped that snapshot as forged ("unconfirmed")."""
    hub, cfg = Hub(), small_config()
    listener = Listener(hub)
    server = make_server(tmp_path, hub, cfg)
    try:
        server._publish_status(0.0)
        server.version += 3  # snapshots published since, by the learner thread
        server._relay_status()
        assert listener.wait(lambda: len(listener.statuses) == 2)
        assert [s.weights_version for s in listener.statuses] == [0, 3]
    finally:
        server.store.close()


def test_a_signal_while_a_starters_handlers_are_put_back_leaves_none_behind(monkeypatch):
    """One raised while SIGTERM's handler was put back left SIGINT's only noted: Ctrl-C did nothing."""
    import signal

    import wfnn_server.spawn as spawn
    from wfnn_io.cli_errors import noting

    real, calls = signal.signal, []

    def put_back(signum, handler):
        calls.append(signum)
        previous = real(signum, handler)
        if len(calls) == 3:  # the first handler put back: a SIGTERM arrives then
            raise KeyboardInterrupt
        return previous

    # Python's own SIGINT handler, as in a terminal (a run started with & inherits it ignored).
    inherited = real(signal.SIGINT, signal.default_int_handler)
    try:
        before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
        monkeypatch.setattr(spawn.signal, "signal", put_back)
        with pytest.raises(KeyboardInterrupt), noting(signal.SIGTERM, signal.SIGINT, keep_ignored=True):
            pass
        monkeypatch.setattr(spawn.signal, "signal", real)
        assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before
        assert len(calls) == 4
    finally:
        real(signal.SIGINT, inherited)


def test_a_server_whose_final_checkpoint_fails_still_closes_its_session(tmp_path, monkeypatch):
    """The failed checkpoint's error skipped closing the Zenoh session, which held the process
    alive (still listening on its port) after its one error line."""
    from wfnn_server import server as served

    closed = []

    class Bus:
        def close(self):
            closed.append(True)

    class FailingServer:
        error = None

        def __init__(self, config, bus):
            pass

        def start(self):
            pass

        def wait(self, timeout):
            return True  # its thread ended (as when a periodic checkpoint failed)

        def stop(self):
            raise IsADirectoryError(21, "is a directory, not a file", "checkpoint.prev.npz")

    monkeypatch.setattr(served, "OfflineBus", Bus)
    monkeypatch.setattr(served, "ThinkServer", FailingServer)
    config = ServerConfig(data_dir=tmp_path, offline=True, replay_only=True)
    with pytest.raises(IsADirectoryError):
        served.run(config)
    assert closed == [True]


def test_a_data_directory_in_or_beside_a_log_being_replayed_is_refused_before_anything_is_written(tmp_path):
    """--data-dir LOG --replay-only LOG wrote a checkpoint, records and a store into the log it read."""
    from tests.mounts import files
    from tests.unit.wfnn_io.test_logs import record
    from wfnn_io import logs
    from wfnn_io.logs import LogFormatError
    from wfnn_server.server import prepare

    record(tmp_path / "runs" / "log")
    record(tmp_path / "runs" / "bare")  # a log whose description names no config: read beside it
    info = json.loads((tmp_path / "runs" / "bare" / "log.json").read_text())
    (tmp_path / "runs" / "bare" / "log.json").write_text(json.dumps({**info, "learner_config": None}))
    before = files(tmp_path / "runs")
    for data_dir, log in ((tmp_path / "runs" / "log", "log"), (tmp_path / "runs" / "log" / "d", "log"),
                          (tmp_path / "runs", "bare")):  # fmt: skip
        config = ServerConfig(
            data_dir=data_dir, offline=True, replay_only=True, replay=(tmp_path / "runs" / log,)
        )
        with pytest.raises(LogFormatError, match="being replayed"):
            prepare(config)
    assert files(tmp_path / "runs") == before and not (tmp_path / "runs" / "log" / "d").exists()
    logs.merge([tmp_path / "runs" / "log"], tmp_path / "runs" / "merged")  # its own log.json names its config
    prepare(ServerConfig(data_dir=tmp_path / "runs", offline=True, replay_only=True,
                         replay=(tmp_path / "runs" / "merged",)))  # fmt: skip
    (tmp_path / "d").mkdir()
    own = ServerConfig(
        data_dir=tmp_path / "d", offline=True, replay_only=True, replay=(tmp_path / "d" / "store",)
    )
    prepare(own)  # its own store: what it would write beside it is its own config


def test_host_names_and_endpoints_longer_than_any_are_refused():
    """A 100 KB --dashboard-host took a minute to wrap in its warning, and held off SIGTERM."""
    from wfnn_io.bus import NetConfig
    from wfnn_server.config import DashboardConfig

    with pytest.raises(ValueError, match="more than a name has"):
        DashboardConfig(port=0, host="a" * 100_000)
    with pytest.raises(ValueError, match="address is longer than"):
        NetConfig(connect=("tcp/" + "a" * 30_000 + ":1",))
    # Certificates inline after '#' make long endpoints that Zenoh takes: so are they here.
    NetConfig(listen=("tls/127.0.0.1:7447#listen_certificate_base64=" + "A" * 4000,))
    DashboardConfig(port=0, host="a" * 253)


@pytest.mark.parametrize("data_dir_there", [False, True])
def test_a_refused_start_leaves_none_of_the_folders_or_empty_store_it_made(tmp_path, data_dir_there):
    import socket

    from wfnn_io.bus import NetConfig
    from wfnn_server.config import DashboardConfig
    from wfnn_server.server import run

    data = tmp_path / "runs" / "s1"
    if data_dir_there:
        data.mkdir(parents=True)
        (data / "notes.txt").write_text("mine")
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        anywhere = NetConfig(listen=("tcp/127.0.0.1:0",))
        network_port = NetConfig(listen=(f"tcp/127.0.0.1:{port}",))
        for net, dashboard in ((network_port, None), (anywhere, DashboardConfig(port=port))):
            config = ServerConfig(controller="t", server_id="s1", data_dir=data, net=net, dashboard=dashboard)
            with pytest.raises(OSError):
                run(config)
            if data_dir_there:
                assert sorted(p.name for p in data.iterdir()) == ["notes.txt"]
            else:
                assert list(tmp_path.iterdir()) == []
    # A store that was there before is never removed (here: a torn byte, which opening it moves
    # to quarantine), even where the start is refused.
    store = data / "store"
    store.mkdir(parents=True)
    (store / "00000000.seg").write_bytes(b"x")
    config = ServerConfig(controller="t", server_id="s1", data_dir=data, net=anywhere,
                          dashboard=DashboardConfig(port=port))  # fmt: skip
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", port))
        taken.listen()
        with pytest.raises((OSError, ValueError)):
            run(config)
    assert [p.read_bytes() for p in (store / "quarantine").iterdir()] == [b"x"]


def test_a_start_refused_while_setting_up_leaves_none_of_the_folders_or_empty_store_it_made(tmp_path):
    """Refused after its store was opened (a learner config that is not JSON): as one refused later."""
    from wfnn_io.bus import NetConfig
    from wfnn_server.server import run

    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    data, net = tmp_path / "runs" / "s1", NetConfig(listen=("tcp/127.0.0.1:0",))
    config = ServerConfig(controller="t", server_id="s1", data_dir=data, learner_config=bad, net=net)
    with pytest.raises((OSError, ValueError)):
        run(config)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.json"]


def test_a_start_refused_after_importing_logs_leaves_no_copy_of_them(tmp_path, monkeypatch):
    """A --replay-only start refused for want of a config, or one stopped while its learner was
    made (a Ctrl-C in a long load, say), left a data directory holding every record it imported."""
    from tests.mounts import files
    from tests.unit.wfnn_io.test_logs import record
    from wfnn_io.bus import NetConfig
    from wfnn_io.logs import LogFormatError
    from wfnn_server import server as server_module

    record(tmp_path / "log")
    info = json.loads((tmp_path / "log" / "log.json").read_text())
    (tmp_path / "bare").mkdir()
    for seg in (tmp_path / "log").glob("*.seg"):  # a log that names no config
        (tmp_path / "bare" / seg.name).write_bytes(seg.read_bytes())
    (tmp_path / "bare" / "log.json").write_text(json.dumps({**info, "learner_config": None}))
    before = files(tmp_path)
    net = NetConfig(listen=("tcp/127.0.0.1:0",))
    bare = ServerConfig(controller="t", server_id="s1", data_dir=tmp_path / "runs" / "s1", net=net,
                        replay=(tmp_path / "bare",), replay_only=True)  # fmt: skip
    with pytest.raises(LogFormatError, match="no learner config"):
        server_module.run(bare)
    assert files(tmp_path) == before and not (tmp_path / "runs").exists()

    def interrupted(self, adopted):
        assert self.store.count == 300  # imported, before the learner is made
        raise KeyboardInterrupt

    monkeypatch.setattr(server_module.ThinkServer, "_start_learner", interrupted)
    with pytest.raises(KeyboardInterrupt):
        server_module.run(dataclasses.replace(bare, replay=(tmp_path / "log",)))
    assert files(tmp_path) == before and not (tmp_path / "runs").exists()


def test_a_refused_start_never_removes_a_store_another_server_has_open(tmp_path):
    """Spelled through a folder that did not exist yet (`missing/../data`), the store looked new."""
    from wfnn_io.bus import NetConfig
    from wfnn_io.logs import ExperienceLog, remove_empty_log
    from wfnn_server.server import run

    data = tmp_path / "data"
    serving = ExperienceLog(data / "store")  # another server's store, open and still empty
    assert serving.made
    try:
        config = ServerConfig(controller="t", server_id="s2", data_dir=tmp_path / "missing" / ".." / "data",
                              net=NetConfig(listen=("tcp/127.0.0.1:0",)))  # fmt: skip
        with pytest.raises(OSError, match="in use"):
            run(config)
        assert not remove_empty_log(data / "store")  # its lock is held
        assert sorted(p.name for p in (data / "store").iterdir()) == [".lock", "00000000.seg", "log.json"]
    finally:
        serving.close()
    assert remove_empty_log(data / "store") and not (data / "store").exists()


def test_the_learner_takes_queued_batches_a_bounded_time_at_once_and_the_queue_is_bounded(
    tmp_path, monkeypatch
):
    """Clients sending faster than the learner takes their experiences in held the learner thread
    in one loop (no thinks, snapshots or checkpoints: clients left the server as dead), and what
    waited for it grew without bound. Now it learns for THINK_CALL_S at most a call, and beyond
    LEARN_QUEUE_BYTES waiting, batches are dropped unstored and unacknowledged, to be sent again."""
    from wfnn_server import server as server_module

    hub, cfg = Hub(), small_config(thinks_per_action=1)
    server = make_server(tmp_path, hub, cfg)  # not started: this thread plays both of its threads
    try:
        codec = Codec("c1", None, "t")
        frames = [codec.encode(batch(cfg, 10 * i, 10)) for i in range(4)]
        monkeypatch.setattr(server_module, "THINK_CALL_S", 0.0)
        monkeypatch.setattr(server_module, "LEARN_QUEUE_BYTES", 2 * server_module._nbytes(batch(cfg, 0, 10)))
        for frame in frames[:3]:
            server._ingest(frame)
        assert server.store.count == 20 and server.counters["ingest/learner_behind"] == 1
        assert len(server._to_learn) == 2
        learner = server.learner
        assert server._learn_queued(learner) is True  # one batch, then its time is up
        assert int(learner.buffer.count[0]) == 10 and len(server._to_learn) == 1
        server._ingest(frames[2])  # sent again by its client: room now
        assert server.store.count == 30
        assert server._learn_queued(learner) is True and server._learn_queued(learner) is False
        assert int(learner.buffer.count[0]) == 30 and server._to_learn_bytes == 0
        server._ingest(frames[3])
        assert server.store.count == 40 and server.counters["ingest/learner_behind"] == 1
    finally:
        server.stop()


def test_a_server_keeps_its_first_thread_failure_as_its_error(tmp_path):
    """A full disk failed the store's write, then the learner's config write: the run ended naming
    the second file, not the write that stopped the server."""
    hub, cfg = Hub(), small_config()
    server = make_server(tmp_path, hub, cfg)
    first = OSError(28, "No space left on device", str(tmp_path / "store" / "00000000.seg"))
    server._failed(first)
    server._failed(OSError(28, "No space left on device", str(tmp_path / "learner_config.json")))
    assert server.error is first and server._stop.is_set()
    server.store.close()


def test_a_clients_config_its_own_overrides_break_is_refused_naming_them_once(tmp_path, caplog):
    """`--alpha 5` (a thesis rate) met a deep client's config: the server logged at every status
    that the client had announced a refused config, which it had not (its lr was 3e-4)."""
    import logging

    hub, cfg = Hub(), small_config(learner="deep")
    with caplog.at_level(logging.ERROR), make_server(tmp_path, hub, None, alpha=5.0) as server:
        for _ in range(3):
            announce(hub, cfg)
        assert wait_for(lambda: server.rejected["config"] == 3)
        assert server.learner is None and server._pending_config is None
    told = [r.getMessage() for r in caplog.records if "learner config" in r.getMessage()]
    assert len(told) == 1 and "cannot take this server's overrides (learning_rate 5.0)" in told[0], told
    assert "announced a learner config that is refused" not in caplog.text


def test_configs_that_cannot_be_used_are_noted_and_logged_up_to_a_bound(tmp_path, caplog, monkeypatch):
    """Each config refused was kept whole and logged, every one of them: a sender announcing one
    config after another (each seed another) grew the server without bound."""
    import dataclasses
    import logging

    import wfnn_server.server as server_module

    monkeypatch.setattr(server_module, "REFUSED_LOGGED", 3)
    hub, cfg = Hub(), small_config(learner="deep")
    with caplog.at_level(logging.ERROR), make_server(tmp_path, hub, None, alpha=5.0) as server:
        for seed in range(6):
            announce(hub, dataclasses.replace(cfg, seed=seed))
        assert wait_for(lambda: server.rejected["config"] == 6)
        assert len(server._unusable) == 3 and all(len(d) == 16 for d in server._unusable)
        announce(hub, dataclasses.replace(cfg, seed=5))  # the last noted: refused at once
        assert wait_for(lambda: server.rejected["config"] == 7)
        assert list(server._unusable)[-1] == server_module._digest(dataclasses.replace(cfg, seed=5))
        # One announced at every heartbeat among a stream of others stays noted (never rebuilt).
        announce(hub, dataclasses.replace(cfg, seed=3))  # the oldest noted: refused, noted last
        announce(hub, dataclasses.replace(cfg, seed=6))
        announce(hub, dataclasses.replace(cfg, seed=7))
        assert wait_for(lambda: server.rejected["config"] == 10)
        assert server_module._digest(dataclasses.replace(cfg, seed=3)) in server._unusable
    assert len([r for r in caplog.records if "cannot take this server's overrides" in r.getMessage()]) == 3


def test_a_config_text_refused_as_it_is_read_is_logged_once_and_shortened(tmp_path, caplog):
    """Every heartbeat repeats it: 20 statuses of a 60 KB learner name logged 1.2 MB, in lines of 60 KB."""
    import logging

    hub = Hub()
    hostile = small_config().to_dict() | {"learner": "x" * 60_000}
    status = ClientStatus(client="c1", spec_hash="0" * 16, learner_config=json.dumps(hostile), following="",
                          weights_version=0, produced_through=-1, acked={}, metrics={})  # fmt: skip
    with caplog.at_level(logging.ERROR), make_server(tmp_path, hub, None) as server:
        for _ in range(5):
            hub.bus().put(KEYS.client_status("c1"), Codec("c1").encode(status), None)
        assert wait_for(lambda: server.rejected["config"] == 5)
    told = [r.getMessage() for r in caplog.records if "announced a learner config" in r.getMessage()]
    assert len(told) == 1 and len(told[0]) < 500, [len(t) for t in told]


def test_one_journal_of_a_client_is_taken_at_a_time(tmp_path, monkeypatch):
    """Two runs under one client id (a second client given it, or a recording of another run
    replayed) number alike: mixed in one store, each one's experiences under the other's numbers
    were dropped as copies and acknowledged."""
    import wfnn_server.server as server_module

    monkeypatch.setattr(server_module, "JOURNAL_HOLD_S", 1.0)
    hub, cfg = Hub(), small_config(thinks_per_action=1)
    listener = Listener(hub)
    ours = dataclasses.replace(batch(cfg, 0, 10), journal="ja")
    with make_server(tmp_path, hub, cfg) as server:
        send(hub, ours)
        assert listener.wait(lambda: listener.acked() == 9)
        other = dataclasses.replace(batch(cfg, 5, 10, seed=1), journal="jb")  # 5-9 under our numbers
        send(hub, other)
        assert listener.wait(lambda: server.rejected["journal_in_use"] == 1)
        assert server.store.count == 10 and server.store.stored_through == {"c1": 9}
        assert all(a.journal == "ja" for a in listener.acks)
        assert listener.wait(lambda: any(s.journals == {"c1": "ja"} for s in listener.statuses))
        # Its statuses keep a journal taken while it sends nothing.
        status = ClientStatus(
            client="c1", spec_hash=cfg.spec_hash(), learner_config=cfg.to_json(), following="",
            weights_version=0, produced_through=9, acked={}, metrics={}, journal="ja",
        )  # fmt: skip
        for _ in range(6):
            hub.bus().put(KEYS.client_status("c1"), Codec("c1").encode(status), None)
            time.sleep(0.25)
        send(hub, other)
        assert listener.wait(lambda: server.rejected["journal_in_use"] == 2)
        # Silent for the hold: the other run is taken (an ended run's successor under that id).
        time.sleep(1.1)
        later = dataclasses.replace(batch(cfg, 10, 5, seed=2), journal="jb")
        send(hub, later)
        assert listener.wait(lambda: listener.acked() == 14)
        assert server.store.count == 15 and listener.acks[-1].journal == "jb"
        # Frames of journals written before journals were named are taken whichever is.
        send(hub, batch(cfg, 15, 5))
        assert listener.wait(lambda: listener.acked() == 19)
        # A status relayed while the learner thread is busy names the journal taken now, not its last.
        server.view.last_status = dataclasses.replace(server.view.last_status, journals={})
        listener.statuses.clear()
        server._relay_status()
        time.sleep(0.2)
        assert listener.statuses and all(s.journals == {"c1": "jb"} for s in listener.statuses)
