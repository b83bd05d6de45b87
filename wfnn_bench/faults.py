"""act-learn-think-C/S across hosts, under network faults (`wfnn-bench faults`).

Four hosts, each its own network namespace (`wfnn_bench.hosts`): the robot (`wfnn-client`, HyDrA
1-DOF in real time at 15 Hz), a Zenoh router (`wfnn-router`) and two think servers
(`wfnn-server --mode client`), each host on its own veth link to the router's host. Every frame
carries the shared key's HMAC. Each case runs the robot for a warm-up, injects one fault, ends
it, and lets the system recover:

- a: 5% loss and 20 +- 10 ms delay on the robot's link (both ways);
- b: the robot partitioned from everything;
- c: the router killed (SIGKILL), then restarted;
- d: the followed server's host partitioned alone;
- e: as a, with TLS on every link to the router (mutual, `deploy/make-tls-certs.sh`);
- f: the followed server on a 1 Mbit/s link, while a second server, started at the fault,
  catches up from the robot's journal.

Measured per case, from the robot's tick trace and applied-snapshot log (one clock: every host
is on this machine) and from the servers' stores, read after they stopped:
- experiences produced, stored by each server, and lost (held by no server);
- tick jitter p99 and overruns during the fault;
- the longest time without newly applied weights, from the fault's start to the run's end;
- failover time (fault start to the client following another server);
- seconds from the fault's end until a snapshot is applied, and until a snapshot applied has
  learned an experience made after the fault.
"""

from __future__ import annotations

import json
import logging
import re
import secrets
import shutil
import subprocess
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from wfnn_bench.common import Progress, check_seed, machine_info, no_progress
from wfnn_bench.hosts import BIN, Hosts
from wfnn_common.config import check_fields
from wfnn_io.persist import save_figure
from wfnn_server.store import ExperienceStore

log = logging.getLogger(__name__)
CONTROLLER = "faults"
PORT = 7447
CASES = {
    "a": "5% loss, 20 +- 10 ms delay on the robot's link",
    "b": "robot partitioned from everything",
    "c": "router killed, then restarted",
    "d": "followed server's host partitioned alone",
    "e": "as a, with TLS on every link and the HMAC key",
    "f": "followed server at 1 Mbit/s while a late server catches up from the journal",
}
GOALS = {
    "experiences_lost": ("<=", 0.0),
    "tick_jitter_p99_ms": ("<=", 2.0),
    "overruns": ("<=", 0.0),
}
REPO = Path(__file__).resolve().parent.parent


@dataclass(frozen=True, kw_only=True)
class FaultsBenchConfig:
    """Options of `wfnn-bench faults`."""

    cases: tuple[str, ...] = tuple(CASES)
    rate_hz: float = 15.0
    warmup_s: float = 10.0
    """Learning before the fault, from the robot's first applied weights."""
    impair_s: float = 60.0
    """Length of the loss and delay of cases a and e."""
    partition_s: float = 10.0
    """Length of the partitions of cases b and d."""
    router_down_s: float = 5.0
    """How long the router stays dead in case c."""
    rate_limit_s: float = 30.0
    """Length of case f's rate limit (the late server starts at its beginning)."""
    after_s: float = 20.0
    """Running on after the fault ends: recovery and catching up."""
    loss: float = 0.05
    delay_ms: float = 20.0
    jitter_ms: float = 10.0
    rate_limit: str = "1mbit"
    seed: int = 0

    def __post_init__(self) -> None:
        check_fields(self)
        check_seed(self.seed)
        unknown = [c for c in self.cases if c not in CASES]
        if unknown or not self.cases:
            raise ValueError(f"cases are some of {', '.join(CASES)}, got {','.join(self.cases)}")
        if not 1.0 <= self.rate_hz <= 1000.0:
            raise ValueError(f"rate_hz must be in [1, 1000], got {self.rate_hz}")

    def fault_s(self, case: str) -> float:
        """How long the fault of `case` lasts."""
        return {
            "a": self.impair_s,
            "b": self.partition_s,
            "c": self.router_down_s,
            "d": self.partition_s,
            "e": self.impair_s,
            "f": self.rate_limit_s,
        }[case]


