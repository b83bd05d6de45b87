"""What the dashboard costs the think server (`wfnn-bench dashboard`).

A think server serves a robot learning in real time (the main job: HyDrA, 1-DOF visual servoing
at 15 Hz, `wfnn-client` in another process); the server's CPU time is read from /proc over a
window after a warm-up, with the dashboard off and with it on and watched the way the page
watches it (one server-sent-events stream, `update_hz` views a second). Runs alternate off/on
`repeats` times.

Figures:
- `added_fraction_attributed`: CPU time the dashboard's own threads spent (counted by the
  dashboard: request handling, JSON, the action-value surface, sampling) over the server's
  other CPU time in the same window. This is the criterion's measure (< 5%): it does not
  depend on run-to-run noise.
- `added_fraction_ab`: server CPU per stored experience, on vs off, minus 1 (medians over the
  repeats): includes effects outside the dashboard's threads (e.g. the GIL), and noise.
"""

from __future__ import annotations

import http.client
import json
import logging
import os
import subprocess
import tempfile
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from wfnn_bench.common import Progress, machine_info, no_progress
from wfnn_common.config import check_fields
from wfnn_io.persist import save_figure
from wfnn_server.spawn import BIN, ServerProcess, free_port, wait_listening

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class DashboardBenchConfig:
    """One benchmark run."""

    seconds: float = 60.0
    """Measured window per run."""
    warmup_s: float = 15.0
    """Before the window: the server starts, the robot connects, learning starts."""
    repeats: int = 2
    """Off/on pairs."""
    update_hz: float = 4.0
    """View updates per second on the stream the benchmark watches (the page's default)."""
    rate_hz: float = 15.0
    """The robot's control rate."""
    think: str = "budget"
    """The server's thinking (`wfnn-server --think`): `budget` (the main job's: thinks_per_action
    per experience, then idle: a light server) or `continuous` (replaying whenever idle: a busy one)."""

    def __post_init__(self) -> None:
        check_fields(self)


def steps(cfg: DashboardBenchConfig) -> int:
    """Progress units: one per run."""
    return 2 * cfg.repeats


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process so far."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


SURFACE_WAIT_S = 60.0
"""How long past the warm-up a measuring window waits for the dashboard's first surface."""


class _Watcher:
    """Watches the dashboard like the page: a server-sent-events stream, read in a thread.

    Where one ends, another begins at once, as the page does (a stream lasts `dashboard.STREAM_S`).
    """

    def __init__(self, port: int) -> None:
        self.port = port
        self.closed = False
        self.connection, self.response = self._connect()
        self.latest: dict[str, Any] = {}
        self.messages = 0
        self.bytes = 0
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _connect(self) -> tuple[http.client.HTTPConnection, http.client.HTTPResponse]:
        connection = http.client.HTTPConnection("127.0.0.1", self.port, timeout=10)
        connection.request("GET", "/api/stream")
        return connection, connection.getresponse()

    def _read(self) -> None:
        try:
            while True:
                for line in self.response:
                    if line.startswith(b"data: "):
                        self.latest = json.loads(line[6:])
                        self.messages += 1
                        self.bytes += len(line)
                if self.closed:
                    return
                self.connection.close()
                self.connection, self.response = self._connect()
        except (OSError, ValueError, http.client.HTTPException):  # the server stopped
            return

    def wait_for_surface(self, timeout_s: float) -> None:
        """Wait until the view has drawn its action-value surface, and one message more.

        Its first drawing compiles the grid's kernel (seconds of the dashboard's CPU): inside the
        window, counted by the dashboard as of a message sent after the window began but charged by
        /proc before it, it made the dashboard seem to cost more than the whole server.
        """
        deadline = time.monotonic() + timeout_s
        while self.latest.get("surface") is None and time.monotonic() < deadline:
            time.sleep(0.05)
        if self.latest.get("surface") is None:
            log.warning("the dashboard drew no action-value surface within %.0f s of the warm-up: the window "
                        "may hold its first drawing's compile", timeout_s)  # fmt: skip
        seen = self.messages
        while self.messages == seen and time.monotonic() < deadline + 5.0:
            time.sleep(0.01)

    def dashboard_cpu_s(self) -> float:
        """The dashboard's own CPU seconds, as of its newest message."""
        return float(self.latest.get("cpu", {}).get("dashboard_s", 0.0))

    def close(self) -> None:
        self.closed = True
        self.connection.close()


