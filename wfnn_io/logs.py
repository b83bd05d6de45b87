"""Experience logs: the one on-disk format of a client's record and of a server's store.

A log is a directory of segment files (`00000000.seg`, ...; `wfnn_io.segments`: CRC-framed
records). Every record is one protocol frame (`wfnn_io.protocol`, itself CRC-checked)
holding an `ExperienceBatch`:

- experiences numbered 0, 1, 2, ... per client (`client`, `first_seq`), in physical units:
  `state` [N, S], `action` [N, A] (as executed), `next_state` [N, S], `reward` [N] (raw),
  `terminal` [N];
- the behaviour policy: `weights_source` names what chose the batch's actions (a server
  `id:incarnation`, `local`, or a controller such as `handcoded`) and `weights_version` [N] the
  snapshot of it (0: none); `flags` [N] the `EXP_*` bits: exploration changed the action, the
  safe action ran, a veto replaced the proposal (and the proposal's own learn-twice record),
  the action filter changed it, a value was not finite (stored, never learned);
- `spec_hash`: the learner spec (state and action ranges) the experiences are for.

A client's journal keeps its frames as sent (HMAC-tagged where it has a key); a server stores
the batches it verified at ingest, untagged: the tag protects the network, not the disk.
Reading a log therefore needs no key; given one, a tagged frame that does not verify is
refused (counted `auth`), which tells a wrong key.

Beside the segments, `log.json` says what the log is: `{"format": "wfnn-log", "version": 1,
"id": "<16 hex>", "learner_config": {...} | null}`. `id` is the log's identity, made when it
was created (a server announces its store's in acks and status: a server restarted with a new,
empty store is another store). A client's journal (`--record DIR`: `DIR/journal/`) records
its learner config there; a server's store (`DATA_DIR/store/`) has it in
`DATA_DIR/learner_config.json` instead, which `log_config` also finds.

`ExperienceLog` is the one writer (the owner: journal and store), `read_entries` the one
reader: read-only, never changing a file, skipping damaged records (reported, with where they
are). This module also summarises, merges, splits and exports logs (`wfnn-logs`).
"""

from __future__ import annotations

import bisect
import contextlib
import errno
import itertools
import json
import logging
import os
import re
import secrets
import shutil
import time
from collections import Counter
from collections.abc import Collection, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeGuard, cast

import numpy as np
from numpy.typing import NDArray

from wfnn_common.config import LearnerConfig
from wfnn_io.persist import (
    atomic_savez,
    atomic_write_text,
    read_regular_text,
    remove_unfinished_writes,
    sync_dir,
)
from wfnn_io.protocol import (
    EXP_AFTER_LOSS,
    EXP_EXPLORED,
    EXP_FILTERED,
    EXP_NON_FINITE,
    EXP_SAFE_ACTION,
    EXP_VETO_ACTUAL,
    EXP_VETO_PROPOSED,
    MAGIC,
    AuthError,
    Codec,
    ExperienceBatch,
    ProtocolError,
    check_id,
    controller_key,
    decode,
    mark_non_finite,
)
from wfnn_io.segments import (
    LOCK,
    Damage,
    FsyncPolicy,
    LogError,
    Position,
    ReadReport,
    SegmentLog,
    named_strays,
    naming,
    read_records,
    segment_numbers,
    stray_segments,
    take_lock,
)

log = logging.getLogger(__name__)

LOG_JSON = "log.json"
LOG_FORMAT = "wfnn-log"
LOG_VERSION = 1
EXPORT_FORMAT = "wfnn-log-export"
FLAG_NAMES = {
    EXP_EXPLORED: "explored", EXP_SAFE_ACTION: "safe_action", EXP_VETO_ACTUAL: "vetoed",
    EXP_VETO_PROPOSED: "veto_proposal", EXP_FILTERED: "filtered", EXP_NON_FINITE: "non_finite",
    EXP_AFTER_LOSS: "after_loss",
}  # fmt: skip


class LogFormatError(ValueError):
    """A directory is not a usable experience log (or logs that do not fit together)."""


def is_log(directory: Path) -> bool:
    """Whether `directory` holds segment files of a whole log (none still being moved into place)."""
    directory = Path(directory)
    return directory.is_dir() and bool(segment_numbers(directory)) and not _unfinished(directory)


def remove_empty_log(directory: Path, also: Collection[str] = (), records: bool = False) -> bool:
    """Remove a log that holds no record (what a refused start made); -> whether it was removed.

    Only a folder of empty segments, its lock, its `log.json` and the files named in `also` (its
    owner's own, such as a journal's `client.json`) goes; anything else in it, or one byte in a
    segment, and it is left whole. So is a log another process has open (its lock is held): one
    that started beside the refused one and took the folder. With `records`, segments that hold
    records go too (a copy the refused start made of logs that still hold them).
    """
    directory = Path(directory)
    if not directory.is_dir() or directory.is_symlink():
        return False
    try:
        lock = take_lock(directory)  # held while it is removed: no owner can open it meanwhile
    except LogError:
        return False
    try:
        entries = list(directory.iterdir())
        own = {LOCK, LOG_JSON, *also}
        for entry in entries:
            if entry.is_symlink() or not entry.is_file():
                return False
            segment = entry.suffix == ".seg" and (records or entry.stat().st_size == 0)
            if entry.name not in own and not segment:
                return False
        for entry in entries:
            entry.unlink()
        directory.rmdir()
    finally:
        os.close(lock)
    return True


def new_log_id() -> str:
    """A fresh log identity (16 hex digits)."""
    return secrets.token_hex(8)


def _is_log_id(identity: object) -> TypeGuard[str]:
    """Whether a `log.json` id can name a store on the wire (acks and statuses carry it)."""
    if not isinstance(identity, str):
        return False
    try:
        check_id(identity, "log id")
    except ValueError:
        return False
    return True


def read_log_json(directory: Path) -> dict[str, Any] | None:
    """A log's `log.json` (None when there is none); LogFormatError when it cannot be read."""
    info = Path(directory) / LOG_JSON
    if not info.exists():
        return None
    try:
        data = json.loads(read_regular_text(info))
    except (OSError, ValueError, RecursionError) as exc:
        raise LogFormatError(f"{info}: unreadable ({exc})") from exc
    if (
        not isinstance(data, dict) or data.get("format") != LOG_FORMAT
        or type(data.get("version")) is not int or not 1 <= data["version"] <= LOG_VERSION
    ):  # fmt: skip
        raise LogFormatError(f"{info}: not a {LOG_FORMAT} version <= {LOG_VERSION} description")
    return data


