"""Versioned save/load of learner weights (with their config) and of experience buffers.

Files are `.npz` archives written atomically (temporary file, fsync, rename), read with
`allow_pickle=False`. Each carries a `format` name and `format_version`; a file of another
format or a newer version is refused with `PersistError`.
"""

from __future__ import annotations

import contextlib
import errno
import io
import json
import os
import re
import stat
import tempfile
import time
import zipfile
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from numpy.typing import NDArray

from wfnn_common.config import LearnerConfig
from wfnn_common.learners import Weights, n_params, weights_from_flat
from wfnn_common.replay import Experiences

WEIGHTS_FORMAT = "wfnn-weights"
EXPERIENCE_FORMAT = "wfnn-experiences"
FORMAT_VERSION = 1


class PersistError(ValueError):
    """A file is not a wfnn file of the expected kind and version, or does not fit."""


MAX_TEXT_BYTES = 64 << 20
"""The largest sidecar (a JSON description, a config, a key) `read_regular_text` reads."""


def read_regular_bytes(path: Path | str, limit: int = MAX_TEXT_BYTES) -> bytes:
    """A small file's content, refusing what is not a regular file.

    Opened without waiting (a FIFO put where a JSON file should be would block the reader for
    good) and checked before it is read; OSError for anything that is not a regular file of at
    most `limit` bytes.
    """
    return read_regular(path, limit)[0]


def read_regular(path: Path | str, limit: int = MAX_TEXT_BYTES) -> tuple[bytes, os.stat_result]:
    """`read_regular_bytes`, with the status of the file it read (one look: the same open file)."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise OSError(errno.EINVAL, "not a regular file", str(path))
        if info.st_size > limit:
            raise OSError(errno.EFBIG, f"larger than {limit} bytes", str(path))
        with os.fdopen(fd, "rb", closefd=False) as f:
            # As much as the file holds (a read of `limit` would reserve that much memory first),
            # and on in pieces where it has grown since.
            data = f.read(info.st_size + 1)
            if len(data) > info.st_size:
                parts, total = [data], len(data)
                while total <= limit and (more := f.read(min(1 << 20, limit + 1 - total))):
                    parts.append(more)
                    total += len(more)
                data = b"".join(parts)
    finally:
        os.close(fd)
    if len(data) > limit:
        raise OSError(errno.EFBIG, f"larger than {limit} bytes", str(path))
    return data, info


def read_regular_head(path: Path | str, n: int) -> bytes:
    """A regular file's first `n` bytes, whatever its size (to look for a mark in its head).

    Opened without waiting, as `read_regular_bytes` is; OSError for anything not a regular file.
    """
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise OSError(errno.EINVAL, "not a regular file", str(path))
        return os.read(fd, n)
    finally:
        os.close(fd)


def read_regular_text(path: Path | str, limit: int = MAX_TEXT_BYTES) -> str:
    """`read_regular_bytes` as UTF-8 text (UnicodeDecodeError for bytes that are not)."""
    return read_regular_bytes(path, limit).decode("utf-8")


def _read_umask() -> int:
    """The process's umask, read without changing it where Linux says it (no race with threads)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)  # at import, before any thread of ours creates files
    os.umask(mask)
    return mask


_UMASK = _read_umask()


