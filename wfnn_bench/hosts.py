"""Hosts on one machine: Linux network namespaces joined by veth links, and faults on those links.

`Hosts` makes one namespace per host and a veth link from each host to a hub host (the router's),
with addresses only inside the namespaces (10.241.<i>.1 on the hub's end of link i, .2 on the
host's). Nothing is routed between links: every host talks only to the hub, as robots and think
servers talk only to their Zenoh router. Processes started with `Hosts.start` run inside a
host's namespace; leaving the context stops them by PID and removes every namespace and link,
also when the code inside failed or SIGTERM stopped it. Namespaces left by a process that died
are removed by the next `Hosts`: each run holds a lock on a file of its own (`OWNERS`, named as
its namespaces' random tag) while they exist, and only namespaces with such a file that nobody
holds are removed (a namespace this tool did not make, or one whose owner runs in another PID
namespace, is left alone).

Faults on a host's link, in both directions, with iptables and tc inside the two namespaces:
- `partition`: every packet dropped (as a cable pulled behind a switch: no error, only silence);
- `impair`: random loss (iptables' statistic match) and delay with jitter (netfilter queues and
  `wfnn_bench.delay_line`, because kernels without the netem qdisc, such as this one, offer no
  delay in tc);
- `limit_rate`: a token bucket (tc tbf).

It needs root, `ip`, `iptables` and `tc`; `unavailable()` says what is missing.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import IO

from wfnn_io.cli_errors import Terminated, handling, noting, terminate

log = logging.getLogger(__name__)

PREFIX = "wfnn"
"""Namespaces are named wfnn<random tag>-<host>: random, as PIDs repeat across PID namespaces."""
OWNERS = Path("/run/wfnn-hosts")
"""Where each run's lock file (<tag>.lock) says its namespaces are in use (held while they are)."""
BIN = Path(sys.executable).parent
PARTITION_RULE = ("INPUT", "-i", "{dev}", "-m", "comment", "--comment", "partition", "-j", "DROP")


def unavailable() -> str | None:
    """Why namespaces cannot be made here, or None when they can."""
    if os.name != "posix" or not sys.platform.startswith("linux"):
        return "network namespaces need Linux"
    if os.geteuid() != 0:
        return "network namespaces and iptables need root"
    missing = [tool for tool in ("ip", "iptables", "tc") if shutil.which(tool) is None]
    if missing:
        return f"{', '.join(missing)} not found (Debian: iproute2, iptables)"
    try:
        OWNERS.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        return f"cannot make {OWNERS}, where runs note their namespaces: {exc.strerror or exc}"
    tag, owner = _new_owner()  # a probe left by a kill is swept as a run's namespaces are
    probe = f"{tag}-probe"
    try:
        made = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
        if made.returncode != 0:
            return f"cannot create a network namespace: {made.stderr.strip()}"
        rule = ["ip", "netns", "exec", probe, "iptables", "-A", "INPUT", "-i", "lo", "-j", "ACCEPT"]
        ipt = subprocess.run(rule, capture_output=True, text=True)
        if ipt.returncode != 0:
            return f"iptables does not work in a namespace: {ipt.stderr.strip()}"
    finally:
        subprocess.run(["ip", "netns", "del", probe], capture_output=True)
        _disown(tag, owner)
    return None


def _sh(*argv: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    done = subprocess.run(list(argv), capture_output=True, text=True)
    if check and done.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)}: {done.stderr.strip() or done.stdout.strip()}")
    return done


def _new_owner() -> tuple[str, int]:
    """A fresh random tag and its lock file in OWNERS, locked -> (tag, descriptor).

    Locked before it takes its name, so that no sweep ever sees it unheld.
    """
    OWNERS.mkdir(parents=True, exist_ok=True)
    tag = f"{PREFIX}{secrets.token_hex(4)}"
    fd, staged = tempfile.mkstemp(dir=OWNERS, prefix=".new-")
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        os.rename(staged, OWNERS / f"{tag}.lock")
    except BaseException:
        os.close(fd)
        Path(staged).unlink(missing_ok=True)
        raise
    return tag, fd


