"""Experience logs: recording, summary, merge, split, export, and refusing what does not fit."""

import os
import time
from pathlib import Path

import numpy as np
import pytest

from sims.boat import BoatVec
from sims.cartpole import CartPoleVec
from wfnn_client.brain import Experience, Recorder
from wfnn_common.config import LearnerConfig
from wfnn_io import logs, persist, segments
from wfnn_io.protocol import EXP_EXPLORED, EXP_VETO_ACTUAL, Codec


def record(directory, task_type=BoatVec, n=300, client="robot1", source="local", seed=0):
    """Record n random experiences of a task; -> the arrays recorded."""
    rng = np.random.default_rng(seed)
    config = LearnerConfig.for_task(task_type)
    recorder = Recorder(directory, config, client, batch_max=64)
    s = rng.uniform(-1, 1, (n, config.state_dim))
    a = rng.uniform(-1, 1, (n, config.action_dim))
    sn = rng.uniform(-1, 1, (n, config.state_dim))
    r = rng.normal(size=n)
    flags = np.where(np.arange(n) % 10 == 0, EXP_EXPLORED, 0) | np.where(
        np.arange(n) % 50 == 1, EXP_VETO_ACTUAL, 0
    )
    for i in range(n):
        recorder.add(Experience(s[i], a[i], sn[i], r[i], False, int(flags[i])), source, i // 100)
    recorder.close()
    return config, (s, a, sn, r, flags)


def test_a_record_reads_back_exactly_with_its_behaviour_metadata(tmp_path):
    config, (s, a, sn, r, flags) = record(tmp_path / "log")
    assert logs.log_config(tmp_path / "log").spec_hash() == config.spec_hash()
    batches = list(logs.read_batches(tmp_path / "log"))
    assert [b.first_seq for b in batches] == [0, 64, 128, 192, 256]
    np.testing.assert_array_equal(np.concatenate([b.state for b in batches]), s)
    np.testing.assert_array_equal(np.concatenate([b.reward for b in batches]), r)
    np.testing.assert_array_equal(np.concatenate([b.action for b in batches]), a)
    np.testing.assert_array_equal(np.concatenate([b.next_state for b in batches]), sn)
    np.testing.assert_array_equal(np.concatenate([b.flags for b in batches]), flags)
    assert np.concatenate([b.weights_version for b in batches]).tolist() == [i // 100 for i in range(300)]
    summary = logs.summarise(tmp_path / "log")
    assert summary.experiences == 300 and summary.clients["robot1"].last_seq == 299
    assert summary.clients["robot1"].gaps == summary.clients["robot1"].duplicates == 0
    assert summary.flags["explored"] == 30 and summary.flags["vetoed"] == 6
    assert summary.behaviour == {"local": 300} and summary.learner_config == config.to_dict()
    # A recorder on the same directory continues the client's numbering.
    again = Recorder(tmp_path / "log", config, batch_max=64)
    assert again.journal.client_id == "robot1" and again.journal.next_seq == 300
    again.close()


def test_merge_keeps_each_experience_once_and_export_gives_plain_arrays(tmp_path):
    config, (s, *_) = record(tmp_path / "a", n=200)
    record(tmp_path / "b", n=150, client="robot2", source="handcoded", seed=1)
    # The same client's log twice (a journal and a server's copy of it): stored once.
    n = logs.merge([tmp_path / "a", tmp_path / "b", tmp_path / "a"], tmp_path / "all")
    assert n == 350
    summary = logs.summarise(tmp_path / "all")
    assert {c: r.experiences for c, r in summary.clients.items()} == {"robot1": 200, "robot2": 150}
    assert summary.behaviour == {"local": 200, "handcoded": 150}
    with pytest.raises(logs.LogFormatError, match="already holds"):
        logs.merge([tmp_path / "a"], tmp_path / "all")
    count = logs.export([tmp_path / "all"], tmp_path / "all.npz")
    with np.load(tmp_path / "all.npz", allow_pickle=False) as data:
        assert count == 350 and data["state"].shape == (350, config.state_dim)
        robot1 = data["client"] == list(data["clients"]).index("robot1")
        np.testing.assert_array_equal(data["state"][robot1], s)
        np.testing.assert_array_equal(data["seq"][robot1], np.arange(200))
        assert str(data["spec_hash"]) == config.spec_hash()


def test_export_keeps_a_file_already_at_its_output_unless_told_to_replace_it(tmp_path):
    """An existing file at --out (another export, or anything of the user's) was silently replaced."""
    record(tmp_path / "a", n=20)
    theirs = tmp_path / "all.npz"
    theirs.write_bytes(b"someone's data")
    with pytest.raises(FileExistsError, match="pass --replace"):
        logs.export([tmp_path / "a"], theirs)
    assert theirs.read_bytes() == b"someone's data"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "all.npz"]  # no temporary left
    link = tmp_path / "link.npz"
    link.symlink_to(tmp_path / "nowhere")  # a dangling link is something at --out too
    with pytest.raises(FileExistsError):
        logs.export([tmp_path / "a"], link)
    assert link.is_symlink() and not (tmp_path / "nowhere").exists()
    assert logs.export([tmp_path / "a"], theirs, replace=True) == 20
    with np.load(theirs, allow_pickle=False) as data:
        assert data["state"].shape[0] == 20


def test_export_never_writes_inside_a_log_or_beside_a_servers_store(tmp_path):
    """`--replace` onto a segment of a live server's store left the server appending to the
    replaced file, and what it had acknowledged was gone from the store; onto its checkpoint,
    what it had learned."""
    record(tmp_path / "a", n=20)
    record(tmp_path / "srv" / "store", n=30, client="robot2")
    checkpoint = tmp_path / "srv" / "checkpoint.npz"
    checkpoint.write_bytes(b"weights")
    segment = sorted((tmp_path / "srv" / "store").glob("*.seg"))[0]
    before = segment.read_bytes()
    for out in (segment, tmp_path / "srv" / "store" / "new.npz", checkpoint, tmp_path / "srv" / "e.npz"):
        with pytest.raises(logs.LogFormatError, match="write somewhere else"):
            logs.export([tmp_path / "a"], out, replace=True)
    assert segment.read_bytes() == before and checkpoint.read_bytes() == b"weights"
    assert not (tmp_path / "srv" / "e.npz").exists() and not (tmp_path / "srv" / "store" / "new.npz").exists()
    assert logs.export([tmp_path / "a"], tmp_path / "e.npz") == 20  # anywhere else, as before
    # A folder is judged by what it holds, not by its files' names: a user's own learner_config.json
    # (for --learner-config) or log.json beside the output is no log.
    (tmp_path / "proj").mkdir()
    (tmp_path / "proj" / "learner_config.json").write_text("{}")
    (tmp_path / "proj" / "log.json").write_text('{"note": 1}')
    assert logs.export([tmp_path / "a"], tmp_path / "proj" / "all.npz") == 20
    (tmp_path / "notes.seg").write_text("a user's file")  # named like a segment, as no log names one
    assert logs.export([tmp_path / "a"], tmp_path / "proj" / "b.npz") == 20


def test_a_file_made_while_a_new_one_is_written_is_kept(tmp_path, monkeypatch):
    """The check before the write is not all: the name is taken in one step, or not at all."""
    target = tmp_path / "out.npz"

    def write(f):
        target.write_bytes(b"made meanwhile")  # another process, between the check and the rename
        f.write(b"new")

    with pytest.raises(FileExistsError, match="not replaced"):
        persist._atomic_write(target, write, replace=False)
    assert target.read_bytes() == b"made meanwhile"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.npz"]
    persist._atomic_write(tmp_path / "new.npz", lambda f: f.write(b"new"), replace=False)
    assert (tmp_path / "new.npz").read_bytes() == b"new" and (tmp_path / "new.npz").stat().st_nlink == 1


def test_split_by_client_behaviour_and_count(tmp_path):
    record(tmp_path / "a", n=200)
    record(tmp_path / "b", n=150, client="robot2", source="handcoded", seed=1)
    logs.merge([tmp_path / "a", tmp_path / "b"], tmp_path / "all")
    assert logs.split(tmp_path / "all", tmp_path / "by_client") == {"robot1": 200, "robot2": 150}
    assert logs.split(tmp_path / "all", tmp_path / "by_source", by="behaviour") == {
        "local": 200,
        "handcoded": 150,
    }
    # Batches of 64, 64, 64, 8 and 64, 64, 22: at most `every` each, whole batches (numbered by
    # experiences done, a batch just before a boundary overfilled its part and starved the next).
    parts = logs.split(tmp_path / "all", tmp_path / "parts", by="count", every=128)
    assert list(parts.values()) == [128, 72, 128, 22]
    parts = logs.split(tmp_path / "all", tmp_path / "parts100", by="count", every=100)
    assert list(parts.values()) == [64, 64, 72, 64, 86]
    assert logs.log_config(tmp_path / "by_client" / "robot2") is not None
    with pytest.raises(ValueError):
        logs.split(tmp_path / "all", tmp_path / "x", by="colour")


def test_logs_of_different_learner_specs_are_refused(tmp_path):
    record(tmp_path / "boat")
    record(tmp_path / "cartpole", task_type=CartPoleVec)
    with pytest.raises(logs.LogFormatError, match="spec"):
        logs.merge([tmp_path / "boat", tmp_path / "cartpole"], tmp_path / "mixed")
    with pytest.raises(logs.LogFormatError, match="no experience log"):
        list(logs.read_batches(tmp_path / "nowhere"))


def test_a_record_of_one_task_is_not_continued_by_another(tmp_path):
    record(tmp_path / "log")
    with pytest.raises(ValueError, match="another run directory"):
        Recorder(tmp_path / "log", LearnerConfig.for_task(CartPoleVec))
    assert logs.summarise(tmp_path / "log").experiences == 300


HOSTILE_SOURCES = ["../../outside", "a/../../b", "[/]", "[bold]x", "." * 40, "x" * 5000, "x" * 64 + "/"]


def test_split_writes_only_under_its_directory_whatever_the_log_names(tmp_path):
    # Client ids and behaviour names come off the network; "..", "a/../../b" and a 5,000
    # character name each get a directory of their own under `out`, and nothing is written
    # elsewhere.
    for i, source in enumerate(HOSTILE_SOURCES):
        record(tmp_path / f"s{i}", n=20, client=f"r{i}", source=source, seed=i)
    record(tmp_path / "dots", n=20, client="..", source="", seed=9)
    logs_made = [tmp_path / f"s{i}" for i in range(len(HOSTILE_SOURCES))] + [tmp_path / "dots"]
    logs.merge(logs_made, tmp_path / "all")
    before = sorted(p.name for p in tmp_path.iterdir())
    parts = logs.split(tmp_path / "all", tmp_path / "out", by="behaviour")
    assert sum(parts.values()) == 20 * (len(HOSTILE_SOURCES) + 1) and len(parts) == len(HOSTILE_SOURCES) + 1
    by_client = logs.split(tmp_path / "all", tmp_path / "out_clients", by="client")
    assert sum(by_client.values()) == 20 * (len(HOSTILE_SOURCES) + 1)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([*before, "out", "out_clients"])
    for out, names in ((tmp_path / "out", parts), (tmp_path / "out_clients", by_client)):
        assert sorted(p.name for p in out.iterdir() if p.name != ".lock") == sorted(names)
        for name in names:
            assert not name.startswith(".") and len(name) <= 64 and "/" not in name
            assert logs.summarise(out / name).experiences == names[name]
    # Each part holds one behaviour, the one its name was made from.
    behaviours = {next(iter(logs.summarise(tmp_path / "out" / n).behaviour)) for n in parts}
    assert behaviours == {*HOSTILE_SOURCES, "(none)"}


def test_inspect_prints_the_names_a_log_holds_verbatim(tmp_path):
    from typer.testing import CliRunner

    from wfnn_io.logs_cli import app

    for i, source in enumerate(HOSTILE_SOURCES[:4]):
        record(tmp_path / f"s{i}", n=20, client=f"r{i}", source=source, seed=i)
    logs.merge([tmp_path / f"s{i}" for i in range(4)], tmp_path / "log [1]")
    result = CliRunner().invoke(app, ["inspect", str(tmp_path / "log [1]")], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    for source in HOSTILE_SOURCES[:4]:
        assert f"chosen by {source}" in result.output
    assert "[1]: 80 experiences" in result.output  # the title keeps the path's brackets


def test_inspect_shows_a_huge_mean_reward_in_a_few_digits(tmp_path):
    """Rewards of 1e308 (forged, or a task's own) had their mean written out in over 300 digits."""
    from typer.testing import CliRunner

    from wfnn_io.logs_cli import app

    config = LearnerConfig.for_task(BoatVec)
    recorder = Recorder(tmp_path / "log", config, "robot1")
    for reward in (1e308, 1e308, -2.0):
        recorder.add(Experience(np.zeros(config.state_dim), np.zeros(config.action_dim),
                                np.zeros(config.state_dim), reward, False, 0), "local", 0)  # fmt: skip
    recorder.close()
    result = CliRunner().invoke(app, ["inspect", str(tmp_path / "log")], env={"COLUMNS": "200"})
    assert result.exit_code == 0 and "6.667e+307" in result.output and "66666" not in result.output


def test_inspect_names_a_segment_missing_between_others(tmp_path):
    from typer.testing import CliRunner

    from wfnn_io.logs_cli import app

    config, _ = record(tmp_path / "full", n=300)
    log = logs.ExperienceLog(tmp_path / "log", config, segment_bytes=4_000)
    for _, _, batch in logs.ExperienceLog(tmp_path / "full").entries():
        log.append(Codec(batch.client).encode(batch))
    log.close()
    assert len(list((tmp_path / "log").glob("*.seg"))) >= 3
    (tmp_path / "log" / "00000001.seg").unlink()
    result = CliRunner().invoke(app, ["inspect", str(tmp_path / "log")], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    assert "damaged, skipped (missing)" in result.output and "segment 1: not there, or empty" in result.output
    (tmp_path / "log" / "00000002.seg").rename(tmp_path / "log" / "000000002.seg")  # renamed by hand
    result = CliRunner().invoke(app, ["inspect", str(tmp_path / "log")], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    assert "named like segments, not read" in result.output and "000000002.seg" in result.output
    (tmp_path / "alone").mkdir()  # only a renamed segment: named, not "no .seg files"
    (tmp_path / "log" / "00000000.seg").rename(tmp_path / "alone" / "0.seg")
    result = CliRunner().invoke(app, ["inspect", str(tmp_path / "alone")], env={"COLUMNS": "300"})
    assert result.exit_code == 2 and "not read: '0.seg'" in result.output, result.output


@pytest.mark.parametrize("damage", [{"learner_config": {"state_low": "wrong"}}, {"id": 7}])
def test_a_log_description_that_cannot_be_used_is_kept_beside_its_replacement(tmp_path, damage):
    import json

    from tests.fakes import small_config

    logs.ExperienceLog(tmp_path / "log", small_config()).close()
    path = tmp_path / "log" / "log.json"
    held = json.dumps({**json.loads(path.read_text()), **damage})
    path.write_text(held)
    logs.ExperienceLog(tmp_path / "log", small_config()).close()
    [kept] = (tmp_path / "log").glob("log.json.unreadable-*")
    assert kept.read_text() == held  # what it held is not lost
    assert isinstance(json.loads(path.read_text())["id"], str)


def _snapshot(directory):
    return sorted((p, p.stat().st_size, p.read_bytes() if p.is_file() else b"") for p in directory.rglob("*"))


def test_no_output_is_written_inside_a_log_being_read(tmp_path):
    """Reading data never changes it, even when the output path names a place inside the input."""
    record(tmp_path / "log")
    before = _snapshot(tmp_path / "log")
    segment = next((tmp_path / "log").glob("*.seg"))
    with pytest.raises(logs.LogFormatError, match="inside the log"):
        logs.export([tmp_path / "log"], segment)
    with pytest.raises(logs.LogFormatError, match="inside the log"):
        logs.export([tmp_path / "log"], tmp_path / "log" / "log.json")
    with pytest.raises(logs.LogFormatError, match="inside the log"):
        logs.merge([tmp_path / "log"], tmp_path / "log" / "sub")
    with pytest.raises(logs.LogFormatError, match="inside the log"):
        logs.split(tmp_path / "log", tmp_path / "log")
    assert _snapshot(tmp_path / "log") == before
    (tmp_path / "data").mkdir()  # a server's data directory: its store, its config beside it
    (tmp_path / "log").rename(tmp_path / "data" / "store")
    with pytest.raises(logs.LogFormatError, match="inside the log"):
        logs.export([tmp_path / "data" / "store"], tmp_path / "data" / "learner_config.json")
    assert not (tmp_path / "data" / "learner_config.json").exists()
    # Nor in a log's subfolder, from another log: --replace over a store's quarantined tail lost
    # what the store had set aside.
    torn = tmp_path / "data" / "store" / "quarantine" / "00000000-0000000018.torn"
    torn.parent.mkdir()
    torn.write_bytes(b"set aside")
    record(tmp_path / "other")
    with pytest.raises(logs.LogFormatError, match="inside the log"):
        logs.export([tmp_path / "other"], torn, replace=True)
    assert torn.read_bytes() == b"set aside"


def test_a_merge_that_fails_leaves_no_log_behind_and_can_be_run_again(tmp_path):
    record(tmp_path / "log")
    (tmp_path / "notalog").mkdir()
    with pytest.raises(logs.LogFormatError):
        logs.merge([tmp_path / "log", tmp_path / "notalog"], tmp_path / "out")
    assert not (tmp_path / "out").exists()
    (tmp_path / "kept").mkdir()
    (tmp_path / "kept" / "notes.txt").write_text("mine")
    with pytest.raises(logs.LogFormatError):
        logs.merge([tmp_path / "log", tmp_path / "notalog"], tmp_path / "kept")
    assert [p.name for p in (tmp_path / "kept").iterdir()] == ["notes.txt"]
    assert logs.merge([tmp_path / "log"], tmp_path / "out") == 300
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "log.json").write_text("my own notes")  # not this project's: left alone
    with pytest.raises(logs.LogFormatError, match="already holds"):
        logs.merge([tmp_path / "log"], tmp_path / "mine")
    assert (tmp_path / "mine" / "log.json").read_text() == "my own notes"
    assert [p.name for p in (tmp_path / "mine").iterdir()] == ["log.json"]


def test_a_log_being_written_never_reads_as_a_log_until_it_is_whole(tmp_path, monkeypatch):
    """A merge cut short (SIGTERM, a crash) left a log that looked complete: read without damage."""
    record(tmp_path / "log")
    seen = []
    real = logs.ExperienceLog.append

    def append(self, frame):
        seen.append((self.directory.name, logs.is_log(tmp_path / "out")))
        if len(seen) == 3:
            raise KeyboardInterrupt  # as Ctrl-C, or SIGTERM through `guarded`
        return real(self, frame)

    monkeypatch.setattr(logs.ExperienceLog, "append", append)
    with pytest.raises(KeyboardInterrupt):
        logs.merge([tmp_path / "log"], tmp_path / "out")
    assert all(name.startswith(logs.PARTIAL) and not a_log for name, a_log in seen)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["log"]
    # What a killed write leaves (its hidden folder) is no log, and the next write clears it.
    monkeypatch.setattr(logs.ExperienceLog, "append", real)
    (tmp_path / "out" / f"{logs.PARTIAL}dead" / "00000000.seg").parent.mkdir(parents=True)
    assert not logs.is_log(tmp_path / "out")
    assert logs.merge([tmp_path / "log"], tmp_path / "out") == 300
    assert not list((tmp_path / "out").glob(f"{logs.PARTIAL}*"))
    assert logs.summarise(tmp_path / "out").experiences == 300


def test_a_second_writer_of_one_output_is_refused(tmp_path, monkeypatch):
    """Each wrote a hidden folder of its own and renamed it into place: one replaced the other."""
    record(tmp_path / "a", client="robot1")
    record(tmp_path / "b", client="robot2", seed=1)
    real = logs.ExperienceLog.append
    second = []

    def append(self, frame):
        if not second:
            with pytest.raises(segments.LogError, match="in use by another writer"):
                logs.merge([tmp_path / "b"], tmp_path / "out")
            second.append(True)
        return real(self, frame)

    monkeypatch.setattr(logs.ExperienceLog, "append", append)
    assert logs.merge([tmp_path / "a"], tmp_path / "out") == 300 and second
    assert set(logs.summarise(tmp_path / "out").clients) == {"robot1"}


def test_a_log_is_written_into_a_mount_point(tmp_path):
    """Written beside its output and renamed, it crossed devices into a file system's root."""
    from tests.mounts import tmpfs

    record(tmp_path / "log")
    with tmpfs(tmp_path / "disk", "4m") as disk:
        assert logs.merge([tmp_path / "log"], disk) == 300
        assert logs.summarise(disk).experiences == 300


def test_a_split_that_fails_in_a_later_part_leaves_none(tmp_path, monkeypatch):
    """The parts written before were left: the output looked like a split missing parts, and the
    same command was then refused."""
    record(tmp_path / "a", client="robot1")
    record(tmp_path / "b", client="robot2", seed=1)
    logs.merge([tmp_path / "a", tmp_path / "b"], tmp_path / "both")
    real, made = logs.ExperienceLog.__init__, []

    def opened(self, directory, *args, **kwargs):
        made.append(directory)
        if len(made) == 2:
            raise OSError(28, "No space left on device")
        real(self, directory, *args, **kwargs)

    monkeypatch.setattr(logs.ExperienceLog, "__init__", opened)
    with pytest.raises(OSError, match="No space"):
        logs.split(tmp_path / "both", tmp_path / "parts")
    assert not (tmp_path / "parts").exists()
    monkeypatch.setattr(logs.ExperienceLog, "__init__", real)
    assert logs.split(tmp_path / "both", tmp_path / "parts") == {"robot1": 300, "robot2": 300}


KILLED_AT_RENAME = """
import os, sys
import os
import time
from pathlib import Path
from wfnn_io import logs

real, moves = os.rename, []

def rename(source, target):  # killed (no handler runs) as the k-th file is moved into place
    if logs.PARTIAL not in str(target):
        moves.append(target)
        if len(moves) == int(sys.argv[1]):
            os._exit(9)
    return real(source, target)

os.rename = rename
if sys.argv[2] == "merge":
    logs.merge([Path(sys.argv[3])], Path(sys.argv[4]))
else:
    logs.split(Path(sys.argv[3]), Path(sys.argv[4]))
"""


def _killed_at_rename(k, command, source, out):
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[3]
    done = subprocess.run([sys.executable, "-c", KILLED_AT_RENAME, str(k), command, str(source), str(out)],
                          cwd=root, capture_output=True, timeout=120)  # fmt: skip
    assert done.returncode == 9, done.stderr.decode()[-2000:]


@pytest.mark.parametrize("k", [1, 2])
def test_a_merge_killed_while_moving_its_files_into_place_leaves_no_log_and_runs_again(tmp_path, k):
    """Killed between its renames, it left segments without log.json: read as a whole log, and
    the same merge was refused ("already holds a log")."""
    record(tmp_path / "log")
    _killed_at_rename(k, "merge", tmp_path / "log", tmp_path / "out")
    assert not logs.is_log(tmp_path / "out")
    with pytest.raises(logs.LogFormatError, match="not a whole log"):
        logs.summarise(tmp_path / "out")
    assert logs.merge([tmp_path / "log"], tmp_path / "out") == 300
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [".lock", "00000000.seg", "log.json"]
    assert logs.summarise(tmp_path / "out").experiences == 300


@pytest.mark.parametrize("k", [1, 2, 3, 4])
def test_a_split_killed_while_moving_its_parts_into_place_leaves_none_and_runs_again(tmp_path, k):
    """Killed between two parts, it left the first whole: a split missing parts, then refused."""
    record(tmp_path / "a", client="robot1")
    record(tmp_path / "b", client="robot2", seed=1)
    logs.merge([tmp_path / "a", tmp_path / "b"], tmp_path / "both")
    _killed_at_rename(k, "split", tmp_path / "both", tmp_path / "parts")
    for part in ("robot1", "robot2"):
        assert not logs.is_log(tmp_path / "parts" / part)
    with pytest.raises(logs.LogFormatError, match="not a whole log"):
        logs.summarise(tmp_path / "parts" / "robot1")
    assert logs.split(tmp_path / "both", tmp_path / "parts") == {"robot1": 300, "robot2": 300}
    assert sorted(p.name for p in (tmp_path / "parts").iterdir()) == [".lock", "robot1", "robot2"]
    assert logs.summarise(tmp_path / "parts" / "robot2").experiences == 300


def test_a_merge_into_a_part_of_a_killed_split_undoes_the_whole_split(tmp_path):
    """A split is all or none: a later write into one of its parts removes the others' files too."""
    record(tmp_path / "a", client="robot1")
    record(tmp_path / "b", client="robot2", seed=1)
    logs.merge([tmp_path / "a", tmp_path / "b"], tmp_path / "both")
    _killed_at_rename(3, "split", tmp_path / "both", tmp_path / "parts")
    assert logs.merge([tmp_path / "b"], tmp_path / "parts" / "robot1") == 300
    assert set(logs.summarise(tmp_path / "parts" / "robot1").clients) == {"robot2"}
    assert not (tmp_path / "parts" / "robot2").exists()
    assert not list((tmp_path / "parts").glob(f"{logs.PARTIAL}*"))


def _two_clients(tmp_path):
    record(tmp_path / "a", client="robot1")
    record(tmp_path / "b", client="robot2", seed=1)
    logs.merge([tmp_path / "a", tmp_path / "b"], tmp_path / "both")
    return tmp_path / "both"


def test_a_killed_split_part_reads_as_no_log_by_any_name(tmp_path, monkeypatch):
    """Through "." or a link to it, a part was judged by the wrong parent: read as whole."""
    both = _two_clients(tmp_path)
    _killed_at_rename(1, "split", both, tmp_path / "parts")
    (tmp_path / "link").symlink_to(tmp_path / "parts" / "robot1")
    assert not logs.is_log(tmp_path / "link")
    monkeypatch.chdir(tmp_path / "parts" / "robot1")
    assert not logs.is_log(Path("."))
    with pytest.raises(logs.LogFormatError, match="not a whole log"):
        logs.summarise(Path("."))


def test_a_failed_split_removes_only_what_it_made(tmp_path, monkeypatch):
    """It removed its output folder, or all that appeared in it meanwhile: another's merged log."""
    both = _two_clients(tmp_path)
    real, opened = logs.ExperienceLog.__init__, []

    def open_log(self, directory, *args, **kwargs):
        opened.append(directory)
        if len(opened) == 2:  # meanwhile another tool writes beside the parts, then the disk fills
            logs.merge([tmp_path / "a"], tmp_path / "parts" / "extra")
            raise OSError(28, "No space left on device")
        real(self, directory, *args, **kwargs)

    monkeypatch.setattr(logs.ExperienceLog, "__init__", open_log)
    with pytest.raises(OSError, match="No space"):
        logs.split(both, tmp_path / "parts")
    monkeypatch.setattr(logs.ExperienceLog, "__init__", real)
    assert sorted(p.name for p in (tmp_path / "parts").iterdir()) == ["extra"]
    assert logs.summarise(tmp_path / "parts" / "extra").experiences == 300


def test_a_write_into_a_part_of_a_split_at_work_is_refused_and_changes_nothing(tmp_path, monkeypatch):
    """Refused on the split's lock, it removed the files the split had moved into that part."""
    both = _two_clients(tmp_path)
    real, refused, moves = logs.os.rename, [], []

    def rename(source, target):
        moves.extend([target] if logs.PARTIAL not in str(target) else [])
        if len(moves) == 2 and not refused:  # robot1's first file is in place
            with pytest.raises(segments.LogError, match="in use"):
                logs.merge([tmp_path / "a"], tmp_path / "parts" / "robot1")
            refused.append(True)
        return real(source, target)

    monkeypatch.setattr(logs.os, "rename", rename)
    assert logs.split(both, tmp_path / "parts") == {"robot1": 300, "robot2": 300} and refused
    assert logs.summarise(tmp_path / "parts" / "robot1").experiences == 300


def test_a_split_part_may_be_a_link_to_another_file_system(tmp_path):
    """All parts were staged in the output's folder, and moving one across devices failed."""
    from tests.mounts import tmpfs

    both = _two_clients(tmp_path)
    with tmpfs(tmp_path / "disk", "4m") as disk:
        (tmp_path / "parts").mkdir()
        (tmp_path / "parts" / "robot1").symlink_to(disk)
        assert logs.split(both, tmp_path / "parts") == {"robot1": 300, "robot2": 300}
        assert logs.summarise(disk).experiences == 300


def test_the_files_list_is_durable_before_a_move_and_the_moves_before_it_goes(tmp_path, monkeypatch):
    """A power cut could keep moved files and lose the list (or the undo's unlinks and not the
    list's removal) on a file system that does not keep metadata changes in order."""
    both = _two_clients(tmp_path)
    events = []
    real_sync, real_rename, real_unlink = logs.sync_dir, logs.os.rename, Path.unlink
    monkeypatch.setattr(logs, "sync_dir", lambda d: (events.append(("sync", Path(d))), real_sync(d))[1])
    monkeypatch.setattr(
        logs.os, "rename", lambda a, b: (events.append(("move", Path(b))), real_rename(a, b))[1]
    )
    monkeypatch.setattr(Path, "unlink", lambda p, **k: (events.append(("unlink", p)), real_unlink(p, **k))[1])
    logs.split(both, tmp_path / "parts")
    moves = [i for i, (kind, _) in enumerate(events) if kind == "move"]
    [gone] = [i for i, (kind, p) in enumerate(events) if kind == "unlink" and p.name == logs.MOVING]
    before = {p for kind, p in events[: moves[0]] if kind == "sync"}
    hidden = {p for kind, p in events if kind == "sync" and p.name.startswith(logs.PARTIAL)}
    assert {tmp_path / "parts", tmp_path / "parts" / "robot1", tmp_path / "parts" / "robot2"} <= before
    assert len(hidden) == 3 and hidden <= before  # the list's folder and each part's pointer's
    synced = {p for kind, p in events[moves[-1] : gone] if kind == "sync"}
    assert {tmp_path / "parts" / "robot1", tmp_path / "parts" / "robot2"} <= synced
    assert ("sync", next(p for p in hidden if p.parent == tmp_path / "parts")) in events[gone:]


def test_an_undo_makes_its_removals_durable_before_the_list_goes(tmp_path, monkeypatch):
    both = _two_clients(tmp_path)
    _killed_at_rename(2, "split", both, tmp_path / "parts")  # robot1's first file moved
    events = []
    real_sync, real_rmtree = logs.sync_dir, logs.shutil.rmtree
    monkeypatch.setattr(logs, "sync_dir", lambda d: (events.append(("sync", Path(d))), real_sync(d))[1])
    monkeypatch.setattr(
        logs.shutil, "rmtree", lambda p, **k: (events.append(("rmtree", Path(p))), real_rmtree(p, **k))[1]
    )
    logs.merge([tmp_path / "b"], tmp_path / "parts" / "robot2")
    [listing] = [
        i for i, (kind, p) in enumerate(events) if kind == "rmtree" and p.parent == tmp_path / "parts"
    ]
    assert ("sync", tmp_path / "parts" / "robot1") in events[:listing]
    assert not (tmp_path / "parts" / "robot1").exists()  # made by the split, and empty again


def test_split_reads_a_log_as_merge_does(tmp_path):
    """It copied a duplicated segment twice and batches of other widths, which merge, export and
    --replay-only deduplicate or refuse: its parts then failed in those tools."""
    import shutil

    record(tmp_path / "log")
    shutil.copy(tmp_path / "log" / "00000000.seg", tmp_path / "log" / "00000001.seg")
    assert logs.summarise(tmp_path / "log").experiences == 600
    assert logs.split(tmp_path / "log", tmp_path / "parts") == {"robot1": 300}
    assert logs.summarise(tmp_path / "parts" / "robot1").clients["robot1"].duplicates == 0
    record(tmp_path / "cart", task_type=CartPoleVec, client="robot2")
    with segments.SegmentLog(tmp_path / "log", marker=logs.MAGIC) as log_:
        for _, frame, _ in logs.read_entries(tmp_path / "cart"):
            log_.append(frame)
    with pytest.raises(logs.LogFormatError, match="learner spec"):  # a boat's log, a cart-pole's batches
        logs.split(tmp_path / "log", tmp_path / "mixed")
    assert not (tmp_path / "mixed").exists()


def test_a_killed_split_moved_elsewhere_still_reads_as_no_log_and_runs_again(tmp_path):
    """Each part pointed to its split's list by where it was: moved, a part read as whole."""
    both = _two_clients(tmp_path)
    _killed_at_rename(2, "split", both, tmp_path / "parts")
    (tmp_path / "parts").rename(tmp_path / "moved")
    assert not logs.is_log(tmp_path / "moved" / "robot1")
    assert logs.split(both, tmp_path / "moved") == {"robot1": 300, "robot2": 300}


def test_a_new_output_folder_is_durable_when_the_write_returns(tmp_path, monkeypatch):
    """The folders a merge or split made (and so all in them) could vanish in a power cut."""
    both = _two_clients(tmp_path)
    synced = []
    real = logs.sync_dir
    monkeypatch.setattr(logs, "sync_dir", lambda d: (synced.append(Path(d)), real(d))[1])
    logs.merge([tmp_path / "a"], tmp_path / "results" / "new" / "merged")
    assert {tmp_path, tmp_path / "results", tmp_path / "results" / "new"} <= set(synced)
    synced.clear()
    logs.split(both, tmp_path / "results" / "parts")
    assert {tmp_path / "results", tmp_path / "results" / "parts"} <= set(synced)


def test_a_failed_split_leaves_what_was_in_its_output_before(tmp_path):
    """It removed the whole folder of each part written, with the notes a user kept there."""
    record(tmp_path / "a", client="robot1")
    record(tmp_path / "b", client="robot2", seed=1)
    logs.merge([tmp_path / "a", tmp_path / "b"], tmp_path / "both")
    (tmp_path / "parts" / "robot1").mkdir(parents=True)
    (tmp_path / "parts" / "robot1" / "notes.txt").write_text("mine")
    (tmp_path / "parts" / "robot2").write_text("a file where the second part goes")
    with pytest.raises(FileExistsError):
        logs.split(tmp_path / "both", tmp_path / "parts")
    assert sorted(p.name for p in (tmp_path / "parts" / "robot1").iterdir()) == ["notes.txt"]


def test_a_merge_that_fills_the_disk_leaves_neither_its_output_nor_a_full_disk(tmp_path):
    from tests.mounts import tmpfs

    record(tmp_path / "log", n=30000)
    with tmpfs(tmp_path / "small", "2m") as small:
        with pytest.raises(OSError, match="No space left"):
            logs.merge([tmp_path / "log"], small / "out")
        assert list(small.iterdir()) == []


def test_split_reads_a_log_whose_description_is_unreadable_as_the_others_do(tmp_path, caplog):
    record(tmp_path / "log")
    (tmp_path / "log" / "log.json").write_text("{not json")
    assert logs.split(tmp_path / "log", tmp_path / "parts") == {"robot1": 300}
    assert any("unreadable" in r.getMessage() for r in caplog.records)


def test_a_split_that_would_write_over_a_log_writes_nothing(tmp_path):
    record(tmp_path / "a", client="robot1")
    record(tmp_path / "b", client="robot2", seed=1)
    logs.merge([tmp_path / "a", tmp_path / "b"], tmp_path / "both")
    logs.split(tmp_path / "a", tmp_path / "parts")  # parts/robot1
    before = _snapshot(tmp_path / "parts")
    with pytest.raises(logs.LogFormatError, match="already holds a log"):
        logs.split(tmp_path / "both", tmp_path / "parts")  # robot1 and robot2: robot1 is taken
    assert _snapshot(tmp_path / "parts") == before and not (tmp_path / "parts" / "robot2").exists()


def test_inspect_json_of_a_log_with_no_readable_experience_is_strict_json(tmp_path):
    import json

    from typer.testing import CliRunner

    from wfnn_io.logs_cli import app

    Recorder(tmp_path / "empty", LearnerConfig.for_task(BoatVec)).close()
    result = CliRunner().invoke(app, ["inspect", "--json", str(tmp_path / "empty")])
    assert result.exit_code == 0, result.output

    def refuse(value):
        raise ValueError(f"not JSON: {value}")

    summary = json.loads(result.output, parse_constant=refuse)
    assert summary["experiences"] == 0 and summary["reward_mean"] is None


def test_the_mean_reward_is_of_the_finite_rewards_and_does_not_overflow(tmp_path, recwarn):
    """One NaN reward (recorded and flagged, never learned) made the whole mean NaN; rewards near
    float64's largest overflowed the sum."""
    config = LearnerConfig.for_task(BoatVec)
    recorder = Recorder(tmp_path / "log", config, "robot1", batch_max=4)
    z = np.zeros(config.state_dim)
    for r in (1e308, 1e308, np.nan, 1e308, -np.inf, 1e308, 1e308):
        recorder.add(Experience(z, np.zeros(config.action_dim), z, r, False, 0), "local", 0)
    recorder.close()
    summary = logs.summarise(tmp_path / "log")
    assert summary.experiences == 7 and summary.reward_mean == pytest.approx(1e308)
    assert not [w for w in recwarn if issubclass(w.category, RuntimeWarning)]


@pytest.mark.parametrize(
    ("runs", "gaps", "duplicates"),
    [
        ([(0, 9), (10, 19), (20, 29)], 0, 0),
        ([(0, 9), (20, 29), (10, 19)], 0, 0),  # a merged log, or a store whose hole was filled later
        ([(20, 29), (0, 9)], 1, 0),
        ([(0, 9), (20, 29), (12, 14)], 2, 0),
        ([(0, 9), (5, 14), (30, 39), (0, 39)], 0, 5 + 15 + 10),
        ([(0, 9), (0, 9), (0, 9)], 0, 20),
    ],
)
def test_gaps_and_duplicates_are_counted_whatever_the_order_of_the_batches(runs, gaps, duplicates):
    run = logs.ClientRun()
    for first, last in runs:
        run.add(first, last)
    assert (run.gaps, run.duplicates) == (gaps, duplicates)
    assert run.experiences == sum(b - a + 1 for a, b in runs)
    assert (run.first_seq, run.last_seq) == (min(a for a, _ in runs), max(b for _, b in runs))


def test_inspect_shows_control_characters_of_names_as_escapes_never_raw(tmp_path):
    """A name off the network holding an escape sequence (here: set the clipboard, clear the
    screen) reached the operator's terminal as it was."""
    from typer.testing import CliRunner

    from wfnn_io.logs_cli import app

    source = "\x1b]52;c;ZXZpbA==\x1b\\\x1b[2J\x9b\r"
    record(tmp_path / "log", n=20, source=source)
    result = CliRunner().invoke(app, ["inspect", str(tmp_path / "log")], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    assert not any(c in result.output for c in "\x1b\x9b\r")
    assert "chosen by \\x1b]52;c;ZXZpbA==\\x1b\\\\x1b[2J\\x9b\\x0d" in result.output


def test_log_records_reach_a_tools_handlers_with_their_control_characters_escaped():
    import io
    import logging

    from wfnn_io.cli_errors import log_printably

    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    root = logging.getLogger()
    root.addHandler(handler)
    try:
        log_printably()
        log_printably()  # once is enough: not a second filter
        logging.getLogger("wfnn.test").error("client %s says %s", "c1", "\x1b[2Jhi\rthere\n")
    finally:
        root.removeHandler(handler)
    # One record, one line: a newline in a name would start a line of the name's choosing.
    assert stream.getvalue() == "client c1 says \\x1b[2Jhi\\x0dthere\\n\n"
    assert len(handler.filters) == 1
    assert handler.filters[0].filter(logging.LogRecord("x", logging.ERROR, "f", 1, "%s %s", ("one",), None))


def test_a_newline_in_a_path_never_starts_a_line_of_its_own(tmp_path):
    """A name like 'x<newline>error: FORGED' printed a forged error line after the tool's own."""
    from typer.testing import CliRunner

    from wfnn_io.logs_cli import app

    record(tmp_path / "log", n=20)
    out = tmp_path / "x\nerror: FORGED.npz"
    result = CliRunner().invoke(
        app, ["export", str(tmp_path / "log"), "--out", str(out)], env={"COLUMNS": "300"}
    )
    assert result.exit_code == 0 and out.exists(), result.output
    assert not any(line.startswith("error:") for line in result.output.splitlines())
    assert "x\\nerror: FORGED.npz" in result.output


@pytest.mark.parametrize("version", [True, 1.0, "1", None])
def test_a_log_description_whose_version_is_not_a_whole_number_is_refused(tmp_path, version):
    import json

    from tests.fakes import small_config

    logs.ExperienceLog(tmp_path / "log", small_config()).close()
    path = tmp_path / "log" / "log.json"
    path.write_text(json.dumps({**json.loads(path.read_text()), "version": version}))
    with pytest.raises(logs.LogFormatError, match="version"):
        logs.read_log_json(tmp_path / "log")


@pytest.mark.parametrize("damage", ["torn", "missing", "unusable config"])
def test_a_record_whose_description_is_damaged_is_still_not_continued_by_another_task(tmp_path, damage):
    """With log.json damaged or gone, a journal took another task's experiences under the same
    client, and then no tool would read any of it (its batches of two specs)."""
    import json

    record(tmp_path / "log")
    path = tmp_path / "log" / "log.json"
    if damage == "torn":
        path.write_text("{")
    elif damage == "missing":
        path.unlink()
    else:
        path.write_text(json.dumps({**json.loads(path.read_text()), "learner_config": {"state_low": 1}}))
    before = {p.name: p.read_bytes() for p in (tmp_path / "log").iterdir()}
    with pytest.raises(ValueError, match=r"records experiences of learner spec .*another run directory"):
        Recorder(tmp_path / "log", LearnerConfig.for_task(CartPoleVec))
    assert {p.name: p.read_bytes() for p in (tmp_path / "log").iterdir()} == before  # refused: unchanged
    Recorder(tmp_path / "log", LearnerConfig.for_task(BoatVec)).close()  # its own task goes on
    assert logs.summarise(tmp_path / "log").experiences == 300


def test_a_record_of_the_other_learner_is_refused_naming_the_learners(tmp_path):
    record(tmp_path / "log")
    with pytest.raises(ValueError, match="the thesis learner's, not the deep learner's"):
        Recorder(tmp_path / "log", LearnerConfig.for_task(BoatVec, learner="deep"))
    with pytest.raises(ValueError, match=r"\(another task or ranges\)"):
        Recorder(tmp_path / "log", LearnerConfig.for_task(CartPoleVec))


def test_a_log_json_of_another_spec_than_the_records_is_told_and_never_written_on(tmp_path):
    """A log.json of another log (a deep learner's config beside a thesis learner's records) was
    shown as the log's own, and merge, split and export wrote it beside records it does not describe."""
    import shutil

    record(tmp_path / "boat", n=100)
    record(tmp_path / "cartpole", task_type=CartPoleVec, n=10)
    shutil.copy(tmp_path / "cartpole" / logs.LOG_JSON, tmp_path / "boat" / logs.LOG_JSON)
    before = {p.name: p.read_bytes() for p in (tmp_path / "boat").iterdir() if p.is_file()}
    summary = logs.summarise(tmp_path / "boat")
    assert summary.experiences == 100 and "its learner config is of spec" in summary.description_error
    for write in (
        lambda: logs.merge([tmp_path / "boat"], tmp_path / "merged"),
        lambda: logs.split(tmp_path / "boat", tmp_path / "parts"),
        lambda: logs.export([tmp_path / "boat"], tmp_path / "out.npz"),
    ):
        with pytest.raises(logs.LogFormatError, match=r"the spec of its log\.json's learner config"):
            write()
    assert not any((tmp_path / name).exists() for name in ("merged", "parts", "out.npz"))
    assert {p.name: p.read_bytes() for p in (tmp_path / "boat").iterdir() if p.is_file()} == before


def test_split_refuses_every_without_by_count(tmp_path):
    record(tmp_path / "log", n=50)
    with pytest.raises(ValueError, match="every is for split by count, not by client"):
        logs.split(tmp_path / "log", tmp_path / "parts", every=3)
    assert not (tmp_path / "parts").exists()


def test_a_second_opener_of_a_new_log_is_refused_before_it_writes_its_description(tmp_path, monkeypatch):
    """Both opened a new log at once: each wrote its log.json before taking the lock, and the one
    refused could leave its own (another id, another learner config) under the other's segments."""
    directory = tmp_path / "log"
    boat, cartpole = LearnerConfig.for_task(BoatVec), LearnerConfig.for_task(CartPoleVec)
    real = logs.write_log_json
    second = []

    def write_log_json(folder, config, log_id):
        if not second:  # another writer opens the same new log while the first writes its log.json
            second.append(True)
            with pytest.raises(segments.LogError, match="in use by another writer"):
                logs.ExperienceLog(folder, cartpole, fsync="never")
        return real(folder, config, log_id)

    monkeypatch.setattr(logs, "write_log_json", write_log_json)
    opened = logs.ExperienceLog(directory, boat, fsync="never")
    assert second
    info = logs.read_log_json(directory)
    assert info["id"] == opened.id
    assert LearnerConfig.from_dict(info["learner_config"]).spec_hash() == boat.spec_hash()


def test_experiences_of_two_runs_under_one_client_id_are_counted_and_named_when_merged(tmp_path, caplog):
    """Only the first copy of each number is kept; the other run's experiences under the same numbers
    were dropped without a word, as if they were the same experiences sent twice."""
    record(tmp_path / "a", n=300, client="twin")
    record(tmp_path / "b", n=200, client="twin", seed=1)  # another run: numbers 0-199 again
    record(tmp_path / "same", n=300, client="twin")  # the same experiences (a journal and a store)
    counts = logs.ReadCounts()
    sources = [tmp_path / "a", tmp_path / "same", tmp_path / "b"]
    kept = sum(len(b) for b in logs.merged(sources, counts=counts))
    assert kept == 300 and counts.conflicts == {"twin": 200}
    with caplog.at_level("WARNING", logger="wfnn_io.logs"):
        assert logs.merge([tmp_path / "a", tmp_path / "b"], tmp_path / "ab") == 300
        assert logs.export([tmp_path / "a", tmp_path / "b"], tmp_path / "ab.npz") == 300
    said = [r.getMessage() for r in caplog.records if "client twin" in r.getMessage()]
    assert len(said) == 2 and all("200 experiences are numbered as other experiences" in m for m in said)
    caplog.clear()
    with caplog.at_level("WARNING", logger="wfnn_io.logs"):
        logs.merge([tmp_path / "a", tmp_path / "same"], tmp_path / "asame")
    assert not [r for r in caplog.records if "numbered as other" in r.getMessage()]


def test_a_log_whose_segments_cannot_be_opened_is_refused_with_its_own_error(tmp_path):
    """The lock, handed to the segments, was closed by both when they failed: the second close's
    'Bad file descriptor' replaced the reason (and could close another thread's file)."""
    fifo = tmp_path / "fifo"
    fifo.mkdir()
    os.mkfifo(fifo / segments.segment_name(0))
    with pytest.raises(segments.LogError, match="not a regular file"):
        logs.ExperienceLog(fifo, fsync="never")
    locked = tmp_path / "locked"
    (locked / segments.LOCK).mkdir(parents=True)
    with pytest.raises(segments.LogError, match="is not a regular file: move it away"):
        logs.ExperienceLog(locked, fsync="never")
    with pytest.raises(ValueError, match="fsync must be"):
        logs.ExperienceLog(tmp_path / "bad", fsync="sometimes")


def test_a_file_set_aside_is_named_once_where_the_reason_names_it_too(tmp_path, caplog):
    """ "PATH: PATH: unreadable (...)" and "PATH: unreadable (PATH: not JSON ...)" named it twice."""
    import logging

    path = tmp_path / "log.json"
    path.write_text("{")
    with caplog.at_level(logging.ERROR):
        kept = logs.set_aside(path, f"unreadable ({path}: not JSON)")
    assert kept.exists() and not path.exists()
    assert caplog.text.count(str(path)) == 1 and "unreadable (not JSON)" in caplog.text


def test_every_reader_flags_a_journals_non_finite_experiences_as_a_server_flags_them(tmp_path):
    """A client's journal keeps its frames as sent, unflagged: inspect said non_finite 0, export
    wrote NaN rows with clean flags, and merge and split passed them on unflagged."""
    from wfnn_io.protocol import EXP_NON_FINITE

    rng = np.random.default_rng(0)
    config = LearnerConfig.for_task(BoatVec)
    recorder = Recorder(tmp_path / "log", config, "robot1", batch_max=16)
    bad = {3: "reward", 10: "state", 11: "next_state", 40: "action"}
    for i in range(50):
        s, sn = rng.uniform(-1, 1, config.state_dim), rng.uniform(-1, 1, config.state_dim)
        a = rng.uniform(-1, 1, config.action_dim)
        r = np.nan if bad.get(i) == "reward" else 0.5
        {"state": s, "action": a, "next_state": sn}.get(bad.get(i, ""), np.zeros(1))[0] = np.inf
        recorder.add(Experience(s, a, sn, r, False, EXP_EXPLORED if i == 10 else 0), "local", 1)
    recorder.close()
    flagged = [3, 10, 11, 40]
    assert logs.summarise(tmp_path / "log").flags["non_finite"] == 4
    arrays = logs.to_arrays([tmp_path / "log"])
    assert np.flatnonzero(arrays["flags"] & EXP_NON_FINITE).tolist() == flagged
    assert arrays["flags"][10] == EXP_NON_FINITE | EXP_EXPLORED  # the flags it had are kept
    logs.merge([tmp_path / "log"], tmp_path / "merged")
    merged = np.concatenate([b.flags for _, _, b in logs.read_entries(tmp_path / "merged")])  # as stored
    assert np.flatnonzero(merged & EXP_NON_FINITE).tolist() == flagged


def test_merge_and_split_refuse_an_output_in_a_log_or_a_servers_data_directory_as_export_does(tmp_path):
    """`split --out STORE` was taken (parts written inside a store: cut short, every reader refused
    the store), as were `merge --out DATA_DIR` and `merge --out STORE/x`."""
    record(tmp_path / "a")
    record(tmp_path / "b", client="robot3")
    record(tmp_path / "srv" / "store", client="robot2")  # a think server's data directory
    (tmp_path / "srv" / "incarnation").write_text("3")
    before = {p: p.read_bytes() for p in (tmp_path / "srv").rglob("*") if p.is_file()}
    refused = [
        (lambda: logs.split(tmp_path / "a", tmp_path / "srv" / "store"), "data directory"),
        (lambda: logs.split(tmp_path / "a", tmp_path / "b"), "already holds a log"),
        (lambda: logs.split(tmp_path / "a", tmp_path / "srv" / "parts"), "think server's data directory"),
        (lambda: logs.merge([tmp_path / "a"], tmp_path / "srv"), "think server's data directory"),
        (lambda: logs.merge([tmp_path / "a"], tmp_path / "srv" / "store" / "x"), "inside the log"),
        (lambda: logs.export([tmp_path / "a"], tmp_path / "srv" / "sub" / "a.npz"), "data directory"),
    ]
    for write, why in refused:
        with pytest.raises(logs.LogFormatError, match=why):
            write()
    assert {p: p.read_bytes() for p in (tmp_path / "srv").rglob("*") if p.is_file()} == before
    assert logs.split(tmp_path / "a", tmp_path / "parts") == {"robot1": 300}  # elsewhere, as before
    # Known by what the server writes beside its store: a store with no segment yet is one all
    # the same, and a user's own log named `store` makes no data directory of its folder.
    (tmp_path / "new" / "store").mkdir(parents=True)
    (tmp_path / "new" / "server_config.json").write_text("{}")
    with pytest.raises(logs.LogFormatError, match="data directory"):
        logs.merge([tmp_path / "a"], tmp_path / "new" / "x")
    logs.merge([tmp_path / "a"], tmp_path / "mine" / "store")
    assert logs.merge([tmp_path / "b"], tmp_path / "mine" / "other") == 300


def test_the_files_a_server_writes_are_those_that_mark_its_data_directory():
    from wfnn_server import server

    written = {
        server.CHECKPOINT,
        server.PREVIOUS_CHECKPOINT,
        server.LEARNER_JSON,
        server.SERVER_JSON,
        "incarnation",
    }
    assert written == set(logs.SERVER_FILES)


def test_an_export_clears_what_exports_cut_short_left_beside_its_file(tmp_path):
    """Each killed export left a full-size temporary file beside its output, for good."""
    record(tmp_path / "a")
    left = [tmp_path / "all.npzab3k_x9q.tmp", tmp_path / "all.npz00000000.tmp"]
    kept = [tmp_path / "all.npz.tmp", tmp_path / "other.npzab3k_x9q.tmp", tmp_path / "all.npzABCDEFGH.tmp"]
    live = tmp_path / "all.npzlive_tmp.tmp"  # another export's, being written: touched just now
    for path in [*left, *kept, live]:
        path.write_bytes(b"x" * 100)
        if path is not live:
            os.utime(path, (time.time() - 3600, time.time() - 3600))
    kept.append(live)
    assert logs.export([tmp_path / "a"], tmp_path / "all.npz") == 300
    assert not any(p.exists() for p in left) and all(p.exists() for p in kept)


def test_merge_and_split_of_logs_without_experiences_are_refused_as_export_is(tmp_path):
    """Merge wrote a log of 0 experiences and split nothing, both with exit 0, where export said
    "no experiences": a log whose records were all damaged looked merged."""
    empty = logs.ExperienceLog(tmp_path / "empty", LearnerConfig.for_task(BoatVec))
    empty.close()
    for write in (lambda: logs.merge([tmp_path / "empty"], tmp_path / "m"),
                  lambda: logs.split(tmp_path / "empty", tmp_path / "s"),
                  lambda: logs.export([tmp_path / "empty"], tmp_path / "e.npz")):  # fmt: skip
        with pytest.raises(logs.LogFormatError, match="no experiences in"):
            write()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty"]


def test_a_merge_the_disk_refuses_names_its_output_not_its_hidden_segment(tmp_path, monkeypatch):
    """A full disk was told as OUT/.partial-*/00000000.seg, a file gone once the write was undone."""
    from wfnn_io.cli_errors import describe

    record(tmp_path / "a")

    def full(self, frame):
        raise OSError(28, "No space left on device", str(self.directory / "00000000.seg"))

    monkeypatch.setattr(logs.ExperienceLog, "append", full)
    writes = [(lambda: logs.merge([tmp_path / "a"], tmp_path / "m"), tmp_path / "m"),
              (lambda: logs.split(tmp_path / "a", tmp_path / "s"), tmp_path / "s" / "robot1")]  # fmt: skip
    for write, out in writes:
        with pytest.raises(OSError) as failed:
            write()
        assert describe(failed.value) == f"{out}: No space left on device"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a"]


def test_a_merge_whose_source_cannot_be_read_names_the_source(tmp_path, monkeypatch):
    """Errors reading a source mid-merge were renamed to the output, as a full disk's are."""
    from wfnn_io.cli_errors import describe

    record(tmp_path / "a")
    record(tmp_path / "b", client="robot2")
    reading = logs.read_batches

    def failing(directory, *args, **kwargs):
        for i, batch in enumerate(reading(directory, *args, **kwargs)):
            if directory == tmp_path / "b" and i == 2:
                raise OSError(5, "Input/output error", str(directory / "00000000.seg"))
            yield batch

    monkeypatch.setattr(logs, "read_batches", failing)
    with pytest.raises(OSError) as failed:
        logs.merge([tmp_path / "a", tmp_path / "b"], tmp_path / "m")
    assert describe(failed.value) == f"{tmp_path / 'b' / '00000000.seg'}: Input/output error"
    assert not (tmp_path / "m").exists()


def test_the_files_that_mark_a_data_directory_are_those_the_server_writes():
    """The server clears its interrupted writes by this list, and merge, split and export know
    its data directory by it: one list, the server's file names."""
    from wfnn_server import server

    written = {server.CHECKPOINT, server.PREVIOUS_CHECKPOINT, server.LEARNER_JSON, server.SERVER_JSON}
    assert set(logs.SERVER_FILES) == written | {"incarnation"}