def _tls_files(work: Path, hosts: Hosts) -> dict[str, Path]:
    """Test certificates and the deployment's own TLS files for case e.

    The certificates name the router's address on every link. The files are
    `deploy/zenoh-tls.json5` (the router) and `deploy/zenoh-tls-connect.json5` (the others), with
    only their certificate directory changed.
    """
    names = ",".join(hosts.hub_address(h) for h in hosts.hosts)
    tls = work / "tls"
    subprocess.run(["bash", str(REPO / "deploy" / "make-tls-certs.sh"), names, str(tls)], check=True,
                   capture_output=True)  # fmt: skip
    files = {}
    for side, name in (("router", "zenoh-tls.json5"), ("side", "zenoh-tls-connect.json5")):
        text = (REPO / "deploy" / name).read_text().replace("/etc/wfnn/tls/", f"{tls}/")
        files[side] = work / name
        files[side].write_text(text)
    return files


class _Case:
    """One case's processes on its hosts."""

    def __init__(self, case: str, cfg: FaultsBenchConfig, hosts: Hosts, work: Path) -> None:
        self.case, self.cfg, self.hosts, self.work = case, cfg, hosts, work
        self.key = work / "wfnn.key"
        self.key.write_text(secrets.token_hex(32))
        self.tls = _tls_files(work, hosts) if case == "e" else None
        self.proto = "tls" if self.tls else "tcp"
        self.router: subprocess.Popen[bytes] | None = None
        self.servers: dict[str, subprocess.Popen[bytes]] = {}
        self.events: dict[str, Any] = {}
        self.target = "robot"
        """The host whose link the fault touches."""

    def start_router(self) -> None:
        argv = [str(BIN / "wfnn-router"), "--listen", f"{self.proto}/0.0.0.0:{PORT}", "--verbose"]
        if self.tls:
            argv += ["--zenoh-config", str(self.tls["router"])]
        self.router = self.hosts.start(self.hosts.hub, argv, "router")

    def start_server(self, host: str) -> None:
        argv = [
            str(BIN / "wfnn-server"), "--id", host, "--controller", CONTROLLER, "--mode", "client",
            "--connect", f"{self.proto}/{self.hosts.hub_address(host)}:{PORT}",
            "--data-dir", str(self.work / host), "--key-file", str(self.key),
            "--seed", str(self.cfg.seed + len(self.servers)), "--checkpoint-period", "5",
            "--quiet", "--verbose",
        ]  # fmt: skip
        if self.tls:
            argv += ["--zenoh-config", str(self.tls["side"])]
        self.servers[host] = self.hosts.start(host, argv, host)

    def client_argv(self, duration_s: float, lockstep: bool = False) -> list[str]:
        """The robot's command: HyDrA in real time, or (`lockstep`) the boat as fast as it learns."""
        sim, rate = ("boat", "0") if lockstep else ("hydra", f"{self.cfg.rate_hz:g}")
        argv = [
            str(BIN / "wfnn-client"), "--sim", sim, "--rate-hz", rate, *(["--lockstep"] if lockstep else []),
            "--episodes", "1000000", "--duration", f"{duration_s:.1f}", "--controller", CONTROLLER,
            "--server", f"{self.proto}/{self.hosts.hub_address('robot')}:{PORT}", "--key-file", str(self.key),
            "--out", str(self.work / "robot"), "--json-stats", str(self.work / "robot.json"),
            "--timing-trace", "--seed", str(self.cfg.seed), "--verbose",
        ]  # fmt: skip
        if self.tls:
            argv += ["--zenoh-config", str(self.tls["side"])]
        return argv

    def followed(self) -> str:
        """The server the robot follows now (from its log)."""
        text = (self.work / "logs" / "robot.log").read_text(errors="replace")
        found = re.findall(r"following server (\w+)", text)
        if not found or found[-1] not in self.servers:
            raise RuntimeError(f"case {self.case}: cannot tell which server the robot follows")
        return str(found[-1])

    def inject(self) -> None:
        h, case = self.hosts, self.case
        followed = self.followed()
        self.target = followed if case in ("d", "f") else "robot"
        self.events["followed_at_fault"] = followed
        if case in ("a", "e"):
            h.impair("robot", self.cfg.loss, self.cfg.delay_ms, self.cfg.jitter_ms, seed=self.cfg.seed)
        elif case == "b":
            h.partition("robot")
        elif case == "c":
            assert self.router is not None
            self.router.kill()
            self.router.wait(timeout=10)
        elif case == "d":
            h.partition(self.target)
        elif case == "f":
            h.limit_rate(self.target, self.cfg.rate_limit)
            self.start_server("think2")

    def end(self) -> None:
        h, case = self.hosts, self.case
        if case in ("a", "e"):
            h.restore("robot")
        elif case == "b":
            h.heal("robot")
        elif case == "c":
            self.start_router()
        elif case == "d":
            h.heal(self.target)
        elif case == "f":
            h.unlimit_rate(self.target)