def write_log_json(directory: Path, config: LearnerConfig | None, log_id: str | None = None) -> None:
    """Say what the log in `directory` is (its identity, and its learner config when known)."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    info = {"format": LOG_FORMAT, "version": LOG_VERSION, "id": log_id,
            "learner_config": config.to_dict() if config is not None else None}  # fmt: skip
    atomic_write_text(directory / LOG_JSON, json.dumps(info, indent=1))


SERVER_CONFIG_JSON = "learner_config.json"
"""A server's learner config, beside its store (a log)."""
SERVER_FILES = (SERVER_CONFIG_JSON, "server_config.json", "incarnation", "checkpoint.npz",
                "checkpoint.prev.npz")  # fmt: skip
"""What a think server writes beside its store (`wfnn_server.server`'s names): a folder holding a
`store` folder and any of them is a server's data directory."""


def log_config(directory: Path) -> LearnerConfig | None:
    """The learner config a log was recorded for, or None when nothing says.

    From the log's `log.json`, or a server's `learner_config.json` beside its store.
    """
    directory = Path(directory)
    data = read_log_json(directory)
    try:
        if data is not None and data.get("learner_config") is not None:
            return LearnerConfig.from_dict(data["learner_config"])
        server = directory.parent / SERVER_CONFIG_JSON
        if server.exists():
            return LearnerConfig.from_dict(json.loads(read_regular_text(server)))
    except (OSError, ValueError, TypeError, RecursionError) as exc:
        raise LogFormatError(f"{directory}: its learner config cannot be read ({exc})") from exc
    return None


def set_aside(path: Path, why: str) -> Path:
    """Rename an unreadable file beside itself (`NAME.unreadable-<unix time>`): kept, never deleted."""
    kept = path.with_name(f"{path.name}.unreadable-{time.time_ns()}")
    os.replace(path, kept)
    why = why.replace(f"{path}: ", "")  # where the reason names the file too: said once
    log.error("%s: %s; kept as %s", path, why, kept.name)
    return kept


MAX_CONFLICTS_LOGGED = 10
"""Clients named in `ReadCounts.warn_conflicts` (ids come from the network)."""


@dataclass
class ReadCounts:
    """What reading a log met besides batches."""

    report: ReadReport = field(default_factory=ReadReport)
    """Records read and damaged spans skipped (segment, offset, length)."""
    refused: Counter[str] = field(default_factory=Counter)
    """Intact records (segment CRC) whose frame was refused, by reason (`auth`, `malformed`, ...)."""
    conflicts: Counter[str] = field(default_factory=Counter)
    """Per client: experiences left out by `merged` as copies of a number already given, whose values
    differ from that one's (two runs under one client id, not the same experience sent twice)."""

    def warn_conflicts(self) -> None:
        """Log, per client, the experiences left out under a number another experience had."""
        for client, n in self.conflicts.most_common(MAX_CONFLICTS_LOGGED):
            log.warning("client %s: %d experiences are numbered as other experiences of that client read "
                        "before them (two runs under one client id?); only the first of each number is "
                        "kept", client, n)  # fmt: skip
        if len(self.conflicts) > MAX_CONFLICTS_LOGGED:
            log.warning("and %d more clients so", len(self.conflicts) - MAX_CONFLICTS_LOGGED)

    @property
    def unreadable(self) -> int:
        """Intact records whose frame is not a valid experience batch."""
        return sum(self.refused.values())

    @property
    def damage(self) -> list[Damage]:
        """Damaged spans skipped."""
        return self.report.damage


CLIENT_JSON = "client.json"
"""A client's journal's own record beside its segments (its client id, reserved numbers, and the
controller its frames are tagged for)."""


MAX_CONTROLLERS = 16
"""Controllers a journal records (the most recent), whose keys a reader tries."""


def client_meta(directory: Path, warn: bool = False) -> dict[str, Any]:
    """A client's journal's `client.json` as a dict (empty where it is missing or unreadable).

    With `warn`, one that is there but unreadable is named in a warning: a reader with a key
    needs the controllers it records to verify the journal's frames.
    """
    path = Path(directory) / CLIENT_JSON
    why = ""
    try:
        meta = json.loads(read_regular_text(path))
    except FileNotFoundError:
        return {}
    except (OSError, ValueError, RecursionError) as exc:
        meta, why = None, f"{type(exc).__name__}: {str(exc)[:200]}"
    if not isinstance(meta, dict):
        if warn:
            log.warning("%s cannot be read (%s): the controllers it records are unknown, so frames tagged "
                        "for any but the default controller fail the key's check", path,
                        why or "not a JSON object")  # fmt: skip
        return {}
    return meta


MAX_TASK_OPTIONS = 256
"""Most options a task record holds (a robot's config has a few dozen fields)."""
MAX_TASK_CHARS = 1024
"""Longest name or value in a task record (a longer one is damage, not a task)."""
Task = dict[str, Any]
"""What a client's experiences are of: {"sim": name, "options": {option: value}} (the options
that differ from their defaults; `wfnn_client.config.ClientConfig.task`)."""


def _task_value(value: Any) -> bool:
    """Whether `value` is what a task option holds: a number, string, boolean, or a list of them."""
    if isinstance(value, list):
        return len(value) <= MAX_TASK_OPTIONS and all(
            _task_value(v) and not isinstance(v, list) for v in value
        )
    if isinstance(value, str):
        return len(value) <= MAX_TASK_CHARS
    return value is None or isinstance(value, bool | int | float)


def journal_task(meta: dict[str, Any]) -> Task | None:
    """The task a journal's `client_meta` records (None: it says none; ValueError: it cannot be read).

    Numbers come back as floats (as `ClientConfig.task` gives them), booleans as booleans.
    """
    if "task" not in meta:
        return None
    task = meta["task"]
    options = task.get("options") if isinstance(task, dict) else None
    if not (isinstance(task, dict) and set(task) == {"sim", "options"} and isinstance(task["sim"], str)
            and 0 < len(task["sim"]) <= MAX_TASK_CHARS and isinstance(options, dict)
            and len(options) <= MAX_TASK_OPTIONS
            and all(isinstance(k, str) and len(k) <= MAX_TASK_CHARS and _task_value(v)
                    for k, v in options.items())):  # fmt: skip
        raise ValueError(f"its {CLIENT_JSON} records a task that cannot be read: {_shown(repr(task), 80)}")
    return {"sim": task["sim"], "options": {k: _as_float(v) for k, v in options.items()}}


