"""A packet delay line in user space: netfilter queues packets here, and each goes on after its delay.

The fault harness (`wfnn_bench.hosts`) needs "20 ms +- 10 ms of delay" on a link. The kernel's
netem qdisc does that, but kernels built without it (as here) only offer loss (nftables'
`numgen random`) and rate limits (tbf). So an nftables rule hands every packet of a link to
netfilter queue N (`queue num N bypass`), and this process gives each packet a verdict of
"accept" once a delay drawn uniformly from [delay - jitter, delay + jitter] has passed, as
netem's default jitter does, reordering included. With `bypass`, packets pass undelayed
whenever no process listens on the queue, so a crashed delay line never cuts the link.

It speaks nfnetlink_queue directly over a netlink socket (the message layouts are in the
kernel's `linux/netfilter/nfnetlink_queue.h`): bind the queue, ask for packet metadata only
(not the payload), read packet ids, send verdicts. Run it inside the namespace whose
netfilter holds the rule:

    ip netns exec HOST python -m wfnn_bench.delay_line --queue 3 --delay-ms 20 --jitter-ms 10

It stops on SIGTERM or SIGINT, accepting every packet it still holds.
"""

from __future__ import annotations

import argparse
import heapq
import logging
import os
import random
import select
import signal
import socket
import struct
import sys
import time
from dataclasses import dataclass

from wfnn_common.config import check_fields

log = logging.getLogger(__name__)

NETLINK_NETFILTER = 12
NFNL_SUBSYS_QUEUE = 3
NFQNL_MSG_PACKET, NFQNL_MSG_VERDICT, NFQNL_MSG_CONFIG = 0, 1, 2
NFQA_CFG_CMD, NFQA_CFG_PARAMS, NFQA_CFG_QUEUE_MAXLEN = 1, 2, 3
NFQNL_CFG_CMD_BIND = 1
NFQNL_COPY_META = 1
NFQA_PACKET_HDR, NFQA_VERDICT_HDR = 1, 2
NF_ACCEPT = 1
NLM_F_REQUEST, NLM_F_ACK = 1, 4
NLMSG_ERROR = 2
NLMSG_HEADER = struct.Struct("=IHHII")  # length, type, flags, sequence, port id (host order)
NFGEN_HEADER = struct.Struct("=BBH")  # family, version, resource id (the queue, big-endian)
ATTR_HEADER = struct.Struct("=HH")  # length, type


@dataclass(frozen=True)
class DelayLineConfig:
    """Options of one delay line."""

    queue: int
    """The netfilter queue number the nftables rule sends packets to."""
    delay_ms: float = 20.0
    jitter_ms: float = 10.0
    """Each packet's delay is uniform in [delay_ms - jitter_ms, delay_ms + jitter_ms] (at least 0)."""
    max_queued: int = 65536
    """Packets the kernel holds for this queue before it drops new ones."""
    seed: int = 0

    def __post_init__(self) -> None:
        check_fields(self)
        if not 0 <= self.queue <= 65535:
            raise ValueError(f"queue must be in [0, 65535], got {self.queue}")
        if not (0.0 <= self.jitter_ms <= self.delay_ms <= 10_000.0):
            raise ValueError(
                f"need 0 <= jitter_ms <= delay_ms <= 10000, got {self.delay_ms}, {self.jitter_ms}"
            )


def _attr(kind: int, payload: bytes) -> bytes:
    """One netlink attribute, padded to 4 bytes."""
    raw = ATTR_HEADER.pack(ATTR_HEADER.size + len(payload), kind) + payload
    return raw + b"\0" * (-len(raw) % 4)


def _message(kind: int, queue: int, attrs: bytes, sequence: int, flags: int = NLM_F_REQUEST) -> bytes:
    """A nfnetlink_queue message of `kind` for `queue`."""
    body = NFGEN_HEADER.pack(socket.AF_UNSPEC, 0, socket.htons(queue)) + attrs
    msg_type = (NFNL_SUBSYS_QUEUE << 8) | kind
    return NLMSG_HEADER.pack(NLMSG_HEADER.size + len(body), msg_type, flags, sequence, 0) + body


def bind_message(queue: int, max_queued: int) -> list[bytes]:
    """The messages that bind `queue` and ask for metadata only."""
    bind = _attr(NFQA_CFG_CMD, struct.pack("!BxH", NFQNL_CFG_CMD_BIND, 0))
    params = _attr(NFQA_CFG_PARAMS, struct.pack("!IB", 0, NFQNL_COPY_META))
    maxlen = _attr(NFQA_CFG_QUEUE_MAXLEN, struct.pack("!I", max_queued))
    return [
        _message(NFQNL_MSG_CONFIG, queue, bind, 1, NLM_F_REQUEST | NLM_F_ACK),
        _message(NFQNL_MSG_CONFIG, queue, params + maxlen, 2, NLM_F_REQUEST | NLM_F_ACK),
    ]