def _wait_for(path: Path, pattern: str, proc: subprocess.Popen[bytes], timeout_s: float) -> bool:
    """Wait until `pattern` appears in the log at `path` (False on timeout or if `proc` ended)."""
    deadline = time.monotonic() + timeout_s
    regex = re.compile(pattern)
    while time.monotonic() < deadline and proc.poll() is None:
        if path.exists() and regex.search(path.read_text(errors="replace")):
            return True
        time.sleep(0.1)
    return False


def run_case(case: str, cfg: FaultsBenchConfig, work: Path) -> dict[str, Any]:
    """One case on fresh hosts; -> its figures."""
    work.mkdir(parents=True, exist_ok=True)
    with Hosts(("robot", "think1", "think2"), logs=work / "logs") as hosts:
        run = _Case(case, cfg, hosts, work)
        run.start_router()
        run.start_server("think1")
        if case != "f":  # in f the second server starts late
            run.start_server("think2")
        time.sleep(1.0)
        fault_s = cfg.fault_s(case)
        duration = 8.0 + cfg.warmup_s + fault_s + cfg.after_s
        robot = hosts.start("robot", run.client_argv(duration), "robot")
        if not _wait_for(work / "logs" / "robot.log", r"following server", robot, 60.0):
            raise RuntimeError(
                f"case {case}: the robot never followed a server ({work / 'logs' / 'robot.log'})"
            )
        time.sleep(cfg.warmup_s)
        run.events["fault_start_unix"] = time.time()
        run.inject()
        time.sleep(fault_s)
        run.events["fault_end_unix"] = time.time()
        run.end()
        try:
            code = robot.wait(timeout=duration + 60)
        except subprocess.TimeoutExpired:
            _dump_stacks(robot.pid, work / "logs" / "robot-stacks.txt")
            raise RuntimeError(f"case {case}: the robot did not stop ({work / 'logs'})") from None
        if code != 0:
            raise RuntimeError(f"case {case}: the robot exited with {code} ({work / 'logs' / 'robot.log'})")
        for host, proc in run.servers.items():
            hosts.stop(proc)
            log.info("case %s: %s stopped", case, host)
    metrics = json.loads((work / "robot.json").read_text())
    client = json.loads((work / "robot" / "journal" / "client.json").read_text())["client"]
    stored = {host: _stored(work / host, client) for host in run.servers}
    return figures(case, cfg, metrics, run.events, stored)


def _dump_stacks(pid: int, path: Path) -> None:
    """Every thread's stack of a process that hangs, where py-spy is installed (for the report)."""
    spy = shutil.which("py-spy") or (str(BIN / "py-spy") if (BIN / "py-spy").exists() else None)
    if spy is not None:
        dump = subprocess.run([spy, "dump", "--native", "--pid", str(pid)], capture_output=True, text=True)
        path.write_text(dump.stdout + dump.stderr)


def _stored(data_dir: Path, client: str) -> int:
    """Experiences of `client` a server's store holds (its sequence numbers are 0, 1, ...)."""
    if not (data_dir / "store").exists():
        return 0
    store = ExperienceStore(data_dir / "store", "check")
    try:
        return int(store.stored_through.get(client, -1)) + 1
    finally:
        store.close()


