"""The client's journal: every experience batch it produced, as sent, in a segment log.

Experiences stay here however long servers take to acknowledge them, so batches produced while
no server was reachable, or lost on the way, are re-sent from here, and a server that joins
late catches up from here. The journal continues across client restarts: the client id and the
next sequence number are recovered from it. The journal is also the run's experience record,
an experience log (`wfnn_common.logs`: the same format as a server store). A local run, which
sends nothing, records its experiences in the same format (`wfnn_client.brain.Recorder`).
"""

from __future__ import annotations

import bisect
import json
import logging
import secrets
from pathlib import Path

from wfnn_common.config import LearnerConfig
from wfnn_common.logs import log_config, write_log_json
from wfnn_common.protocol import ExperienceBatch, ProtocolError, check_id, decode
from wfnn_common.segments import FsyncPolicy, Position, SegmentLog

log = logging.getLogger(__name__)


class Journal:
    """Append-only journal of encoded `ExperienceBatch` frames with an index by sequence number."""

    def __init__(
        self,
        directory: Path,
        client_id: str | None = None,
        *,
        fsync: FsyncPolicy = "interval",
        fsync_interval_s: float = 0.05,
        segment_bytes: int = 8 << 20,
        learner_config: LearnerConfig | None = None,
    ) -> None:
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        recorded = log_config(directory)
        if (
            learner_config is not None
            and recorded is not None
            and recorded.spec_hash() != learner_config.spec_hash()
        ):
            raise ValueError(
                f"{directory} records experiences of learner spec {recorded.spec_hash()}, not "
                f"{learner_config.spec_hash()} (another task or ranges): use another run directory"
            )
        write_log_json(directory, learner_config or recorded)
        meta = directory / "client.json"
        if meta.exists():
            stored = json.loads(meta.read_text())["client"]
            if client_id is not None and client_id != stored:
                raise ValueError(
                    f"journal {directory} belongs to client {stored!r}, not {client_id!r}; "
                    "use another record directory or the same client id"
                )
            client_id = stored
        else:
            client_id = check_id(client_id or f"c{secrets.token_hex(4)}", "client id")
            meta.write_text(json.dumps({"client": client_id}))
        self.client_id: str = client_id
        self.log = SegmentLog(
            directory, fsync=fsync, fsync_interval_s=fsync_interval_s, segment_bytes=segment_bytes
        )
        self._last: list[int] = []
        """Last sequence number of each journaled batch, ascending."""
        self._where: list[Position] = []
        self.next_seq = 0
        for pos, frame in self.log.read():
            try:
                _, _, batch = decode(frame, expect=ExperienceBatch)
            except ProtocolError as exc:
                log.error("journal record at %s unreadable (%s); skipped", pos, exc)
                continue
            assert isinstance(batch, ExperienceBatch)
            if batch.first_seq != self.next_seq:
                log.error(
                    "journal batch at %s starts at %d, expected %d", pos, batch.first_seq, self.next_seq
                )
            self._index(batch.last_seq, pos)
        if self.next_seq:
            log.info("journal %s: client %s continues at experience %d", directory, client_id, self.next_seq)

    def _index(self, last_seq: int, pos: Position) -> None:
        self._last.append(last_seq)
        self._where.append(pos)
        self.next_seq = last_seq + 1

    def append(self, frame: bytes, last_seq: int) -> None:
        """Journal one encoded batch whose last experience is `last_seq`."""
        self._index(last_seq, self.log.append(frame))

    def frames_from(self, seq: int, max_frames: int) -> tuple[list[bytes], int]:
        """Up to `max_frames` journaled frames, from the one holding experience `seq`.

        Returns the frames and the last experience they hold (-1 when there are none).
        """
        i = bisect.bisect_left(self._last, seq)
        out: list[bytes] = []
        if i >= len(self._last):
            return out, -1
        for pos, frame in self.log.read(self._where[i]):
            if pos != self._where[i + len(out)]:
                continue  # a record that was unreadable when the journal was opened
            out.append(frame)
            if len(out) >= max_frames or i + len(out) >= len(self._where):
                break
        return out, self._last[i + len(out) - 1]

    def sync(self) -> None:
        """Make the journal durable (per its fsync policy)."""
        self.log.sync()

    def close(self) -> None:
        """Sync and close."""
        self.log.close()