def _as_float(value: Any) -> Any:
    if isinstance(value, list):
        return [_as_float(v) for v in value]
    return float(value) if isinstance(value, int) and not isinstance(value, bool) else value


def same_task(a: Task, b: Task) -> bool:
    """Whether two task records are one task: by value and type (True is not 1.0)."""
    return _typed(a) == _typed(b)


def _typed(value: Any) -> str:
    return json.dumps(value, sort_keys=True, default=repr)


def describe_task(task: Task, most: int = 5) -> str:
    """A task in one line: its sim, then the first `most` options that differ from their defaults."""
    items = sorted(task["options"].items())
    options = ", ".join(f"{_shown(k, 60)} {_shown_value(v)}" for k, v in items[:most])
    options += f", and {len(items) - most} more" if len(items) > most else ""
    sim = _shown(task["sim"], 60)
    return f"{sim} ({options})" if options else sim


def task_difference(recorded: Task, given: Task) -> str:
    """How `given` differs from `recorded`, option by option ("default": not set, its default)."""
    if recorded["sim"] != given["sim"]:
        return f"{describe_task(recorded)} there, {describe_task(given)} here"
    mine, theirs = recorded["options"], given["options"]
    keys = sorted(k for k in {*mine, *theirs} if _typed(mine.get(k)) != _typed(theirs.get(k)))
    said = [f"{_shown(k, 60)} {_shown_value(mine.get(k, 'default'))} there, "
            f"{_shown_value(theirs.get(k, 'default'))} here" for k in keys[:5]]  # fmt: skip
    return "; ".join(said) + (f"; and {len(keys) - 5} more options" if len(keys) > 5 else "")


def _shown(text: str, most: int) -> str:
    """`text` on one line (control characters escaped), cut to `most` characters."""
    escaped = "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)
    return escaped if len(escaped) <= most else escaped[: most - 3] + "..."


def _shown_value(value: Any) -> str:
    """An option's value as a person reads it: 15.0 as 15, a boolean as true/false, lists joined."""
    if isinstance(value, list):
        return _shown(",".join(_shown_value(v) for v in value[:8]) + (",..." if len(value) > 8 else ""), 120)
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float) and value.is_integer() and abs(value) < 1e15:
        return str(int(value))
    return _shown(str(value), 60)


def journal_controllers(meta: dict[str, Any]) -> list[str]:
    """The controllers a journal's `client_meta` records that its frames were tagged for (oldest first)."""
    named = meta.get("controllers", [])
    if not isinstance(named, list):
        return []
    kept = []
    for name in named[-MAX_CONTROLLERS:]:
        try:
            kept.append(check_id(name, "controller name"))
        except ValueError:
            continue
    return kept


def _candidate_keys(directory: Path, key: bytes) -> list[bytes]:
    """The keys a tag in this log may have been made with.

    Its controllers', then the default controller's, then the shared key itself (frames of
    clients from before tags named their controller).
    """
    names = [*journal_controllers(client_meta(directory, warn=True)), "default"]
    return [*dict.fromkeys(controller_key(key, name) for name in names), key]


def _decode_batch(frame: bytes, keys: list[bytes | None]) -> ExperienceBatch:
    """The batch of a stored frame whose tag, if any, verifies with one of `keys` (the last's error)."""
    for key in keys[:-1]:
        try:
            return cast(ExperienceBatch, decode(frame, key, expect=ExperienceBatch, mac="if_present").message)
        except AuthError:
            continue
    return cast(ExperienceBatch, decode(frame, keys[-1], expect=ExperienceBatch, mac="if_present").message)


def first_spec(directory: Path) -> str | None:
    """The learner spec of a log's first valid batch, or None where it holds none (read-only).

    What a log whose log.json is damaged or missing still says of its experiences: every batch
    carries its spec, and a log's batches share one (a log of another spec is refused).
    """
    for _, frame in read_records(directory, None, None, marker=MAGIC):
        try:
            return _decode_batch(frame, [None]).spec_hash  # tags unverified: only the spec is read
        except ProtocolError:
            continue
    return None


REFUSALS_TOLD = 5
"""Refused records named one by one in a read of a log; the rest are counted in one line."""


def read_entries(
    directory: Path, key: bytes | None = None, counts: ReadCounts | None = None
) -> Iterator[tuple[Position, bytes, ExperienceBatch]]:
    """Every experience batch in a log, oldest first: (where, frame, batch).

    Read-only. Damaged records are skipped (resynchronising on the next frame), frames that
    are not valid batches are refused; both are counted in `counts`. With `key`, a tag must
    verify with the key of a controller the client's journal records, the default controller's
    or the shared key itself (a wrong key is told: every tagged record is refused `auth`).
    """
    counts = counts if counts is not None else ReadCounts()
    keys: list[bytes | None] = [*_candidate_keys(directory, key)] if key else [None]
    refused: Counter[str] = Counter()  # this read's (`counts` may hold earlier reads' too)
    for position, frame in read_records(directory, None, counts.report, marker=MAGIC):
        try:
            batch = _decode_batch(frame, keys)
        except ProtocolError as exc:
            counts.refused[exc.reason] += 1
            refused[exc.reason] += 1
            if refused.total() <= REFUSALS_TOLD and not counts.report.quiet:  # a wrong key: told, not listed
                log.error("%s: record at %s is not an experience batch (%s); skipped",
                          directory, position, exc)  # fmt: skip
            continue
        assert isinstance(batch, ExperienceBatch)
        yield position, frame, batch
    if refused.total() > REFUSALS_TOLD and not counts.report.quiet:
        reasons = ", ".join(f"{reason} {n}" for reason, n in sorted(refused.items()))
        log.error("%s: %d records refused in all (%s), the first %d named above",
                  directory, refused.total(), reasons, REFUSALS_TOLD)  # fmt: skip


def read_batches(
    directory: Path, key: bytes | None = None, counts: ReadCounts | None = None
) -> Iterator[ExperienceBatch]:
    """Every experience batch in a log, oldest first (see `read_entries`); read-only.

    Experiences holding NaN or infinity are flagged EXP_NON_FINITE, as a server flags them at
    ingest: a client's journal keeps its frames as sent, unflagged.
    """
    check_log(directory)
    for _, _, batch in read_entries(directory, key, counts):
        yield mark_non_finite(batch)[0]