def _atomic_write(
    path: Path, write: Callable[[BinaryIO], object], keep_previous: Path | None = None, replace: bool = True
) -> None:
    """Write a file so that a crash leaves the old file or the new one, never a torn one.

    `write(f)` fills a temporary file beside `path`, which is fsynced and renamed over it. With
    `keep_previous`, the file being replaced is moved there first (a crash between the two
    renames leaves the previous file and no newest one; readers fall back to it). With `replace`
    false, a file at `path` is never replaced: FileExistsError, before and after the write.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    _check_replaceable(path)
    if not replace and os.path.lexists(path):
        raise _not_replaced(path)
    if keep_previous is not None:
        _check_replaceable(Path(keep_previous))
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=_short(path.name), suffix=".tmp")
    except OSError as exc:  # named by the file asked for, not the temporary one beside it
        raise naming_file(exc, path) from exc
    try:
        # mkstemp makes the file 0600; the new file gets the mode the old one had, or the mode
        # open() would give it, so that a lab's shared results stay readable to the group.
        try:
            mode = path.stat().st_mode & 0o7777
        except FileNotFoundError:
            mode = 0o666 & ~_UMASK
        os.chmod(fd, mode)
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        if keep_previous is not None and path.exists():
            os.replace(path, keep_previous)
        if replace:
            os.replace(tmp, path)
        else:
            _link_new(Path(tmp), path)
    except OSError as exc:
        Path(tmp).unlink(missing_ok=True)
        raise naming_file(exc, path) from exc
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    sync_dir(path.parent)


def unfinished_write_of(name: str, target: str) -> bool:
    """Whether a file called `name` is the temporary file an atomic write of `target` fills.

    That is the target's (cut) name, mkstemp's 8 random characters and ".tmp", so that only what
    a crashed write left is cleared away, never a user's file named alike.
    """
    prefix = _short(target)
    middle = name[len(prefix) : -len(".tmp")] if name.startswith(prefix) and name.endswith(".tmp") else ""
    return re.fullmatch(r"[a-z0-9_]{8}", middle) is not None


def remove_unfinished_writes(folder: Path, targets: Iterable[str], older_than_s: float = 0.0) -> list[Path]:
    """Delete the temporary files that interrupted atomic writes of `targets` left in `folder`.

    One that never got renamed holds nothing its target does not (full size: one per crash
    would pile up). Regular files only (a link named alike is not followed), and only those
    untouched for `older_than_s` (a write under way now fills its file); -> those deleted.
    """
    names = list(targets)
    gone: list[Path] = []
    with contextlib.suppress(OSError):  # a folder that is not there yet holds none
        for entry in os.scandir(folder):
            if not any(unfinished_write_of(entry.name, name) for name in names):
                continue
            with contextlib.suppress(OSError):  # gone meanwhile, or not ours to delete
                if not entry.is_file(follow_symlinks=False):
                    continue
                if older_than_s and entry.stat(follow_symlinks=False).st_mtime >= time.time() - older_than_s:
                    continue
                os.unlink(entry.path)
                gone.append(Path(entry.path))
    return gone


def _short(name: str, most: int = 200) -> str:
    """A file's name cut to `most` bytes, to start a temporary name beside it.

    A name of 240 to 255 bytes is legal, and with the random part and suffix added, its whole
    length made the temporary file's name too long: the write was refused.
    """
    return name.encode(errors="surrogateescape")[:most].decode(errors="ignore")


def _link_new(tmp: Path, path: Path) -> None:
    """Give `tmp` the name `path` only where nothing has it: a file made there meanwhile is kept.

    A hard link fails where the name exists, in one step; the temporary name is then dropped.
    File systems without hard links get a check and a rename (a file made between the two would
    be replaced).
    """
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise _not_replaced(path) from None
    except OSError as exc:
        if exc.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EMLINK, errno.ENOSYS):
            raise
        if os.path.lexists(path):
            raise _not_replaced(path) from None
        os.replace(tmp, path)
        return
    tmp.unlink()


def _not_replaced(path: Path) -> FileExistsError:
    """The refusal of a write that may not replace what is at `path`."""
    return FileExistsError(errno.EEXIST, "exists (it is not replaced)", str(path))


def _check_replaceable(path: Path) -> None:
    """OSError unless `path` is missing or a regular file (a write renames a new file over it).

    A directory cannot be replaced; a FIFO, socket or device would be, silently, by a regular
    file that whatever reads it never sees.
    """
    if path.is_dir():
        raise IsADirectoryError(errno.EISDIR, "is a directory, not a file", str(path))
    if path.exists() and not path.is_file():
        raise OSError(errno.EINVAL, "exists and is not a regular file", str(path))


def naming_file(exc: OSError, path: Path) -> OSError:
    """`exc` naming `path` (what the user asked to write) where it names another file or none.

    A temporary file's name means nothing to the user; and a write or close that failed (a full
    disk) names no file, where a run with several outputs must say which one failed.
    """
    if str(exc.filename) != str(path) and exc.strerror:
        named = type(exc)(exc.errno, exc.strerror, str(path))
        named.renamed_from = exc  # type: ignore[attr-defined]  # its cause, which `describe` leaves unsaid
        return named
    return exc


def sync_dir(directory: Path) -> None:
    """Make the creations and renames in `directory` durable."""
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


MANIFEST = "manifest"
"""The member, first in every archive written here, that lists the names of the others: an archive
whose members are not those is damaged (one flipped bit in a zip's central directory can hide the
members after it, and the rest would load without them)."""


def atomic_savez(
    path: Path, arrays: dict[str, Any], keep_previous: Path | None = None, replace: bool = True
) -> None:
    """Write an `.npz` atomically (see `_atomic_write`), its `MANIFEST` first."""
    if MANIFEST in arrays:
        raise ValueError(f"{MANIFEST!r} is the name of the member that lists the others")
    members = {MANIFEST: np.str_(json.dumps(list(arrays))), **arrays}
    _atomic_write(path, lambda f: np.savez(f, **members), keep_previous, replace)


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write a file's bytes atomically (see `_atomic_write`)."""
    _atomic_write(path, lambda f: f.write(data))


