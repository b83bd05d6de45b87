"""The Zenoh bus itself: two sessions on loopback (multicast scouting off), in one process."""

import json
import threading
import time

import pytest

from wfnn_io import bus as bus_module
from wfnn_io.bus import Channel, NetConfig, ZenohBus
from wfnn_server.spawn import endpoint, free_port


def _until_subscribed(sender: ZenohBus, key: str, arrived: threading.Event) -> None:
    """Put on `key` until the receiver's callback says the subscription reached the sender."""
    deadline = time.monotonic() + 30.0
    while not arrived.wait(0.1):
        assert time.monotonic() < deadline, "the subscription never reached the sender"
        sender.put(key, b"x", Channel.CONTROL)


def test_publishers_are_bounded_and_a_key_published_again_after_eviction_still_arrives(monkeypatch):
    """A server acks on a key naming the client: every id it ever answered kept a publisher."""
    monkeypatch.setattr(bus_module, "MAX_PUBLISHERS", 4)
    port = free_port()
    sender = ZenohBus(NetConfig(listen=(endpoint(port),)))
    receiver = ZenohBus(NetConfig(connect=(endpoint(port),)))
    got: list[str] = []
    arrived = threading.Event()

    def on_sample(key: str, payload: bytes) -> None:
        got.append(key)
        arrived.set()

    try:
        receiver.subscribe("wfnn/t/**", on_sample)
        _until_subscribed(sender, "wfnn/t/hello", arrived)
        keys = [f"wfnn/t/ack/c{i}" for i in range(12)] + ["wfnn/t/ack/c0", "wfnn/t/ack/c11"]
        for key in keys:
            # Acks go out on CONTROL, which drops a frame rather than wait on a busy link (the
            # client sends again): so each key is put until it arrives, and a publisher that
            # eviction left broken shows as a key that never arrives.
            before, deadline = got.count(key), time.monotonic() + 30.0
            while got.count(key) == before:
                assert time.monotonic() < deadline, f"{key} never arrived; got {got}"
                sender.put(key, b"x", Channel.CONTROL)
                for _ in range(50):
                    if got.count(key) > before:
                        break
                    time.sleep(0.01)
            assert len(sender._publishers) <= 4
    finally:
        receiver.close()
        sender.close()


def test_a_peer_that_stops_reading_acks_does_not_hold_the_acking_thread():
    """A server acks from its ingest thread: a subscriber to acks that never reads them must not
    hold that thread (blocking, each put would wait on the full link, 5 s before Zenoh closes it)."""
    port = free_port()
    sender = ZenohBus(NetConfig(listen=(endpoint(port),)))
    stalled = ZenohBus(NetConfig(connect=(endpoint(port),)))
    release, arrived = threading.Event(), threading.Event()

    def never_done(key: str, payload: bytes) -> None:
        arrived.set()
        release.wait(30.0)  # holds the receiving session's thread, as a peer that stops reading

    try:
        stalled.subscribe("wfnn/t/ack/**", never_done)
        _until_subscribed(sender, "wfnn/t/ack/c1", arrived)
        payload, longest = bytes(16_384), 0.0
        for _ in range(4_000):  # 64 MiB: far beyond what the link's queues hold
            start = time.monotonic()
            sender.put("wfnn/t/ack/c1", payload, Channel.CONTROL)
            longest = max(longest, time.monotonic() - start)
        assert longest < 1.0, f"a put waited {longest:.2f} s on a peer that does not read"
    finally:
        release.set()
        stalled.close()
        sender.close()


def test_a_link_that_takes_nothing_is_closed_after_block_close_ms_not_zenohs_5_s():
    """A blocked send holds everything behind it (see `NetConfig.block_close_ms`)."""
    key = "transport/link/tx/queue/congestion_control/block/wait_before_close"
    assert json.loads(bus_module.zenoh_config(NetConfig()).get_json(key)) == 1_000_000  # microseconds
    assert json.loads(bus_module.zenoh_config(NetConfig(block_close_ms=250)).get_json(key)) == 250_000
    with pytest.raises(ValueError, match="block_close_ms"):
        NetConfig(block_close_ms=0)


def test_a_zenoh_config_files_own_wait_before_close_is_kept(tmp_path):
    """A deployment on a slow link raised it in its file; wfnn's 1 s replaced it without a word."""
    key = "transport/link/tx/queue/congestion_control/block/wait_before_close"
    own = tmp_path / "slow.json5"
    own.write_text("{ transport: { link: { tx: { queue: { congestion_control: { block: "
                   "{ wait_before_close: 10000000 } } } } } } }")  # fmt: skip
    assert json.loads(bus_module.zenoh_config(NetConfig(zenoh_config=str(own))).get_json(key)) == 10_000_000
    other = tmp_path / "other.json5"
    other.write_text("{ transport: { link: { tx: { lease: 5000 } } } }")
    assert json.loads(bus_module.zenoh_config(NetConfig(zenoh_config=str(other))).get_json(key)) == 1_000_000


@pytest.mark.multiprocess
def test_a_peer_process_that_exits_leaves_nothing_mapped_by_default():
    """With Zenoh's shared memory on, every start of a peer process (a think server restarted) left
    two of its segments mapped here for good, about 18 MB: a robot grew by that at each restart."""
    import subprocess
    import sys

    def mapped() -> int:
        with open("/proc/self/maps") as maps:
            return sum(".zenoh" in line for line in maps)

    port = free_port()
    receiver = ZenohBus(NetConfig(listen=(endpoint(port),)))
    got: list[int] = []
    receiver.subscribe("wfnn/t/**", lambda key, payload: got.append(len(payload)))
    before = mapped()
    sender = (
        "import time\n"
        "from wfnn_io.bus import Channel, NetConfig, ZenohBus\n"
        f"bus = ZenohBus(NetConfig(connect=({endpoint(port)!r},)))\n"
        "for _ in range(40):\n"
        "    bus.put('wfnn/t/x', bytes(200_000), Channel.DATA)\n"
        "    time.sleep(0.05)\n"
        "bus.close()\n"
    )
    try:
        for _ in range(2):
            subprocess.run([sys.executable, "-c", sender], check=True, timeout=60)
        assert got, "nothing arrived from the peer processes"
        assert mapped() == before
    finally:
        receiver.close()
