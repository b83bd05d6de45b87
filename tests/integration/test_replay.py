"""Passive learning: `wfnn-server --replay-only` learns from recorded experience logs, then serves on."""

import json
import os
import subprocess

import pytest

from tests.integration.procs import BIN, endpoint, free_port
from wfnn_io import logs
from wfnn_io.persist import load_weights

pytestmark = pytest.mark.multiprocess
ENV = {**os.environ, "COLUMNS": "160"}


def _run(*args, timeout=180):
    return subprocess.run([str(a) for a in args], capture_output=True, text=True, timeout=timeout, env=ENV)


def _record(out, sim="boat", episodes="2"):
    proc = _run(BIN / "wfnn-client", "--sim", sim, "--episodes", episodes, "--rate-hz", "0", "--lockstep",
                "--thinks", "3", "--out", out)  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return json.loads((out / "metrics.json").read_text())


def _replay(data_dir, *logs_dirs, options=(), listen=True):
    net = ["--listen", endpoint(free_port())] if listen else []  # without: no network is joined
    args = [BIN / "wfnn-server", "--id", "srv", "--controller", "it", *net, "--data-dir", data_dir, "--quiet",
            *options]  # fmt: skip
    for d in logs_dirs:
        args += ["--replay-only", d]
    return _run(*args)


def test_replay_only_learns_every_recorded_experience_once_and_refuses_a_foreign_log(tmp_path):
    _record(tmp_path / "rec")
    summary = logs.summarise(tmp_path / "rec" / "journal")
    assert summary.experiences == 400 and summary.learner_config is not None
    proc = _replay(tmp_path / "d", tmp_path / "rec" / "journal")
    assert proc.returncode == 0, proc.stdout + proc.stderr  # stopped by itself
    config, _, meta = load_weights(tmp_path / "d" / "checkpoint.npz")
    (client,) = summary.clients
    assert meta["stored_through"] == meta["learned_through"] == {client: 399}
    assert meta["thinks"] == config.thinks_per_action * 400 and config.thinks_per_action == 3
    # The store is an experience log too; replaying the same record again adds nothing.
    assert logs.summarise(tmp_path / "d" / "store").experiences == 400
    proc = _replay(tmp_path / "d", tmp_path / "rec" / "journal", listen=False)  # offline: no port taken
    said = " ".join((proc.stdout + proc.stderr).split())
    assert proc.returncode == 0 and "no network" in said, said
    assert "replay-only: 0 experiences imported, 400 stored, 1200 thinks in all" in said
    _, _, again = load_weights(tmp_path / "d" / "checkpoint.npz")
    assert again["thinks"] == meta["thinks"] and logs.summarise(tmp_path / "d" / "store").experiences == 400
    # A record of another task (learner spec) is refused with a clear error; nothing is stored.
    _record(tmp_path / "cartpole", sim="cartpole", episodes="1")
    proc = _replay(tmp_path / "d", tmp_path / "cartpole" / "journal")
    assert proc.returncode == 2 and "spec" in proc.stdout + proc.stderr
    assert logs.summarise(tmp_path / "d" / "store").experiences == 400
    # Passive learning with the best wire pulled toward the logged actions, a smaller learning
    # rate and another seed.
    options = ("--bc-weight", "0.5", "--alpha", "0.05", "--seed", "7")
    proc = _replay(tmp_path / "bc", tmp_path / "rec" / "journal", options=options)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    config, _, _ = load_weights(tmp_path / "bc" / "checkpoint.npz")
    assert (config.bc_weight, config.alpha, config.seed) == (0.5, 0.05, 7)
    assert (summary.learner_config["bc_weight"], summary.learner_config["alpha"]) == (0.0, 0.25)
    proc = _replay(tmp_path / "other", tmp_path / "nowhere")
    assert proc.returncode == 2 and "no experience log" in proc.stdout + proc.stderr


def test_wfnn_logs_inspects_merges_and_exports_records(tmp_path):
    _record(tmp_path / "a")
    _record(tmp_path / "b", episodes="1")
    proc = _run(BIN / "wfnn-logs", "inspect", "--json", tmp_path / "a" / "journal")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["experiences"] == 400
    proc = _run(BIN / "wfnn-logs", "merge", tmp_path / "a" / "journal", tmp_path / "b" / "journal",
                "--out", tmp_path / "all")  # fmt: skip
    assert proc.returncode == 0 and "600 experiences" in proc.stdout
    proc = _run(BIN / "wfnn-logs", "export", tmp_path / "all", "--out", tmp_path / "all.npz")
    assert proc.returncode == 0 and (tmp_path / "all.npz").exists()
    before = (tmp_path / "all.npz").read_bytes()
    proc = _run(BIN / "wfnn-logs", "export", tmp_path / "a" / "journal", "--out", tmp_path / "all.npz")
    assert proc.returncode == 2 and "exists (pass --replace" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and (tmp_path / "all.npz").read_bytes() == before
    proc = _run(BIN / "wfnn-logs", "export", tmp_path / "a" / "journal", "--out", tmp_path / "all.npz",
                "--replace")  # fmt: skip
    assert proc.returncode == 0 and "400 experiences" in proc.stdout
    proc = _run(
        BIN / "wfnn-logs", "inspect", "--json", tmp_path / "missing"
    )  # the error never goes in the JSON
    assert proc.returncode == 2 and "no experience log" in proc.stderr and proc.stdout == ""


def test_replay_only_with_the_deep_learner_and_its_overrides(tmp_path):
    """Passive learning, deep learner: its config from the log, the pull and rate from the server."""
    options = '{"deep": {"hidden": [16, 16], "value_hidden": 8, "warmup": 50}, "batch_size": 32}'
    proc = _run(BIN / "wfnn-client", "--sim", "boat", "--episodes", "2", "--rate-hz", "0", "--lockstep",
                "--thinks", "3", "--learner", "deep", "--learner-options", options,
                "--out", tmp_path / "rec")  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr
    summary = logs.summarise(tmp_path / "rec" / "journal")
    assert summary.experiences == 400 and summary.learner_config["learner"] == "deep"
    proc = _replay(
        tmp_path / "d", tmp_path / "rec" / "journal", options=("--bc-weight", "0.5", "--alpha", "0.001")
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    config, params, meta = load_weights(tmp_path / "d" / "checkpoint.npz")
    assert config.learner == "deep" and config.bc_weight == 0.5 and config.deep.lr == 0.001
    assert config.deep.hidden == (16, 16) and params.flat.shape[0] == 1
    # Three updates per experience stored in the learner (states beyond the sanity limits are not).
    assert 0 < meta["thinks"] <= 3 * 400 and meta["thinks"] % 3 == 0
    assert meta["learned_through"] == meta["stored_through"]