def _stored(server: ServerProcess) -> int:
    """Experiences in the server's store, read from its log files (the same way on and off)."""
    from wfnn_io.logs import summarise

    return summarise(server.data_dir / "store").experiences


def _one(cfg: DashboardBenchConfig, on: bool, work: Path) -> dict[str, Any]:
    port, web = free_port(), free_port()
    args = (
        "--think",
        cfg.think,
        *(("--dashboard", str(web), "--dashboard-hz", str(cfg.update_hz)) if on else ()),
    )
    run_dir = work / f"{'on' if on else 'off'}-{port}"
    with ServerProcess(run_dir / "server", port, *args, server_id="bench") as server:
        assert server.proc is not None
        duration = cfg.warmup_s + cfg.seconds + 10.0
        robot = subprocess.Popen(
            [str(BIN / "wfnn-client"), "--sim", "hydra", "--rate-hz", str(cfg.rate_hz), "--episodes", "1000",
             "--duration", str(duration), "--server", server.endpoint, "--out", str(run_dir / "client")],
            stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT,
        )  # fmt: skip
        try:
            watcher = None
            if on:
                wait_listening(web)
                watcher = _Watcher(web)
            time.sleep(cfg.warmup_s)
            if watcher is not None:
                watcher.wait_for_surface(SURFACE_WAIT_S)
            # The dashboard's count is as of its newest message (at most 1/update_hz old).
            window = {"cpu0": _cpu_s(server.proc.pid), "t0": time.monotonic(), "stored0": _stored(server),
                      "dash0": watcher.dashboard_cpu_s() if watcher else 0.0}  # fmt: skip
            time.sleep(cfg.seconds)
            window.update(cpu1=_cpu_s(server.proc.pid), t1=time.monotonic(), stored1=_stored(server),
                          dash1=watcher.dashboard_cpu_s() if watcher else 0.0)  # fmt: skip
            messages = watcher.messages if watcher else 0
            kib = watcher.bytes / 1024 / max(messages, 1) if watcher else 0.0
        finally:
            if watcher is not None:
                watcher.close()
            robot.terminate()
            robot.wait(timeout=30)
    cpu = window["cpu1"] - window["cpu0"]
    dash = window["dash1"] - window["dash0"]
    stored = window["stored1"] - window["stored0"]
    return {
        "dashboard": on,
        "window_s": window["t1"] - window["t0"],
        "server_cpu_s": cpu,
        "server_cpu_fraction_of_a_core": cpu / (window["t1"] - window["t0"]),
        "experiences_stored": stored,
        # None (null) where the window saw no experience: the robot had not begun to send yet.
        "server_cpu_ms_per_experience": 1e3 * cpu / stored if stored > 0 else None,
        "dashboard_cpu_s": dash,
        "messages": messages,
        "kib_per_message": kib,
    }


