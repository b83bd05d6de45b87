"""Real processes on loopback for the integration tests: free ports, servers started and stopped."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

BIN = Path(sys.executable).parent
ENV = {**os.environ, "COLUMNS": "160", "PYTHONUNBUFFERED": "1"}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def wait_listening(port: int, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.05)
    raise TimeoutError(f"nothing listens on port {port} after {timeout} s")


class ServerProcess:
    """`wfnn-server` in router mode on a loopback port; stopped (SIGTERM, then SIGKILL) on exit."""

    def __init__(self, data_dir: Path, port: int, *args: str, server_id: str = "srv", controller: str = "it"):
        self.data_dir, self.port, self.args = data_dir, port, list(args)
        self.server_id, self.controller = server_id, controller
        self.proc: subprocess.Popen[str] | None = None
        self.log = data_dir.parent / f"{server_id}-{port}.log"

    def start(self) -> ServerProcess:
        cmd = [
            str(BIN / "wfnn-server"), "--id", self.server_id, "--controller", self.controller,
            "--listen", endpoint(self.port), "--data-dir", str(self.data_dir), "--quiet", "--verbose",
            *self.args,
        ]  # fmt: skip
        with open(self.log, "a") as log:
            self.proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=ENV, text=True)
        wait_listening(self.port)
        return self

    def kill(self) -> None:
        assert self.proc is not None
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(timeout=10)

    def stop(self) -> int:
        if self.proc is None or self.proc.poll() is not None:
            return self.proc.returncode if self.proc else 0
        self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(timeout=10)
            raise

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def output(self) -> str:
        return self.log.read_text() if self.log.exists() else ""

    def __enter__(self) -> ServerProcess:
        return self.start()

    def __exit__(self, *_: object) -> None:
        self.stop()


def client(*args: str, timeout: float = 300) -> subprocess.Popen[str]:
    """Start `wfnn-client` with `args`."""
    cmd = [str(BIN / "wfnn-client"), "--controller", "it", *args]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=ENV, text=True)


def finish(proc: subprocess.Popen[str], timeout: float = 300) -> str:
    out, _ = proc.communicate(timeout=timeout)
    assert proc.returncode == 0, out
    return out
