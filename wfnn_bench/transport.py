"""act-learn-think-C/S transport across processes on one machine (loopback Zenoh).

1. Throughput: this process (the client: `RemoteBrain`, journal included) produces N boat
   experiences as fast as it can; a `wfnn-server` process stores them (fsync interval) and
   acknowledges. experiences/s = N / (time until the last one is acknowledged); lost = N minus
   what the server's store holds afterwards (read from its files). The server does not think
   in this phase, so the figure is transport + store.
2. Real time: `wfnn-client`'s loop (in this process) runs the boat at 15 Hz against a server
   that thinks continuously (a busy server on the same two cores). Reported: tick lateness
   (jitter) and snapshot latency from publish on the server to applied in the client (one host,
   one clock), from every tick and every snapshot.
3. Outage: the same loop; the server is SIGKILLed mid-run and restarted a few seconds later.
   Reported: tick jitter while no server was reachable, and, counted by sequence numbers, how
   many experiences the client produced that are missing from the restarted server's store; of
   those, how many its journal still holds (sent again at its next start) and how many are lost
   (in neither).
"""

from __future__ import annotations

import json
import tempfile
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sims.boat import BoatVec
from wfnn_bench.common import Progress, check_seed, machine_info, no_progress
from wfnn_client.brain import Experience
from wfnn_client.config import ClientConfig
from wfnn_client.remote import RemoteBrain, RemoteConfig
from wfnn_client.run import run as run_client
from wfnn_common.config import LearnerConfig, check_fields
from wfnn_common.learner import WFNN
from wfnn_io.bus import NetConfig, ZenohBus
from wfnn_io.logs import read_batches
from wfnn_io.persist import save_figure
from wfnn_server.spawn import ServerProcess, free_port
from wfnn_server.store import ExperienceStore

CONTROLLER = "bench"
GOALS = {
    "experiences_per_s": (">=", 50_000.0),
    "experiences_lost": ("<=", 0.0),
    "snapshot_p99_ms": ("<=", 50.0),
    "tick_jitter_p99_ms": ("<=", 2.0),
}


@dataclass(frozen=True, kw_only=True)
class TransportBenchConfig:
    """Options of `wfnn-bench transport`."""

    experiences: int = 200_000
    """Experiences sent in the throughput phase."""
    batch_max: int = 256
    """Experiences per frame at most."""
    rate_hz: float = 15.0
    tick_seconds: float = 30.0
    """Length of the real-time phase."""
    busy_server: bool = True
    """The server thinks continuously during the real-time phase."""
    outage_seconds: float = 12.0
    """Length of the outage phase (0 skips it)."""
    outage_down_s: float = 3.0
    """How long the server stays dead."""
    seed: int = 0

    def __post_init__(self) -> None:
        check_fields(self)
        check_seed(self.seed)
        if not 1.0 <= self.rate_hz <= 1000.0:  # a tick the client keeps (as the faults bench's)
            raise ValueError(f"rate_hz must be in [1, 1000], got {self.rate_hz}")
        # The server is killed at 30% of the phase and restarted outage_down_s later; it needs a few
        # seconds to start and take the re-sends before the client stops. A shorter phase never
        # restarted it, and reported everything sent meanwhile as "missing after restart".
        shortest = (self.outage_down_s + RESTART_S) / 0.7
        if 0.0 < self.outage_seconds < shortest:
            raise ValueError(f"outage_seconds must be 0 (no outage phase) or at least {shortest:.1f} (the "
                             f"server is down {self.outage_down_s:g} s from 30% of it, then restarts), got "
                             f"{self.outage_seconds:g}")  # fmt: skip


RESTART_S = 3.0
"""What the outage phase leaves a restarted server to start and take the client's re-sends."""


def steps(cfg: TransportBenchConfig) -> int:
    """Progress units: thousands of experiences, then seconds of ticking."""
    return cfg.experiences // 1000 + int(cfg.tick_seconds) + int(cfg.outage_seconds)


def _wait(predicate: Any, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.002)
    return False