def atomic_write_text(path: Path, text: str) -> None:
    """Write a text file atomically (see `_atomic_write`)."""
    _atomic_write(path, lambda f: f.write(text.encode()))


def make_directory(path: Path, what: str) -> None:
    """Make directory `path` (and its parents); NotADirectoryError naming `what` if a file is there."""
    path = Path(path)
    if os.path.lexists(path) and not path.is_dir():
        _nowhere(path, what)
        raise NotADirectoryError(errno.ENOTDIR, f"exists and is not a directory ({what})", str(path))
    try:
        path.mkdir(parents=True, exist_ok=True)
    except FileExistsError as exc:  # a folder on the way is a link to nowhere, say
        if exc.filename is not None:
            _nowhere(Path(exc.filename), what)
        raise


def _nowhere(path: Path, what: str) -> None:
    """NotADirectoryError if `path` is a symbolic link to nowhere (mkdir says only "File exists")."""
    if path.is_symlink() and not path.exists():
        why = f"is a symbolic link to nowhere (a loop, or a missing target) ({what})"
        raise NotADirectoryError(errno.ENOTDIR, why, str(path))


def folders_to_be_made(folder: Path) -> list[Path]:
    """The folders of `folder`'s path that do not exist yet, deepest first (what a run makes).

    Resolved first: spelled `build/../runs` with no `build`, an existing `runs` would be counted
    as missing (and removed after a refused start). A missing folder named before `..` is not
    counted, and so is left if made.
    """
    folder = Path(os.path.realpath(folder))
    missing = []
    while not os.path.lexists(folder) and folder != folder.parent:
        missing.append(folder)
        folder = folder.parent
    return missing


def remove_empty_folders(folders: list[Path]) -> None:
    """Remove those of `folders` (deepest first) that are empty folders: what a refused start made.

    One filled or gone meanwhile is left as it is, silently: the refusal is what is said.
    """
    for folder in folders:
        with contextlib.suppress(OSError):
            if folder.is_dir() and not folder.is_symlink() and not any(folder.iterdir()):
                folder.rmdir()


PROBE_BYTES = 64 << 10
"""What `writable` writes to see that there is room: as much as a run's small outputs take."""


