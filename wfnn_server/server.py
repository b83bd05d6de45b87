"""The think server of act-learn-think-C/S: store experiences, replay them, publish weights.

    ingest thread:  frames from the bus -> decode/check (CRC, MAC, spec) -> store (dedupe,
                    in order per client) -> ack once durable -> hand to the learner thread
    learner thread: learn_many -> think (thinks_per_action per experience) -> publish a
                    snapshot every publish_period_s and as soon as the think budget is spent
                    -> status heartbeat -> checkpoint

Bus callbacks only put frames on a queue, and nothing a frame holds can end a thread: every
message is handled inside a guard that counts what fails by reason. Restart resumes from the
newest readable checkpoint (weights, counters, config; the previous one is kept beside it) and
the stored experiences; experiences stored after that checkpoint are owed their thinks again.
Nothing in the data directory is deleted: a file that cannot be read is set aside, renamed.
"""

from __future__ import annotations

import bisect
import collections
import dataclasses
import hashlib
import itertools
import logging
import math
import os
import queue
import threading
import time
from collections import Counter, OrderedDict
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np
from numpy.typing import NDArray

from wfnn_common.config import ConfigError, LearnerConfig
from wfnn_common.learners import Learner, make_learner
from wfnn_common.schedule import ThinkSchedule
from wfnn_io.bus import Bus, Channel, Inbox, OfflineBus, guarded
from wfnn_io.cli_errors import Terminated, log_failure
from wfnn_io.logs import (
    SERVER_FILES,
    LogFormatError,
    ReadCounts,
    check_log,
    common_config,
    merged,
    read_log_json,
    set_aside,
    widths,
)
from wfnn_io.persist import (
    PersistError,
    atomic_write_text,
    folders_to_be_made,
    load_checkpoint,
    load_weights,
    make_directory,
    read_regular_bytes,
    read_regular_text,
    remove_empty_folders,
    remove_unfinished_writes,
    save_weights,
    writable,
    write_json,
)
from wfnn_io.protocol import (
    EXP_NON_FINITE,
    MAX_PRODUCED,
    MAX_SEQ,
    Ack,
    CameraView,
    ClientStatus,
    Codec,
    ExperienceBatch,
    FrameTooLarge,
    Keys,
    ProtocolError,
    ServerStatus,
    SpecMismatch,
    Unsendable,
    WeightSnapshot,
    check_frame,
    count_rejected,
    load_key,
    mark_non_finite,
    older_peer,
    take,
)
from wfnn_io.segments import ReadReport, check_free
from wfnn_server.config import ServerConfig
from wfnn_server.store import ENDLESS, Admission, ExperienceStore, Hole, without
from wfnn_server.view import ViewModel, kept

if TYPE_CHECKING:
    from wfnn_server.dashboard import Dashboard

FloatArray = NDArray[np.float64]

log = logging.getLogger(__name__)

CHECKPOINT = "checkpoint.npz"
PREVIOUS_CHECKPOINT = "checkpoint.prev.npz"
"""The checkpoint before the newest: a server that cannot read the newest falls back to it."""
THINK_CALL_S = 0.1
"""About the longest one think call runs (`_think`), well inside the status period."""
STOP_JOIN_S = 30.0
"""How long `stop` waits for each thread before it gives up on the final checkpoint."""
LEARN_QUEUE_BYTES = 256 << 20
"""Stored experiences waiting for the learner thread, at most (their arrays' bytes): beyond it,
new batches are dropped unstored and come again from their clients' journals."""
CLIENT_TIMEOUT_S = 2.0
"""A client whose heartbeat (twice a second) has not arrived for this long is reported silent."""
MAX_LISTED = 256
"""Clients whose experience numbers a snapshot or status lists: the most recently heard. Every
client the store ever held would outgrow the frames a robot accepts (and the status's limit)
on a long-lived server, or under forged ids; a client missing from one is heard again at its
next heartbeat or batch (and its acknowledgements come on their own)."""
LOSS_LOG_S = 10.0
"""Shortest interval between two logged loss declarations of one client: without a key, anyone
can send them as fast as frames go (each is counted in `ingest/declared_lost` all the same)."""
MAX_CAMERAS = 16
"""Clients whose newest camera picture is kept for the dashboard (the most recent ones)."""
REFUSED_LOGGED = 256
"""Announced config texts refused and logged, each once (every heartbeat repeats it; forged ones
may each differ): past this many, they are only counted (`rejected/config`)."""
JOURNAL_HOLD_S = 3.0
"""How long a client's journal must be silent before another journal of that client is taken
(`ThinkServer._check_journal`)."""
MAX_HEARD = 4096
"""Clients whose heartbeats (and dashboard statuses) are kept: the most recently heard."""
LOGGED_CLIENTS = 16
"""Clients named in the log per check as silent, or as heard again (the rest counted in one line)."""
LEARNER_JSON = "learner_config.json"
REPLAY_ONLY_NO_CONFIG = (
    "replay-only: no learner config (give --learner-config, or logs that record one: a client's "
    "journal, or a server's DATA_DIR/store beside its learner_config.json)"
)


def lower_priority(nice: int) -> None:
    """Make the calling thread `nice` steps less urgent (Linux threads; elsewhere nothing)."""
    if nice <= 0 or not hasattr(os, "setpriority"):
        return
    try:
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, min(os.getpriority(os.PRIO_PROCESS, tid) + nice, 19))
    except OSError as exc:
        log.warning("could not lower the think thread's priority: %s", exc)


def _digest(cfg: LearnerConfig) -> bytes:
    """A learner config's digest (its JSON's), kept in place of the text (up to 64 KB each)."""
    return hashlib.blake2b(cfg.to_json().encode(), digest_size=16).digest()


class _OtherSpec(PersistError):
    """A readable checkpoint of another learner spec than the server's."""