def throughput(
    cfg: TransportBenchConfig, work: Path, progress: Progress, shared_memory: bool = True
) -> dict[str, Any]:
    """Phase 1: experiences/s from this process into a server's store, and how many were lost.

    With shared_memory False, Zenoh moves every frame over TCP, as it would between hosts.
    """
    lcfg = LearnerConfig.for_task(BoatVec, thinks_per_action=0, seed=cfg.seed)
    (work / "learner.json").write_text(lcfg.to_json())
    port = free_port()
    tag = "shm" if shared_memory else "tcp"
    shm = ["--shared-memory"] if shared_memory else ["--no-shared-memory"]
    server = ServerProcess(work / f"srv1-{tag}", port, "--learner-config", str(work / "learner.json"), *shm,
                           controller=CONTROLLER).start()  # fmt: skip
    try:
        bus = ZenohBus(NetConfig(connect=(server.endpoint,), shared_memory=shared_memory))
        remote = RemoteConfig(
            controller=CONTROLLER, journal_dir=work / f"journal-{tag}", batch_max=cfg.batch_max
        )
        brain = RemoteBrain(WFNN(lcfg), remote, bus)
        brain.start()
    except BaseException:
        server.stop()
        raise
    try:
        if not _wait(lambda: brain.following != "", 30.0):
            raise TimeoutError("the server's weights never arrived")
        rng = np.random.default_rng(cfg.seed)
        n = cfg.experiences
        states = rng.uniform(-1, 1, (n + 1, lcfg.state_dim))
        actions = rng.uniform(-1, 1, (n, lcfg.action_dim))
        rewards = rng.uniform(-1, 0, n)
        first = brain.produced_through + 1
        t0 = time.perf_counter()
        for i in range(n):
            brain.learn(Experience(states[i], actions[i], states[i + 1], float(rewards[i])), None)
            if i % 1000 == 999:
                progress(1)
        produced_s = time.perf_counter() - t0
        last = first + n - 1
        done = _wait(lambda: brain.all_acked(), 300.0)
        acked_s = time.perf_counter() - t0
        if not done:
            raise TimeoutError(f"not every experience was acknowledged in 300 s (up to {last})")
    finally:
        brain.stop()  # closes the Zenoh session too (an open one would hold the process at exit)
        server.stop()
    store = ExperienceStore(work / f"srv1-{tag}" / "store", "check")
    held = store.stored_through.get(brain.id, -1) - first + 1
    store.close()
    return {
        "experiences": n,
        "experiences_per_s": n / acked_s,
        "experiences_lost": int(n - held),
        "produce_s": produced_s,
        "acknowledged_s": acked_s,
        "batches": int(brain.counters["uplink/batches"]),
        "resent_frames": int(brain.counters["uplink/resent_frames"]),
        "shared_memory": shared_memory,
    }


def realtime(cfg: TransportBenchConfig, work: Path, progress: Progress) -> dict[str, Any]:
    """Phase 2: tick jitter at rate_hz and snapshot latency with a busy server."""
    port = free_port()
    args = ["--think", "continuous"] if cfg.busy_server else []
    server = ServerProcess(work / "srv2", port, *args, controller=CONTROLLER).start()
    done = [0]

    def on_status(fields: dict[str, Any]) -> None:
        elapsed = int(fields["elapsed_s"])
        if elapsed > done[0]:
            progress(elapsed - done[0])
            done[0] = elapsed

    try:
        client = ClientConfig(
            sim="boat", episodes=10**6, duration_s=cfg.tick_seconds, rate_hz=cfg.rate_hz,
            server=(server.endpoint,), controller=CONTROLLER, out=work / "client", timing_trace=True,
            seed=cfg.seed,
        )  # fmt: skip
        metrics = run_client(client, on_status)
    finally:
        server.stop()
    progress(max(int(cfg.tick_seconds) - done[0], 0))
    trace = metrics["trace"]
    late = np.asarray(trace["tick_lateness_ms"])
    snap = np.asarray(trace["snapshot_latency_ms"])
    return {
        "ticks": int(late.size),
        "overruns": int(metrics["client/overruns"]),
        "safe_actions": int(metrics["client/safe_actions"]),
        "tick_jitter_p50_ms": float(np.percentile(late, 50)),
        "tick_jitter_p99_ms": float(np.percentile(late, 99)),
        "tick_jitter_max_ms": float(late.max()),
        "act_latency_p99_ms": float(np.percentile(trace["act_latency_ms"], 99)),
        "snapshots_applied": int(snap.size),
        "snapshot_p50_ms": float(np.percentile(snap, 50)) if snap.size else float("nan"),
        "snapshot_p99_ms": float(np.percentile(snap, 99)) if snap.size else float("nan"),
        "server_thinks_per_s": float(metrics.get("server/think/thinks_per_s", float("nan"))),
        "staleness_s_p50": float(metrics.get("weights/staleness_s_p50", float("nan"))),
        "tick_lateness_ms": late.tolist(),
        "snapshot_latency_ms": snap.tolist(),
    }


