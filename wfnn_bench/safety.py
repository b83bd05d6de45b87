"""What survives damage, restarts and attacks: real `wfnn-client` / `wfnn-server` processes.

1. Damaged logs. A boat run's journal is damaged two ways, a torn tail (the last record cut
   short, as a client killed mid-append leaves it) and 8 bytes overwritten 2,000 bytes in; on
   each, `wfnn-logs inspect` and `wfnn-server --replay-only` run. Reported: bytes of the log
   the tools changed (compared byte by byte with a copy taken before), and experiences
   recovered of those the log held.
2. A server restarted empty. A robot at 30 Hz streams to a server that is killed after a few
   seconds; another starts under the same id and port with an empty data directory.
   Reported: experiences the robot produced, and how many the new server's store holds.
3. A token and query storm, key on. An attacker without the key declares 30 server liveliness
   tokens and a queryable on every weights key that never answers, while a keyed robot follows
   a keyed server. Reported: the longest stretch without newly applied weights.
4. Huge frames. Eight frames of 40 MB (past what Zenoh reassembles here) and eight of 30 MB
   (past what the robot copies) on the weights key of a robot ticking at 50 Hz. Reported:
   overruns and tick lateness.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from wfnn_bench.common import Progress, check_seed, machine_info, no_progress
from wfnn_common.config import check_fields
from wfnn_io import logs
from wfnn_io.bus import Channel, NetConfig, ZenohBus
from wfnn_io.persist import save_figure
from wfnn_io.protocol import Codec, Keys, ServerStatus
from wfnn_server.spawn import ServerProcess, free_port

CONTROLLER = "bench"
BIN = Path(sys.executable).parent
GOALS = {
    "logs_bytes_changed": ("<=", 0.0),
    "restart_experiences_missing": ("<=", 0.0),
    "storm_longest_without_weights_s": ("<=", 1.0),
    "huge_frames_overruns": ("<=", 0.0),
}


@dataclass(frozen=True, kw_only=True)
class SafetyBenchConfig:
    """Options of `wfnn-bench safety`."""

    episodes: int = 4
    """Boat episodes recorded for the damaged-log phase (200 experiences each)."""
    restart_seconds: float = 12.0
    """Length of the restart phase (the server is killed a third of the way in)."""
    storm_seconds: float = 10.0
    """Length of the token-storm phase (the storm starts after 3 s)."""
    frames_seconds: float = 10.0
    """Length of each huge-frame phase (the frames arrive after 3 s)."""
    seed: int = 0

    def __post_init__(self) -> None:
        check_fields(self)
        check_seed(self.seed)
        if self.episodes < 1 or min(self.restart_seconds, self.storm_seconds, self.frames_seconds) < 6:
            raise ValueError("episodes must be >= 1 and each phase at least 6 s long")


def steps(cfg: SafetyBenchConfig) -> int:
    """Progress units: one per phase."""
    return 5


def _run(*args: Any, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "COLUMNS": "160"}
    return subprocess.run([str(a) for a in args], capture_output=True, text=True, timeout=timeout, env=env)


def _client(*args: Any) -> subprocess.Popen[str]:
    cmd = [str(BIN / "wfnn-client"), "--controller", CONTROLLER, *map(str, args)]
    env = {**os.environ, "COLUMNS": "160"}
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)


def _finish(proc: subprocess.Popen[str], timeout: float = 120) -> None:
    out, _ = proc.communicate(timeout=timeout)
    if proc.returncode != 0:
        raise RuntimeError(f"wfnn-client failed: {out[-2000:]}")


@contextlib.contextmanager
def _attacked(port: int, *client_args: Any) -> Iterator[ZenohBus]:
    """A robot (`wfnn-client` with `client_args`) following the server on `port`, and an attacker.

    The attacker's session connects to the same router; on leaving, the robot's run is waited for.
    """
    proc = _client(*client_args, "--server", f"tcp/127.0.0.1:{port}")
    rogue = ZenohBus(NetConfig(connect=(f"tcp/127.0.0.1:{port}",)))
    try:
        yield rogue
        _finish(proc)
    finally:
        rogue.close()
        if proc.poll() is None:
            proc.kill()


def _bytes_changed(before: dict[str, bytes], directory: Path) -> int:
    """Bytes that differ from `before` (a file gone counts whole; new files, e.g. none, too)."""
    after = {str(p.relative_to(directory)): p.read_bytes() for p in directory.rglob("*") if p.is_file()}
    changed = 0
    for name in before.keys() | after.keys():
        a, b = before.get(name, b""), after.get(name, b"")
        changed += abs(len(a) - len(b)) + sum(x != y for x, y in zip(a, b, strict=False))
    return changed


def _snapshot(directory: Path) -> dict[str, bytes]:
    return {str(p.relative_to(directory)): p.read_bytes() for p in directory.rglob("*") if p.is_file()}


def damaged_logs(cfg: SafetyBenchConfig, work: Path) -> dict[str, Any]:
    """Phase 1: the tools on a journal with a torn tail and one damaged in the middle."""
    rec = work / "rec"
    proc = _run(BIN / "wfnn-client", "--sim", "boat", "--episodes", cfg.episodes, "--rate-hz", "0",
                "--lockstep", "--thinks", "3", "--seed", cfg.seed, "--out", rec)  # fmt: skip
    if proc.returncode != 0:
        raise RuntimeError(f"recording failed: {proc.stdout[-2000:]}{proc.stderr[-2000:]}")
    total = logs.summarise(rec / "journal").experiences
    out: dict[str, Any] = {"experiences": total}
    for case in ("torn_tail", "middle"):
        journal = work / case
        shutil.copytree(rec / "journal", journal)
        seg = journal / "00000000.seg"
        raw = bytearray(seg.read_bytes())
        if case == "torn_tail":
            raw = raw[:-100]  # the last record cut short
        else:
            raw[2000:2008] = bytes([0xA5]) * 8
        seg.write_bytes(bytes(raw))
        before = _snapshot(journal)
        inspect = _run(BIN / "wfnn-logs", "inspect", "--json", journal)
        if inspect.returncode != 0:
            raise RuntimeError(f"inspect failed: {inspect.stdout}{inspect.stderr}")
        summary = json.loads(inspect.stdout)
        changed_inspect = _bytes_changed(before, journal)
        data = work / f"srv-{case}"
        replay = _run(BIN / "wfnn-server", "--id", "srv", "--controller", CONTROLLER, "--quiet",
                      "--listen", f"tcp/127.0.0.1:{free_port()}", "--data-dir", data,
                      "--replay-only", journal)  # fmt: skip
        imported = logs.summarise(data / "store").experiences if replay.returncode == 0 else 0
        out[case] = {
            "inspect_exit": inspect.returncode, "inspect_experiences": summary["experiences"],
            "damage": summary["damage"], "inspect_bytes_changed": changed_inspect,
            "replay_exit": replay.returncode, "replay_experiences": imported,
            "replay_bytes_changed": _bytes_changed(before, journal),
        }  # fmt: skip
    return out


def restart_empty(cfg: SafetyBenchConfig, work: Path) -> dict[str, Any]:
    """Phase 2: the followed server killed and restarted empty under the same id and port."""
    port = free_port()
    stats, out = work / "restart.json", work / "restart-client"
    first = ServerProcess(work / "restart-a", port, controller=CONTROLLER).start()
    proc = _client("--sim", "positioning", "--episodes", 100_000, "--duration", cfg.restart_seconds,
                   "--rate-hz", 30, "--server", f"tcp/127.0.0.1:{port}", "--out", out,
                   "--json-stats", stats)  # fmt: skip
    try:
        time.sleep(cfg.restart_seconds / 3)
        first.kill()
        with ServerProcess(work / "restart-b", port, controller=CONTROLLER):
            _finish(proc)
            time.sleep(0.5)
    finally:
        first.stop()
        if proc.poll() is None:
            proc.kill()
    result = json.loads(stats.read_text())
    produced = int(result["uplink/produced_through"]) + 1
    client_id = json.loads((out / "journal" / "client.json").read_text())["client"]
    summary = logs.summarise(work / "restart-b" / "store")
    held = summary.clients[client_id].experiences if client_id in summary.clients else 0
    return {"produced": produced, "stored_by_new_server": held, "missing": produced - held,
            "following": result["following"]}  # fmt: skip


def token_storm(cfg: SafetyBenchConfig, work: Path) -> dict[str, Any]:
    """Phase 3: 30 fake server tokens and a weights queryable that never answers, key on."""
    port = free_port()
    key = work / "key"
    key.write_text("0123456789abcdef0123456789abcdef")
    stats = work / "storm.json"
    keys = Keys(CONTROLLER)
    with ServerProcess(work / "storm-srv", port, "--key-file", str(key), controller=CONTROLLER):
        with _attacked(port, "--sim", "positioning", "--episodes", 100_000, "--duration", cfg.storm_seconds,
                       "--rate-hz", 30, "--key-file", key, "--out", work / "storm-client",
                       "--json-stats", stats) as rogue:  # fmt: skip
            time.sleep(3.0)
            rogue.queryable(keys.weights("**"), lambda: None)  # never replies: each query waits it out
            for i in range(30):
                rogue.declare_token(keys.server_alive(f"fake{i:02d}"))
            forged = ServerStatus(server="fake00", incarnation=1, store="fake", started_ns=1, spec_hash="",
                                  learner_config="",
                                  weights_version=0, stored_through={}, rejected={}, metrics={})  # fmt: skip
            deadline = time.monotonic() + cfg.storm_seconds - 4.0
            while time.monotonic() < deadline:  # unsigned statuses of a fake server, twice a second
                rogue.put(keys.server_status("fake00"), Codec("fake00").encode(forged), Channel.LATEST)
                time.sleep(0.5)
    result = json.loads(stats.read_text())
    return {
        "longest_without_weights_s": result["downlink/longest_without_weights_s"],
        "weightless_stretches": result.get("downlink/weightless_stretches", 0.0),
        "snapshots_applied_p50_latency_ms": result.get("downlink/snapshot_latency_ms_p50"),
        "rejected_status_auth": result.get("downlink/rejected_status_auth", 0.0),
        "following": result["following"],
    }


def huge_frames(cfg: SafetyBenchConfig, work: Path, megabytes: int) -> dict[str, Any]:
    """Phase 4: eight frames of `megabytes` MB on the weights key of a robot at 50 Hz."""
    port = free_port()
    stats = work / f"frames{megabytes}.json"
    keys = Keys(CONTROLLER)
    with ServerProcess(work / f"frames{megabytes}-srv", port, controller=CONTROLLER):
        with _attacked(port, "--sim", "boat", "--episodes", 100_000, "--duration", cfg.frames_seconds,
                       "--rate-hz", 50, "--out", work / f"frames{megabytes}-client",
                       "--json-stats", stats) as rogue:  # fmt: skip
            time.sleep(3.0)
            frame = b"WFNN" + bytes((megabytes << 20) - 4)
            t0 = time.monotonic()
            for _ in range(8):
                rogue.put(keys.weights("srv"), frame, Channel.DATA)
            sent_s = time.monotonic() - t0
    result = json.loads(stats.read_text())
    return {
        "megabytes": megabytes, "frames": 8, "send_s": sent_s,
        "overruns": result["client/overruns"], "tick_jitter_p99_ms": result["client/tick_jitter_ms_p99"],
        "tick_jitter_max_ms": result["client/tick_jitter_ms_max"], "ticks": result["ticks"],
        "oversized_dropped_by_client": result.get("downlink/oversized_weights", 0.0),
        "longest_without_weights_s": result["downlink/longest_without_weights_s"],
    }  # fmt: skip


def run(cfg: SafetyBenchConfig, progress: Progress = no_progress) -> dict[str, Any]:
    """Every phase; returns the JSON-ready result."""
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="wfnn-safety-") as tmp:
        work = Path(tmp)
        damaged = damaged_logs(cfg, work)
        progress(1)
        restart = restart_empty(cfg, work)
        progress(1)
        storm = token_storm(cfg, work)
        progress(1)
        frames = [huge_frames(cfg, work, mb) for mb in (40, 30)]
        progress(2)
    tools = ("inspect_bytes_changed", "replay_bytes_changed")
    changed = sum(damaged[c][k] for c in ("torn_tail", "middle") for k in tools)
    figures = {
        "logs_bytes_changed": float(changed),
        "restart_experiences_missing": float(restart["missing"]),
        "storm_longest_without_weights_s": float(storm["longest_without_weights_s"]),
        "huge_frames_overruns": float(sum(f["overruns"] for f in frames)),
    }
    goals = {}
    for name, (op, bound) in GOALS.items():
        met = figures[name] <= bound if op == "<=" else figures[name] >= bound
        goals[name] = {"goal": f"{op} {bound:g}", "value": figures[name], "met": bool(met)}
    return {
        "benchmark": "safety", "config": asdict(cfg), "machine": machine_info(),
        "damaged_logs": damaged, "restart_empty": restart, "token_storm": storm, "huge_frames": frames,
        **figures, "goals": goals, "wall_s": time.perf_counter() - t0,
    }  # fmt: skip


def plot(result: dict[str, Any], path: Path) -> None:
    """Four panels: recovered experiences, the restarted server's store, the storm, huge frames."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(16, 4))
    d = result["damaged_logs"]
    names = ["torn tail\ninspect", "torn tail\nreplay", "middle\ninspect", "middle\nreplay"]
    values = [d["torn_tail"]["inspect_experiences"], d["torn_tail"]["replay_experiences"],
              d["middle"]["inspect_experiences"], d["middle"]["replay_experiences"]]  # fmt: skip
    axes[0].bar(names, values, color="tab:blue")
    axes[0].axhline(d["experiences"], color="k", ls="--", label="in the log")
    axes[0].set_title(f"damaged logs: experiences read\n(bytes changed {result['logs_bytes_changed']:.0f})")
    axes[0].legend(loc="lower right")
    r = result["restart_empty"]
    axes[1].bar(["produced", "stored by the\nnew empty server"], [r["produced"], r["stored_by_new_server"]],
                color=["tab:gray", "tab:green"])  # fmt: skip
    axes[1].set_title("server restarted empty, same id")
    s = result["token_storm"]
    axes[2].bar(["longest without\nnew weights"], [s["longest_without_weights_s"]], color="tab:orange")
    axes[2].axhline(1.0, color="r", ls="--", label="goal 1 s")
    axes[2].set_ylabel("s")
    axes[2].set_title("30 fake tokens + a silent queryable")
    axes[2].legend()
    frames = result["huge_frames"]
    labels = [f"{f['megabytes']} MB x{f['frames']}" for f in frames]
    x = range(len(frames))
    axes[3].bar([i - 0.2 for i in x], [f["tick_jitter_p99_ms"] for f in frames], 0.4, label="jitter p99 (ms)")
    axes[3].bar([i + 0.2 for i in x], [f["tick_jitter_max_ms"] for f in frames], 0.4, label="jitter max (ms)")
    axes[3].axhline(20.0, color="r", ls="--", label="period (50 Hz)")
    axes[3].set_xticks(list(x), labels)
    axes[3].set_title(f"huge frames at 50 Hz: {result['huge_frames_overruns']:.0f} overruns")
    axes[3].legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)