def writable(path: Path) -> None:
    """Raise OSError now if file `path` cannot be written later (its missing folders made then).

    Nothing is made now: a run refused after this check (a bad option) leaves no folder behind.
    The nearest folder that exists is where the probe file goes.
    """
    path = Path(path)
    _check_replaceable(path)
    existing = path.parent
    while not os.path.lexists(existing) and existing != existing.parent:  # a dangling link is in the way
        existing = existing.parent
    if not existing.is_dir():  # a file where a folder is needed
        raise FileExistsError(
            errno.EEXIST, "a file is in the way (a directory is needed there)", str(existing)
        )
    try:
        prefix = f".{_short(path.name)}."
        with tempfile.NamedTemporaryFile(dir=existing, prefix=prefix, suffix=".probe") as probe:
            # Some bytes, not only a name: a full disk still makes an empty file, and a run told
            # its output can be written would only find out after all its work.
            probe.write(bytes(PROBE_BYTES))
            probe.flush()
    except OSError as exc:
        raise naming_file(exc, path) from exc


def save_figure(fig: Any, path: Path, dpi: int) -> None:
    """Write a matplotlib figure as a PNG atomically (the old picture or the new one, never a torn one)."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi)
    atomic_write_bytes(Path(path), buffer.getvalue())


def to_jsonable(obj: Any) -> Any:
    """Numpy scalars/arrays, paths -> plain JSON values (NaN and infinity -> null)."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return to_jsonable(obj.item())
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    if isinstance(obj, Path):
        return str(obj)
    return obj


def write_json(path: Path, data: dict[str, Any]) -> None:
    """Write `data` as JSON atomically (a crash never leaves half a file)."""
    atomic_write_text(Path(path), json.dumps(to_jsonable(data), indent=1))


MAX_INFLATION_BYTES = 64 << 20
"""How much larger than stored the members of an archive may unpack, all together: this project
writes its arrays uncompressed, and a small file whose members inflate to gigabytes is not one of
its files (64 members of 64 MiB each made a 3.7 MB file take 4 GB)."""
MAX_MEMBERS = 64
"""Most members an archive read here may have."""


def _members(path: Path, f: BinaryIO) -> list[str]:
    """The array names of the archive's members (open as `f`), checked before any is unpacked."""
    with zipfile.ZipFile(f) as archive:
        infos = archive.infolist()
    if len(infos) > MAX_MEMBERS:
        raise PersistError(f"{path}: {len(infos)} members, more than {MAX_MEMBERS}")
    listed = any(info.filename == MANIFEST + ".npy" for info in infos)
    if not listed and any(info.comment for info in infos):
        # Where no manifest lists the members (a file of an older version, or not written here),
        # a member's comment is what a damaged comment length makes of the members after it.
        raise PersistError(f"{path}: a member carries a comment, which no version writes: damaged, "
                           "or not a file of this project")  # fmt: skip
    stored = os.fstat(f.fileno()).st_size  # what the members declare they hold may lie
    unpacked = sum(info.file_size for info in infos)
    if unpacked > stored + MAX_INFLATION_BYTES:
        raise PersistError(f"{path}: its members would unpack from {stored:,} to {unpacked:,} bytes (this "
                           "project stores its arrays uncompressed)")  # fmt: skip
    return [info.filename.removesuffix(".npy") for info in infos]


def _check_manifest(path: Path, names: list[str], manifest: Any) -> None:
    """The members present must be those the archive's `MANIFEST` lists (files written before it: none)."""
    try:
        listed = json.loads(str(manifest))
    except (ValueError, RecursionError):
        listed = None
    if not isinstance(listed, list) or not all(isinstance(n, str) for n in listed):
        raise PersistError(f"{path}: damaged (its list of members is unreadable)")
    present = [n for n in names if n != MANIFEST]
    if sorted(present) != sorted(listed):
        missing = sorted(set(listed) - set(present))
        extra = sorted(set(present) - set(listed))
        raise PersistError(f"{path}: damaged (members missing: {', '.join(missing)[:200] or 'none'}; "
                           f"not listed: {', '.join(extra)[:200] or 'none'})")  # fmt: skip