def verdict_message(queue: int, packet_id: int, verdict: int = NF_ACCEPT) -> bytes:
    """The message that lets packet `packet_id` of `queue` go on (or drops it)."""
    return _message(
        NFQNL_MSG_VERDICT, queue, _attr(NFQA_VERDICT_HDR, struct.pack("!II", verdict, packet_id)), 0
    )


def parse_messages(data: bytes) -> list[tuple[str, int]]:
    """The messages in one netlink read -> [("packet", id) | ("error", errno)]; others are skipped."""
    out: list[tuple[str, int]] = []
    at = 0
    while at + NLMSG_HEADER.size <= len(data):
        length, msg_type, _, _, _ = NLMSG_HEADER.unpack_from(data, at)
        if length < NLMSG_HEADER.size or at + length > len(data):
            break
        body = data[at + NLMSG_HEADER.size : at + length]
        if msg_type == NLMSG_ERROR and len(body) >= 4:
            out.append(("error", -struct.unpack_from("=i", body)[0]))  # 0 is an acknowledgement
        elif msg_type == (NFNL_SUBSYS_QUEUE << 8) | NFQNL_MSG_PACKET:
            a = NFGEN_HEADER.size
            while a + ATTR_HEADER.size <= len(body):
                a_len, a_type = ATTR_HEADER.unpack_from(body, a)
                if a_len < ATTR_HEADER.size:
                    break
                if a_type & 0x7FFF == NFQA_PACKET_HDR and a_len >= ATTR_HEADER.size + 4:
                    out.append(("packet", struct.unpack_from("!I", body, a + ATTR_HEADER.size)[0]))
                    break
                a += (a_len + 3) & ~3
        at += (length + 3) & ~3
    return out


class DelayLine:
    """Holds each queued packet for its delay, then accepts it."""

    def __init__(self, cfg: DelayLineConfig) -> None:
        self.cfg = cfg
        self.rng = random.Random(cfg.seed)
        self.sock = socket.socket(socket.AF_NETLINK, socket.SOCK_RAW, NETLINK_NETFILTER)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
        self.sock.bind((0, 0))
        self.held: list[tuple[float, int]] = []
        self.passed = 0
        for message in bind_message(cfg.queue, cfg.max_queued):
            self.sock.send(message)
            for kind, value in parse_messages(self.sock.recv(65536)):
                if kind == "error" and value != 0:
                    raise OSError(value, f"binding netfilter queue {cfg.queue}: {os.strerror(value)}")

    def _release(self, until: float) -> None:
        while self.held and self.held[0][0] <= until:
            _, packet_id = heapq.heappop(self.held)
            self.sock.send(verdict_message(self.cfg.queue, packet_id))
            self.passed += 1

    def run(self, stop: list[bool]) -> None:
        """Serve until `stop[0]`; then accept what is held."""
        low, high = self.cfg.delay_ms - self.cfg.jitter_ms, self.cfg.delay_ms + self.cfg.jitter_ms
        while not stop[0]:
            now = time.monotonic()
            self._release(now)
            wait = min(self.held[0][0] - now, 0.1) if self.held else 0.1
            ready, _, _ = select.select([self.sock], [], [], max(wait, 0.0))
            if not ready:
                continue
            try:
                data = self.sock.recv(1 << 20)
            except OSError as exc:  # ENOBUFS: the kernel dropped messages; the packets stay queued
                log.warning("delay line %d: %s", self.cfg.queue, exc)
                continue
            arrived = time.monotonic()
            for kind, value in parse_messages(data):
                if kind == "packet":
                    delay_s = max(self.rng.uniform(low, high), 0.0) / 1e3
                    heapq.heappush(self.held, (arrived + delay_s, value))
        self._release(float("inf"))


def main(argv: list[str] | None = None) -> int:
    """Run one delay line (see the module docstring)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--queue", type=int, required=True)
    parser.add_argument("--delay-ms", type=float, default=20.0)
    parser.add_argument("--jitter-ms", type=float, default=10.0)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    try:
        line = DelayLine(
            DelayLineConfig(
                queue=args.queue, delay_ms=args.delay_ms, jitter_ms=args.jitter_ms, seed=args.seed
            )
        )
    except (ValueError, OSError) as exc:
        print(f"wfnn delay line: {exc}", file=sys.stderr)
        return 2
    stop = [False]

    def on_signal(*_: object) -> None:
        stop[0] = True

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    print(f"delay line on queue {args.queue}: {args.delay_ms:g} +- {args.jitter_ms:g} ms", flush=True)
    line.run(stop)
    log.info("delay line %d: %d packets passed", args.queue, line.passed)
    return 0


if __name__ == "__main__":
    sys.exit(main())