def check_log(directory: Path) -> None:
    """Refuse, naming why, a directory that is not a whole log (LogFormatError)."""
    if not is_log(directory):
        if _unfinished(directory):
            raise LogFormatError(
                f"{directory}: not a whole log: a write of it is under way, or was cut short (run that "
                "write again: what it left is removed then)"
            )
        strays = stray_segments(directory) if Path(directory).is_dir() else []
        if strays:  # a log's segments renamed by hand: said, as readers say it of a log
            raise LogFormatError(f"{directory}: no segment named as a log names them (00000000.seg on); "
                                 f"named like segments, not read: {named_strays(strays)}")  # fmt: skip
        raise LogFormatError(f"{directory}: no experience log here (no .seg files)")


class ExperienceLog:
    """The owner's handle on an experience log (a client's journal, a server's store).

    Opening it repairs a torn tail (moved to quarantine, see `wfnn_io.segments`) and gives
    the log an identity if it has none; `entries` reads it back with the one reader.
    """

    def __init__(
        self,
        directory: Path,
        config: LearnerConfig | None = None,
        *,
        fsync: FsyncPolicy = "interval",
        fsync_interval_s: float = 0.02,
        segment_bytes: int = 64 << 20,
    ) -> None:
        self.directory = Path(directory)
        try:
            self.directory.mkdir(parents=True)
            self.made = True
            """Whether opening it made its folder (a new log)."""
        except FileExistsError:
            self.made = False
        # Held from here: a log in use is refused before its log.json is set aside or rewritten, and
        # of two opening a new log at once, the one refused has written nothing.
        lock = take_lock(self.directory)
        try:
            self._open(config, lock, fsync, fsync_interval_s, segment_bytes)
        except BaseException:
            os.close(lock)
            raise

    def _open(self, config: LearnerConfig | None, lock: int, fsync: FsyncPolicy, fsync_interval_s: float,
              segment_bytes: int) -> None:  # fmt: skip
        damaged = ""
        try:
            info = read_log_json(self.directory)
        except LogFormatError as exc:
            info, damaged = None, str(exc)
        recorded, unusable = None, ""
        if info is not None and info.get("learner_config") is not None:
            try:
                recorded = LearnerConfig.from_dict(info["learner_config"])
            except (ValueError, TypeError) as exc:
                log.error("%s: the learner config it records is not usable (%s)", self.directory, exc)
                unusable = f"its learner config is not usable ({exc})"
        if config is not None and recorded is not None and recorded.spec_hash() != config.spec_hash():
            raise LogFormatError(
                f"{self.directory} records experiences of learner spec {recorded.spec_hash()}, not "
                f"{config.spec_hash()} ({recorded.spec_difference(config)}): use another run directory"
            )
        if config is not None and recorded is None:  # log.json damaged or gone: the records still say
            spec = first_spec(self.directory)
            if spec is not None and spec != config.spec_hash():
                raise LogFormatError(
                    f"{self.directory} records experiences of learner spec {spec}, not "
                    f"{config.spec_hash()} (another task, ranges or network; its {LOG_JSON} is damaged or "
                    "missing): use another run directory"
                )
        if damaged:  # only once nothing refuses the log: a refused open changes nothing
            set_aside(self.directory / LOG_JSON, damaged)
        identity = info.get("id") if info is not None else None
        self.id: str = identity if _is_log_id(identity) else new_log_id()
        """The log's identity, made when it was created."""
        if info is not None and identity != self.id:
            unusable = unusable or f"its id is not a name ({identity!r})"
        if info is None or identity != self.id or (config is not None and recorded is None):
            if unusable:  # rewritten below: what it held is kept beside it, never lost
                set_aside(self.directory / LOG_JSON, unusable)
            write_log_json(self.directory, config or recorded, self.id)
        self.segments = SegmentLog(
            self.directory, fsync=fsync, fsync_interval_s=fsync_interval_s, segment_bytes=segment_bytes,
            marker=MAGIC, lock=lock,
        )  # fmt: skip
        self.counts = ReadCounts()
        """What the last full read met (damage skipped, frames refused)."""

    def entries(self) -> Iterator[tuple[Position, bytes, ExperienceBatch]]:
        """Every batch stored so far: (where, frame, batch); what it skips is counted in `counts`."""
        self.counts = ReadCounts()
        self.segments.flush()
        return read_entries(self.directory, counts=self.counts)

    def append(self, frame: bytes) -> Position:
        """Store one encoded batch; where it starts."""
        return self.segments.append(frame)

    def frame_at(self, position: Position) -> bytes | None:
        """The frame stored at `position`, or None if that record is not valid."""
        return self.segments.read_at(position)

    def due(self) -> bool:
        """Whether appended frames wait for `sync` (per the fsync policy)."""
        return self.segments.due()

    def sync(self) -> None:
        """Make appended frames durable."""
        self.segments.sync()

    def close(self) -> None:
        """Sync and close."""
        self.segments.close()


@dataclass
class ClientRun:
    """One client's experiences in a log."""

    experiences: int = 0
    first_seq: int = -1
    last_seq: int = -1
    gaps: int = 0
    """Places where the numbering skips (experiences missing from the log)."""
    duplicates: int = 0
    """Experiences present more than once."""
    held: list[list[int]] = field(default_factory=list, repr=False)
    """The numbers present, as disjoint [first, last] runs in order (batches may come in any order:
    a merged log, or a server's store where re-sent experiences filled a hole)."""

    def add(self, first: int, last: int) -> None:
        """Count experiences first..last: duplicates of what is held, and the gaps left between."""
        self.experiences += last - first + 1
        self.first_seq = first if self.first_seq < 0 else min(self.first_seq, first)
        self.last_seq = max(self.last_seq, last)
        held = self.held
        if not held or first > held[-1][1] + 1:  # past the end: the usual case, in O(1)
            held.append([first, last])
        else:
            i = bisect.bisect_left(held, first, key=lambda run: run[1] + 1)  # first reaching first - 1
            j = i
            while j < len(held) and held[j][0] <= last + 1:
                self.duplicates += max(0, min(last, held[j][1]) - max(first, held[j][0]) + 1)
                j += 1
            if j > i:  # runs i..j-1 touch first..last (in order): one run now
                first, last = min(first, held[i][0]), max(last, held[j - 1][1])
            held[i:j] = [[first, last]]
        self.gaps = len(held) - 1