def figures(
    case: str, cfg: FaultsBenchConfig, metrics: dict[str, Any], events: dict[str, Any], stored: dict[str, int]
) -> dict[str, Any]:
    """One case's figures (see the module docstring).

    From the robot's metrics with its timing trace, the fault's Unix times and the experiences
    each server stored.
    """
    trace = metrics["trace"]
    start, end = events["fault_start_unix"], events["fault_end_unix"]
    due = np.asarray(trace["tick_due_unix"])
    late_ms = np.asarray(trace["tick_lateness_ms"])
    produced_by_tick = np.asarray(trace["tick_produced_through"])
    during = (due >= start) & (due <= end)
    period = 1.0 / cfg.rate_hz
    around = due[(due >= start - period) & (due <= end + period)]  # a skipped tick at either edge counts
    gaps = np.diff(around) if around.size > 1 else np.zeros(0)
    overruns = int(np.sum(np.maximum(np.round(gaps / period) - 1, 0)))
    produced = int(metrics["uplink/produced_through"]) + 1
    applied = [(float(t), str(s), int(v), int(lt)) for t, s, v, lt in trace["snapshots_applied"]]
    times = np.asarray([a[0] for a in applied])
    # The longest stretch without newly applied weights that overlaps the fault or what follows it.
    marks = np.concatenate([times, [metrics_end(due, period)]])
    before = marks[marks < start]
    after = marks[marks >= start]
    edges = np.concatenate([before[-1:], after])
    without = float(np.max(np.diff(edges))) if edges.size > 1 else float("nan")
    first_after = next((t for t in times if t >= end), None)
    after_ticks = np.nonzero(due >= end)[0]
    target = int(produced_by_tick[after_ticks[0]]) if after_ticks.size else None
    learned = next((t for t, _, _, lt in applied if t >= end and target is not None and lt >= target), None)
    failovers = [f for f in metrics["failovers"] if f["at_unix"] >= start]
    # A failover is to another server while the fault lasts; switching servers after it ends (all
    # of them were unreachable meanwhile) is recovery, kept in `failovers`.
    during_fault = [f for f in failovers if f["at_unix"] <= end]
    return {
        "case": case,
        "description": CASES[case],
        "fault_s": end - start,
        "experiences_produced": produced,
        "experiences_stored": stored,
        "experiences_lost": int(produced - max(stored.values(), default=0)),
        "experiences_missing_per_server": {s: produced - n for s, n in stored.items()},
        "tick_jitter_p99_ms": float(np.percentile(late_ms[during], 99)) if during.any() else float("nan"),
        "tick_jitter_max_ms": float(late_ms[during].max()) if during.any() else float("nan"),
        "overruns": overruns,
        "overruns_whole_run": int(metrics["client/overruns"]),
        "ticks_during_fault": int(during.sum()),
        "without_weights_s": without,
        "failover_s": float(during_fault[0]["at_unix"] - start) if during_fault else None,
        "failovers": failovers,
        "snapshots_resume_s": float(first_after - end) if first_after is not None else None,
        "learning_resumes_s": float(learned - end) if learned is not None else None,
        "following_at_end": metrics["following"],
        "snapshots_applied": len(applied),
        "events": events,
        "timeline": {"applied": applied, "tick_due_unix": due.tolist(), "tick_lateness_ms": late_ms.tolist()},
    }


def metrics_end(due: np.ndarray, period: float) -> float:
    """When the robot's last tick ended (the run's end, for stretches still open)."""
    return float(due[-1] + period) if due.size else 0.0


@contextmanager
def _workdir(keep: Path | None) -> Iterator[Path]:
    if keep is not None:
        keep.mkdir(parents=True, exist_ok=True)
        yield keep
        return
    with tempfile.TemporaryDirectory(prefix="wfnn-faults-") as tmp:
        yield Path(tmp)


