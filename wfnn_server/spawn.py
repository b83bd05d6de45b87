"""Start a `wfnn-server` as a child process on a loopback port (benchmarks, tests, demos)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from wfnn_io.cli_errors import noting

BIN = Path(sys.executable).parent


def free_port() -> int:
    """A TCP port on 127.0.0.1 that is free now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def endpoint(port: int) -> str:
    """The Zenoh endpoint of a loopback TCP port."""
    return f"tcp/127.0.0.1:{port}"


def wait_listening(port: int, timeout_s: float = 30.0) -> None:
    """Block until something accepts connections on the port."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.05)
    raise TimeoutError(f"nothing listens on port {port} after {timeout_s} s")


class ServerProcess:
    """`wfnn-server` in router mode on 127.0.0.1:port; `stop` sends SIGTERM (final checkpoint)."""

    def __init__(
        self, data_dir: Path, port: int, *args: str, server_id: str = "srv", controller: str = "default"
    ) -> None:
        self.data_dir, self.port, self.args = Path(data_dir), port, list(args)
        self.server_id, self.controller = server_id, controller
        self.proc: subprocess.Popen[bytes] | None = None
        self.log = self.data_dir.parent / f"{server_id}-{port}.log"

    @property
    def endpoint(self) -> str:
        """Where clients connect."""
        return endpoint(self.port)

    def start(self) -> ServerProcess:
        """Start and wait until it listens."""
        cmd = [
            str(BIN / "wfnn-server"), "--id", self.server_id, "--controller", self.controller,
            "--listen", self.endpoint, "--data-dir", str(self.data_dir), "--quiet", "--verbose", *self.args,
        ]  # fmt: skip
        self.data_dir.parent.mkdir(parents=True, exist_ok=True)
        env = {**os.environ, "COLUMNS": "160", "PYTHONUNBUFFERED": "1"}
        self.proc = None
        try:
            with (
                noting(signal.SIGTERM, signal.SIGINT, keep_ignored=True) as noted,
                open(self.log, "ab") as log,
            ):
                # A signal raised inside Popen, after the fork, would leave a server nobody can stop.
                self.proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)
            if noted:  # the server stopped first: the caller's own handler, now restored, may end the process
                self.stop()
                signal.raise_signal(noted[0])
                raise InterruptedError(f"signal {noted[0]} while the server started")
            wait_listening(self.port)
        except BaseException:  # not listening in time, or the caller stopped (Ctrl-C, SIGTERM) meanwhile:
            self.stop()  # the caller never gets this server to stop, so it would outlive it
            raise
        return self

    def kill(self) -> None:
        """SIGKILL, as a crash."""
        assert self.proc is not None
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(timeout=10)

    def stop(self, timeout_s: float = 60.0) -> int:
        """SIGTERM and wait; returns the exit code.

        A server normally stops within a second, but one on a busy shared CI machine once took 21 s
        to reach its final checkpoint (every thread ended; the cause was not found), so the wait
        is generous.
        """
        if self.proc is None or self.proc.poll() is not None:
            return self.proc.returncode if self.proc else 0
        self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(timeout=10)
            raise

    def alive(self) -> bool:
        """Still running."""
        return self.proc is not None and self.proc.poll() is None

    def output(self) -> str:
        """What it logged."""
        return self.log.read_text(errors="replace") if self.log.exists() else ""

    def __enter__(self) -> ServerProcess:
        return self.start()

    def __exit__(self, *_: object) -> None:
        self.stop()