def outage(cfg: TransportBenchConfig, work: Path, progress: Progress) -> dict[str, Any]:
    """Phase 3: SIGKILL the server mid-run, restart it; jitter meanwhile and experiences missing."""
    port = free_port()
    server = ServerProcess(work / "srv3", port, "--checkpoint-period", "1", controller=CONTROLLER).start()
    client = ClientConfig(
        sim="boat", episodes=10**6, duration_s=cfg.outage_seconds, rate_hz=cfg.rate_hz,
        server=(server.endpoint,), controller=CONTROLLER, out=work / "client3", seed=cfg.seed,
    )  # fmt: skip
    stop, failed = threading.Event(), []

    def outage_now() -> None:
        try:
            if stop.wait(cfg.outage_seconds * 0.3):
                return
            server.kill()
            if not stop.wait(cfg.outage_down_s):
                server.start()
        except BaseException as exc:  # reported below, in the benchmark's thread
            failed.append(exc)

    # The client in this thread, the outage in a helper: Ctrl-C or SIGTERM reach the client's own
    # handlers, which end it at once (in a thread of its own it ran on, and wrote its files into
    # the temporary folder after that was removed).
    helper = threading.Thread(target=outage_now, name="wfnn-bench-outage")
    helper.start()
    try:
        metrics = run_client(client)
    finally:
        stop.set()
        helper.join(timeout=60)
        server.stop()
    progress(int(cfg.outage_seconds))
    if failed:
        raise RuntimeError("the server's restart failed during the outage phase") from failed[0]
    client_id = json.loads((work / "client3" / "journal" / "client.json").read_text())["client"]
    store = ExperienceStore(work / "srv3" / "store", "check")
    stored = store.stored_through.get(client_id, -1) + 1
    store.close()
    produced = int(metrics["uplink/produced_through"]) + 1
    journaled = journal_holds(work / "client3" / "journal", stored, produced)
    return {
        "down_s": cfg.outage_down_s,
        "outage_ticks": int(metrics["client/outage_ticks"]),
        "tick_jitter_p99_ms_during_outage": metrics["client/tick_jitter_ms_p99_outage"],
        "tick_jitter_p99_ms": float(metrics["client/tick_jitter_ms_p99"]),
        "overruns": int(metrics["client/overruns"]),
        "experiences_produced": produced,
        "experiences_stored": stored,
        "experiences_missing": produced - stored,
        "experiences_missing_in_journal": journaled,
        "experiences_missing_lost": produced - stored - journaled,
        "outages": metrics["outages"],
    }


def journal_holds(journal: Path, start: int, stop: int) -> int:
    """How many of experiences start..stop-1 a client's journal holds (read-only)."""
    held = np.zeros(max(stop - start, 0), dtype=bool)
    for batch in read_batches(journal):
        lo, hi = max(batch.first_seq, start), min(batch.last_seq + 1, stop)
        if lo < hi:
            held[lo - start : hi - start] = True
    return int(held.sum())