@dataclass
class Summary:
    """What a log holds (`wfnn-logs inspect`)."""

    experiences: int = 0
    batches: int = 0
    clients: dict[str, ClientRun] = field(default_factory=dict)
    spec_hashes: Counter[str] = field(default_factory=Counter)
    behaviour: Counter[str] = field(default_factory=Counter)
    """Experiences per `weights_source` (what chose the actions)."""
    flags: Counter[str] = field(default_factory=Counter)
    """Experiences per EXP_* flag name."""
    terminal: int = 0
    reward_mean: float = float("nan")
    """Mean of the finite rewards (NaN where there are none); those that are not are flagged."""
    refused: Counter[str] = field(default_factory=Counter)
    """Intact records whose frame was refused, by reason."""
    damage: list[Damage] = field(default_factory=list)
    """Damaged spans skipped (segment, offset, length, kind)."""
    strays: list[str] = field(default_factory=list)
    """Files named like segments but not as the log names them: not read."""
    learner_config: dict[str, Any] | None = None
    description_error: str = ""
    """Why `log.json` (or the store's learner config) could not be read, if it could not."""
    task: str = ""
    """The task a client's journal records its experiences are of, in a line ("": not said, or not a
    journal; "unreadable: ..." where its record cannot be read)."""
    task_record: Task | None = None
    """That task as recorded (`journal_task`): what a script compares."""

    @property
    def unreadable(self) -> int:
        """Intact records whose frame is not a valid experience batch."""
        return sum(self.refused.values())

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready."""
        return {
            "experiences": self.experiences, "batches": self.batches,
            "clients": {c: {k: v for k, v in vars(r).items() if k != "held"} for c, r in self.clients.items()},  # noqa: E501
            "spec_hashes": dict(self.spec_hashes), "behaviour": dict(self.behaviour),
            "flags": dict(self.flags),
            "terminal": self.terminal, "reward_mean": self.reward_mean, "unreadable": self.unreadable,
            "refused": dict(self.refused), "damage": [vars(d) for d in self.damage],
            "skipped_bytes": sum(d.length for d in self.damage), "strays": self.strays,
            "learner_config": self.learner_config, "description_error": self.description_error,
            "task": self.task, "task_record": self.task_record,
        }  # fmt: skip


def _mean(values: NDArray[np.float64], weights: NDArray[np.float64] | None = None) -> float:
    """The (weighted) mean of finite values, without overflowing where they are near float64's largest."""
    scale = float(np.abs(values).max()) or 1.0
    scaled = values / scale
    return scale * float(np.mean(scaled) if weights is None else np.sum(scaled * weights))


def summarise(directory: Path, key: bytes | None = None) -> Summary:
    """Count a log's experiences per client, behaviour policy and flag; find gaps and duplicates."""
    out = Summary()
    counts = ReadCounts()
    means: list[tuple[int, float]] = []
    """(finite rewards, their mean) per batch: summed as they came, rewards near float64's largest
    overflowed, and one NaN (recorded, flagged, never learned) made the whole mean NaN."""
    for batch in read_batches(directory, key, counts):
        n = len(batch)
        out.batches += 1
        out.experiences += n
        out.clients.setdefault(batch.client, ClientRun()).add(batch.first_seq, batch.last_seq)
        out.spec_hashes[batch.spec_hash] += n
        out.behaviour[batch.weights_source or "(none)"] += n
        for bit, name in FLAG_NAMES.items():
            out.flags[name] += int(np.count_nonzero(batch.flags & bit))
        out.terminal += int(np.count_nonzero(batch.terminal))
        finite = batch.reward[np.isfinite(batch.reward)]
        if finite.size:
            means.append((finite.size, _mean(finite)))
    out.refused, out.damage, out.strays = counts.refused, counts.damage, counts.report.strays
    total = sum(n for n, _ in means)
    if total:  # weights that sum to 1: no partial sum beyond the largest term
        out.reward_mean = _mean(np.array([m for _, m in means]), np.array([n / total for n, _ in means]))
    try:
        config = log_config(directory)
    except LogFormatError as exc:  # the experiences are still there: say so, read on
        out.description_error = str(exc)
        config = None
    out.learner_config = config.to_dict() if config is not None else None
    try:
        recorded = journal_task(client_meta(directory))
    except ValueError as exc:
        out.task = f"unreadable: {exc}"
    else:
        out.task, out.task_record = (describe_task(recorded) if recorded is not None else ""), recorded
    if config is not None and out.spec_hashes and config.spec_hash() not in out.spec_hashes:
        out.description_error = (f"its learner config is of spec {config.spec_hash()}, its experiences of "
                                 f"{', '.join(out.spec_hashes)} (a {LOG_JSON} of another log?)")  # fmt: skip
    return out


def write_log(
    directory: Path,
    batches: Iterable[ExperienceBatch],
    config: LearnerConfig | None,
    sender: str = "wfnn-logs",
) -> int:
    """Write batches as a new log (refuses a directory that already holds one); -> experiences.

    See `_write_logs`: a write cut short by anything (a full disk, a signal, a crash or a power
    cut) never leaves what reads as a log there, and the same command can be run again.
    """
    return _write_logs(Path(directory), {"": batches}, config, sender)[""]


PARTIAL = ".partial-"
"""The name of a write's hidden folders (one inside each of its outputs) until all is whole."""
MOVING = "moving.json"
"""In a write's hidden folder in its root: the files (paths under the root) being moved into place,
and the part folders made for them. While it is there none of them is part of a log; a write cut
short then (killed, a power cut) is undone by the next write there."""
PART_OF = "part-of"
"""In a split part's hidden folder: the path of its split's `moving.json` (the part is no whole
log while that is there)."""
_NAME = re.compile(r"[A-Za-z0-9_\-][A-Za-z0-9_.\-]{0,63}")
"""A path component that a `moving.json` may name (as `_directory_name` makes them)."""
_LOG_FILE = re.compile(r"[0-9]{1,20}\.seg|log\.json")
"""The only files an undo removes: a log's own (a hostile list cannot name others)."""


