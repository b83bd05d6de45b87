"""Real processes on loopback for the integration tests."""

from __future__ import annotations

import os
import signal
import subprocess
from pathlib import Path

from wfnn_server.spawn import BIN, endpoint, free_port
from wfnn_server.spawn import ServerProcess as _ServerProcess

__all__ = ["ServerProcess", "client", "endpoint", "finish", "free_port"]
ENV = {**os.environ, "COLUMNS": "160", "PYTHONUNBUFFERED": "1"}


class ServerProcess(_ServerProcess):
    """A test server of the controller `it`."""

    def __init__(self, data_dir: Path, port: int, *args: str, server_id: str = "srv") -> None:
        super().__init__(data_dir, port, *args, server_id=server_id, controller="it")


def client(*args: str) -> subprocess.Popen[str]:
    """Start `wfnn-client` for the controller `it` with `args` (thinking locally: no controller)."""
    local = "local" in args or not {"--server", "--listen"} & set(args)  # refuses C/S options
    cmd = [str(BIN / "wfnn-client"), *([] if local else ["--controller", "it"]), *args]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=ENV, text=True,
                            preexec_fn=_interruptible)  # fmt: skip


def _interruptible() -> None:
    """SIGINT as in a terminal: a test run started in the background (&) inherits it ignored, and
    a child would then ignore the Ctrl-C a test sends it."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def finish(proc: subprocess.Popen[str], timeout: float = 300) -> str:
    out, _ = proc.communicate(timeout=timeout)
    assert proc.returncode == 0, out
    return out
