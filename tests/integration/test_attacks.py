"""Real processes on loopback under the faults and attacks of the data-safety issue.

A server restarted empty under the same id, frames far larger than any snapshot on the weights
key, and the command-line tools reading damaged logs: what survives, what the robot's tick
makes of it, and that reading changes nothing.
"""

import json
import time

import pytest

from tests.integration.procs import ServerProcess, client, endpoint, finish, free_port
from tests.mounts import files
from wfnn_io.bus import Channel, NetConfig, ZenohBus
from wfnn_io.protocol import Keys
from wfnn_server.store import ExperienceStore

pytestmark = [pytest.mark.slow, pytest.mark.multiprocess]
KEYS = Keys("it")


def stored(store_dir, client_id):
    store = ExperienceStore(store_dir, "check")
    try:
        return store.stored_through.get(client_id, -1), store.count
    finally:
        store.close()


def _streaming_client(port, tmp_path):
    """A client streaming the positioning task at 30 Hz for 10 s to the server on `port`, after
    4 s of it; -> the client's process."""
    proc = client("--sim", "positioning", "--episodes", "1000", "--duration", "10", "--rate-hz", "30",
                  "--server", endpoint(port), "--out", str(tmp_path / "c"),
                  "--json-stats", str(tmp_path / "stats.json"))  # fmt: skip
    time.sleep(4.0)
    return proc


def _produced(tmp_path):
    """The finished client's figures, the last experience it produced and its id."""
    result = json.loads((tmp_path / "stats.json").read_text())
    client_id = json.loads((tmp_path / "c" / "journal" / "client.json").read_text())["client"]
    return result, int(result["uplink/produced_through"]), client_id


def test_a_server_restarted_empty_under_the_same_id_ends_with_every_experience(tmp_path):
    port = free_port()
    first = ServerProcess(tmp_path / "a", port).start()
    try:
        proc = _streaming_client(port, tmp_path)
        first.kill()
        # The same id and port, a new empty data directory: incarnation 1 again, another store.
        with ServerProcess(tmp_path / "b", port):
            finish(proc, timeout=60)
            time.sleep(0.5)
    finally:
        first.stop()
    result, produced, client_id = _produced(tmp_path)
    assert produced > 200
    assert stored(tmp_path / "b" / "store", client_id) == (produced, produced + 1)
    assert result["following"] == "srv"