def _write_logs(
    root: Path, parts: Mapping[str, Iterable[ExperienceBatch]], config: LearnerConfig | None, sender: str
) -> dict[str, int]:
    """Write each part's batches as a new log at root / part ("": root itself), all or none.

    Each output is locked throughout (a second writer is refused), and each log is written in a
    hidden folder inside its output (`.partial-*`, on the output's file system) and made
    durable. Then the list of the files (`moving.json`, in root's hidden folder) is made durable,
    they are moved into place, and the list is removed last. A write that fails removes only
    what it made; what a killed one left (its folders, and the files its list names that it had
    moved) is removed by the next write there, and readers meanwhile take none of it for a log.
    """
    targets = {name: root / name if name else root for name in parts}
    for target in targets.values():  # all checked before any is written: a refusal writes nothing
        _check_new(target)
        if target.exists() and not target.is_dir():
            raise FileExistsError(
                errno.EEXIST, "a file is in the way (a directory is needed there)", str(target)
            )
    token = f"{PARTIAL}{secrets.token_hex(4)}"
    made: list[Path] = []
    """Folders this write made, and lock files (unmade if it fails)."""
    above = root.parent
    while not above.is_dir() and above != above.parent:  # the folder that holds what it makes
        above = above.parent
    locks: list[int] = []
    codec = Codec(sender)
    written: dict[str, int] = {}
    try:
        for folder in dict.fromkeys([root, *targets.values()]):
            if not folder.is_dir():
                folder.mkdir(parents=True)
                made.append(folder)
            if not (folder / LOCK).exists():
                made.append(folder / LOCK)
            locks.append(take_lock(folder))
        for folder in reversed([root.parent, *root.parent.parents]):  # new folders' entries durable
            if folder == above or above in folder.parents:
                sync_dir(folder)
        _undo_unfinished(root, list(targets.values()))
        for target in targets.values():
            _check_new(target)  # again, now that no other writer can make one there
        files: list[str] = []
        for name, batches in parts.items():
            staging = targets[name] / token
            # No fsync per record: each segment is made durable when it is full, and the last at the end.
            out = ExperienceLog(staging, config, fsync="interval", fsync_interval_s=float("inf"))
            written[name] = 0
            try:
                for batch in batches:  # reading the sources: their errors name what failed
                    frame = codec.encode(batch)
                    with naming(targets[name]):  # the output asked for, not its hidden segment (undone)
                        out.append(frame)
                    written[name] += len(batch)
                with naming(targets[name]):
                    out.sync()
            finally:
                out.close()
            files += sorted(
                f"{name}/{p.name}" if name else p.name for p in staging.iterdir() if p.name != LOCK
            )
        _publish(root, token, targets, files, [name for name, t in targets.items() if name and t in made])
    except BaseException:
        if (root / token / MOVING).exists():
            _undo(root, root / token)
        for folder in dict.fromkeys([root, *targets.values()]):
            shutil.rmtree(folder / token, ignore_errors=True)
        for thing in reversed(made):  # a folder only where it is empty again: nothing else is lost
            with contextlib.suppress(OSError):
                thing.rmdir() if thing.name != LOCK else thing.unlink()
        raise
    finally:
        for fd in locks:
            os.close(fd)
    return written


def _staged(root: Path, token: str, name: str) -> Path:
    """Where a write whose hidden folders are `token` staged file `name` (a path under root)."""
    part, _, leaf = name.rpartition("/")
    return (root / part if part else root) / token / leaf


def _publish(root: Path, token: str, targets: dict[str, Path], files: list[str], made: list[str]) -> None:
    """Move staged files (see `_staged`) to their paths under root, all or none.

    The list of them is made durable, with each part's pointer to it and the folders holding
    them, before the first move; the list is removed last, once the moves are durable.
    """
    listing = root / token
    atomic_write_text(listing / MOVING, json.dumps({"files": files, "made": made}))
    sync_dir(listing)
    for name, target in targets.items():
        if name:
            atomic_write_text(target / token / PART_OF, os.path.realpath(listing / MOVING))
            sync_dir(target / token)
            sync_dir(target)
    sync_dir(root)
    for name in files:
        os.rename(_staged(root, token, name), root / name)
    for folder in sorted({(root / name).parent for name in files}, key=lambda p: -len(p.parts)):
        sync_dir(folder)
    (listing / MOVING).unlink()
    sync_dir(listing)  # the logs are whole from here
    for target in dict.fromkeys([root, *targets.values()]):
        shutil.rmtree(target / token, ignore_errors=True)
    sync_dir(root)


def _moving(marker: Path) -> tuple[list[str], list[str]]:
    """A `moving.json`'s (files, folders made), those with safe names only; ([], []) if unreadable."""
    try:
        data = json.loads(read_regular_text(marker))
    except (OSError, ValueError, RecursionError):
        return [], []

    def safe(names: object) -> list[str]:
        if not isinstance(names, list):
            return []
        return [n for n in names if isinstance(n, str) and 1 <= len(n.split("/")) <= 2
                and all(_NAME.fullmatch(c) for c in n.split("/"))]  # fmt: skip

    if not isinstance(data, dict):
        return [], []
    return safe(data.get("files")), safe(data.get("made"))


def _listing_of_part(hidden: Path) -> Path | None:
    """The split's `moving.json` that a part's hidden folder points to, while it is there.

    Where the split wrote it (the path its pointer names: a part may be a link to another file
    system), or beside the part where its folders are now (moved, or mounted elsewhere, since).
    """
    try:
        written = Path(read_regular_text(hidden / PART_OF).strip())
    except (OSError, ValueError):
        return None
    here = Path(os.path.realpath(hidden)).parent.parent / hidden.name / MOVING
    for listed in (here, written):
        if listed.name == MOVING and listed.parent.name == hidden.name and listed.is_file():
            return listed
    return None


def _unfinished(directory: Path) -> bool:
    """Whether files in `directory` are listed as being moved into place by a write not yet whole.

    By a write into it, or a split of which it is a part: one at work now, or one cut short.
    """
    for hidden in Path(os.path.realpath(directory)).glob(f"{PARTIAL}*"):
        if (hidden / MOVING).exists() or _listing_of_part(hidden) is not None:
            return True
    return False


def _undo(root: Path, listing: Path) -> None:
    """Remove a write's hidden folders (`listing` is root's), and the files its list says it moved."""
    token = listing.name
    files, made = _moving(listing / MOVING) if (listing / MOVING).exists() else ([], [])
    gone: set[Path] = set()
    for name in files:
        staged = _staged(root, token, name)
        if _LOG_FILE.fullmatch(staged.name) and staged.parent.is_dir() and not staged.exists():
            (root / name).unlink(missing_ok=True)  # moved: it is in place, and goes
            gone.add((root / name).parent)
    for folder in gone:
        sync_dir(folder)  # the files gone durably before the list that names them
    for part in {name.split("/")[0] for name in files if "/" in name}:
        shutil.rmtree(root / part / token, ignore_errors=True)
    for part in made:
        _unmake(root / part)
    sync_dir(root)
    shutil.rmtree(listing, ignore_errors=True)
    sync_dir(root)


def _unmake(folder: Path) -> None:
    """Remove a folder a cut-short write made, where nothing but its lock file is in it (unheld)."""
    try:
        lock = take_lock(folder)
    except OSError:  # in use, or gone
        return
    try:
        if [p.name for p in folder.iterdir()] == [LOCK]:
            (folder / LOCK).unlink()
            folder.rmdir()
    except OSError:
        pass
    finally:
        os.close(lock)