def _disown(tag: str, fd: int) -> None:
    """Remove and unlock `tag`'s lock file (its namespaces are gone)."""
    (OWNERS / f"{tag}.lock").unlink(missing_ok=True)
    os.close(fd)


def _own(tag: str) -> int | None:
    """Lock an existing lock file of `tag` -> its descriptor; None where it is held (or gone)."""
    try:
        fd = os.open(OWNERS / f"{tag}.lock", os.O_RDWR)
    except FileNotFoundError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return None
    return fd


def sweep_stale() -> list[str]:
    """Remove the namespaces this tool made whose owners no longer run; -> their names.

    A run holds its tag's lock file while its namespaces exist: a file nobody holds is a dead
    run's (its namespaces, if any, and the file go), and a namespace with no file at all is no
    namespace of this tool's (left alone).
    """
    listed = _sh("ip", "netns", "list", check=False).stdout.split("\n")
    names = [line.split(" ")[0] for line in listed if line.startswith(PREFIX)]
    removed = []
    for lock in sorted(OWNERS.glob(f"{PREFIX}*.lock")) if OWNERS.is_dir() else []:
        tag = lock.name.removesuffix(".lock")
        fd = _own(tag)
        if fd is None:  # its owner runs
            continue
        try:
            for name in names:
                if name.split("-")[0] == tag:
                    for pid in _sh("ip", "netns", "pids", name, check=False).stdout.split():
                        _kill(int(pid))
                    _sh("ip", "netns", "del", name, check=False)
                    removed.append(name)
        finally:
            _disown(tag, fd)
    return removed


def _kill(pid: int) -> None:
    try:
        os.kill(pid, signal.SIGKILL)
    except ProcessLookupError:
        pass


@dataclass
class Link:
    """The veth link between a host and the hub."""

    index: int
    host: str
    host_dev: str
    hub_dev: str

    @property
    def host_address(self) -> str:
        """The host's end."""
        return f"10.241.{self.index}.2"

    @property
    def hub_address(self) -> str:
        """The hub's end."""
        return f"10.241.{self.index}.1"


@dataclass
class _Impairment:
    lines: list[subprocess.Popen[bytes]] = field(default_factory=list)


