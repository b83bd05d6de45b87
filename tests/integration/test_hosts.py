"""act-learn-think-C/S across hosts: Linux network namespaces joined by veth links, with faults.

Each test builds its own hosts (`wfnn_bench.hosts`), with addresses only inside them, and removes
them afterwards. They are skipped, saying why, where namespaces cannot be made (not root, no
`ip`, `iptables` or `tc`). The benchmark (`wfnn-bench faults`) runs the cases at full length;
these run them short and check behaviour: nothing lost, the tick kept, learning back after.
"""

import itertools
import json
import subprocess
import sys
import time

import pytest

from wfnn_bench import faults, hosts

WHY = hosts.unavailable()
pytestmark = [
    pytest.mark.netns,
    pytest.mark.multiprocess,
    pytest.mark.slow,
    pytest.mark.skipif(WHY is not None, reason=f"no network namespaces here: {WHY}"),
]

ECHO = """
import socket, sys
s = socket.socket()
s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
s.bind((sys.argv[1], 9000)); s.listen(); print("ready", flush=True)
while True:
    c, _ = s.accept()
    c.sendall(c.recv(100)); c.close()
"""

PROBE = """
import socket, sys, time
t0 = time.monotonic()
try:
    c = socket.create_connection((sys.argv[1], 9000), timeout=float(sys.argv[2]))
    c.sendall(b"ping"); ok = c.recv(100) == b"ping"
except OSError:
    ok = False
print(("ok" if ok else "fail"), time.monotonic() - t0)
"""


def probe(h, host, address, timeout_s=1.0):
    """(reached, seconds) for a TCP round trip from `host` to the echo server at `address`."""
    out = subprocess.run(h.exec_argv(host, [sys.executable, "-c", PROBE, address, str(timeout_s)]),
                         capture_output=True, text=True, timeout=30).stdout.split()  # fmt: skip
    return out[0] == "ok", float(out[1])


def namespaces():
    return subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout


def test_hosts_reach_the_hub_only_and_faults_act_on_the_link(tmp_path):
    with hosts.Hosts(("robot", "think1"), logs=tmp_path) as h:
        echo = h.start(h.hub, [sys.executable, "-u", "-c", ECHO, "0.0.0.0"], "echo")
        h.start("think1", [sys.executable, "-u", "-c", ECHO, "0.0.0.0"], "echo1")
        time.sleep(1.0)
        hub = h.hub_address("robot")
        assert probe(h, "robot", hub)[0]
        assert not probe(h, "robot", h.address("think1"))[0]  # nothing is routed between links
        h.partition("robot")
        assert not probe(h, "robot", hub)[0]
        assert probe(h, "think1", h.hub_address("think1"))[0]  # only the robot's link is cut
        h.heal("robot")
        assert probe(h, "robot", hub)[0]
        h.impair("robot", loss=0.0, delay_ms=20.0, jitter_ms=10.0)
        reached, seconds = probe(h, "robot", hub, timeout_s=5.0)
        # connect and echo: at least two round trips, each >= 2 x 10 ms
        assert reached and seconds >= 0.04
        h.restore("robot")
        reached, seconds = probe(h, "robot", hub)
        assert reached and seconds < 0.04
        names = [h.ns(n) for n in ("router", "robot", "think1")]
        assert all(n in namespaces() for n in names)
        assert echo.poll() is None
    assert not any(n in namespaces() for n in names)
    assert echo.poll() is not None  # stopped by its PID


def test_hosts_are_removed_when_the_code_inside_fails(tmp_path):
    with pytest.raises(RuntimeError, match="inside"), hosts.Hosts(("robot",), logs=tmp_path) as h:
        proc = h.start("robot", [sys.executable, "-c", "import time; time.sleep(60)"], "sleeper")
        names = [h.ns("router"), h.ns("robot")]
        raise RuntimeError("inside")
    assert proc.poll() is not None
    assert not any(n in namespaces() for n in names)


def test_only_namespaces_of_owners_that_are_gone_are_swept(tmp_path):
    """A namespace of the project's name pattern was removed whenever no process had the PID in its
    name here: another tool's, or a live run's in another PID namespace, its processes killed."""
    import os

    foreign = f"{hosts.PREFIX}{os.urandom(4).hex()}"
    live, live_fd = hosts._new_owner()  # held here, as by a run elsewhere
    dead, dead_fd = hosts._new_owner()
    orphan, orphan_fd = hosts._new_owner()  # a run killed before its first namespace
    os.close(dead_fd)  # their owners died: the lock files are left, held by nobody
    os.close(orphan_fd)
    made = [f"{tag}-x" for tag in (foreign, live, dead)]
    try:
        for name in made:
            subprocess.run(["ip", "netns", "add", name], check=True, capture_output=True)
        swept = hosts.sweep_stale()
        assert f"{dead}-x" in swept and f"{dead}-x" not in namespaces()
        assert f"{foreign}-x" in namespaces() and f"{live}-x" in namespaces()
        assert not (hosts.OWNERS / f"{dead}.lock").exists() and not (hosts.OWNERS / f"{orphan}.lock").exists()
        assert (hosts.OWNERS / f"{live}.lock").exists()
    finally:
        for name in made:
            subprocess.run(["ip", "netns", "del", name], capture_output=True)
        hosts._disown(live, live_fd)