def _noted(heard: dict[str, float], client: str, most: int) -> dict[str, float]:
    """`heard` with `client` heard now; beyond `most` clients, a new dict of the newer half.

    A new dict rather than one emptied and refilled: another thread may be reading this one.
    """
    heard[client] = time.monotonic()
    if len(heard) <= most:
        return heard
    return dict(sorted(list(heard.items()), key=lambda item: item[1])[-(most // 2) :])


def _is_count(value: Any) -> bool:
    """A count or experience number in a checkpoint: an integer in [0, MAX_SEQ] (fits an int64)."""
    return type(value) is int and 0 <= value <= MAX_SEQ


class _Refused(ProtocolError):
    """A well-formed message this server does not take (the reason names why)."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason  # type: ignore[misc]  # per instance, not per class


class ThinkServer:
    """One think server: a WFNN learner fed by every client of its controller."""

    def __init__(self, config: ServerConfig, bus: Bus) -> None:
        self.config = config
        self.bus = bus
        self.keys = Keys(config.controller)
        self.id = config.server_id
        key = load_key(str(config.key_file) if config.key_file else None)
        self.codec = Codec(config.server_id, key, config.controller)
        self._key = key
        """The shared key as given (logs replayed check each their own controller's tags)."""
        self.data_dir = config.data_dir
        self.data_dir.mkdir(parents=True, exist_ok=True)
        # The store first: its lock refuses a second server on this data directory before that
        # one counts an incarnation or touches a file here.
        self.store = ExperienceStore(
            self.data_dir / "store", self.id, fsync=config.fsync,
            fsync_interval_s=config.fsync_interval_s, segment_bytes=config.segment_bytes,
        )  # fmt: skip
        try:
            self._set_up(config)
        except BaseException:  # a start refused (bad logs or config): the store closed, unlocked
            self.store.close()
            self.store.remove_if_new(served=False)  # nothing served yet: what it holds, the logs hold
            raise

    def _set_up(self, config: ServerConfig) -> None:
        """The rest of `__init__`, once the store (and its lock) is this server's."""
        self._remove_unfinished_writes()
        self.incarnation = self._next_incarnation()
        """This start's number: counted in the file `incarnation` by `start` (a start refused
        before it serves leaves the count as it was)."""
        self.started_ns = time.time_ns()
        self._started_monotonic = time.monotonic()
        """This start by the monotonic clock: statuses tell the uptime it gives (`ServerStatus.uptime_ms`)."""
        self.rejected: Counter[str] = Counter()
        """Frames rejected, by reason (protocol errors, spec, no_config, sender)."""
        self.counters: Counter[str] = Counter()
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._inbox: Inbox[tuple[str, bytes]] = Inbox()
        """Frames received, waiting for the ingest thread (bounded in bytes: a flood is dropped)."""
        self._to_learn: collections.deque[ExperienceBatch] = collections.deque()
        """Stored batches waiting for the learner thread, bounded by LEARN_QUEUE_BYTES (`_ingest`)."""
        self._storing = False
        """Whether the ingest thread is storing a batch it has not queued yet."""
        self._to_learn_bytes = 0
        self._to_learn_lock = threading.Lock()
        """Held while `_to_learn_bytes` changes (the ingest thread adds, the learner thread takes)."""
        self._status_sent = 0.0
        """When a status was last published (monotonic), by either thread."""
        self._threads: list[threading.Thread] = []
        self._latest_frame: bytes | None = None
        self._spec_warned: set[str] = set()
        self._loss_logged: dict[str, float] = {}
        """When each client's last declared loss was logged (one line per client per LOSS_LOG_S)."""
        self._heard: dict[str, float] = {}
        """Per client: when its heartbeat (status) last arrived (monotonic); at most MAX_HEARD."""
        self._recent: dict[str, float] = {}
        """Per client: when its heartbeat or an admitted batch last arrived; what MAX_LISTED picks from."""
        self._journals: dict[str, str] = {}
        """Per client: the journal whose experiences are taken (`_check_journal`; ingest thread)."""
        self._journal_heard: dict[str, float] = {}
        """Per client: when its taken journal was last heard (a batch or a status); at most MAX_HEARD."""
        self._journal_logged: set[tuple[str, str]] = set()
        self._older: set[str] = set()
        """Clients told to speak an older protocol version (`older_peer`)."""
        self._silent: set[str] = set()
        """Clients logged as silent (heartbeat older than CLIENT_TIMEOUT_S), until heard again."""
        self._heard_lock = threading.Lock()
        """Held where `_heard` is replaced (ingest thread) and where `_silent` is updated from it
        (learner thread), so that neither loses the other's change."""
        self.error: BaseException | None = None
        self._failure_lock = threading.Lock()
        self.view = ViewModel(server=self.id, incarnation=self.incarnation, controller=config.controller)
        """What read-only views (the dashboard) may look at; replaced field by field, never in place."""
        self.dashboard: Dashboard | None = None
        """The live web view, while serving with `config.dashboard`."""

        # Learner state (owned by the learner thread once running).
        self.learner: Learner | None = None
        self.learner_config: LearnerConfig | None = None
        self.spec_hash = ""
        self._config_json = ""
        """The effective learner config as JSON, announced in every status."""
        self._pending_config: LearnerConfig | None = None
        self._unusable: OrderedDict[bytes, None] = OrderedDict()
        """Digests of configs (as JSON) that no learner could be made from (not adopted again), the
        REFUSED_LOGGED noted last (any sender may announce configs, each other than the last)."""
        self._unusable_logged = 0
        """Such configs logged (each once, the first REFUSED_LOGGED; the rest only counted)."""
        self._refused_texts: set[bytes] = set()
        """Digests of announced config texts refused as they were read, each logged once."""
        self._seconds_per_think: float | None = None
        """How long one think took lately (None until measured): sizes each think call."""
        self.version = 0
        self.schedule = ThinkSchedule()
        """Thinks owed, how far they have reached (`learned_through`) and relearning after a reset."""
        self._staleness: list[int] = []
        self._q_chosen: list[float] = []
        self._rewards: list[float] = []
        self.imported, replay_config = self._import_logs(config.replay) if config.replay else (0, None)
        """Experiences imported from `config.replay` logs (new to the store)."""
        self._queued_through: dict[str, int] = dict(self.store.stored_through)
        """Per client: the last experience handed to the learner (its thinks are owed)."""
        self._unqueued: dict[str, list[Hole]] = {}
        """Per client: the store's holes when the learner was built that it has not been handed
        since (in order). A checkpoint records them: a fill stored after it is owed its thinks."""
        self._thought_holes: dict[str, list[Hole]] = {}
        """Per client: holes whose experiences an earlier run's checkpoint had thought (a record
        damaged since): their fill is learned again, for the replay, but owes no thinks (in order)."""
        self._loaded_through: dict[str, int] = {}
        """Per client: the last experience the learner was given from the store when it was built."""
        self._loaded_fills: set[tuple[str, int]] = set()
        """(client, first experience) of the records filling holes that the learner was given then."""
        self._queued_fills: set[tuple[str, int]] = set()
        """(client, first experience) of the queued batches filling holes (below `_loaded_through`)."""
        # --learner-config or an earlier run's, else the config the logs say they were recorded for
        cfg = self._initial_config() or replay_config
        if config.replay_only and cfg is None:
            raise LogFormatError(REPLAY_ONLY_NO_CONFIG)
        if config.replay_only and self.store.count == 0:  # else it saved untrained weights, and exited 0
            raise LogFormatError("replay-only: the logs hold no readable experience, nor does the store")
        if cfg is not None:
            self._start_learner(cfg)

    # ------------------------------------------------------------------ start-up
    def _remove_unfinished_writes(self) -> None:
        """Delete what a crash mid-write left of this server's own files (`NAME<random>.tmp`).

        An atomic write fills a temporary file beside its target and renames it; one that never
        got renamed holds nothing the target does not (checkpoints are full-size: one per crash
        would pile up). Only this server writes here: the store's lock says so.
        """
        for path in remove_unfinished_writes(self.data_dir, SERVER_FILES):
            log.info("%s: left by a write a crash interrupted; deleted", path)

    def _next_incarnation(self) -> int:
        """One more than the last start's incarnation (written by `start`).

        From the file `incarnation`, or where that is unreadable, from the checkpoints' record of it.
        """
        path = self.data_dir / "incarnation"
        previous = 0
        if path.exists():
            try:
                previous = int(read_regular_bytes(path).decode(errors="replace").strip())
                if not _is_count(previous) or previous == MAX_SEQ:
                    raise ValueError(f"not a count below {MAX_SEQ}: {previous}")
            except (OSError, ValueError) as exc:
                set_aside(path, f"unreadable ({exc})")
                previous = 0
                for name in (CHECKPOINT, PREVIOUS_CHECKPOINT):
                    try:
                        recorded = load_weights(self.data_dir / name)[2].get("incarnation", 0)
                    except (PersistError, OSError, ValueError, TypeError):
                        continue
                    if _is_count(recorded) and recorded < MAX_SEQ:  # a damaged record counts for nothing
                        previous = max(previous, recorded)
        return previous + 1

    def _initial_config(self) -> LearnerConfig | None:
        """The learner config from --learner-config, or adopted by an earlier run, or None.

        A --learner-config that cannot be used is an error (ConfigError). The data directory's
        own copy that cannot be read is set aside, and the newest readable checkpoint's config
        is used instead (else none: the server adopts a client's again).
        """
        if self.config.learner_config is not None:
            path = self.config.learner_config
            try:
                text = read_regular_text(path)
            except OSError as exc:
                raise ConfigError(f"learner config {path}: {exc.strerror or exc}") from exc
            except UnicodeDecodeError:
                raise ConfigError(f"learner config {path}: not text (a JSON file is UTF-8)") from None
            given = LearnerConfig.from_json(text, f"learner config {path}")
            self._check_data_dir_spec(given)
            return given
        path = self.data_dir / LEARNER_JSON
        if path.exists():
            try:
                held = LearnerConfig.from_json(read_regular_text(path), str(path))
            except (OSError, ConfigError, UnicodeDecodeError) as exc:  # not text: as unreadable
                set_aside(path, f"unreadable ({exc})")
            else:
                # A copy edited by hand into another spec set the checkpoints aside (the training
                # lost) and left every stored experience unlearned, without a word.
                checkpoint = self._checkpoints_config()
                if checkpoint is not None and checkpoint[0].spec_hash() != held.spec_hash():
                    raise ConfigError(
                        f"data directory {self.data_dir}: {LEARNER_JSON} is spec {held.spec_hash()} "
                        f"({held.spec_difference(checkpoint[0])}), its {checkpoint[1]} spec "
                        f"{checkpoint[0].spec_hash()}: put the file back as it was, or move the "
                        "checkpoints out to start that learner afresh"
                    )
                return held
        saved = self._checkpoints_config()
        if saved is None:
            return None
        log.warning("learner config taken from %s (with the overrides it was saved with)", saved[1])
        return saved[0]

    def _checkpoints_config(self) -> tuple[LearnerConfig, str] | None:
        """The config the newest readable checkpoint was saved with, and that checkpoint's name."""
        for name in (CHECKPOINT, PREVIOUS_CHECKPOINT):
            try:
                return load_weights(self.data_dir / name)[0], name
            except (PersistError, OSError):
                continue
        return None

    def _overridden(self, cfg: LearnerConfig) -> LearnerConfig:
        """`cfg` with this server's overrides (`ServerConfig.overrides`: seed, bc_weight, learning rate).

        A deep learner also trains on this server's device, compiled where the server says.
        """
        cfg = self.config.overrides.apply(cfg)
        if cfg.learner == "deep":  # trains where this server says, whatever the client's config says
            cfg = dataclasses.replace(cfg, deep=dataclasses.replace(cfg.deep, device=self.config.device,
                                                                    compile=self.config.compile))  # fmt: skip
        return cfg

    def _import_logs(self, directories: tuple[Path, ...]) -> tuple[int, LearnerConfig | None]:
        """Store the experiences of logs that the store lacks.

        Every log is read through first (readable, one learner spec, the server's own spec where
        it has one), so a log that does not fit leaves the store untouched. Logs are read, never
        changed: damaged records are skipped and reported. Returns how many experiences were
        imported and the learner config the logs were recorded for (if said). Logs in which every
        record was refused (a wrong key, say) are an error that names the reasons.
        """
        for directory in directories:  # what is not a log is named as such, before any other refusal
            check_log(directory)
        known, described = self._initial_config(), common_config(directories)
        spec = known.spec_hash() if known is not None else ""
        if described is not None and spec and described.spec_hash() != spec:
            raise LogFormatError(
                f"the logs were recorded for learner spec {described.spec_hash()}, this server's is {spec}"
            )
        spec = spec or (described.spec_hash() if described is not None else "")
        chosen = known or described
        if chosen is not None:  # this server's flags on it: else refused once the logs were stored
            self._overridden(chosen)
        elif self.config.replay_only:  # refused before the logs are read through and stored
            raise LogFormatError(REPLAY_ONLY_NO_CONFIG)
        dims = widths(chosen)
        counts = ReadCounts()
        offered = sum(len(b) for b in merged(directories, self._key, spec, counts, dims))
        counts.warn_conflicts()
        if counts.damage:
            log.warning("the logs hold %d damaged spans (%d bytes), skipped", len(counts.damage),
                        counts.report.skipped_bytes)  # fmt: skip
        if counts.refused:
            reasons = ", ".join(f"{n} {why}" for why, n in counts.refused.most_common())
            if offered == 0:
                hint = " (a wrong --key-file?)" if "auth" in counts.refused else ""
                raise LogFormatError(
                    f"every record of the logs was refused: {reasons}{hint}; nothing imported"
                )
            log.warning("records refused while reading the logs: %s", reasons)
        imported = 0
        told = ReadCounts(ReadReport(quiet=True))  # the first read told what it met
        for batch in merged(directories, self._key, spec, told, dims=dims):
            for admitted in self.store.parts(mark_non_finite(batch)[0], allow_gap=True):
                if admitted.new is None:
                    continue
                if admitted.missing:  # in none of the logs so far (damaged, or never there): a hole
                    first = admitted.new.first_seq
                    log.warning("client %s: experiences %d-%d are in none of the logs so far; imported what "
                                "follows (the client is asked for them if it comes)", batch.client,
                                first - admitted.missing, first - 1)  # fmt: skip
                self.store.append(admitted.new, admitted.lost, allow_gap=True)
                imported += len(admitted.new)
        self.store.sync()
        log.info("imported %d of %d experiences from %d logs", imported, offered, len(directories))
        return imported, described

    def replayed(self) -> bool:
        """Whether every stored experience has had its thinks (nothing queued or owed)."""
        learner = self.learner
        # In the order a batch moves: being stored (ingest thread), queued, then learned and owed.
        return (learner is not None and not self._storing and not self._to_learn
                and self.schedule.settled(int(learner.thinks[0])))  # fmt: skip

    def _check_data_dir_spec(self, given: LearnerConfig) -> None:
        """Refuse a --learner-config of another spec than the learner this data directory holds.

        Its checkpoints would not fit (they would be set aside, the training lost to this server)
        and its stored experiences would not be learned: a mistaken flag, refused like a client's
        run directory of another task.
        """
        path = self.data_dir / LEARNER_JSON
        saved: tuple[LearnerConfig, str] | None
        try:
            saved = LearnerConfig.from_json(read_regular_text(path), str(path)), LEARNER_JSON
        except (OSError, ValueError):  # missing or unreadable (as `_initial_config` falls back): an
            saved = self._checkpoints_config()  # unreadable copy did not make a mistaken flag pass
        if saved is not None and saved[0].spec_hash() != given.spec_hash():
            held, name = saved
            raise ConfigError(
                f"data directory {self.data_dir} holds a learner of spec {held.spec_hash()} "
                f"({name}); --learner-config is spec {given.spec_hash()} (another task, ranges "
                "or network): use another --data-dir, or start without --learner-config"
            )

    def _start_learner(self, adopted: LearnerConfig) -> None:
        """Build the learner, resume the checkpoint if it fits, and load the stored experiences.

        The adopted config is saved as it came, before this server's overrides: a restart
        without a flag drops the flag's effect. It is saved once its learner is built, so that a
        config no learner can be made from is not adopted again at every restart.
        """
        cfg = self._overridden(adopted)
        learner, meta = self._resume(cfg)
        learner.prepare_thinking()  # at construction: before the server's threads run
        atomic_write_text(self.data_dir / LEARNER_JSON, adopted.to_json())
        checkpointed: dict[str, int] = meta.get("stored_through", {})
        unqueued: dict[str, list[Hole]] = meta.get("unqueued", {})
        # The store's holes that the checkpoint counts as thought (at or below its mark, not among
        # the ranges it had not handed over) owe nothing when filled; the others are owed. A
        # checkpoint that does not say (written before it could) counts none as thought.
        self._thought_holes, self._unqueued = {}, {}
        marks = checkpointed if "unqueued" in meta else {}
        for client, holes in list(self.store.holes.items()):  # the ingest thread may be storing
            mark = marks.get(client, -1)
            thought = _less(without(holes, mark + 1, ENDLESS), unqueued.get(client, []))
            if thought:
                self._thought_holes[client] = thought
            if rest := _less(holes, thought):
                self._unqueued[client] = rest
        budget = int(meta.get("budget", 0))
        tpa = cfg.thinks_per_action
        loaded = other_spec = 0
        done_through = dict(self.store.stored_through)  # before the load: what it surely holds
        spec = cfg.spec_hash()
        for batch in self.store.batches():
            if not _fits(batch, cfg, spec):
                # Stored under a config adopted before that made no learner (another task), or
                # of widths its spec does not have (imported before logs were checked for them):
                # kept, as acknowledged, but not for this learner.
                other_spec += len(batch)
                continue
            ok = self._learn_batch(learner, batch)
            loaded += len(batch)
            through = self._loaded_through.get(batch.client, -1)
            if batch.last_seq <= through:  # a hole filled after later experiences were stored
                self._loaded_fills.add((batch.client, batch.first_seq))
            self._loaded_through[batch.client] = max(through, batch.last_seq)
            # Experiences stored after the checkpoint, or in ranges it had not handed to its learner
            # (holes filled since), have not had their thinks yet.
            after = np.arange(batch.first_seq, batch.last_seq + 1) > checkpointed.get(batch.client, -1)
            after |= _in_ranges(batch.first_seq, batch.last_seq, unqueued.get(batch.client, []))
            budget += tpa * int(np.count_nonzero(ok & after))
        self.schedule = ThinkSchedule(learned_through=dict(meta.get("learned_through", {})))
        self.schedule.resume(int(learner.thinks[0]), budget, done_through)
        relearn = min(int(meta.get("relearn", 0)), self.config.recovery_thinks_max)
        if relearn:
            self.schedule.recover(int(learner.thinks[0]), relearn)
            log.warning("relearning after a divergence reset: %d thinks still to do", relearn)
        self.learner, self.learner_config, self.spec_hash = learner, cfg, cfg.spec_hash()
        self._config_json = cfg.to_json()
        self.view.learner_config, self.view.weights_version = cfg, self.version
        log.info(
            "learner %s (spec %s, seed %d); %d stored experiences loaded, %d thinks owed",
            cfg.short_repr(), self.spec_hash, cfg.seed, loaded, self.budget,
        )  # fmt: skip
        if other_spec:
            self.counters["store/other_spec"] = other_spec
            log.warning("%d stored experiences are of another learner spec: kept, not learned", other_spec)

    def _resume(self, cfg: LearnerConfig) -> tuple[Learner, dict[str, Any]]:
        """The learner of the newest readable checkpoint that fits `cfg` (or fresh) and its meta.

        A newest checkpoint that cannot be read is set aside (renamed, so that the next
        checkpoint does not rotate it over the previous one) and the previous one is tried.
        """
        for name in (CHECKPOINT, PREVIOUS_CHECKPOINT):
            path = self.data_dir / name
            if not path.exists():
                continue
            try:
                ck_cfg, params, meta, training = load_checkpoint(path)
                if ck_cfg.spec_hash() != cfg.spec_hash():
                    raise _OtherSpec(f"checkpoint spec {ck_cfg.spec_hash()} is not {cfg.spec_hash()}")
                learner = make_learner(cfg, params=params)
                learner.load_training_state(training)
                for key in ("thinks", "resets", "version", "budget", "relearn"):
                    if not _is_count(meta.get(key, 0)):
                        raise PersistError(f"checkpoint meta {key} is not a count: {meta.get(key)!r}")
                for key in ("stored_through", "learned_through"):
                    through = meta.get(key, {})
                    numbers = through.values() if isinstance(through, dict) else [None]
                    if not all(v == -1 or _is_count(v) for v in numbers):
                        raise PersistError(f"checkpoint meta {key} is not a map of experience numbers")
                if "unqueued" in meta:  # absent from checkpoints written before it was recorded
                    meta["unqueued"] = _ranges(meta["unqueued"])
                learner.thinks[:] = int(meta.get("thinks", 0))
                learner.resets[:] = int(meta.get("resets", 0))
                self.version = int(meta.get("version", 0))
            except (PersistError, OSError, KeyError, ValueError, TypeError, ArithmeticError) as exc:
                log.error("checkpoint %s cannot be used (%s)", path, exc)
                # Renamed, so that the next checkpoint's rotation never writes over it.
                why = "of another learner spec" if isinstance(exc, _OtherSpec) else "unreadable"
                set_aside(path, f"{why}; the previous checkpoint, else fresh weights, are used")
                continue
            log.info("resumed %s: version %d, %d thinks", name, self.version, int(learner.thinks[0]))
            return learner, meta
        if any((self.data_dir / name).exists() for name in (CHECKPOINT, PREVIOUS_CHECKPOINT)):
            log.error("no usable checkpoint: fresh weights; every stored experience is owed its thinks again")
        return make_learner(cfg), {}

    @staticmethod
    def _learn_batch(learner: Learner, batch: ExperienceBatch) -> NDArray[np.bool_]:
        """Store a batch's learnable experiences in the learner; -> which were stored [N]."""
        ok = np.zeros(len(batch), dtype=np.bool_)
        keep = batch.learnable()
        if keep.any():
            ok[keep] = learner.learn_many(batch.state[keep], batch.action[keep], batch.next_state[keep],
                                          batch.reward[keep], batch.terminal[keep])  # fmt: skip
        return ok

    # ------------------------------------------------------------------ running
    def start(self) -> ThinkServer:
        """Subscribe, declare presence and start the ingest and learner threads."""
        bus, keys = self.bus, self.keys
        if self.config.dashboard is not None:  # bound first: a port in use stops the start before any ack
            from wfnn_server.dashboard import Dashboard  # the web view loads only when asked for

            self.dashboard = Dashboard(self.config.dashboard, self.view)
        # Counted now that the start holds (a dashboard port in use has been refused by now).
        atomic_write_text(self.data_dir / "incarnation", str(self.incarnation))

        def receive(kind: str) -> Callable[[str, bytes], None]:
            def put(key: str, data: bytes) -> None:
                if self.codec.key is not None:  # a flood failing the tag must not push out genuine frames
                    try:
                        check_frame(data, self.codec.key)
                    except ProtocolError as exc:
                        count_rejected(exc, data, self.rejected, f"{kind} frame")
                        return
                self._inbox.put((kind, data), len(data))  # beyond its bound: dropped, counted

            return put

        bus.subscribe(keys.experiences(), receive("exp"))
        bus.subscribe(keys.resend(self.id), receive("exp"))
        bus.subscribe(keys.client_status(), receive("status"))
        if self.config.dashboard is not None:  # pictures only for people watching
            bus.subscribe(keys.camera_view(), receive("camera"))
        bus.queryable(keys.weights(self.id), lambda: self._latest_frame)
        bus.declare_token(keys.server_alive(self.id))
        for name, target in (("ingest", self._ingest_loop), ("learner", self._learner_loop)):
            thread = threading.Thread(target=guarded(target, self._failed), name=f"wfnn-{name}", daemon=True)
            thread.start()
            self._threads.append(thread)
        if self.dashboard is not None:
            self.dashboard.start()
        log.info(
            "server %s (incarnation %d) serving controller %s; %d experiences stored",
            self.id, self.incarnation, self.config.controller, self.store.count,
        )  # fmt: skip
        return self

    def _failed(self, exc: BaseException) -> None:
        """A thread ended by `exc` (called in its handler): kept, logged, and the others stop.

        The first failure is kept: it is the cause, and the threads failing after it (the same
        full disk, another file) name only their own symptom.
        """
        with self._failure_lock:
            if self.error is None:
                self.error = exc
        log_failure(log, "server thread failed; stopping", exc)
        self._stop.set()

    def stop(self) -> None:
        """Stop the threads, write a final checkpoint and close the store."""
        self._stop.set()
        self._wake.set()
        try:
            if self.dashboard is not None:
                self.dashboard.stop()
                self.dashboard = None
            for thread in self._threads:
                thread.join(timeout=STOP_JOIN_S)
            running = [t.name for t in self._threads if t.is_alive()]
            self._threads.clear()
            if running:
                # A checkpoint beside a think in flight would count its thinks as paid (the
                # budget is taken before they are done) and never do them after a restart.
                log.warning("%s still running %g s after the stop: no final checkpoint (the last one "
                            "stands, and what came after it is owed again at the next start)",
                            ", ".join(running), STOP_JOIN_S)  # fmt: skip
            elif self.learner is not None:
                self.checkpoint()
        finally:
            self.store.close()

    def wait(self, timeout: float | None = None) -> bool:
        """Block until stopped (or a thread failed); returns whether stopped."""
        return self._stop.wait(timeout)

    def __enter__(self) -> ThinkServer:
        return self.start()

    def __exit__(self, *_: object) -> None:
        self.stop()

    # ------------------------------------------------------------------ ingest thread
    def _ingest_loop(self) -> None:
        while not self._stop.is_set():
            try:
                kind, data = self._inbox.get(timeout=0.01)
            except queue.Empty:
                kind = ""
            if kind:
                self._handle(kind, data)
            if self.store.due():
                for client, through in self.store.sync().items():
                    self._ack(client, through)
            if time.monotonic() - self._status_sent > 2 * self.config.status_period_s:
                self._relay_status()
        for client, through in self.store.sync().items():
            self._ack(client, through)

    def _handle(self, kind: str, data: bytes) -> None:
        """One received message; what it provokes is counted, never raised (a store's OSError is)."""
        handle = {"exp": self._ingest, "status": self._client_status, "camera": self._camera_view}[kind]
        take(data, handle, self.rejected, f"{kind} frame")

    def _allowed(self, client: str) -> None:
        allowed = self.config.allow_clients
        if allowed and client not in allowed:
            raise _Refused("client_not_allowed", f"client {client} is not among --allow-client")

    def _ingest(self, frame: bytes) -> None:
        sender, batch = self.codec.decode(frame, ExperienceBatch)
        if sender != batch.client:
            raise _Refused("sender", f"frame from {sender} carries experiences of {batch.client}")
        self._allowed(batch.client)
        self._check_spec(batch)
        self._check_journal(batch.client, batch.journal)
        if self._to_learn_bytes >= LEARN_QUEUE_BYTES:
            # The learner is behind by that much: this batch is neither stored nor acknowledged,
            # and its client sends it again from its journal (as one the inbox dropped), so that
            # what waits for the learner stays bounded and no flood holds the learner thread.
            if not self.counters["ingest/learner_behind"]:
                log.warning("the learner is %d MiB of experiences behind: new batches are dropped (and "
                            "sent again) until it catches up", LEARN_QUEUE_BYTES >> 20)  # fmt: skip
            self.counters["ingest/learner_behind"] += 1
            return
        batch, non_finite = mark_non_finite(batch)
        self.counters["ingest/batches"] += 1
        parts = self.store.parts(batch)
        admitted = next(parts)
        if admitted.lost:
            said = self.view.clients.get(batch.client)
            if said is None or batch.last_seq > said.produced_through:
                # A loss is declared only in a re-send of what the client's journal holds, which its
                # status has announced: one frame declaring everything up to a huge number lost would
                # make each later batch a duplicate, for good. Refused as a gap (it is sent again).
                self.rejected["declared_beyond_produced"] += 1
                admitted = Admission(None, gap=True)
            elif admitted.new is None:  # nothing new in it: the holes before it are given up
                self._declared_lost(batch, self.store.declare_lost(batch))
        if admitted.new is None:
            self.counters["ingest/duplicates" if admitted.duplicate else "ingest/gaps"] += 1
            # The client is re-sending or skipped ahead: tell it where our run of its data ends.
            self._ack(batch.client, self.store.durable_through.get(batch.client, -1))
            return
        for part in itertools.chain([admitted], parts):
            new = cast(ExperienceBatch, part.new)
            if non_finite:
                self.counters["ingest/non_finite"] += int(np.count_nonzero(new.flags & EXP_NON_FINITE))
            if part.lost:
                self._declared_lost(batch, part.lost)
            if new.first_seq <= self.store.stored_through.get(new.client, -1):
                self._queued_fills.add((new.client, new.first_seq))  # below what the learner was given
                self.counters["ingest/holes_filled"] += len(new)
            self._storing = True  # stored, not yet queued: not replayed (`replayed` reads this first)
            try:
                self.store.append(new, part.lost)
                with self._to_learn_lock:
                    self._to_learn_bytes += _nbytes(new)
                self._to_learn.append(new)
            finally:
                self._storing = False
        self._recent = _noted(self._recent, batch.client, 2 * MAX_LISTED)
        self._wake.set()

    def _check_journal(self, client: str, journal: str) -> None:
        """Take `client`'s experiences of `journal`, unless another journal of it was heard just now.

        Two runs under one client id number their experiences alike: a second client given the
        same --client-id, or batches of another run recorded and replayed (a key does not tell
        them from fresh ones). Mixed in one store, each run's experiences under a number the other
        had would be dropped as copies and acknowledged. So one journal of a client is taken at a
        time: another is refused until the taken one has been silent for JOURNAL_HOLD_S (a run
        ended; its statuses come every half second). "" (a frame of a journal written before
        journals were named) is taken whichever is.
        """
        if not journal:
            return
        taken = self._journals.get(client)
        if taken is not None and taken != journal:
            silent = time.monotonic() - self._journal_heard.get(client, -math.inf)
            if silent < JOURNAL_HOLD_S:
                if (client, journal) not in self._journal_logged and len(self._journal_logged) < MAX_LISTED:
                    self._journal_logged.add((client, journal))
                    log.error("client %s: experiences of its journal %s refused while its journal %s is "
                              "streaming (two clients given one --client-id, or a recording of another run "
                              "replayed)", client, journal, taken)  # fmt: skip
                raise _Refused("journal_in_use", f"client {client}: journal {taken} is streaming")
            log.warning("client %s: taking its journal %s (journal %s silent for %.1f s)", client, journal,
                        taken, silent)  # fmt: skip
        self._journals[client] = journal
        self._journal_streams(client)

    def _journal_streams(self, client: str) -> None:
        """Note `client`'s taken journal heard now (at most MAX_HEARD clients: the forgotten lose theirs)."""
        heard = _noted(self._journal_heard, client, MAX_HEARD)
        if heard is not self._journal_heard:
            self._journals = {c: j for c, j in self._journals.items() if c in heard}
        self._journal_heard = heard

    def _declared_lost(self, batch: ExperienceBatch, lost: int) -> None:
        if not lost:
            return
        self.counters["ingest/declared_lost"] += lost
        now, last = time.monotonic(), self._loss_logged.get(batch.client)
        if len(self._loss_logged) >= MAX_LISTED if last is None else now - last < LOSS_LOG_S:
            return
        self._loss_logged[batch.client] = now
        log.warning("client %s declares %d experiences before %d lost (its journal lacks them)",
                    batch.client, lost, batch.first_seq)  # fmt: skip

    def _check_spec(self, batch: ExperienceBatch) -> None:
        cfg = self.learner_config or self._pending_config
        if cfg is None:
            raise _NoConfig("no learner config yet (waiting for a client status or --learner-config)")
        if not _fits(batch, cfg, cfg.spec_hash()):
            if batch.client not in self._spec_warned and len(self._spec_warned) < MAX_LISTED:
                self._spec_warned.add(batch.client)  # once per client, and not for every forged id
                log.error(
                    "client %s sends experiences for spec %s (S=%d, A=%d); this server's learner is "
                    "spec %s (S=%d, A=%d): refused",
                    batch.client, batch.spec_hash, batch.state.shape[1], batch.action.shape[1],
                    cfg.spec_hash(), cfg.state_dim, cfg.action_dim,
                )  # fmt: skip
            raise SpecMismatch(f"spec {batch.spec_hash} is not {cfg.spec_hash()}")

    def _client_status(self, frame: bytes) -> None:
        sender, status = self.codec.decode(frame, ClientStatus)
        if sender != status.client:
            raise _Refused("sender", f"status from {sender} names client {status.client}")
        self._allowed(status.client)
        older_peer(frame, f"client {status.client}", self._older, "this server's acks and weights")
        self.counters["ingest/client_status"] += 1
        self._recent = _noted(self._recent, status.client, 2 * MAX_LISTED)
        with self._heard_lock:
            heard = _noted(self._heard, status.client, MAX_HEARD)
            if heard is not self._heard:  # clients forgotten: they leave the dashboard too
                self._heard, self._silent = heard, self._silent & set(heard)
                self.view.clients = {c: v for c, v in self.view.clients.items() if c in self._heard}
        if status.journal and self._journals.get(status.client) == status.journal:
            self._journal_streams(status.client)  # still streaming
        said, before = kept(status), self.view.clients.get(status.client)
        if said.produced_through > MAX_PRODUCED:
            # More than any client numbers (a forgery): it would lift the bound on the losses that
            # client may declare, and one declared up to it make its later batches duplicates.
            self.rejected["status_beyond_produced"] += 1
            said = dataclasses.replace(said, produced_through=-1)  # the figure heard before stays, below
        if before is not None and before.produced_through > said.produced_through:
            # An older status (replayed: a key does not stop that) never lowers what the client is
            # known to have produced, the bound on the losses it may declare.
            said = dataclasses.replace(said, produced_through=before.produced_through)
        self.view.clients = {**self.view.clients, status.client: said}
        if self.learner_config is not None or self._pending_config is not None:
            return
        try:
            cfg = LearnerConfig.from_json(status.learner_config)
        except ConfigError as exc:
            self.rejected["config"] += 1
            digest = hashlib.blake2b(status.learner_config.encode(), digest_size=16).digest()
            if digest not in self._refused_texts and len(self._refused_texts) < REFUSED_LOGGED:
                self._refused_texts.add(digest)  # logged at every heartbeat, a line of up to 60 KB each
                log.error("client %s announced a learner config that is refused: %.300s", status.client, exc)
            return
        digest = _digest(cfg)
        if digest in self._unusable:  # refused once already, and said so then
            self._unusable.move_to_end(digest)  # announced again: noted last, so kept past others
            self.rejected["config"] += 1
            return
        try:
            overridden = self._overridden(cfg)
        except ConfigError as exc:  # this server's own flags, not the client's config (--alpha 5: no deep lr)
            self.rejected["config"] += 1
            if self._unusable_once(digest):
                given = self.config.overrides
                flags = ", ".join(f"{f.name} {getattr(given, f.name)}" for f in dataclasses.fields(given)
                                  if getattr(given, f.name) not in (None, ""))  # fmt: skip
                log.error("client %s's learner config cannot take this server's overrides (%s): %.300s; "
                          "restart the server without them", status.client, flags, exc)  # fmt: skip
            return
        if overridden.spec_hash() != status.spec_hash:
            self.rejected["config"] += 1
            log.error("client %s announced a learner config that is refused: its spec is %s, the status "
                      "says %s", status.client, cfg.spec_hash(), status.spec_hash)  # fmt: skip
            return
        log.info("adopting the learner config of client %s", status.client)
        self._pending_config = cfg
        self._wake.set()

    def _unusable_once(self, digest: bytes) -> bool:
        """Note a config no learner can be made from, by its `_digest`; -> whether to log it.

        It is logged the first time, while fewer than REFUSED_LOGGED were: past that, only counted.
        The last ones noted are kept, so that one announced at every heartbeat is not tried again
        (for a deep learner, seconds of torch each time).
        """
        if digest in self._unusable:
            self._unusable.move_to_end(digest)
            return False
        self._unusable[digest] = None
        if len(self._unusable) > REFUSED_LOGGED:
            self._unusable.popitem(last=False)
        self._unusable_logged += 1
        return self._unusable_logged <= REFUSED_LOGGED

    def _camera_view(self, frame: bytes) -> None:
        sender, view = self.codec.decode(frame, CameraView)
        if sender != view.client:
            raise _Refused("sender", f"camera view from {sender} names client {view.client}")
        self._allowed(view.client)
        self.counters["ingest/camera_views"] += 1
        # Only heard clients' pictures are kept (each can be megabytes; ids can be forged).
        kept = {c: v for c, v in self.view.camera_views.items() if c in self._heard and c != view.client}
        self.view.camera_views = {**dict(list(kept.items())[-(MAX_CAMERAS - 1) :]), view.client: view}

    def _ack(self, client: str, through: int) -> None:
        ack = Ack(client=client, server=self.id, incarnation=self.incarnation, store=self.store.id,
                  started_ns=self.started_ns, stored_through=through,
                  journal=self._journals.get(client, ""))  # fmt: skip
        self.bus.put(self.keys.ack(client, self.id), self.codec.encode(ack), Channel.CONTROL)

    # ------------------------------------------------------------------ learner thread
    def _learner_loop(self) -> None:
        cfg = self.config
        lower_priority(cfg.think_nice)
        now = time.monotonic()
        next_publish = next_status = now
        next_checkpoint = now + cfg.checkpoint_period_s
        # Thinks restored from a checkpoint were not thought in any status period: the count
        # starts from the learner's own (here, or where one is made below).
        last_status, last_thinks = now, self._thinks()
        while not self._stop.is_set():
            pending = self._pending_config
            if self.learner is None and pending is not None:
                try:
                    self._start_learner(pending)
                    last_thinks = self._thinks()
                except (ValueError, RuntimeError, MemoryError) as exc:  # a client's config, not ours
                    self.rejected["config"] += 1
                    if self._unusable_once(_digest(pending)):
                        why = str(exc).splitlines()[0][:300] if str(exc) else type(exc).__name__
                        log.error("the adopted learner config cannot make a learner (%s); waiting for "
                                  "another", why)  # fmt: skip
                finally:
                    # Only now: while the learner was built (seconds, for torch), the adopted config
                    # kept another client's from being adopted and checked the batches that came.
                    self._pending_config = None
            learner = self.learner
            thought = False
            if learner is not None:
                behind = self._learn_queued(learner)
                thought = self._think(learner) or behind  # more to do: no waiting
                caught_up = self._advance_learned(learner)
                now = time.monotonic()
                if now >= next_publish or caught_up:
                    self.publish()
                    next_publish = now + cfg.publish_period_s
                if now >= next_checkpoint and not self._stop.is_set():  # after a stop: its own, or none
                    self.checkpoint()
                    next_checkpoint = now + cfg.checkpoint_period_s
            now = time.monotonic()
            if now >= next_status:
                thinks = self._thinks()
                self._publish_status((thinks - last_thinks) / max(now - last_status, 1e-9))
                last_status, last_thinks = now, thinks
                next_status = now + cfg.status_period_s
            if not thought:
                due = min(next_status, next_publish) if learner is not None else next_status
                self._wake.wait(timeout=max(0.0, due - time.monotonic()))
                self._wake.clear()

    def _thinks(self) -> int:
        """The learner's thinks so far (restored ones included), 0 before there is one."""
        learner = self.learner
        return int(learner.thinks[0]) if learner is not None else 0

    def _learn_queued(self, learner: Learner) -> bool:
        """Learn waiting stored batches (one at least, for about THINK_CALL_S); whether some still wait.

        Bounded in time as `_think` is: while clients send faster than the learner takes their
        experiences in, a loop until the queue was empty never ended, and the server stopped
        thinking, publishing snapshots and checkpointing (its clients left it as dead).
        """
        tpa = learner.config.thinks_per_action
        deadline = time.monotonic() + THINK_CALL_S
        while self._to_learn:
            # Left in the queue until learned and its thinks owed, so that an empty queue means
            # every batch handed over was (`replayed`, which ends a --replay-only run, reads it).
            batch = self._to_learn[0]
            try:
                key = (batch.client, batch.first_seq)
                fill = key in self._queued_fills
                self._queued_fills.discard(key)
                through = self._loaded_through.get(batch.client, -1)
                if not _fits(batch, learner.config, self.spec_hash):
                    # Queued for a config that made no learner: counted in store/other_spec when this
                    # learner was built from the store, which holds them.
                    pass
                elif (key in self._loaded_fills) if fill else batch.last_seq <= through:
                    # Stored and queued before the learner was built, which learned it from the store
                    # (its thinks in the budget then): learning the queued copy would learn it twice.
                    self._loaded_fills.discard(key)
                    self.schedule.owe(0, batch.client, batch.last_seq)  # done once that budget is paid
                else:
                    stored = ok = self._learn_batch(learner, batch)
                    thought = self._thought_holes.get(batch.client)
                    if fill and thought:  # thought before a record of it was damaged: learned, not owed
                        ok = ok & ~_in_ranges(batch.first_seq, batch.last_seq, thought)
                    self.schedule.owe(tpa * int(np.count_nonzero(ok)), batch.client, batch.last_seq)
                    self._observe(learner, batch, stored)
                queued = self._queued_through.get(batch.client, -1)
                self._hand_over(batch.client, batch.first_seq, batch.last_seq)
                self._queued_through[batch.client] = max(batch.last_seq, queued)
            finally:
                self._to_learn.popleft()  # only this thread takes from the queue
                with self._to_learn_lock:
                    self._to_learn_bytes -= _nbytes(batch)
            if self._to_learn and time.monotonic() >= deadline:  # one batch a call at least
                return True
        return False

    def _hand_over(self, client: str, first: int, last: int) -> None:
        """Record that first..last went to the learner."""
        for holes in (self._unqueued, self._thought_holes):
            if client in holes:
                i, j = _overlapping(holes[client], first, last)
                holes[client][i:j] = without(holes[client][i:j], first, last)
                if not holes[client]:
                    del holes[client]

    def _observe(self, learner: Learner, batch: ExperienceBatch, stored: NDArray[np.bool_]) -> None:
        """Q of the actions the current weights choose in the new states; divergence; staleness.

        Only the experiences the learner stored [N] count: a non-finite or flagged one, or one its
        sanity limits refused (a reward of 1e300), is never learned, so it neither feeds the
        published figures nor becomes the state the dashboard draws. Values and the state drawn
        are of finite next states only: a terminal experience's need not be one.
        """
        if batch.weights_source == f"{self.id}:{self.incarnation}":
            self._staleness.extend((self.version - batch.weights_version.astype(np.int64)).tolist())
        self._rewards.extend(batch.reward[stored].tolist())
        keep = stored & np.isfinite(batch.next_state).all(axis=1)
        if not keep.any():
            return
        values = learner.greedy_values(batch.next_state[keep])[0]
        self._q_chosen.extend(values.tolist())
        # Newest last (a view shows the newest state sent), and only heard clients kept.
        others = {c: v for c, v in self.view.latest_state.items() if c != batch.client and c in self._recent}
        self.view.latest_state = {**others, batch.client: batch.next_state[keep][-1].copy()}
        monitor = learner.monitor
        if monitor.first_diverged(values) >= 0:  # in one pass: one call per experience cost most of a batch
            self._reset_diverged(learner, f"chosen-action values above {monitor.threshold:.2f} for "
                                          f"{monitor.patience} experiences")  # fmt: skip

    def _reset_diverged(self, learner: Learner, why: str) -> None:
        """Fresh weights after a divergence, relearnt from the stored experiences; followers told."""
        learner.reset_weights(np.ones(1, dtype=np.bool_))
        n = int(learner.buffer.count[0])
        relearn = min(learner.config.thinks_per_action * n, self.config.recovery_thinks_max)
        self.schedule.recover(int(learner.thinks[0]), relearn)
        log.warning("divergence: %s; weights reset, relearning from %d stored experiences", why, n)
        self.publish()  # followers learn of it at once and may fail over

    def _think(self, learner: Learner) -> bool:
        """Think at most think_batch times, and for about THINK_CALL_S at most.

        The learner thread also publishes the status heartbeat and snapshots, and sees the stop
        signal, between calls: a network whose update takes 0.5 s would otherwise go silent for
        think_batch of them, and clients would leave it as dead. The first call thinks once.
        """
        batch = self.config.think_batch
        if self._seconds_per_think is None:
            batch = 1
        elif self._seconds_per_think > 0.0:
            batch = max(1, min(batch, int(THINK_CALL_S / self._seconds_per_think)))
        n = self.schedule.next_thinks(batch, int(learner.thinks[0]), stored=learner.buffer.count[0] > 0,
                                      continuous=self.config.think == "continuous")  # fmt: skip
        if n:
            t0 = time.monotonic()
            learner.think(n)
            took = (time.monotonic() - t0) / n
            if not np.isfinite(learner.params.flat).all():
                # Such weights never recover, and thinking on stored experiences alone (continuous,
                # or relearning) brings no new states for the values' monitor to catch them by.
                self._reset_diverged(learner, "the weights are no longer finite")
            lately = self._seconds_per_think
            self._seconds_per_think = took if lately is None else 0.8 * lately + 0.2 * took
        return n > 0

    def _advance_learned(self, learner: Learner) -> bool:
        """Move learned_through past the experiences whose thinks are done; True if it moved."""
        return self.schedule.advance(int(learner.thinks[0]))

    @property
    def budget(self) -> int:
        """Thinks still owed."""
        return self.schedule.budget

    @property
    def learned_through(self) -> dict[str, int]:
        """Per client: the experiences whose thinks are all done."""
        return self.schedule.learned_through

    def publish(self) -> None:
        """Publish the current weights as a snapshot (and keep it for the queryable)."""
        learner = self.learner
        if learner is None:
            return
        self.version += 1
        snapshot = WeightSnapshot(
            server=self.id, incarnation=self.incarnation, store=self.store.id, started_ns=self.started_ns,
            version=self.version, spec_hash=self.spec_hash,
            published_ns=time.time_ns(), thinks=int(learner.thinks[0]),
            diverged=self.schedule.recovering(int(learner.thinks[0])),
            learned_through=self._listed(self.learned_through), params=learner.params.flat[:1],
        )  # fmt: skip
        frame = self.codec.encode(snapshot)
        self._latest_frame = frame
        self.view.published, self.view.weights_version = learner.params.copy(), self.version
        self.bus.put(self.keys.weights(self.id), frame, Channel.LATEST)

    def _listed(self, through: dict[str, int]) -> dict[str, int]:
        """`through`'s entries of the MAX_LISTED most recently heard clients (all, where fewer)."""
        if len(through) <= MAX_LISTED:
            return dict(through)
        recent = sorted(list(self._recent.items()), key=lambda item: item[1])[-MAX_LISTED:]
        return {client: through[client] for client, _ in recent if client in through}

    def _check_clients(self) -> int:
        """Log clients whose heartbeat stopped or came back; -> how many are heard now.

        At most LOGGED_CLIENTS of each by name per check, the rest counted in one line, and after
        the lock is released: without a key thousands of forged ids can fall silent at once, and a
        line each, written under the lock the ingest thread waits on, held up this thread's status
        heartbeat past the clients' timeout.
        """
        now = time.monotonic()
        heard = 0
        back: list[str] = []
        silent: list[tuple[str, float]] = []
        with self._heard_lock:
            for client, seen in list(self._heard.items()):
                if now - seen <= CLIENT_TIMEOUT_S:
                    heard += 1
                    if client in self._silent:
                        self._silent.discard(client)
                        back.append(client)
                elif client not in self._silent:
                    self._silent.add(client)
                    silent.append((client, now - seen))
        for client in back[:LOGGED_CLIENTS]:
            log.info("client %s is heard again", client)
        for client, quiet in silent[:LOGGED_CLIENTS]:
            log.warning("client %s silent for %.1f s", client, quiet)
        if len(back) > LOGGED_CLIENTS or len(silent) > LOGGED_CLIENTS:
            log.warning("%d more clients heard again and %d more silent (not named)",
                        max(0, len(back) - LOGGED_CLIENTS), max(0, len(silent) - LOGGED_CLIENTS))  # fmt: skip
        return heard

    def _publish_status(self, thinks_per_s: float) -> None:
        learner = self.learner
        metrics: dict[str, float] = {
            "think/thinks_per_s": thinks_per_s,
            "think/thinks": float(learner.thinks[0]) if learner else 0.0,
            "think/budget": float(self.budget),
            "store/experiences": float(self.store.count),
            "store/torn_bytes_cut": float(self.store.log.segments.recovery.torn_bytes_cut),
            "store/damaged_spans": float(len(self.store.log.counts.damage)),
            "store/unreadable_records": float(self.store.unreadable),
            "store/missing": float(self.store.missing()),
            "learn/divergence_resets": float(learner.resets[0]) if learner else 0.0,
            "learn/diverged": float(learner is not None and self.schedule.recovering(int(learner.thinks[0]))),
            "learn/rejected_by_limits": float(learner.rejected[0]) if learner else 0.0,
            "clients/heard": float(self._check_clients()),
            "clients/silent": float(len(self._silent)),
            "ingest/inbox_dropped": float(self._inbox.dropped),
            **{k: float(v) for k, v in dict(self.counters).items()},
        }
        if self._q_chosen:
            q = np.asarray(self._q_chosen)
            metrics.update({"learn/q_chosen_mean": float(q.mean()), "learn/q_chosen_max": float(q.max())})
            self._q_chosen.clear()
        if self._rewards:
            metrics["learn/reward_mean"] = float(np.mean(self._rewards))
            self._rewards.clear()
        if self._staleness:
            lag = np.asarray(self._staleness)
            for p in (50, 90, 99):
                metrics[f"learn/staleness_versions_p{p}"] = float(np.percentile(lag, p))
            self._staleness.clear()
        listed = self._listed(self.store.durable_through)
        status = ServerStatus(
            server=self.id, incarnation=self.incarnation, store=self.store.id, started_ns=self.started_ns,
            spec_hash=self.spec_hash, learner_config=self._config_json, weights_version=self.version,
            stored_through=listed, rejected=dict(self.rejected), metrics=metrics,
            uptime_ms=int((time.monotonic() - self._started_monotonic) * 1000.0),
            journals=self._streaming(listed),
        )  # fmt: skip
        self.view.last_status = status
        self._status_sent = time.monotonic()
        try:
            frame = self.codec.encode(status)
        except (FrameTooLarge, Unsendable) as exc:  # not the learner's end: robots keep the last status
            self.counters["publish/status_unsent"] += 1
            log.error("status not sent: %s", exc)
            return
        self.bus.put(self.keys.server_status(self.id), frame, Channel.LATEST)
        for listener in self.view.status_listeners:
            listener(status)

    def _streaming(self, clients: Iterable[str]) -> dict[str, str]:
        """The journal taken of each of `clients` that is streaming now (heard within JOURNAL_HOLD_S).

        A run that ended holds nothing a successor must wait for. Read by either thread: the
        ingest thread replaces or adds to these dicts, and only their entries are looked up here.
        """
        journals, heard, now = self._journals, self._journal_heard, time.monotonic()
        return {
            c: j for c in clients if (j := journals.get(c)) and now - heard.get(c, -math.inf) < JOURNAL_HOLD_S
        }

    def _relay_status(self) -> None:
        """The learner thread's last status again, with what is stored now (ingest thread).

        The learner thread publishes statuses between think calls; one update of a large
        network (a client's config can ask for one) takes seconds, and robots drop a server
        silent for 2 s. The store is this thread's: its acknowledged points are current.
        """
        last = self.view.last_status
        if last is None:
            return
        self._status_sent = time.monotonic()
        # The weights version too: snapshots go out more often than statuses, and a client drops a
        # snapshot whose version no status has reached within its status timeout as forged.
        listed = self._listed(self.store.durable_through)
        status = dataclasses.replace(
            last, stored_through=listed, weights_version=self.version, journals=self._streaming(listed)
        )
        try:
            frame = self.codec.encode(status)
        except (FrameTooLarge, Unsendable):
            return  # counted where the learner thread made it
        self.bus.put(self.keys.server_status(self.id), frame, Channel.LATEST)
        self.counters["publish/status_relayed"] += 1

    def checkpoint(self) -> None:
        """Save weights, counters and config atomically (resumed at the next start)."""
        learner, cfg = self.learner, self.learner_config
        if learner is None or cfg is None:
            return
        meta = {
            "version": self.version, "incarnation": self.incarnation, "thinks": int(learner.thinks[0]),
            "resets": int(learner.resets[0]), "budget": self.budget,
            "stored_through": dict(self._queued_through), "learned_through": dict(self.learned_through),
            "unqueued": {c: [list(h) for h in r] for c, r in self._unqueued.items()},
            "server": self.id,
            # Relearning after a divergence reset still to do: resumed, or a restart would publish
            # weights that were just reset as healthy and stop relearning them.
            "relearn": max(0, self.schedule.recover_until - int(learner.thinks[0])),
        }  # fmt: skip
        newest, previous = self.data_dir / CHECKPOINT, self.data_dir / PREVIOUS_CHECKPOINT
        save_weights(
            newest, cfg, learner.params, meta, keep_previous=previous, training=learner.training_state()
        )
        log.info(
            "checkpoint: version %d, %d thinks, %d experiences",
            self.version,
            meta["thinks"],
            self.store.count,
        )


def _overlapping(ranges: list[Hole], first: int, last: int) -> tuple[int, int]:
    """i, j: ranges[i:j] are those of the ordered, disjoint `ranges` that meet first..last."""
    return (bisect.bisect_left(ranges, first, key=lambda h: h[1]),
            bisect.bisect_right(ranges, last, key=lambda h: h[0]))  # fmt: skip


def _in_ranges(first: int, last: int, ranges: list[Hole]) -> NDArray[np.bool_]:
    """Which of first..last [last - first + 1] lie in the ordered, disjoint `ranges`."""
    inside = np.zeros(last - first + 1, dtype=bool)
    i, j = _overlapping(ranges, first, last)
    for a, b in ranges[i:j]:
        inside[max(a, first) - first : min(b, last) + 1 - first] = True
    return inside


def _less(ranges: list[Hole], taken: list[Hole]) -> list[Hole]:
    """The ordered, disjoint `ranges` less the ordered, disjoint `taken`, in one sweep."""
    out: list[Hole] = []
    k = 0
    for a, b in ranges:
        while k < len(taken) and taken[k][1] < a:  # ends before this range and every later one
            k += 1
        start, t = a, k
        while t < len(taken) and taken[t][0] <= b:
            if taken[t][0] > start:
                out.append((start, taken[t][0] - 1))
            start = max(start, taken[t][1] + 1)
            t += 1
        if start <= b:
            out.append((start, b))
    return out


def _ranges(value: Any) -> dict[str, list[Hole]]:
    """A checkpoint's per-client ranges, checked (PersistError for anything else)."""
    if not isinstance(value, dict) or not all(
        isinstance(r, list)
        and all(isinstance(h, list) and len(h) == 2 and all(map(_is_count, h)) and h[0] <= h[1] for h in r)
        and all(r[n - 1][1] < r[n][0] for n in range(1, len(r)))  # in order, apart
        for r in value.values()
    ):
        raise PersistError("checkpoint meta unqueued is not a map of ordered experience ranges")
    return {str(c): [(int(a), int(b)) for a, b in r] for c, r in value.items()}


def _nbytes(batch: ExperienceBatch) -> int:
    """The bytes a batch's arrays hold."""
    return sum(a.nbytes for a in (batch.state, batch.action, batch.next_state, batch.reward, batch.terminal,
                                  batch.weights_version, batch.flags))  # fmt: skip


def _fits(batch: ExperienceBatch, config: LearnerConfig, spec: str) -> bool:
    """Whether a batch is of the config's learner spec (`spec`, its hash), with the widths it fixes."""
    return (
        batch.spec_hash == spec
        and batch.state.shape[1] == config.state_dim
        and batch.action.shape[1] == config.action_dim
    )


class _NoConfig(ProtocolError):
    """Experiences arrived before the server has a learner config (not acked; re-sent later)."""

    reason = "no_config"


SERVER_JSON = "server_config.json"


def prepare(config: ServerConfig) -> list[str]:
    """Check what serving needs before the network is joined; -> warnings to show.

    Makes the data directory, reads the key file, and refuses a non-loopback endpoint without a
    key unless `insecure`. The whole server config is written there (`server_config.json`) by
    `record`, once the server serves: a refused start leaves the last run's record as it was.
    """
    from wfnn_io.bus import check_exposure

    _check_apart(config)
    make_directory(config.data_dir, "--data-dir")
    keyed = load_key(str(config.key_file) if config.key_file else None) is not None
    warnings = check_exposure(config.net, keyed, config.insecure)
    if config.dashboard is not None and not config.dashboard.loopback:
        warnings.append(f"the dashboard on {config.dashboard.host} can be read by anyone who reaches it "
                        "(learner config, clients, camera pictures): no key protects it")  # fmt: skip
        log.warning(warnings[-1])
    check_free(config.data_dir / "store")  # a server already on this data directory keeps its record
    writable(config.data_dir / SERVER_JSON)  # before it serves: a folder in its place was found after
    return warnings


def _check_apart(config: ServerConfig) -> None:
    """Refuse a data directory that is (or is in) a log being replayed, or that a log beside it reads.

    Reading data never changes it: the server writes its checkpoint, records and store there, and
    its learner config beside its store, where a log whose own description names no config reads
    one too (`log_config`; the server's own store aside).
    """
    data = config.data_dir.resolve()
    for source in config.replay:
        src = Path(source).resolve()
        if (
            data == src
            or src in data.parents
            or (src.parent == data and src.name != "store" and _config_beside(src))
        ):
            raise LogFormatError(
                f"--data-dir {config.data_dir} would write into (or beside) the log {source} being "
                "replayed; use another data directory"
            )


def _config_beside(log_dir: Path) -> bool:
    """Whether a log's learner config is read beside it (its own description names none)."""
    try:
        info = read_log_json(log_dir)
    except LogFormatError:
        return True
    return info is None or info.get("learner_config") is None


def record(config: ServerConfig) -> None:
    """Write the whole server config into its data directory (`server_config.json`)."""
    write_json(config.data_dir / SERVER_JSON, dataclasses.asdict(config))


def run(config: ServerConfig, on_status: Any = None, on_started: Any = None) -> dict[str, Any]:
    """Serve until SIGTERM/SIGINT (checkpointing on the way out); -> the final figures.

    `on_status(status)` is called with each `ServerStatus` published (for a status line), and
    `on_started(server)` once it serves (its dashboard, if any, is bound by then). The signals
    are caught from the start: one that arrives while the server is still starting stops it
    cleanly as soon as it has started (in client mode, one during the wait for the router ends the
    run there, `Terminated`). The figures: experiences stored and imported, thinks.
    """
    import signal

    from wfnn_io.bus import Stopped, ZenohBus

    stop = threading.Event()
    signals: list[int] = []

    def on_signal(signum: int, _: Any) -> None:
        log.info("signal %d: checkpointing and stopping", signum)
        signals.append(signum)
        stop.set()

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGTERM, signal.SIGINT)}
    made = folders_to_be_made(config.data_dir)
    server: ThinkServer | None = None  # made: a refusal inside removes its own new store
    serving = False
    try:
        prepare(config)
        try:  # in client mode, a wait for the router that a signal ends as it ends a run
            bus: Bus = OfflineBus() if config.offline else ZenohBus(config.net, stop)
        except Stopped:
            raise Terminated(signals[-1] if signals else signal.SIGTERM) from None
        try:
            server = ThinkServer(config, bus)
        except BaseException:
            bus.close()  # an open session would hold the process at exit
            raise
        try:
            server.start()
            serving = True
            record(config)  # once it serves: a refused start leaves the last run's record as it was
            if on_started is not None:
                on_started(server)
            shown = None
            while (
                not stop.wait(0.2) and not server.wait(0) and not (config.replay_only and server.replayed())
            ):
                if on_status is not None and server.view.last_status is not shown:
                    shown = server.view.last_status
                    on_status(shown)
        finally:
            try:
                server.stop()  # a second signal meanwhile must not cut the final checkpoint short
            finally:
                bus.close()  # also where the final checkpoint failed: an open session held the process
    except BaseException:
        if not serving:  # a refused start: the store and folders it made go, if still empty
            if server is not None:
                server.store.remove_if_new()
            remove_empty_folders(made)
        raise
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    if server.error is not None:
        raise RuntimeError("think server failed") from server.error
    learner = server.learner
    return {"experiences": server.store.count, "imported": server.imported,
            "thinks": int(learner.thinks[0]) if learner is not None else 0}  # fmt: skip