def _open(path: Path, expected_format: str, wanted: Callable[[str], bool]) -> dict[str, Any]:
    """The arrays of an archive of `expected_format` that `wanted` takes (the rest are never unpacked).

    Opened without waiting and refused unless it is a regular file (a FIFO in its place would
    block the reader for good), and read from that one open file.
    """
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except FileNotFoundError:
        raise PersistError(f"{path}: no such file") from None
    except OSError as exc:
        raise PersistError(f"{path}: cannot be opened ({exc.strerror or exc})") from None
    try:
        mode = os.fstat(fd).st_mode
    except OSError:
        mode = 0
    if not stat.S_ISREG(mode):  # before fdopen, whose refusal of a folder named its descriptor, not it
        os.close(fd)
        raise PersistError(f"{path}: {'is a directory' if stat.S_ISDIR(mode) else 'not a regular file'}")
    try:
        with os.fdopen(fd, "rb") as f:
            names = _members(Path(path), f)
            take = [n for n in names if n in ("format", "format_version", MANIFEST) or wanted(n)]
            f.seek(0)
            with np.load(f, allow_pickle=False) as data:
                arrays = {k: data[k] for k in take}
    except PersistError:
        raise
    except Exception as exc:  # a truncated or damaged archive fails in zipfile, zlib or numpy alike
        detail = str(exc).split(". ")[0][:120]
        raise PersistError(f"{path}: not a readable .npz file ({type(exc).__name__}: {detail})") from None
    if MANIFEST in arrays:
        _check_manifest(Path(path), names, arrays.pop(MANIFEST))
    fmt = str(arrays.get("format", ""))
    if fmt != expected_format:
        raise PersistError(f"{path}: expected format {expected_format!r}, found {fmt!r}")
    raw = np.asarray(arrays.get("format_version", -1))
    if raw.shape != () or raw.dtype.kind not in "iu":  # a float, string, bool or array: damaged
        raise PersistError(f"{path}: format version {str(raw)[:40]!r} is not an integer")
    version = int(raw)
    if not 1 <= version <= FORMAT_VERSION:
        raise PersistError(f"{path}: format version {version} is not supported (<= {FORMAT_VERSION})")
    return arrays


def save_weights(
    path: Path, config: LearnerConfig, params: Weights, meta: dict[str, Any] | None = None,
    keep_previous: Path | None = None, training: dict[str, NDArray[Any]] | None = None,
) -> None:  # fmt: skip
    """Save a population's weights [P, n_params] with the config that defines them.

    `training`: the learner's training state beyond the weights (the deep learner's critics,
    targets and optimiser), kept as `train/<name>` arrays. With `keep_previous`, the file
    replaced is kept there (see `atomic_savez`). PersistError where the weights are not finite:
    `load_weights` would refuse the file, so none is written (the one there, if any, is kept).
    """
    if not np.isfinite(params.flat).all():
        raise PersistError(f"{path}: weights that are not finite are not saved")
    atomic_savez(
        path,
        {
            "format": np.str_(WEIGHTS_FORMAT),
            "format_version": np.int64(FORMAT_VERSION),
            "config": np.str_(config.to_json()),
            "spec_hash": np.str_(config.spec_hash()),
            "meta": np.str_(json.dumps(meta or {})),
            "params": params.flat,
            **{TRAINING_PREFIX + name: value for name, value in (training or {}).items()},
        },
        keep_previous,
    )


TRAINING_PREFIX = "train/"
WEIGHTS_MEMBERS = ("config", "spec_hash", "meta", "params")


def load_weights(path: Path) -> tuple[LearnerConfig, Weights, dict[str, Any]]:
    """Inverse of `save_weights` -> (config, params, meta); the training state is never unpacked."""
    config, params, meta, _ = load_checkpoint(path, training=False)
    return config, params, meta