def rows(result: dict[str, Any], cfg: SafetyBenchConfig) -> list[tuple[str, Any]]:
    """The figures of `wfnn-bench safety`'s table: (name, value) rows."""
    d = result["damaged_logs"]
    rows: list[tuple[str, Any]] = [("experiences in the recorded log", d["experiences"])]
    for case in ("torn_tail", "middle"):
        c = d[case]
        rows += [
            (f"{case}: read by inspect / imported by replay-only",
             f"{c['inspect_experiences']} / {c['replay_experiences']}"),
            (f"{case}: bytes changed by inspect / replay-only",
             f"{c['inspect_bytes_changed']} / {c['replay_bytes_changed']}"),
        ]  # fmt: skip
    r, s = result["restart_empty"], result["token_storm"]
    rows += [
        (
            "restart empty: produced / stored by the new server",
            f"{r['produced']} / {r['stored_by_new_server']}",
        ),
        ("token storm: longest without new weights (s)", s["longest_without_weights_s"]),
        ("token storm: unsigned statuses refused", s["rejected_status_auth"]),
    ]
    for f in result["huge_frames"]:
        rows.append((f"{f['megabytes']} MB frames x{f['frames']} at 50 Hz: overruns, jitter p99 / max (ms)",
                     f"{f['overruns']:.0f}, {f['tick_jitter_p99_ms']:.2f} / "
                     f"{f['tick_jitter_max_ms']:.2f}"))  # fmt: skip
    rows += [(f"goal {k} {g['goal']}", "met" if g["met"] else "NOT met") for k, g in result["goals"].items()]
    rows.append(("wall_s", result["wall_s"]))
    return rows
