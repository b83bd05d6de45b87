"""The one atomic write (`wfnn_io.persist`) at the edges of what a file system allows."""

from pathlib import Path

import numpy as np


def test_a_file_of_a_legal_name_of_255_bytes_is_written_and_probed():
    """Temporary names were the whole name and more: names of 240 to 255 bytes were refused."""
    import tempfile

    from wfnn_io.persist import atomic_savez, atomic_write_text, writable

    with tempfile.TemporaryDirectory() as d:
        for name in ("a" * 250 + ".json", "é" * 125 + ".npz"):
            path = Path(d) / name
            assert len(path.name.encode()) >= 254
            writable(path)
            if name.endswith(".npz"):
                atomic_savez(path, {"x": np.zeros(2)}, replace=False)
            else:
                atomic_write_text(path, "x")
            assert path.exists()
        assert len(list(Path(d).iterdir())) == 2  # nothing else left


def test_no_room_for_an_output_is_found_before_the_run_and_the_error_names_the_output(tmp_path):
    """A full disk still makes an empty file, so the probe writes bytes; and a write that fails
    (naming no file) names the output it was for. A file size limit stands in for a full disk."""
    import subprocess
    import sys

    script = f"""
import resource, signal, sys
from pathlib import Path
from wfnn_io.persist import atomic_write_text, writable
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit then fails with EFBIG
resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096))
out = Path({str(tmp_path)!r}) / "results.json"
for attempt in (lambda: writable(out), lambda: atomic_write_text(out, "x" * 100_000)):
    try:
        attempt()
        print("written")
    except OSError as exc:
        print("refused", exc.errno, exc.filename)
"""
    lines = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60,
                           check=True).stdout.split("\n")  # fmt: skip
    out = str(tmp_path / "results.json")
    assert lines[:2] == [f"refused 27 {out}", f"refused 27 {out}"]
    assert list(tmp_path.iterdir()) == []  # no probe, no temporary file left


def test_a_folder_to_make_at_a_link_to_nowhere_is_refused_saying_so(tmp_path):
    import pytest

    from wfnn_io.persist import make_directory

    (tmp_path / "loop").symlink_to("loop")
    (tmp_path / "dangling").symlink_to("missing")
    for name in ("loop", "dangling", "dangling/run"):
        with pytest.raises(NotADirectoryError, match=r"symbolic link to nowhere.*--out"):
            make_directory(tmp_path / name, "--out")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dangling", "loop"]
    (tmp_path / "file").write_text("x")
    with pytest.raises(NotADirectoryError, match="exists and is not a directory"):
        make_directory(tmp_path / "file", "--out")
    make_directory(tmp_path / "a" / "b", "--out")
    assert (tmp_path / "a" / "b").is_dir()