class Hosts:
    """Namespaced hosts around a hub (see the module docstring)."""

    def __init__(self, hosts: tuple[str, ...], hub: str = "router", logs: Path | None = None) -> None:
        for name in (*hosts, hub):
            if not name.isalnum() or len(name) > 12:
                raise ValueError(f"host names are letters and digits, at most 12, got {name!r}")
        if len(set((*hosts, hub))) != len(hosts) + 1:
            raise ValueError("host names must differ")
        self.hub, self.hosts = hub, hosts
        self.tag = ""
        """wfnn<random>: its namespaces' names begin with it (made on entering)."""
        self._owner: int | None = None
        self._signals = contextlib.ExitStack()
        self.logs = logs
        self.links: dict[str, Link] = {}
        self.procs: list[subprocess.Popen[bytes]] = []
        self._made: list[str] = []
        self._impaired: dict[str, _Impairment] = {}
        self._next_queue = 1

    def ns(self, host: str) -> str:
        """The namespace of `host`."""
        return f"{self.tag}-{host}"

    def __enter__(self) -> Hosts:
        # SIGTERM (a CI's cancel, `timeout`) ends the run as Ctrl-C does, through `close`: by
        # default it ended the process with its namespaces and servers left running.
        self._signals.enter_context(handling(terminate, signal.SIGTERM))
        try:
            self.tag, self._owner = _new_owner()
            sweep_stale()
            self._make()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        signum = self.close()
        if signum is not None and kind is None:  # asked to stop while leaving: stop, as asked
            raise Terminated(signum)

    def _make(self) -> None:
        for host in (self.hub, *self.hosts):
            self._made.append(self.ns(host))  # first: a signal during `add` must not leave it unknown
            _sh("ip", "netns", "add", self.ns(host))
            _sh("ip", "-n", self.ns(host), "link", "set", "lo", "up")
        for index, host in enumerate(self.hosts, start=1):
            # Interface names are unique per namespace; both ends start in the hub's namespace.
            link = Link(index, host, host_dev=f"h{index}", hub_dev=f"to{host}"[:15])
            hub_ns, host_ns = self.ns(self.hub), self.ns(host)
            _sh("ip", "-n", hub_ns, "link", "add", link.hub_dev, "type", "veth",
                "peer", "name", link.host_dev, "netns", host_ns)  # fmt: skip
            _sh("ip", "-n", hub_ns, "addr", "add", f"{link.hub_address}/24", "dev", link.hub_dev)
            _sh("ip", "-n", host_ns, "addr", "add", f"{link.host_address}/24", "dev", link.host_dev)
            _sh("ip", "-n", hub_ns, "link", "set", link.hub_dev, "up")
            _sh("ip", "-n", host_ns, "link", "set", link.host_dev, "up")
            self.links[host] = link

    def address(self, host: str) -> str:
        """Where other hosts reach `host` (the hub: give the link's host instead)."""
        return self.links[host].host_address

    def hub_address(self, host: str) -> str:
        """Where `host` reaches the hub."""
        return self.links[host].hub_address

    def exec_argv(self, host: str, argv: list[str]) -> list[str]:
        """`argv` run inside `host`'s namespace."""
        return ["ip", "netns", "exec", self.ns(host), *argv]

    def start(
        self, host: str, argv: list[str], log_name: str | None = None, env: dict[str, str] | None = None
    ) -> subprocess.Popen[bytes]:
        """Start `argv` inside `host` (output to logs/<log_name>.log); stopped by `close`."""
        out: int | IO[bytes] = subprocess.DEVNULL
        handle = None
        if self.logs is not None and log_name is not None:
            self.logs.mkdir(parents=True, exist_ok=True)
            handle = open(self.logs / f"{log_name}.log", "ab")  # closed below: the child holds its own
            out = handle
        environment = {**os.environ, "PYTHONUNBUFFERED": "1", "COLUMNS": "160", **(env or {})}
        try:
            proc = subprocess.Popen(
                self.exec_argv(host, argv),
                stdout=out,
                stderr=subprocess.STDOUT,
                env=environment,
                start_new_session=True,
            )
        finally:
            if handle is not None:
                handle.close()
        self.procs.append(proc)
        return proc

    def _rules(self, host: str, action: str, *rule: str) -> None:
        """Add (`action` -A/-I) or delete (-D) an iptables rule on both ends of `host`'s link."""
        link = self.links[host]
        for ns, dev in ((self.ns(host), link.host_dev), (self.ns(self.hub), link.hub_dev)):
            _sh("ip", "netns", "exec", ns, "iptables", action, *[dev if r == "{dev}" else r for r in rule])

    def partition(self, host: str) -> None:
        """Drop every packet on `host`'s link, both ways, until `heal`."""
        self._rules(host, "-I", *PARTITION_RULE)

    def heal(self, host: str) -> None:
        """End `partition`."""
        self._rules(host, "-D", *PARTITION_RULE)

    def impair(
        self, host: str, loss: float = 0.05, delay_ms: float = 20.0, jitter_ms: float = 10.0, seed: int = 0
    ) -> None:
        """Random loss on arrival and delay (uniform in delay +- jitter) on departure, on both ends."""
        if host in self._impaired:
            raise RuntimeError(f"{host}'s link is impaired already")
        if not 0.0 <= loss < 1.0:
            raise ValueError(f"loss must be in [0, 1), got {loss}")
        link = self.links[host]
        state = _Impairment()
        self._impaired[host] = state
        if loss > 0:
            self._rules(host, "-A", "INPUT", "-i", "{dev}", "-m", "statistic", "--mode", "random",
                        "--probability", f"{loss:.6f}", "-j", "DROP")  # fmt: skip
        if delay_ms <= 0:
            return
        for end, (ns, dev) in enumerate(((self.ns(host), link.host_dev), (self.ns(self.hub), link.hub_dev))):
            queue = self._next_queue
            self._next_queue += 1
            argv = [sys.executable, "-m", "wfnn_bench.delay_line", "--queue", str(queue), "--delay-ms",
                    str(delay_ms), "--jitter-ms", str(jitter_ms), "--seed", str(seed * 2 + end)]  # fmt: skip
            line = subprocess.Popen(["ip", "netns", "exec", ns, *argv], stdout=subprocess.PIPE,
                                    stderr=subprocess.STDOUT)  # fmt: skip
            state.lines.append(line)
            self.procs.append(line)
            assert line.stdout is not None
            ready = line.stdout.readline()  # bound before the rule sends packets its way
            if not ready.startswith(b"delay line"):
                raise RuntimeError(f"the delay line did not start: {ready!r} {line.stdout.read()!r}")
            _sh("ip", "netns", "exec", ns, "iptables", "-A", "OUTPUT", "-o", dev, "-j", "NFQUEUE",
                "--queue-num", str(queue), "--queue-bypass")  # fmt: skip

    def restore(self, host: str) -> None:
        """End `impair` on `host`'s link."""
        state = self._impaired.pop(host)
        link = self.links[host]
        for ns, dev in ((self.ns(host), link.host_dev), (self.ns(self.hub), link.hub_dev)):
            for chain in ("INPUT", "OUTPUT"):  # every rule but a partition's
                listed = _sh("ip", "netns", "exec", ns, "iptables", "-S", chain).stdout.splitlines()
                for rule in listed:
                    if rule.startswith(f"-A {chain}") and dev in rule.split() and "partition" not in rule:
                        _sh("ip", "netns", "exec", ns, "iptables", "-D", *rule.split()[1:])
        for line in state.lines:
            line.send_signal(signal.SIGTERM)
            line.wait(timeout=10)

    def limit_rate(self, host: str, rate: str = "1mbit") -> None:
        """Limit `host`'s link to `rate` each way (tc tbf on both ends)."""
        link = self.links[host]
        for ns, dev in ((self.ns(host), link.host_dev), (self.ns(self.hub), link.hub_dev)):
            _sh("ip", "netns", "exec", ns, "tc", "qdisc", "replace", "dev", dev, "root", "tbf", "rate", rate,
                "burst", "16kb", "latency", "200ms")  # fmt: skip

    def unlimit_rate(self, host: str) -> None:
        """End `limit_rate`."""
        link = self.links[host]
        for ns, dev in ((self.ns(host), link.host_dev), (self.ns(self.hub), link.hub_dev)):
            _sh("ip", "netns", "exec", ns, "tc", "qdisc", "del", "dev", dev, "root", check=False)

    def stop(self, proc: subprocess.Popen[bytes], timeout_s: float = 60.0) -> int:
        """SIGTERM `proc` (by PID) and wait; SIGKILL after `timeout_s`. -> exit code."""
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=10)
        return int(proc.returncode)

    def close(self) -> int | None:
        """Stop every process (by PID), then remove the namespaces and their links.

        A SIGTERM meanwhile waits for the cleanup it asks for: -> its number, if one came (leaving
        the context raises it then, unless something else is raised already).
        """
        with noting(signal.SIGTERM) as noted:
            self._close()
        if noted:
            log.warning("signal %d while the hosts were removed: stopping now that they are", noted[0])
        self._signals.close()
        return noted[0] if noted else None

    def _close(self) -> None:
        for proc in reversed(self.procs):
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + 30.0
        for proc in self.procs:
            try:
                proc.wait(timeout=max(deadline - time.monotonic(), 0.1))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=10)
        for ns in reversed(self._made):  # anything still inside (children) goes too
            for pid in _sh("ip", "netns", "pids", ns, check=False).stdout.split():
                _kill(int(pid))
            _sh("ip", "netns", "del", ns, check=False)  # removing a namespace removes its veth ends
        self._made.clear()
        if self._owner is not None:  # its namespaces are gone: no lock file left to sweep
            _disown(self.tag, self._owner)
            self._owner = None
