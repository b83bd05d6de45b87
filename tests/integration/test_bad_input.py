"""Bad input to the command-line tools: one clear line, a nonzero exit, no traceback, nothing lost.

Each case is what a new user does: a truncated weights file, a mistyped endpoint, a port in
use, a missing or short key file, a run or data directory that is a file, read-only or full, a
missing or corrupt learner config, and a benchmark asked to write where it cannot.
"""

import contextlib
import os
import socket
import subprocess

import pytest

from tests.integration.procs import BIN, ServerProcess, endpoint, free_port
from tests.mounts import fill, read_only, tmpfs

pytestmark = [pytest.mark.slow, pytest.mark.multiprocess]
ENV = {**os.environ, "COLUMNS": "100"}


def run(*args, timeout=120):
    return subprocess.run([str(a) for a in args], capture_output=True, text=True, timeout=timeout, env=ENV)


def refused(proc, *words):
    """A nonzero exit, no traceback, an `error:` line naming `words`, and little else."""
    out = proc.stdout + proc.stderr
    assert proc.returncode != 0, out
    assert "Traceback" not in out and 'File "' not in out, out
    errors = [line for line in out.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, out
    for word in words:
        assert word.lower() in errors[0].lower(), out
    assert len(out.splitlines()) <= 6, out  # the start line, the error, and at most a progress line
    return errors[0]


@contextlib.contextmanager
def port_in_use():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        yield s.getsockname()[1]


def client(*args):
    return run(BIN / "wfnn-client", "--sim", "boat", "--episodes", "1", "--rate-hz", "0", *args)


def server(*args):
    return run(BIN / "wfnn-server", "--quiet", *args)


# --------------------------------------------------------------------------- wfnn-client
def test_client_truncated_weights_file(tmp_path):
    proc = client("--thinks", "1", "--out", tmp_path / "a")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    weights = (tmp_path / "a" / "weights.npz").read_bytes()
    (tmp_path / "w.npz").write_bytes(weights[: len(weights) // 2])
    refused(client("--weights", tmp_path / "w.npz", "--out", tmp_path / "b"), "w.npz", "npz")
    assert not (tmp_path / "b").exists()  # the refused start made no run directory it leaves behind
    # Nor the folders above one it had to make (x/ and x/y/ of --out x/y/z were left).
    refused(client("--weights", tmp_path / "w.npz", "--out", tmp_path / "x" / "y" / "z"), "w.npz")
    assert not (tmp_path / "x").exists()
    # And never a folder the user had, however --out spells it (build/../mine, with no build).
    (tmp_path / "mine").mkdir()
    refused(client("--weights", tmp_path / "w.npz", "--out", tmp_path / "build" / ".." / "mine"), "w.npz")
    assert (tmp_path / "mine").is_dir()
    # Weights of the other learner: the error says which learner they are for.
    proc = client("--learner", "deep", "--thinks", "1", "--out", tmp_path / "d")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    refused(client("--weights", tmp_path / "d" / "weights.npz", "--out", tmp_path / "c"), "--learner deep")
    # The other learner's weights for another task: switching learner would not help, so no hint.
    proc = run(BIN / "wfnn-client", "--sim", "cartpole", "--episodes", "1", "--rate-hz", "0",
               "--learner", "deep", "--thinks", "1", "--out", tmp_path / "e")  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr
    other = client("--weights", tmp_path / "e" / "weights.npz", "--out", tmp_path / "f")
    refused(other, "weights.npz", "spec")
    assert "--learner" not in other.stdout + other.stderr


def test_an_unknown_nomad_behaviour_is_refused_naming_every_known_one(tmp_path):
    """The sim's own check named servo and wander only: forage is the client's."""
    proc = run(BIN / "wfnn-client", "--sim", "nomad", "--behaviour", "nosuch", "--episodes", "1",
               "--rate-hz", "0", "--out", tmp_path / "run")  # fmt: skip
    refused(proc, "--behaviour", "servo", "wander", "forage", "nosuch")
    assert not (tmp_path / "run").exists()


def test_a_refused_start_leaves_the_last_runs_record_as_it_was(tmp_path):
    """Weights that do not fit (another task's, or a damaged file) refuse the start before it writes."""
    proc = client("--thinks", "1", "--out", tmp_path / "run")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    (tmp_path / "bad.npz").write_bytes(b"not weights")

    def record():
        files = sorted((tmp_path / "run").rglob("*"))
        return [
            (p, p.stat().st_size, p.stat().st_mtime_ns, p.read_bytes() if p.is_file() else b"") for p in files
        ]

    before = record()
    refused(client("--weights", tmp_path / "bad.npz", "--out", tmp_path / "run"), "bad.npz")
    mix = f"wfnn=0.5,weights:{tmp_path / 'bad.npz'}=0.5"
    refused(client("--behaviour-policy", mix, "--out", tmp_path / "run"), "bad.npz")
    assert record() == before
    # Another task on the same run directory: its journal refuses the start, and the record stays.
    other = run(BIN / "wfnn-client", "--sim", "cartpole", "--episodes", "1", "--rate-hz", "0",
                "--thinks", "1", "--out", tmp_path / "run")  # fmt: skip
    refused(other, "journal")
    assert record() == before


def test_client_bad_endpoint(tmp_path):
    refused(client("--server", "localhost-7447", "--out", tmp_path / "r"), "endpoint")
    refused(client("--server", "tcp/127.0.0.1:99999", "--out", tmp_path / "r"), "port")


def test_client_port_in_use(tmp_path):
    with port_in_use() as port:
        proc = client("--listen", endpoint(port), "--server", endpoint(free_port()), "--out", tmp_path / "r")
        refused(proc, "address already in use")


def test_client_missing_key_file(tmp_path):
    server = endpoint(free_port())
    proc = client("--server", server, "--key-file", tmp_path / "nokey", "--out", tmp_path / "r")
    refused(proc, "key file")


def test_client_out_is_a_file(tmp_path):
    (tmp_path / "f").write_text("x")
    refused(client("--out", tmp_path / "f"), "not a directory")
    assert (tmp_path / "f").read_text() == "x"


def test_client_out_on_a_read_only_file_system(tmp_path):
    with tmpfs(tmp_path / "m", "1m") as root:
        read_only(root)
        refused(client("--out", root / "run"), "read-only")


def test_client_out_on_a_full_disk(tmp_path):
    with tmpfs(tmp_path / "m", "256k") as root:
        fill(root)
        refused(client("--out", root / "run"), "no space")


def test_client_refuses_a_non_loopback_server_without_a_key(tmp_path):
    refused(client("--server", "tcp/192.0.2.7:7447", "--out", tmp_path / "r"), "--key-file", "--insecure")


def test_client_start_is_one_short_line_and_the_config_goes_to_the_run_directory(tmp_path):
    proc = client("--thinks", "1", "--out", tmp_path / "r")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    first = proc.stdout.splitlines()[0]
    assert first.startswith("wfnn-client boat") and "run directory" in first  # one line, even in a file
    assert len(proc.stdout.split("run directory")[0]) < 200
    assert "boat episodes: 1/1, " in proc.stdout  # progress as lines where the output is no terminal
    assert "NomadConfig" not in proc.stdout and "hydra=" not in proc.stdout
    import json

    saved = json.loads((tmp_path / "r" / "config.json").read_text())
    assert saved["client"]["sim"] == "boat" and "nomad" in saved["client"]


# --------------------------------------------------------------------------- wfnn-server
def serve(tmp_path, data_dir, *args):
    return server("--id", "srv", "--listen", endpoint(free_port()), "--data-dir", data_dir, *args)


def test_server_port_in_use(tmp_path):
    with port_in_use() as port:
        refused(server("--listen", endpoint(port), "--data-dir", tmp_path / "d"), "address already in use")


def test_server_bad_listen_endpoint(tmp_path):
    refused(server("--listen", "tcp:127.0.0.1:7447", "--data-dir", tmp_path / "d"), "endpoint")


def test_server_data_dir_is_a_file(tmp_path):
    (tmp_path / "f").write_text("x")
    refused(serve(tmp_path, tmp_path / "f"), "not a directory")


def test_server_data_dir_read_only(tmp_path):
    with tmpfs(tmp_path / "m", "1m") as root:
        read_only(root)
        refused(serve(tmp_path, root / "data"), "read-only")


def test_server_data_dir_full(tmp_path):
    with tmpfs(tmp_path / "m", "256k") as root:
        fill(root)
        refused(serve(tmp_path, root / "data"), "no space")


def test_server_missing_or_corrupt_learner_config(tmp_path):
    refused(serve(tmp_path, tmp_path / "d", "--learner-config", tmp_path / "none.json"), "learner config")
    (tmp_path / "bad.json").write_text('{"state_low": [0, 1], "alpha": ')
    refused(serve(tmp_path, tmp_path / "d", "--learner-config", tmp_path / "bad.json"), "not json")
    (tmp_path / "inf.json").write_text('{"state_low": [0], "state_high": [1], "action_low": [0], '
                                       '"action_high": [1], "alpha": Infinity}')  # fmt: skip
    refused(serve(tmp_path, tmp_path / "d", "--learner-config", tmp_path / "inf.json"), "alpha")


def test_server_missing_or_short_key_file(tmp_path):
    refused(serve(tmp_path, tmp_path / "d", "--key-file", tmp_path / "nokey"), "key file")
    (tmp_path / "short").write_text("abc")
    refused(serve(tmp_path, tmp_path / "d", "--key-file", tmp_path / "short"), "at least 16")


def test_server_refuses_listening_beyond_loopback_without_a_key(tmp_path):
    refused(server("--listen", "tcp/0.0.0.0:0", "--data-dir", tmp_path / "d"), "--key-file", "--insecure")


def test_server_starts_with_a_corrupt_incarnation_and_learner_config_in_its_data_dir(tmp_path):
    data = tmp_path / "d"
    data.mkdir()
    (data / "incarnation").write_text("not a number")
    (data / "learner_config.json").write_text("{truncated")
    with ServerProcess(data, free_port()) as srv:
        assert srv.alive()
    assert srv.proc.returncode == 0, srv.output()
    assert (data / "incarnation").read_text() == "1"
    assert len(list(data.glob("*.unreadable-*"))) == 2  # both kept, set aside


# --------------------------------------------------------------------------- wfnn-bench
def test_bench_json_on_a_read_only_path_fails_before_running(tmp_path):
    with tmpfs(tmp_path / "m", "1m") as root:
        read_only(root)
        proc = run(BIN / "wfnn-bench", "boat", "--controllers", "2", "--targets", "1", "--thinks", "1",
                   "--json", root / "boat.json")  # fmt: skip
        refused(proc, "read-only")
        assert "median" not in proc.stdout  # nothing ran


def test_bench_plot_must_be_a_png_and_the_run_starts_with_one_line_of_its_options(tmp_path):
    tiny = ("cartpole", "--runs", "1", "--steps", "1", "--thinks", "0", "--max-attempt-steps", "1",
            "--json", tmp_path / "c.json")  # fmt: skip
    proc = run(BIN / "wfnn-bench", *tiny, "--plot", tmp_path / "c.txt")
    refused(proc, "--plot", ".png")
    assert "cart-pole" not in proc.stdout and not list(tmp_path.iterdir())  # refused before the run
    proc = run(BIN / "wfnn-bench", *tiny, "--plot", tmp_path / "c.png")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.splitlines()[0] == "wfnn-bench cartpole runs=1, steps=1, thinks=0, max_attempt_steps=1"
    assert (tmp_path / "c.json").exists() and (tmp_path / "c.png").exists()


def test_router_refuses_a_mistyped_endpoint_and_a_port_in_use():
    refused(run(BIN / "wfnn-router", "--listen", "127.0.0.1:7447"), "endpoint", "tcp/")
    with port_in_use() as port:
        refused(run(BIN / "wfnn-router", "--listen", endpoint(port)), str(port))