def _undo_unfinished(root: Path, targets: list[Path]) -> None:
    """Undo what killed writes left in root and the targets (whose locks are held).

    And what a killed split of which a target is a part left (under the split root's lock).
    """
    held = {os.path.realpath(root)}
    for folder in dict.fromkeys([root, *targets]):
        for hidden in sorted(folder.glob(f"{PARTIAL}*")):
            if not hidden.exists():  # undone with its split's root above
                continue
            listing = _listing_of_part(hidden)
            if listing is None:
                _undo(folder, hidden)
                continue
            split_root = listing.parent.parent
            lock = None if os.path.realpath(split_root) in held else take_lock(split_root)
            try:
                _undo(split_root, listing.parent)
            finally:
                if lock is not None:
                    os.close(lock)
            shutil.rmtree(hidden, ignore_errors=True)


def _check_new(directory: Path) -> None:
    """Refuse to write a log where one is (its segments, or only its description).

    What a write cut short while moving its files into place left is no log: the next write
    removes it (`_undo_unfinished`).
    """
    if _unfinished(directory):
        return
    if is_log(directory) or (directory / LOG_JSON).exists():
        raise LogFormatError(f"{directory} already holds a log; write to a new directory")


def check_outside(out: Path, sources: Iterable[Path]) -> None:
    """Refuse an output path in (or equal to) a log being read, or at its server's config beside it.

    Reading data never changes it: `log_config` reads that config too.
    """
    target = Path(out).resolve()
    for source in sources:
        src = Path(source).resolve()
        if target in (src, src.parent / SERVER_CONFIG_JSON) or src in target.parents:
            raise LogFormatError(f"{out} is inside the log {source} being read; write somewhere else")


def check_place(out: Path) -> None:
    """Refuse an output path inside any log, read or not, or in a think server's data directory.

    A live server's store went on appending to the segment an export replaced (what it had
    acknowledged was gone); a split into a store's folder, cut short, left every reader refusing
    the store as "a write under way"; an export over a checkpoint lost what the server had learned.
    An output that is itself a log is `_check_new`'s to refuse.
    """
    target = Path(out).resolve()
    for folder in [target, *target.parents]:
        if folder != target and is_log(folder):  # a live one has its segment from the start
            raise LogFormatError(f"{out} is inside the log {folder}; write somewhere else")
        # By what the server writes beside its store, not by the store: one with no segment yet,
        # or one a write cut short, is a store all the same, and a user's log named `store` none.
        if (folder / "store").is_dir() and any(os.path.lexists(folder / name) for name in SERVER_FILES):
            raise LogFormatError(f"{out} is in a think server's data directory {folder}; "
                                 "write somewhere else")  # fmt: skip


def common_config(directories: Iterable[Path]) -> LearnerConfig | None:
    """The learner config of logs that must agree on their spec (None if none says).

    A log whose description cannot be read says nothing (a warning): its batches still carry
    their spec hash, which readers check.
    """
    found: LearnerConfig | None = None
    for directory in directories:
        try:
            config = log_config(directory)
        except LogFormatError as exc:
            log.warning("%s", exc)
            continue
        if config is None:
            continue
        if found is not None and config.spec_hash() != found.spec_hash():
            raise LogFormatError(
                f"{directory}: learner spec {config.spec_hash()} differs from the others' {found.spec_hash()}"
            )
        found = found or config
    return found


def merged(
    directories: Iterable[Path], key: bytes | None = None, spec: str = "", counts: ReadCounts | None = None,
    dims: tuple[int, int] | None = None, config: LearnerConfig | None = None,
) -> Iterator[ExperienceBatch]:  # fmt: skip
    """The batches of several logs, each client's experiences once (the first copy of each number).

    Logs of the same client (its journal and a server's store, say) overlap: what one has already
    given is trimmed from the others. A copy left out whose values differ from the one given is
    counted in `counts.conflicts` (two runs under one client id). Batches of a learner spec other
    than `spec`, or whose state and action widths are not `dims` (without them: the first batch's),
    are refused: a LogFormatError, as a spec fixes its widths. The logs' learner `config`, where
    given, gives both (what is written with the batches must describe them). What reading skips
    is counted in `counts`.
    """
    if config is not None:
        spec, dims = spec or config.spec_hash(), dims or widths(config)
    given: dict[str, dict[int, int]] = {}
    """Per client: the digest of the values of each experience given, by number (0 without `counts`)."""
    for directory in directories:
        for batch in read_batches(directory, key, counts):
            spec = spec or batch.spec_hash
            if batch.spec_hash != spec:
                whose = "the first's" if config is None else f"the spec of its {LOG_JSON}'s learner config"
                raise LogFormatError(
                    f"{directory}: experiences of learner spec {batch.spec_hash}, not {spec} ({whose})"
                )
            have = (batch.state.shape[1], batch.action.shape[1])
            dims = dims or have
            if have != dims:
                raise LogFormatError(
                    f"{directory}: experiences {batch.first_seq}-{batch.last_seq} of client {batch.client!r} "
                    f"have {have[0]} state and {have[1]} action variables; their learner spec has "
                    f"{dims[0]} and {dims[1]}"
                )
            seen = given.setdefault(batch.client, {})
            numbers = range(batch.first_seq, batch.last_seq + 1)
            digests = _digests(batch) if counts is not None else [0] * len(batch)  # compared only to count
            keep = np.array([s not in seen for s in numbers])
            if counts is not None and not keep.all():
                pairs = zip(numbers, digests, keep, strict=True)
                differ = sum(1 for s, d, k in pairs if not k and seen[s] != d)
                if differ:
                    counts.conflicts[batch.client] += differ
            if not keep.any():
                continue
            seen.update((s, d) for s, d, k in zip(numbers, digests, keep, strict=True) if k)
            if keep.all():
                yield batch
                continue
            # Keep each contiguous run of new experiences as its own batch.
            edges = np.flatnonzero(np.diff(np.concatenate([[0], keep.astype(np.int8), [0]])))
            for start, stop in zip(edges[::2], edges[1::2], strict=True):
                yield batch.slice(int(start), int(stop))


def _digests(batch: ExperienceBatch) -> list[int]:
    """A digest of each experience's values [N] (state, action, next state, reward, terminal).

    Not its flags or weights version: a server marks what it cannot learn, and that is the same
    experience.
    """
    n = len(batch)
    values = np.concatenate([batch.state, batch.action, batch.next_state, batch.reward.reshape(n, 1),
                             batch.terminal.reshape(n, 1)], axis=1, dtype=np.float64)  # fmt: skip
    return [hash(row.tobytes()) for row in values]


