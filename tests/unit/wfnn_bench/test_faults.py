"""The fault benchmark's pieces that need no namespaces: the delay line's netlink messages, the
figures computed from a robot's trace, and the harness' refusal where it cannot run."""

import socket
import struct

import numpy as np
import pytest

from wfnn_bench import delay_line, hosts
from wfnn_bench.faults import FaultsBenchConfig, figures


def packet_message(packet_id: int, queue: int = 3) -> bytes:
    """A nfnetlink_queue packet message as the kernel sends it (header attribute, then a mark)."""
    hdr = delay_line._attr(delay_line.NFQA_PACKET_HDR, struct.pack("!IHB", packet_id, 0x0800, 3))
    mark = delay_line._attr(3, struct.pack("!I", 7))
    return delay_line._message(delay_line.NFQNL_MSG_PACKET, queue, hdr + mark, 0, 0)


def test_delay_line_reads_packet_ids_and_errors_from_one_netlink_read():
    error = struct.pack("=IHHII", 36, delay_line.NLMSG_ERROR, 0, 1, 0) + struct.pack("=i", -1) + b"\0" * 16
    data = packet_message(41) + error + packet_message(42)
    assert delay_line.parse_messages(data) == [("packet", 41), ("error", 1), ("packet", 42)]


def test_delay_line_ignores_a_truncated_message():
    whole = packet_message(5)
    assert delay_line.parse_messages(whole[:-4]) == []
    assert delay_line.parse_messages(whole + whole[:10]) == [("packet", 5)]


def test_delay_line_verdict_names_the_queue_and_the_packet():
    msg = delay_line.verdict_message(9, 1234)
    length, msg_type, flags, _, _ = delay_line.NLMSG_HEADER.unpack_from(msg)
    assert length == len(msg) and msg_type == (3 << 8) | 1 and flags == delay_line.NLM_F_REQUEST
    _, _, queue = delay_line.NFGEN_HEADER.unpack_from(msg, 16)
    assert socket.ntohs(queue) == 9
    assert struct.unpack_from("!II", msg, 24) == (delay_line.NF_ACCEPT, 1234)


def test_delay_line_bind_asks_for_metadata_only_and_an_acknowledgement():
    bind, params = delay_line.bind_message(3, 100)
    assert delay_line.NLMSG_HEADER.unpack_from(bind)[2] & delay_line.NLM_F_ACK
    # params: copy range 0, copy mode META (1), then the queue length attribute
    assert struct.unpack_from("!IB", params, 24) == (0, delay_line.NFQNL_COPY_META)


@pytest.mark.parametrize("kwargs", [{"queue": -1}, {"queue": 1, "delay_ms": 5.0, "jitter_ms": 10.0}])
def test_delay_line_refuses_impossible_settings(kwargs):
    with pytest.raises(ValueError):
        delay_line.DelayLineConfig(**kwargs)


def test_faults_config_refuses_unknown_cases():
    with pytest.raises(ValueError, match="cases are some of"):
        FaultsBenchConfig(cases=("a", "z"))


def test_hosts_say_why_they_cannot_run_without_root(monkeypatch):
    monkeypatch.setattr(hosts.os, "geteuid", lambda: 1000)
    assert hosts.unavailable() == "network namespaces and iptables need root"


def test_hosts_refuse_names_that_cannot_name_a_namespace():
    with pytest.raises(ValueError, match="letters and digits"):
        hosts.Hosts(("robot", "../etc"))
    with pytest.raises(ValueError, match="differ"):
        hosts.Hosts(("router",))


def synthetic_run(rate_hz=15.0, skip_tick_at=12.0):
    """A 30 s robot trace: a fault from 10 to 15 s, one tick skipped in it, no snapshot applied
    from 10 to 16.5 s, and the first one to have learned a post-fault experience at 17 s."""
    period = 1.0 / rate_hz
    due = [k * period for k in range(int(30 * rate_hz))]
    due = [t for t in due if abs(t - skip_tick_at) > period / 2]
    lateness = [0.5 + (3.0 if 11.0 < t < 11.1 else 0.0) for t in due]
    produced = [int(t * rate_hz) for t in due]
    applied = []
    for t in np.arange(0.25, 30.0, 0.25):
        if 10.0 <= t < 16.5:
            continue
        # before 17 s every snapshot has learned only what was made before the fault
        learned = int(min(t, 9.9) * rate_hz) if t < 17.0 else int((t - 0.3) * rate_hz)
        applied.append([float(t), "think1" if t < 10 else "think2", int(t * 4), learned])
    metrics = {
        "trace": {"tick_due_unix": due, "tick_lateness_ms": lateness, "tick_produced_through": produced,
                  "snapshots_applied": applied},
        "uplink/produced_through": produced[-1], "client/overruns": 1, "following": "think2",
        "failovers": [{"from": "think1", "to": "think2", "at_unix": 11.5},
                      {"from": "x", "to": "think1", "at_unix": 2.0}],
    }  # fmt: skip
    return metrics, {"fault_start_unix": 10.0, "fault_end_unix": 15.0}


def test_figures_come_from_the_window_of_the_fault():
    metrics, events = synthetic_run()
    produced = metrics["uplink/produced_through"] + 1
    got = figures("d", FaultsBenchConfig(), metrics, events, {"think1": produced - 3, "think2": produced})
    assert got["experiences_lost"] == 0
    assert got["experiences_missing_per_server"] == {"think1": 3, "think2": 0}
    assert got["overruns"] == 1  # the tick skipped at 12 s
    assert got["tick_jitter_max_ms"] == pytest.approx(3.5)
    assert got["failover_s"] == pytest.approx(1.5)  # the failover at 2 s came before the fault
    assert got["without_weights_s"] == pytest.approx(16.5 - 9.75)
    assert got["snapshots_resume_s"] == pytest.approx(1.5)
    assert got["learning_resumes_s"] == pytest.approx(2.0)


def test_figures_count_experiences_that_no_server_holds_as_lost():
    metrics, events = synthetic_run()
    produced = metrics["uplink/produced_through"] + 1
    got = figures("b", FaultsBenchConfig(), metrics, events, {"think1": produced - 5, "think2": produced - 2})
    assert got["experiences_lost"] == 2
    assert got["failover_s"] == pytest.approx(1.5)


def test_a_switch_of_server_after_the_fault_is_recovery_not_failover():
    metrics, events = synthetic_run()
    metrics["failovers"] = [{"from": "think1", "to": "think2", "at_unix": 15.4}]
    produced = metrics["uplink/produced_through"] + 1
    got = figures("b", FaultsBenchConfig(), metrics, events, {"think1": produced, "think2": produced})
    assert got["failover_s"] is None and len(got["failovers"]) == 1