def run(cfg: TransportBenchConfig, progress: Progress = no_progress) -> dict[str, Any]:
    """Both phases; the figures the issue asks for at the top level, details per phase."""
    with tempfile.TemporaryDirectory(prefix="wfnn-transport-") as tmp:
        work = Path(tmp)
        t0 = time.perf_counter()
        phase1 = throughput(cfg, work, progress)
        tcp = throughput(cfg, work, no_progress, shared_memory=False)
        phase2 = realtime(cfg, work, progress)
        phase3 = outage(cfg, work, progress) if cfg.outage_seconds > 0 else None
        wall = time.perf_counter() - t0
    result: dict[str, Any] = {
        "benchmark": "transport",
        "config": asdict(cfg),
        "machine": machine_info(),
        "experiences_per_s": phase1["experiences_per_s"],
        "experiences_lost": phase1["experiences_lost"] + tcp["experiences_lost"],
        "experiences_per_s_tcp": tcp["experiences_per_s"],
        "snapshot_p50_ms": phase2["snapshot_p50_ms"],
        "snapshot_p99_ms": phase2["snapshot_p99_ms"],
        "tick_jitter_p99_ms": phase2["tick_jitter_p99_ms"],
        "outage_tick_jitter_p99_ms": phase3["tick_jitter_p99_ms_during_outage"] if phase3 else None,
        "outage_experiences_missing": phase3["experiences_missing"] if phase3 else None,
        "outage_experiences_lost": phase3["experiences_missing_lost"] if phase3 else None,
        "throughput": phase1,
        "throughput_tcp": tcp,
        "realtime": phase2,
        "outage": phase3,
        "wall_s": wall,
    }
    result["goals"] = {
        name: {
            "goal": f"{op} {bound:g}",
            "met": bool(result[name] >= bound if op == ">=" else result[name] <= bound),
        }
        for name, (op, bound) in GOALS.items()
    }
    return result


def plot(result: dict[str, Any], path: Path) -> None:
    """Tick lateness and snapshot latency distributions (log-scale counts)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rt = result["realtime"]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, key, title, goal in (
        (
            axes[0],
            "tick_lateness_ms",
            f"tick lateness at {result['config']['rate_hz']:g} Hz, busy server",
            2.0,
        ),
        (axes[1], "snapshot_latency_ms", "snapshot publish -> applied", 50.0),
    ):
        values = np.asarray(rt[key])
        ax.hist(values, bins=60, color="tab:blue")
        ax.axvline(float(np.percentile(values, 99)) if values.size else 0.0, color="k", ls="--", label="p99")
        ax.axvline(goal, color="tab:red", ls=":", label=f"goal {goal:g} ms")
        ax.set_yscale("log")
        ax.set_xlabel("ms")
        ax.set_title(title)
        ax.legend()
    fig.suptitle(
        f"{result['experiences_per_s']:,.0f} experiences/s client -> server store, "
        f"{result['experiences_lost']} lost"
    )
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)


def _in_journal_and_lost(outage: dict[str, Any] | None) -> str:
    if outage is None:
        return "-"
    return f"{outage['experiences_missing_in_journal']} / {outage['experiences_missing_lost']}"


def rows(result: dict[str, Any], cfg: TransportBenchConfig) -> list[tuple[str, Any]]:
    """The figures of `wfnn-bench transport`'s table: (name, value) rows."""
    rows: list[tuple[str, Any]] = [
        (k, result[k])
        for k in (
            "experiences_per_s",
            "experiences_lost",
            "snapshot_p50_ms",
            "snapshot_p99_ms",
            "tick_jitter_p99_ms",
        )
    ]
    rt = result["realtime"]
    rows += [
        ("experiences_per_s over TCP (no shared memory)", result["experiences_per_s_tcp"]),
        ("tick_jitter_p50_ms", rt["tick_jitter_p50_ms"]),
        ("tick_jitter_max_ms", rt["tick_jitter_max_ms"]),
        ("ticks / overruns / safe actions", f"{rt['ticks']} / {rt['overruns']} / {rt['safe_actions']}"),
        ("snapshots applied", rt["snapshots_applied"]),
        ("server thinks/s while ticking", rt["server_thinks_per_s"]),
        ("outage: tick jitter p99 ms (server dead)", result["outage_tick_jitter_p99_ms"]),
        ("outage: experiences missing after restart", result["outage_experiences_missing"]),
        ("outage: of them in the journal / lost", _in_journal_and_lost(result["outage"])),
        ("wall_s", result["wall_s"]),
    ]
    rows += [(f"goal {k} {g['goal']}", "met" if g["met"] else "NOT met") for k, g in result["goals"].items()]
    return rows