def merge(sources: list[Path], out: Path, key: bytes | None = None) -> int:
    """Merge logs into a new log at `out` (see `merged`); -> experiences written."""
    check_outside(out, sources)
    check_place(out)
    config = common_config(sources)
    counts = ReadCounts()
    batches = merged(sources, key, config=config, counts=counts)
    first = next(batches, None)
    if first is None:  # as export refuses: an empty log written with exit 0 said nothing was wrong
        raise LogFormatError(f"no experiences in {', '.join(map(str, sources))}; nothing written")
    written = write_log(out, itertools.chain([first], batches), config)
    counts.warn_conflicts()
    return written


def widths(config: LearnerConfig | None) -> tuple[int, int] | None:
    """A config's state and action widths (None without a config)."""
    return None if config is None else (config.state_dim, config.action_dim)


def split(
    source: Path, out: Path, by: str = "client", every: int = 0, key: bytes | None = None
) -> dict[str, int]:
    """Split a log into new logs under `out`; -> experiences per new log.

    One log per client (`by="client"`) or per behaviour policy (`by="behaviour"`), or chunks of
    at most `every` experiences (`by="count"`; whole batches: a batch larger alone is a part of
    its own). The log is read as `merged` reads it: each client's experiences once, and batches
    that do not fit its spec refused.
    """
    if by not in ("client", "behaviour", "count"):
        raise ValueError(f"split by client, behaviour or count, not {by!r}")
    if by == "count" and every < 1:
        raise ValueError("split by count needs every >= 1")
    if by != "count" and every:  # else silently ignored
        raise ValueError(f"every is for split by count, not by {by}")
    check_outside(out, [source])
    check_place(out)
    _check_new(Path(out))  # its parts go inside it: in a log, one cut short had every reader refuse it
    config = common_config([source])  # an unreadable description: a warning, as for the other commands
    groups: dict[str, list[ExperienceBatch]] = {}
    names: dict[str, str] = {}
    part, in_part = 0, 0
    # Read as merge and export read it: each experience once, and widths that fit their spec.
    counts = ReadCounts()
    for batch in merged([source], key, config=config, counts=counts):
        if by == "client":
            label = batch.client
        elif by == "behaviour":
            label = batch.weights_source
        else:  # numbered by experiences done, a large batch just before a boundary overfilled one part
            if in_part and in_part + len(batch) > every:
                part, in_part = part + 1, 0
            in_part += len(batch)
            label = f"part{part:04d}"
        if label not in names:
            names[label] = _directory_name(label, set(names.values()))
        groups.setdefault(names[label], []).append(batch)
    counts.warn_conflicts()
    if not groups:
        raise LogFormatError(f"no experiences in {source}; nothing written")
    return _write_logs(Path(out), groups, config, "wfnn-logs")


def _directory_name(label: str, taken: set[str]) -> str:
    """A directory name for a part of a split log, unique among `taken`.

    Client ids and behaviour names come from the log, which came from the network: "..",
    "a/../../b" or a 60 KiB name must not write anywhere but one new directory under `out`. Only
    [A-Za-z0-9_.-] is kept (anything else becomes "_"), no leading dot, at most 64 characters.
    """
    name = re.sub(r"[^A-Za-z0-9_.\-]", "_", label).lstrip(".")[:64] or "none"
    unique, n = name, 2
    while unique in taken:
        suffix = f"-{n}"
        unique, n = name[: 64 - len(suffix)] + suffix, n + 1
    return unique


def to_arrays(sources: list[Path], key: bytes | None = None) -> dict[str, Any]:
    """The experiences of logs (merged) as flat numpy arrays [N, ...] with their numbering."""
    counts = ReadCounts()
    batches = list(merged(sources, key, config=common_config(sources), counts=counts))
    counts.warn_conflicts()
    if not batches:
        raise LogFormatError(f"no experiences in {', '.join(map(str, sources))}")
    clients = sorted({b.client for b in batches})
    sources_names = sorted({b.weights_source for b in batches})
    cat = np.concatenate
    return {
        "state": cat([b.state for b in batches]), "action": cat([b.action for b in batches]),
        "next_state": cat([b.next_state for b in batches]), "reward": cat([b.reward for b in batches]),
        "terminal": cat([b.terminal for b in batches]), "flags": cat([b.flags for b in batches]),
        "weights_version": cat([b.weights_version for b in batches]),
        "seq": cat([np.arange(b.first_seq, b.last_seq + 1) for b in batches]),
        "client": cat([np.full(len(b), clients.index(b.client), dtype=np.int32) for b in batches]),
        "weights_source": cat([np.full(len(b), sources_names.index(b.weights_source), dtype=np.int32)
                               for b in batches]),
        "clients": np.array(clients), "weights_sources": np.array(sources_names),
        "spec_hash": np.str_(batches[0].spec_hash),
    }  # fmt: skip


UNFINISHED_AGE_S = 600.0
"""An export's temporary file untouched this long was left by one cut short: a live export
writes to its file as it goes (a second export to the same file deleted the first's)."""


def _clear_unfinished_writes(out: Path) -> None:
    """Remove what killed exports to `out` left beside it (a full-size temporary file each)."""
    for path in remove_unfinished_writes(out.parent, [out.name], older_than_s=UNFINISHED_AGE_S):
        log.info("%s: left by an export that was cut short; deleted", path)


def export(sources: list[Path], out: Path, key: bytes | None = None, replace: bool = False) -> int:
    """Write logs' experiences as one `.npz` of plain arrays (`to_arrays`); -> experiences.

    A file already at `out` is kept (FileExistsError) unless `replace`: it may be another
    export, or anything else of the user's, and merge and split refuse an output that holds a
    log in the same way.
    """
    check_outside(out, sources)
    if Path(out).is_dir():
        raise IsADirectoryError(21, "is a directory (export writes one .npz file)", str(out))
    # Any folder above it, not only its own: --replace over a store's quarantined tail (in a
    # subfolder of the store) lost what the store had set aside.
    check_place(out)
    if not replace and os.path.lexists(out):  # before the logs are read, which may take long
        raise FileExistsError(errno.EEXIST, "exists (pass --replace to write over it)", str(out))
    arrays = to_arrays(sources, key)
    config = common_config(sources)
    _clear_unfinished_writes(Path(out))
    atomic_savez(out, {"format": np.str_(EXPORT_FORMAT), "format_version": np.int64(1),
                       "learner_config": np.str_(config.to_json() if config else ""), **arrays},
                 replace=replace)  # fmt: skip
    return int(arrays["reward"].shape[0])