def load_checkpoint(
    path: Path, training: bool = True
) -> tuple[LearnerConfig, Weights, dict[str, Any], dict[str, NDArray[Any]]]:
    """Inverse of `save_weights` -> (config, params, meta, training state: {} unless `training`)."""
    arrays = _open(
        path, WEIGHTS_FORMAT,
        lambda name: name in WEIGHTS_MEMBERS or (training and name.startswith(TRAINING_PREFIX)),
    )  # fmt: skip
    try:
        config = LearnerConfig.from_json(str(arrays["config"]), f"{path}: its config")
        meta = json.loads(str(arrays["meta"]))
        if not isinstance(meta, dict):
            raise PersistError(f"{path}: meta is not a map")
    except (KeyError, ValueError, RecursionError) as exc:
        raise PersistError(f"{path}: {exc}") from exc
    if str(arrays.get("spec_hash", "")) != config.spec_hash():
        raise PersistError(f"{path}: spec hash does not match its config")
    try:
        if np.asarray(arrays["params"]).dtype.kind not in "fiu":  # complex would lose its imaginary part
            raise TypeError(f"{np.asarray(arrays['params']).dtype} is not a real number type")
        flat = np.ascontiguousarray(arrays["params"], dtype=np.float64)
    except (KeyError, ValueError, TypeError) as exc:
        raise PersistError(f"{path}: no usable params ({exc})") from exc
    size = n_params(config)
    one = config.learner == "deep"
    if flat.ndim != 2 or flat.shape[0] < 1 or flat.shape[1] != size or (one and flat.shape[0] != 1):
        raise PersistError(f"{path}: params {flat.shape} do not fit the config ({size} per net)")
    if not np.isfinite(flat).all():
        raise PersistError(f"{path}: params contain non-finite values")
    state = {k[len(TRAINING_PREFIX) :]: v for k, v in arrays.items() if k.startswith(TRAINING_PREFIX)}
    try:
        weights = weights_from_flat(config, flat)
    except (ValueError, IndexError, TypeError) as exc:
        raise PersistError(f"{path}: params do not make the config's network ({exc})") from exc
    return config, weights, meta, state


def save_experiences(path: Path, config: LearnerConfig, exp: Experiences) -> None:
    """Save a block of experiences [N, ...] (the learner's scaled units, raw rewards)."""
    atomic_savez(
        path,
        {
            "format": np.str_(EXPERIENCE_FORMAT),
            "format_version": np.int64(FORMAT_VERSION),
            "config": np.str_(config.to_json()),
            "spec_hash": np.str_(config.spec_hash()),
            **exp._asdict(),
        },
    )


def load_experiences(path: Path, config: LearnerConfig | None = None) -> Experiences:
    """Inverse of `save_experiences`; with `config`, refuses experiences of another spec."""
    arrays = _open(
        path, EXPERIENCE_FORMAT, lambda name: name in ("config", "spec_hash", *Experiences._fields)
    )
    missing = [name for name in ("spec_hash", *Experiences._fields) if name not in arrays]
    if missing:
        raise PersistError(f"{path}: no {', '.join(missing)}")
    if any(np.ndim(arrays[name]) == 0 for name in Experiences._fields):
        raise PersistError(f"{path}: an experience array is a single number, not one per experience")
    if config is not None and str(arrays["spec_hash"]) != config.spec_hash():
        raise PersistError(
            f"{path}: experiences were recorded for spec {arrays['spec_hash']}, "
            f"this learner is {config.spec_hash()}"
        )
    if config is None:
        try:
            config = LearnerConfig.from_json(str(arrays.get("config", "")), f"{path}: its config")
        except (ValueError, RecursionError) as exc:
            raise PersistError(f"{path}: {exc}") from exc
    exp = Experiences(*(np.asarray(arrays[name]) for name in Experiences._fields))
    n = exp.reward.shape[0]
    s, a = config.state_dim, config.action_dim
    shapes = {"state": (n, s), "action": (n, a), "next_state": (n, s), "reward": (n,), "terminal": (n,)}
    for name, shape in shapes.items():
        array = getattr(exp, name)
        if array.shape != shape:
            raise PersistError(f"{path}: {name} is {array.shape}, not {shape} (N experiences, S={s}, A={a})")
        if array.dtype.kind not in ("b" if name == "terminal" else "fiu"):
            raise PersistError(f"{path}: {name} holds {array.dtype}, not "
                               f"{'booleans' if name == 'terminal' else 'real numbers'}")  # fmt: skip
    return exp
