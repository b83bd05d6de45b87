"""The robot side's learner roles: `act` on the current weights, `learn` (record/send) experiences.

    brain.start()
    while running:
        acted = brain.act(x)                # None: no valid weights yet -> the safe action
        ... execute, observe x_next, r ...
        brain.learn(Experience(x, u, x_next, r, ...), acted)
        brain.sync()                        # lock-step runs only: wait for the thinks
    brain.stop()

`LocalBrain` thinks in this process (act-learn-think-MT, or act-learn-think in lock-step);
`wfnn_client.remote.RemoteBrain` sends experiences to think servers over the bus
(act-learn-think-C/S).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, NamedTuple, Protocol

import numpy as np
from numpy.typing import NDArray

from wfnn_client.journal import Journal
from wfnn_client.think_thread import ActLearnThinkMT
from wfnn_common.config import LearnerConfig
from wfnn_common.learner import ActResult
from wfnn_common.learners import Learner
from wfnn_io.cli_errors import interrupts_after
from wfnn_io.logs import Task
from wfnn_io.protocol import EXP_EXPLORED, Codec, ExperienceBatch

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

LOCAL_SOURCE = "local"
"""The weights source of an in-process learner (the experiences' `weights_source`)."""


class Acted(NamedTuple):
    """An action chosen by `act`, and the weights that chose it."""

    result: ActResult
    source: str
    """Who made the weights: a server id and incarnation ("srv:3"), or "local"."""
    version: int
    """Version of the snapshot from `source`."""


@dataclass(frozen=True)
class Experience:
    """One experience in physical units, as executed, with its EXP_* flags."""

    state: FloatArray
    action: FloatArray
    next_state: FloatArray
    reward: float
    terminal: bool = False
    flags: int = 0


def as_recorded(experience: Experience, acted: Acted | None) -> tuple[Experience, str, int]:
    """An experience as it is recorded and sent, with the weights that chose its action.

    Flagged explored where exploration changed its action; (source, version) of the weights
    ("", 0: the safe action).
    """
    if acted is None:
        return experience, "", 0
    if acted.result.explored:
        experience = replace(experience, flags=experience.flags | EXP_EXPLORED)
    return experience, acted.source, acted.version


def experience_batch(
    client: str, spec_hash: str, first_seq: int, source: str, experiences: Sequence[Experience],
    versions: Sequence[int], journal: str = "",
) -> ExperienceBatch:  # fmt: skip
    """Experiences numbered from `first_seq` by `journal`, all chosen by weights of `source`: one batch."""
    e = experiences
    return ExperienceBatch(
        client=client, spec_hash=spec_hash, first_seq=first_seq, weights_source=source,
        state=np.stack([x.state for x in e]), action=np.stack([x.action for x in e]),
        next_state=np.stack([x.next_state for x in e]), reward=np.array([x.reward for x in e]),
        terminal=np.array([x.terminal for x in e], dtype=np.bool_),
        weights_version=np.array(versions, dtype=np.uint64),
        flags=np.array([x.flags for x in e], dtype=np.uint8), journal=journal,
    )  # fmt: skip


class Recorder:
    """A local run's experience record: experiences batched into a journal (an experience log).

    `add` only buffers; a batch is encoded and appended every `batch_max` experiences or when
    the weights that chose the actions change source, and the rest at `close`. Appends are
    left to the OS (they survive the process dying, not a power cut) and synced at `close`. With
    `background`, batches are encoded and appended by a writer thread, so that a slow disk does
    not hold up the control tick that calls `add`; a failed write is raised by `check` and
    `close`.
    """

    def __init__(
        self, directory: Path, config: LearnerConfig, client_id: str | None = None, batch_max: int = 256,
        background: bool = False, task: Task | None = None,
    ) -> None:  # fmt: skip
        self.journal = Journal(directory, client_id, fsync="never", learner_config=config, task=task)
        self.codec = Codec(self.journal.client_id)
        self.spec_hash = config.spec_hash()
        self.batch_max = batch_max
        self._experiences: list[Experience] = []
        self._versions: list[int] = []
        self._source = ""
        self.recorded = 0
        self.error: BaseException | None = None
        """What stopped the writer thread, if anything."""
        self._queue: queue.SimpleQueue[tuple[str, list[Experience], list[int]] | None] | None = None
        self._writer: threading.Thread | None = None
        if background:
            self._queue = queue.SimpleQueue()
            self._writer = threading.Thread(target=self._write_all, name="wfnn-record", daemon=True)
            self._writer.start()

    def add(self, experience: Experience, source: str, version: int) -> None:
        """Record one experience (physical units), chosen by weights `version` of `source`."""
        if self._experiences and source != self._source:
            self.flush()
        self._source = source
        self._experiences.append(experience)
        self._versions.append(version)
        if len(self._experiences) >= self.batch_max:
            self.flush()

    def flush(self) -> None:
        """Append the buffered experiences as one batch (with `background`, hand them to the writer)."""
        if not self._experiences:
            return
        batch = (self._source, self._experiences, self._versions)
        self._experiences, self._versions = [], []
        if self._queue is None:
            self._write(*batch)
        elif self.error is None:
            self._queue.put(batch)

    def _write(self, source: str, experiences: list[Experience], versions: list[int]) -> None:
        batch = experience_batch(self.journal.client_id, self.spec_hash, self.journal.next_seq, source,
                                 experiences, versions)  # fmt: skip
        self.journal.append(self.codec.encode(batch), batch.last_seq)
        self.recorded += len(batch)

    def _write_all(self) -> None:
        """The writer thread: batches in order until `close` says there are no more."""
        assert self._queue is not None
        while (item := self._queue.get()) is not None:
            if self.error is None:
                try:
                    self._write(*item)
                except BaseException as exc:  # kept for `check` and `close`; later batches are dropped
                    self.error = exc
                    log.error("the experience record cannot be written: %s", exc)

    def check(self) -> None:
        """Raise the writer thread's error, if any."""
        if self.error is not None:
            raise RuntimeError("writing the experience record failed") from self.error

    def close(self) -> None:
        """Flush, sync and close (raises the writer's error, once the journal is closed)."""
        try:
            self.flush()
            if self._queue is not None and self._writer is not None:
                self._queue.put(None)
                self._writer.join()
        finally:
            self.journal.close()
        self.check()


class Brain(Protocol):
    """What the control loop needs from the learner (see the module docstring)."""

    @property
    def following(self) -> str:
        """Whose weights `act` uses ("" when none)."""
        ...

    @property
    def connected(self) -> bool:
        """Whether the weights come from a healthy source right now."""
        ...

    def start(self) -> None:
        """Start background work."""
        ...

    def stop(self) -> None:
        """Stop background work, flushing what must be kept."""
        ...

    def act(self, state: FloatArray, explore: bool = True) -> Acted | None:
        """The learner's action for `state`, or None when no valid weights exist."""
        ...

    def learn(self, experience: Experience, acted: Acted | None) -> None:
        """Record an experience; never blocks the tick. `acted`: what chose its action."""
        ...

    def sync(self, timeout_s: float) -> bool:
        """Lock-step: wait until every learned experience has had its thinks; False on timeout."""
        ...

    def metrics(self) -> dict[str, float]:
        """Namespaced figures of the brain."""
        ...

    def report(self, metrics: dict[str, Any]) -> None:
        """Figures of the control loop to pass on (numbers go into the client's status heartbeat)."""
        ...

    def check(self) -> None:
        """Raise if background work has failed."""
        ...


class LocalBrain:
    """Thinking in this process: a background think thread, or inline in lock-step mode."""

    def __init__(
        self,
        learner: Learner,
        lockstep: bool = False,
        think_batch: int = 50,
        recorder: Recorder | None = None,
        learns: bool = True,
        version: int = 0,
    ) -> None:
        self.learner = learner
        # Before the control loop and the think thread run: loading torch among them would hold up ticks.
        learner.prepare_thinking(compile=learns)
        self.lockstep = lockstep
        self.mt = None if lockstep or not learns else ActLearnThinkMT(learner, think_batch, version=version)
        self._offset = version - int(learner.thinks[0]) if version else 0
        """Lock-step (and a run that learns nothing) numbers its weights by its thinks, from
        `version` on: the version of the weights it was given (the threaded run's counts its
        snapshots, which may have run ahead of its thinks)."""
        self.frozen = None if learns else learner.snapshot()
        """A run that learns nothing acts on the weights it was given, as they are: acting on the
        learner's own, its divergence monitor would reset them to random ones (and save those)."""
        self.recorder = recorder
        """Where every experience is recorded (an experience log), if anywhere."""
        self._told_refused = False

    @property
    def version(self) -> int:
        """The weights version `act` uses, after the version of the weights it was given.

        The snapshots published (lock-step, and a run that learns nothing: the thinks).
        """
        return self.mt.version if self.mt is not None else int(self.learner.thinks[0]) + self._offset

    @property
    def following(self) -> str:
        """Always the in-process learner."""
        return LOCAL_SOURCE

    @property
    def connected(self) -> bool:
        """The in-process learner is always there."""
        return True

    def start(self) -> None:
        """Start the think thread (none in lock-step)."""
        if self.mt is not None:
            self.mt.start()

    def stop(self) -> None:
        """Stop the think thread; close the record (also when the think thread failed)."""
        try:
            if self.mt is not None:
                self.mt.stop()
        finally:
            if self.recorder is not None:
                self.recorder.close()

    def act(self, state: FloatArray, explore: bool = True) -> Acted | None:
        """Best wire of the newest snapshot (lock-step: of the learner itself)."""
        if self.mt is None:
            # None: the learner's own weights, or in a run that learns nothing the frozen copy.
            result = self.learner.act(state, explore, params=self.frozen)
            return Acted(result, LOCAL_SOURCE, self.version)
        return Acted(self.mt.act(state, explore), LOCAL_SOURCE, self.mt.version)

    def learn(self, experience: Experience, acted: Acted | None) -> None:
        """Record; queue for the think thread, or learn and think now (lock-step)."""
        e = experience
        if self.recorder is not None:
            self.recorder.add(*as_recorded(e, acted))
        if self.mt is None:
            # Thinks are owed per stored experience, as in the think thread and on a server. Ctrl-C
            # or SIGTERM waits for them: the learner is saved as the run ends, never half-updated.
            with interrupts_after():
                if self.learner.learn(e.state, e.action, e.next_state, e.reward, e.terminal):
                    self.learner.think()
        else:
            self.mt.learn(e.state, e.action, e.next_state, e.reward, e.terminal)

    def sync(self, timeout_s: float) -> bool:
        """Lock-step thinks happen inside `learn`; the threaded brain waits for its queue to drain."""
        if self.mt is None:
            return True
        deadline = time.monotonic() + timeout_s
        while self.mt.queued or self.mt.budget > 0:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.0005)
        return True

    def metrics(self) -> dict[str, float]:
        """Thinks, snapshots, resets, and experiences stored and refused (by the learner's sanity checks).

        The first refusal is told in a warning: a task whose states leave their declared ranges has
        every experience refused, and the run learns nothing.
        """
        refused, stored = float(self.learner.rejected.sum()), float(self.learner.buffer.count[0])
        if refused and not self._told_refused:
            self._told_refused = True
            cfg = self.learner.config
            log.warning("the learner refuses experiences (%d so far, %d stored): a reward, state or action "
                        "that is not finite, a reward beyond 1e30, or a state beyond its declared range "
                        "(%s to %s) by more than %g times its width: does the task leave its declared "
                        "observation space?", refused, stored, np.array2string(np.asarray(cfg.state_low),
                        precision=3, threshold=8), np.array2string(np.asarray(cfg.state_high), precision=3,
                        threshold=8), cfg.valid_margin)  # fmt: skip
        return {
            "think/thinks": float(self.learner.thinks.sum()),
            "weights/version": float(self.version),
            "learn/divergence_resets": float(self.learner.resets.sum()),
            "learn/experiences": stored,
            "learn/rejected": refused,
        }

    def report(self, metrics: dict[str, Any]) -> None:
        """Nobody to tell in-process."""

    @property
    def thinking(self) -> bool:
        """Whether its think thread still runs after `stop` (a long think outlived the wait)."""
        return self.mt is not None and self.mt.thinking

    def finish_thinking(self, timeout_s: float) -> bool:
        """After `stop`, wait up to timeout_s more for a think thread that outlived its wait.

        A long think does (a first compiled update, a slow machine) -> whether it has finished.
        """
        if self.mt is not None and self.mt.thinking:
            self.mt.stop(timeout_s)  # the queue it left joins the replay buffer once it ends
        return not self.thinking

    def check(self) -> None:
        """Raise the think thread's or the record's error, if any."""
        if self.mt is not None and self.mt.error is not None:
            raise RuntimeError("think thread failed") from self.mt.error
        if self.recorder is not None:
            self.recorder.check()
