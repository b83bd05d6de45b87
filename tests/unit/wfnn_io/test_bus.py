"""The Zenoh bus itself: two sessions on loopback (multicast scouting off), in one process."""

import threading
import time

from wfnn_io import bus as bus_module
from wfnn_io.bus import Channel, NetConfig, ZenohBus
from wfnn_server.spawn import endpoint, free_port


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
        deadline = time.monotonic() + 30.0
        while not arrived.wait(0.1):  # until the subscription has reached the sender
            assert time.monotonic() < deadline, "the subscription never reached the sender"
            sender.put("wfnn/t/hello", b"x", Channel.CONTROL)
        keys = [f"wfnn/t/ack/c{i}" for i in range(12)] + ["wfnn/t/ack/c0", "wfnn/t/ack/c11"]
        for key in keys:
            sender.put(key, b"x", Channel.CONTROL)
        assert len(sender._publishers) <= 4
        while len([k for k in got if k.startswith("wfnn/t/ack/")]) < len(keys):
            assert time.monotonic() < deadline, got
            time.sleep(0.01)
        assert [k for k in got if k.startswith("wfnn/t/ack/")] == keys  # reliable, in order, none lost
    finally:
        receiver.close()
        sender.close()
