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