def run(cfg: FaultsBenchConfig, progress: Progress = no_progress, keep: Path | None = None) -> dict[str, Any]:
    """Every case in `cfg.cases`, one after the other, on fresh hosts."""
    t0 = time.perf_counter()
    cases: dict[str, Any] = {}
    with _workdir(keep) as work:
        for case in cfg.cases:
            log.info("case %s: %s", case, CASES[case])
            cases[case] = run_case(case, cfg, work / f"case-{case}")
            progress(1)
            if keep is None:
                shutil.rmtree(work / f"case-{case}", ignore_errors=True)
    result: dict[str, Any] = {
        "benchmark": "faults",
        "config": asdict(cfg),
        "machine": machine_info(),
        "cases": cases,
        "wall_s": time.perf_counter() - t0,
    }
    result["goals"] = {
        case: {
            name: {
                "goal": f"{op} {bound:g}",
                "value": c[name],
                "met": bool(c[name] >= bound if op == ">=" else c[name] <= bound),
            }
            for name, (op, bound) in GOALS.items()
        }
        for case, c in cases.items()
    }
    for case, c in cases.items():
        goals = result["goals"][case]
        if case == "d":
            goals["failover_s"] = {
                "goal": "<= 2",
                "value": c["failover_s"],
                "met": c["failover_s"] is not None and c["failover_s"] <= 2.0,
            }
        if case in ("b", "c"):
            goals["learning_resumes_s"] = {
                "goal": "<= 2",
                "value": c["learning_resumes_s"],
                "met": c["learning_resumes_s"] is not None and c["learning_resumes_s"] <= 2.0,
            }
        if case == "f":
            late = c["experiences_missing_per_server"].get("think2")
            goals["late_server_missing"] = {"goal": "<= 0", "value": late, "met": late == 0}
    return result


def table_rows(result: dict[str, Any]) -> list[list[str]]:
    """One row per case for the CLI's table."""

    def f(value: Any, fmt: str = "{:.2f}") -> str:
        return "-" if value is None else fmt.format(value)

    rows = []
    for case, c in result["cases"].items():
        stored = "/".join(str(n) for n in c["experiences_stored"].values())
        rows.append(
            [
                case,
                str(c["experiences_produced"]),
                stored,
                str(c["experiences_lost"]),
                f(c["tick_jitter_p99_ms"]),
                str(c["overruns"]),
                f(c["without_weights_s"]),
                f(c["failover_s"]),
                f(c["snapshots_resume_s"]),
                f(c["learning_resumes_s"]),
            ]
        )
    return rows


TABLE_HEADER = ["case", "produced", "stored t1/t2", "lost", "p99 ms", "overruns", "no weights s",
                "failover s", "snapshots s", "learning s"]  # fmt: skip
"""Per case: experiences produced by the robot, stored by think1 and think2, held by neither;
tick jitter p99 and overruns during the fault; the longest time without new weights; failover
time; seconds from the fault's end until snapshots, and learned weights, reach the robot."""


def plot(result: dict[str, Any], path: Path) -> None:
    """Per case: tick lateness and the weights version applied against time, the fault shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = result["cases"]
    fig, axes = plt.subplots(len(cases), 1, figsize=(10, 2.4 * len(cases)), squeeze=False)
    for ax, (case, c) in zip(axes[:, 0], cases.items(), strict=True):
        t0 = c["events"]["fault_start_unix"]
        due = np.asarray(c["timeline"]["tick_due_unix"]) - t0
        ax.plot(due, c["timeline"]["tick_lateness_ms"], lw=0.6, color="tab:blue", label="tick lateness (ms)")
        ax.axvspan(0.0, c["fault_s"], color="tab:red", alpha=0.15, label="fault")
        ax.axhline(2.0, color="tab:blue", ls=":", lw=0.8)
        ax.set_ylabel("ms")
        twin = ax.twinx()
        for server in sorted({a[1] for a in c["timeline"]["applied"]}):
            pts = [(a[0] - t0, a[2]) for a in c["timeline"]["applied"] if a[1] == server]
            twin.plot(*zip(*pts, strict=True), ".", ms=2, label=f"version applied ({server})")
        twin.set_ylabel("weights version")
        ax.set_title(
            f"{case}: {c['description']} (lost {c['experiences_lost']}, p99 "
            f"{c['tick_jitter_p99_ms']:.2f} ms)",
            fontsize=9,
        )
        handles = ax.get_legend_handles_labels()[0] + twin.get_legend_handles_labels()[0]
        ax.legend(handles=handles, fontsize=7, loc="upper left")
    axes[-1, 0].set_xlabel("s from the fault's start")
    fig.tight_layout()
    save_figure(fig, path, dpi=100)
    plt.close(fig)