def test_a_hole_damage_left_in_a_servers_store_is_re_sent_by_the_client(tmp_path):
    """Acknowledged experiences damaged on the server's disk: the restarted server asks for them
    (its acks stop before the hole) and the client's journal re-sends them."""
    from wfnn_io.segments import read_records

    port = free_port()
    server = ServerProcess(tmp_path / "a", port).start()
    try:
        proc = _streaming_client(port, tmp_path)
        # Records enough that one in the middle can be damaged (a slow start streams fewer in 4 s,
        # and damage to the last record is a torn tail, not a hole).
        deadline = time.monotonic() + 60
        while len(list(read_records(tmp_path / "a" / "store"))) < 4 and time.monotonic() < deadline:
            time.sleep(0.2)
        server.stop()
        records = list(read_records(tmp_path / "a" / "store"))
        assert len(records) >= 4
        (segment,) = sorted((tmp_path / "a" / "store").glob("*.seg"))
        raw = bytearray(segment.read_bytes())
        position, frame = records[len(records) // 2]  # a record with records after it
        middle = position.offset + len(frame) // 2
        raw[middle : middle + 3] = bytes(b ^ 0xFF for b in raw[middle : middle + 3])
        segment.write_bytes(bytes(raw))
        store = ExperienceStore(tmp_path / "a" / "store", "check")
        damaged = store.missing()
        store.close()
        assert damaged > 0
        with ServerProcess(tmp_path / "a", port):
            finish(proc, timeout=60)
            time.sleep(0.5)
    finally:
        server.stop()
    _, produced, client_id = _produced(tmp_path)
    store = ExperienceStore(tmp_path / "a" / "store", "check")
    try:
        assert store.holes == {} and store.lost == {}
        assert (store.stored_through.get(client_id), store.count) == (produced, produced + 1)
    finally:
        store.close()


@pytest.mark.parametrize("megabytes", [40, 30])
def test_huge_frames_on_the_weights_key_never_delay_the_tick(tmp_path, megabytes):
    """Eight frames of 40 MB (past what Zenoh reassembles) or 30 MB (past what the client copies)."""
    port = free_port()
    stats = tmp_path / "stats.json"
    with ServerProcess(tmp_path / "srv", port):
        proc = client("--sim", "boat", "--episodes", "1000", "--duration", "8", "--rate-hz", "50",
                      "--server", endpoint(port), "--out", str(tmp_path / "c"),
                      "--json-stats", str(stats))  # fmt: skip
        rogue = ZenohBus(NetConfig(connect=(endpoint(port),)))
        try:
            time.sleep(3.0)
            frame = b"WFNN" + bytes((megabytes << 20) - 4)
            for _ in range(8):
                rogue.put(KEYS.weights("srv"), frame, Channel.DATA)
        finally:
            rogue.close()
        finish(proc, timeout=60)
    result = json.loads(stats.read_text())
    # 0 in every run here (and `wfnn-bench safety`); one late tick is allowed for a busy CI machine,
    # where 748d969 had six.
    assert result["client/overruns"] <= 1
    assert result["following"] == "srv" and result["downlink/longest_without_weights_s"] < 1.0
    # None was decoded (a snapshot that beat its server's first status may be "unannounced").
    rejected = {k for k, v in result.items() if k.startswith("downlink/rejected_") and v}
    assert rejected <= {"downlink/rejected_unannounced", "downlink/rejected_stale"}, rejected


def _run(*args, timeout=180):
    import os
    import subprocess

    env = {**os.environ, "COLUMNS": "160"}
    return subprocess.run([str(a) for a in args], capture_output=True, text=True, timeout=timeout, env=env)


def _record(out):
    from tests.integration.procs import BIN

    proc = _run(BIN / "wfnn-client", "--sim", "boat", "--episodes", "2", "--rate-hz", "0", "--lockstep",
                "--thinks", "3", "--out", out)  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_the_tools_read_damaged_logs_without_changing_a_byte(tmp_path):
    from tests.integration.procs import BIN

    _record(tmp_path / "rec")
    journal = tmp_path / "rec" / "journal"
    seg = journal / "00000000.seg"
    raw = bytearray(seg.read_bytes())
    raw[2000:2008] = b"\xa5" * 8  # 8 bytes overwritten 2,000 bytes in
    seg.write_bytes(bytes(raw) + b"torn tail of a record")
    before = files(journal)
    proc = _run(BIN / "wfnn-logs", "inspect", "--json", journal)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert [d["kind"] for d in summary["damage"]] == ["corrupt", "tail"]
    assert 400 - 256 <= summary["experiences"] < 400  # one batch (of up to 256) lost of 400
    proc = _run(BIN / "wfnn-server", "--id", "srv", "--controller", "it", "--listen", endpoint(free_port()),
                "--data-dir", tmp_path / "d", "--quiet", "--replay-only", journal)  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert files(journal) == before
    client_id = json.loads((journal / "client.json").read_text())["client"]
    assert stored(tmp_path / "d" / "store", client_id) == (399, summary["experiences"])
    # A keyed client's journal read with a wrong key: every record refused, nothing imported,
    # and a nonzero exit that says why.
    from tests.fakes import small_config
    from tests.unit.test_data_safety import journal as keyed_journal

    keyed_journal(tmp_path / "keyed", small_config(), key=b"k" * 32)
    (tmp_path / "wrong").write_text("w" * 32)
    proc = _run(BIN / "wfnn-server", "--id", "s2", "--controller", "it", "--listen", endpoint(free_port()),
                "--data-dir", tmp_path / "d2", "--quiet", "--key-file", tmp_path / "wrong",
                "--replay-only", tmp_path / "keyed")  # fmt: skip
    assert proc.returncode == 2 and "refused: 20 auth" in proc.stdout + proc.stderr
    assert "Traceback" not in proc.stdout + proc.stderr