def run(cfg: DashboardBenchConfig, progress: Progress = no_progress) -> dict[str, Any]:
    """Alternate off/on runs; the cost figures."""
    t0 = time.perf_counter()
    runs: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="wfnn-dash-") as tmp:
        for _ in range(cfg.repeats):
            for dashboard_on in (False, True):
                runs.append(_one(cfg, dashboard_on, Path(tmp)))
                progress(1)
    # Only windows that saw experiences measure a think server's work; an idle server's CPU can
    # be below one clock tick, so there is no share of it to take either.
    measured = [r for r in runs if r["server_cpu_ms_per_experience"] is not None]
    if len(measured) < len(runs):
        log.warning("%d of %d windows saw no experience stored (the robot had not begun to send): their "
                    "figures are left out; give a longer --warmup or --seconds", len(runs) - len(measured),
                    len(runs))  # fmt: skip
    off = [r["server_cpu_ms_per_experience"] for r in measured if not r["dashboard"]]
    on = [r for r in measured if r["dashboard"]]
    attributed = [r["dashboard_cpu_s"] / (r["server_cpu_s"] - r["dashboard_cpu_s"]) for r in on
                  if r["server_cpu_s"] > r["dashboard_cpu_s"]]  # fmt: skip
    per_exp_off = _median(off)
    per_exp_on = _median([r["server_cpu_ms_per_experience"] for r in on])
    added = _median(attributed)
    ab = (
        per_exp_on / per_exp_off - 1.0
        if per_exp_off is not None and per_exp_on is not None and per_exp_off > 0
        else None
    )
    return {
        "benchmark": "dashboard",
        "config": asdict(cfg),
        "machine": machine_info(),
        "runs": runs,
        "added_fraction_attributed": added,
        "added_fraction_ab": ab,
        "server_cpu_ms_per_experience_off": per_exp_off,
        "server_cpu_ms_per_experience_on": per_exp_on,
        "dashboard_cpu_ms_per_update": _median(
            [1e3 * r["dashboard_cpu_s"] / (r["window_s"] * cfg.update_hz) for r in on]
        ),
        # None: not measured (no window with the dashboard on saw the server work).
        "goal": {
            "goal": "< 5% of the think server's CPU time at 4 updates/s",
            "met": None if added is None else added < 0.05,
        },
        "wall_s": time.perf_counter() - t0,
    }


def _median(values: list[float]) -> float | None:
    """The median, or None where there is nothing to take it of."""
    return float(np.median(values)) if values else None


def plot(result: dict[str, Any], path: Path) -> None:
    """Server CPU per experience off/on, and the dashboard's attributed share."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
    runs = result["runs"]
    for on, colour in ((False, "tab:blue"), (True, "tab:orange")):
        values = [r["server_cpu_ms_per_experience"] for r in runs
                  if r["dashboard"] == on and r["server_cpu_ms_per_experience"] is not None]  # fmt: skip
        a.scatter([int(on)] * len(values), values, color=colour, s=40)
    a.set_xticks([0, 1], ["dashboard off", f"on, {result['config']['update_hz']:g} updates/s"])
    a.set_ylabel("server CPU ms per experience")
    a.set_title(f"think server CPU (HyDrA at 15 Hz, --think {result['config']['think']})")
    shares = [100 * r["dashboard_cpu_s"] / (r["server_cpu_s"] - r["dashboard_cpu_s"]) for r in runs
              if r["dashboard"] and r["server_cpu_ms_per_experience"] is not None
              and r["server_cpu_s"] > r["dashboard_cpu_s"]]  # fmt: skip
    b.bar(range(len(shares)), shares, color="tab:orange")
    b.axhline(5.0, color="crimson", ls="--", label="5% goal")
    b.set_ylabel("dashboard CPU / server's other CPU (%)")
    b.set_xlabel("run")
    b.set_title("dashboard's attributed cost")
    b.legend()
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)


def rows(result: dict[str, Any], cfg: DashboardBenchConfig) -> list[tuple[str, Any]]:
    """The figures of `wfnn-bench dashboard`'s table: (name, value) rows."""
    rows: list[tuple[str, Any]] = [
        ("dashboard CPU / server's other CPU (attributed, median)", result["added_fraction_attributed"]),
        ("server CPU per experience, on / off - 1 (A/B, medians)", result["added_fraction_ab"]),
        ("server CPU ms per experience, off", result["server_cpu_ms_per_experience_off"]),
        ("server CPU ms per experience, on", result["server_cpu_ms_per_experience_on"]),
        ("dashboard CPU ms per update", result["dashboard_cpu_ms_per_update"]),
        ("server CPU (fraction of a core), runs", " ".join(
            f"{r['server_cpu_fraction_of_a_core']:.3f}{'*' * r['dashboard']}" for r in result["runs"])),
        (f"goal {result['goal']['goal']}", {True: "met", False: "NOT met"}.get(result["goal"]["met"],
                                                                               "not measured")),
        ("wall_s", result["wall_s"]),
    ]  # fmt: skip
    return rows