def test_a_sigterm_while_the_hosts_are_removed_stops_the_run_after_the_cleanup(tmp_path, monkeypatch):
    """It was logged and lost: a benchmark went on to its next case."""
    import os
    import signal

    from wfnn_io.cli_errors import Terminated

    with pytest.raises(Terminated), hosts.Hosts(("robot",)) as h:
        real = h._close
        monkeypatch.setattr(h, "_close", lambda: (os.kill(os.getpid(), signal.SIGTERM), real())[1])
        names = [h.ns("router"), h.ns("robot")]
    assert not any(n in namespaces() for n in names)
    assert signal.getsignal(signal.SIGTERM) is not hosts.terminate


HELD = """
import sys, time
from pathlib import Path
from wfnn_bench import hosts
with hosts.Hosts(("robot",)) as h:
    h.start("robot", [sys.executable, "-c", "import time; time.sleep(60)"])
    print(h.ns("robot"), flush=True)
    time.sleep(60)
"""


def test_sigterm_removes_the_hosts_and_stops_their_processes(tmp_path):
    """SIGTERM (a CI's cancel) ended the run with its namespaces and servers left running."""
    import signal
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    proc = subprocess.Popen([sys.executable, "-c", HELD], cwd=root, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        name = proc.stdout.readline().strip()
        assert name in namespaces()
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert name not in namespaces()
    tag = name.split("-")[0]
    assert not (hosts.OWNERS / f"{tag}.lock").exists()


SHORT = {"warmup_s": 4.0, "impair_s": 6.0, "partition_s": 5.0, "router_down_s": 3.0, "rate_limit_s": 8.0,
         "after_s": 8.0}  # fmt: skip


@pytest.mark.parametrize("case", ["b", "c", "d", "e", "f"])
def test_nothing_is_lost_and_the_tick_holds_across_hosts_under_a_fault(tmp_path, case):
    cfg = faults.FaultsBenchConfig(cases=(case,), **SHORT)
    got = faults.run_case(case, cfg, tmp_path / case)
    # The tick held through the fault (a HyDrA tick makes an experience only where it is learnable,
    # so ticks, not experiences, are counted here).
    assert got["ticks_during_fault"] >= 0.9 * cfg.rate_hz * cfg.fault_s(case)
    assert got["experiences_produced"] > 0
    assert got["experiences_lost"] == 0, got["experiences_stored"]
    assert got["overruns"] == 0
    # Every tick starts within half its period of its schedule, on a loaded 2-core CI machine too
    # (20.2 ms was seen there); the 2 ms figure is the benchmark's, on a quiet machine.
    assert got["tick_jitter_p99_ms"] < 500.0 / cfg.rate_hz
    assert got["learning_resumes_s"] is not None  # weights that learned after the fault reached the robot
    if case == "d":
        assert got["failovers"] and got["failovers"][0]["from"] == got["events"]["followed_at_fault"]
    if case == "f":
        assert got["experiences_missing_per_server"]["think2"] == 0  # the late server caught up
    if case in ("b", "c"):
        assert got["without_weights_s"] >= cfg.fault_s(case) - 0.5  # nothing reached the robot meanwhile


def test_in_lockstep_a_server_whose_link_goes_down_does_not_cut_the_robot_off_the_other(tmp_path):
    # Lock-step sends experiences as fast as the followed server learns, so the router's queue to
    # a server whose link went down fills within the lease; a send that blocks there held the
    # router's forwarding of the robot's experiences and status to the healthy server too, for
    # Zenoh's 5 s (the robot went 3.7 s without weights and dropped both servers).
    cfg = faults.FaultsBenchConfig(cases=("d",))
    with hosts.Hosts(("robot", "think1", "think2"), logs=tmp_path / "logs") as h:
        run = faults._Case("d", cfg, h, tmp_path)
        run.start_router()
        run.start_server("think1")
        run.start_server("think2")
        time.sleep(1.0)
        robot = h.start("robot", run.client_argv(30.0, lockstep=True), "robot")
        assert faults._wait_for(tmp_path / "logs" / "robot.log", r"following server", robot, 60.0)
        time.sleep(6.0)
        followed = run.followed()
        down = next(s for s in run.servers if s != followed)
        start = time.time()
        h.partition(down)
        time.sleep(10.0)
        end = time.time()
        h.heal(down)
        assert robot.wait(timeout=120) == 0
        for proc in run.servers.values():
            h.stop(proc)
    log = (tmp_path / "logs" / "robot.log").read_text()
    assert f"server {down} is gone" in log  # the fault was seen
    assert f"server {followed} is gone" not in log
    trace = json.loads((tmp_path / "robot.json").read_text())["trace"]
    applied = sorted(float(t) for t, server, _, _ in trace["snapshots_applied"] if server == followed)
    during = [t for t in applied if start - 1.0 <= t <= end]
    assert during and during[0] < start and during[-1] > end - 1.0
    assert max(b - a for a, b in itertools.pairwise(during)) < 2.0  # the healthy server's weights kept coming
