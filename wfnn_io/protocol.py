"""The wfnn wire protocol: framed, versioned, CRC-32C-checked msgpack messages (never pickle).

Every frame, little-endian:

    magic "WFNN" | version u8 | type u8 | flags u8 | reserved u8 | sender 16s | seq u64 |
    body_len u32 | msgpack body | [HMAC-SHA256 tag, 32 bytes, when flags & FLAG_MAC] | CRC-32C u32

The CRC covers everything before it and detects corruption; the optional HMAC (over header and
body, with a shared key) stops forged frames on the network: a receiver configured with a key
rejects frames without a valid tag. The tag protects transport, not storage: a server stores
the batches it has verified without one, and readers of logs check tags only where they are
present (`decode(..., mac="if_present")`), so a wrong key is still detected. Arrays travel
as raw little-endian bytes with their dtype and shape. Each message type has a body size limit.
`decode` raises nothing but `ProtocolError` subclasses, whose `reason` names the rejection for
counters.

Key expressions of a controller live in `Keys`.
"""

from __future__ import annotations

import dataclasses
import hashlib
import hmac
import logging
import re
import struct
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any, ClassVar, Literal, NamedTuple, TypeVar

import crcmod.predefined
import msgpack
import numpy as np
from numpy.typing import NDArray

from wfnn_common.checks import cut_repr

log = logging.getLogger(__name__)

MAGIC = b"WFNN"
PROTOCOL_VERSION = 7
"""Version 2 added the store identity to `Ack`, `WeightSnapshot` and `ServerStatus`; version 3 the
server's effective learner config to `ServerStatus`; version 4 the start (`started_ns`) to `Ack`
and `WeightSnapshot`; version 5 the optional `lost_from` to `ExperienceBatch` (a version 4 reader
would refuse a declaration carrying it as malformed: it is told of the version instead); version
6 the optional `uptime_ms` to `ServerStatus`; version 7 the optional journal identity to
`ExperienceBatch`, `Ack` and `ClientStatus`, and the journals a server takes to `ServerStatus`."""
FLAG_MAC = 0x01
HEADER = struct.Struct("<4sBBBB16sQI")
"""magic, version, type, flags, reserved, sender, seq, body_len."""
CRC_SIZE = 4
MAC_SIZE = 32
MIN_FRAME = HEADER.size + CRC_SIZE
_ID_PATTERN = re.compile(r"[A-Za-z0-9_.\-]{1,16}")
_crc32c = crcmod.predefined.mkPredefinedCrcFun("crc-32c")

FloatArray = NDArray[np.float64]


CRC_CHUNK = 1 << 18
"""Bytes per call of the CRC routine: it holds the GIL, so a long frame is checked in pieces
between which the control tick's thread may run."""


def crc32c(data: bytes | bytearray | memoryview) -> int:
    """CRC-32C (Castagnoli) of `data`."""
    view = memoryview(data)
    if len(view) <= CRC_CHUNK:
        return int(_crc32c(view))
    crc = _crc32c(view[:CRC_CHUNK])
    for start in range(CRC_CHUNK, len(view), CRC_CHUNK):
        crc = _crc32c(view[start : start + CRC_CHUNK], crc)
    return int(crc)


# --------------------------------------------------------------------------- errors
class ProtocolError(Exception):
    """A frame or message that must be rejected; `reason` is a short counter name."""

    reason: ClassVar[str] = "malformed"


class Truncated(ProtocolError):
    """The frame is shorter than its header says."""

    reason = "truncated"


class BadMagic(ProtocolError):
    """Not a wfnn frame."""

    reason = "bad_magic"


class VersionMismatch(ProtocolError):
    """A protocol version this build does not speak."""

    reason = "version"


class UnknownType(ProtocolError):
    """A message type this build does not know, or not the one expected on this key."""

    reason = "type"


class FrameTooLarge(ProtocolError):
    """The body exceeds its message type's size limit."""

    reason = "oversized"


class Unsendable(ProtocolError):
    """A message its receivers would refuse (a field out of its bounds): refused when encoded."""

    reason = "unsendable"


class CorruptFrame(ProtocolError):
    """The CRC does not match: bits changed in transit or on disk."""

    reason = "crc"


class AuthError(ProtocolError):
    """A key is configured and the frame has no valid HMAC tag."""

    reason = "auth"


class MalformedBody(ProtocolError):
    """The body is not the msgpack map its message type defines."""

    reason = "malformed"


class SpecMismatch(ProtocolError):
    """The message is for a learner of another spec (network shape or state/action ranges)."""

    reason = "spec"


def _check_journal(journal: str) -> None:
    """A journal identity: "" (not said) or a log id (1-16 of [A-Za-z0-9_.-])."""
    if journal and not _ID_PATTERN.fullmatch(journal):
        raise MalformedBody(f"journal: not a log id: {journal[:40]!r}")


def check_id(name: str, what: str = "id") -> str:
    """A sender id or controller name: 1-16 of [A-Za-z0-9_.-] (safe in frames and key expressions)."""
    if not isinstance(name, str) or not _ID_PATTERN.fullmatch(name):
        raise ValueError(f"{what} must be 1-16 characters of [A-Za-z0-9_.-], got {cut_repr(name, 60)}")
    return name


# --------------------------------------------------------------------------- messages
class MsgType(IntEnum):
    """Message type codes carried in the frame header."""

    EXPERIENCES = 1
    ACK = 2
    WEIGHTS = 3
    SERVER_STATUS = 4
    CLIENT_STATUS = 5
    CAMERA_VIEW = 6


SINCE: dict[MsgType, int] = {
    MsgType.EXPERIENCES: 1, MsgType.ACK: 4, MsgType.WEIGHTS: 4, MsgType.SERVER_STATUS: 3,
    MsgType.CLIENT_STATUS: 1, MsgType.CAMERA_VIEW: 1,
}  # fmt: skip
"""The oldest protocol version whose body of each type this build reads (logs written by
version 1 stay readable: experience batches have not changed)."""

MAX_BODY: dict[MsgType, int] = {
    MsgType.EXPERIENCES: 8 << 20,
    MsgType.ACK: 64 << 10,
    MsgType.WEIGHTS: 32 << 20,
    MsgType.SERVER_STATUS: 1 << 20,
    MsgType.CLIENT_STATUS: 1 << 20,
    MsgType.CAMERA_VIEW: 4 << 20,
}
"""Body size limit per message type (bytes)."""


def max_frame(msg_type: MsgType, body: int | None = None) -> int:
    """The longest frame of a message type (or with a body of at most `body` bytes)."""
    return HEADER.size + (MAX_BODY[msg_type] if body is None else body) + MAC_SIZE + CRC_SIZE


MAX_FRAME = max(max_frame(t) for t in MsgType)
"""The longest frame of any type."""

_DTYPES = {"<f8", "<f4", "<i8", "<u8", "<i4", "<u4", "|u1", "|b1"}


def _array(dtype: str, ndim: int) -> dict[str, Any]:
    """Field metadata: an array of exactly this dtype and number of dimensions."""
    return {"dtype": dtype, "ndim": ndim}


_F8_1, _F8_2 = _array("<f8", 1), _array("<f8", 2)
_OPTIONAL = {"optional": True}
"""Field metadata: left out of the body where the field holds its default (read back as it)."""
_B1_1, _U8_1, _U1_1 = _array("|b1", 1), _array("<u8", 1), _array("|u1", 1)


MAX_SEQ = (1 << 62) - 1
"""The largest experience number (every count and acknowledgement of it fits an int64)."""
MAX_PRODUCED = MAX_SEQ // 2
"""More experiences than any client numbers (2^61: 73,000 years at a million a second). A figure
beyond it that a peer tells of this client's experiences, without a key, is forged: one taken as
what a server holds, or as what a client has produced, would make that client's later batches
duplicates for good, as no numbering of its own gets past it."""
_SEQ = {"range": (-1, MAX_SEQ)}
"""Field metadata: an experience number, or -1 for none (each value, for a map)."""
MAX_VERSION = (1 << 64) - 1
"""The largest weights version: experience batches record the version that chose each action as
an unsigned 64-bit integer."""
_VERSION = {"range": (0, MAX_VERSION)}
"""Field metadata: a weights version (a negative one, applied, stopped a client's uplink)."""
MAX_SPEC_CHARS = 64
"""Longest spec hash (`LearnerConfig.spec_hash` gives 16 characters): a receiver keeps the newest
of every heard sender's."""
_SPEC = {"max_chars": MAX_SPEC_CHARS}

# Experience flags (ExperienceBatch.flags).
EXP_EXPLORED = 0x01
"""Exploration changed the learner's action."""
EXP_SAFE_ACTION = 0x02
"""The configured safe action was executed (no valid weights, or the tick missed its deadline)."""
EXP_VETO_ACTUAL = 0x04
"""A veto replaced the proposed action; this is the executed action's experience (Eq 5.1)."""
EXP_VETO_PROPOSED = 0x08
"""The vetoed, never executed proposal learned with the observed outcome (Eq 5.4)."""
EXP_FILTERED = 0x10
"""The action filter (maximum acceleration) changed the proposed action."""
EXP_NON_FINITE = 0x20
"""A value of the experience is NaN or infinite: stored as received (its numbering kept
whole), never learned. Set by the server at ingest and by every reader of a log (`mark_non_finite`):
a client's journal keeps its frames as it sent them."""
EXP_AFTER_LOSS = 0x40
"""On a batch's first experience: the experiences numbered between what its receiver holds and
this one are lost (the sender's journal lost them to damage); the receiver's run goes on after
the gap instead of waiting for them."""


@dataclass(frozen=True, kw_only=True, eq=False)
class ExperienceBatch:
    """Experiences numbered first_seq, first_seq + 1, ... by their client, in physical units.

    Shapes: state, next_state [N, S]; action [N, A]; reward, terminal, weights_version,
    flags [N]. `weights_version[i]` is the version of the snapshot from `weights_source` that
    chose action i (0: no snapshot, the safe action).
    """

    TYPE: ClassVar[MsgType] = MsgType.EXPERIENCES
    client: str
    spec_hash: str = field(metadata=_SPEC)
    first_seq: int
    weights_source: str
    state: FloatArray = field(metadata=_F8_2)
    action: FloatArray = field(metadata=_F8_2)
    next_state: FloatArray = field(metadata=_F8_2)
    reward: FloatArray = field(metadata=_F8_1)
    terminal: NDArray[np.bool_] = field(metadata=_B1_1)
    weights_version: NDArray[np.uint64] = field(metadata=_U8_1)
    flags: NDArray[np.uint8] = field(metadata=_U1_1)
    lost_from: int = field(default=-1, metadata=_OPTIONAL)
    """With EXP_AFTER_LOSS: the first experience its sender declares lost (the ones through
    first_seq - 1 are too), its acknowledged point + 1 then; -1: from whatever its receiver lacks
    first. Not in the body at -1 (frames that declare nothing are as before)."""
    journal: str = field(default="", metadata=_OPTIONAL)
    """The identity of the client's journal that numbered them (its log id; "": not said, as in
    logs written before version 7). Two runs under one client id number their experiences alike:
    a server takes one journal of a client at a time (`ServerStatus.journals`)."""

    def __len__(self) -> int:
        return int(self.reward.shape[0])

    @property
    def last_seq(self) -> int:
        """Sequence number of the last experience."""
        return self.first_seq + len(self) - 1

    def validate(self) -> None:
        """Shapes agree with each other."""
        n = len(self)
        s, a = self.state.shape[1], self.action.shape[1]
        if n < 1 or not 0 <= self.first_seq <= MAX_SEQ - n + 1:
            raise MalformedBody(f"experience batch needs N >= 1 and 0 <= first_seq, last_seq <= MAX_SEQ, "
                                f"got {n}, {self.first_seq}")  # fmt: skip
        _check_journal(self.journal)
        if not (self.lost_from == -1 or 0 <= self.lost_from < self.first_seq):
            raise MalformedBody(
                f"lost_from must be -1 or before first_seq {self.first_seq}, got {self.lost_from}"
            )
        expected = {"state": (n, s), "action": (n, a), "next_state": (n, s), "terminal": (n,),
                    "weights_version": (n,), "flags": (n,)}  # fmt: skip
        for name, shape in expected.items():
            if getattr(self, name).shape != shape:
                raise MalformedBody(f"{name}: expected shape {shape}, found {getattr(self, name).shape}")

    def non_finite(self) -> NDArray[np.bool_]:
        """Which experiences hold a NaN or infinite state, action, reward or next state [N].

        The next state of a terminal experience is never used (no value follows it), so a task
        that reports a failure with a state it cannot measure still has that reward learned, as
        a learner given the experience directly learns it.
        """
        return ~(
            np.isfinite(self.state).all(axis=1) & np.isfinite(self.action).all(axis=1)
            & (np.isfinite(self.next_state).all(axis=1) | self.terminal.astype(np.bool_))
            & np.isfinite(self.reward)
        )  # fmt: skip

    def learnable(self) -> NDArray[np.bool_]:
        """Which experiences may be learned: not flagged non-finite, and finite [N]."""
        return ((self.flags & EXP_NON_FINITE) == 0) & ~self.non_finite()

    def slice(self, start: int, stop: int | None = None) -> ExperienceBatch:
        """The experiences of indices [start, stop) (to the end without `stop`), renumbered."""
        part = slice(start, stop)
        return dataclasses.replace(
            self, first_seq=self.first_seq + start, state=self.state[part], action=self.action[part],
            next_state=self.next_state[part], reward=self.reward[part], terminal=self.terminal[part],
            weights_version=self.weights_version[part], flags=self.flags[part],
        )  # fmt: skip


@dataclass(frozen=True, kw_only=True, eq=False)
class Ack:
    """A server has durably stored every experience of `client` numbered <= stored_through."""

    TYPE: ClassVar[MsgType] = MsgType.ACK
    client: str
    server: str
    incarnation: int
    store: str
    """The identity of the server's store (made when the store was created): a server restarted
    with a new, empty store is another store, whatever its id and incarnation."""
    started_ns: int
    """The server's start (`ServerStatus.started_ns`): a client takes acks only of the start the
    server's status announces (a store restored from a backup counts its incarnations again)."""
    stored_through: int = field(metadata=_SEQ)
    """-1: nothing stored yet."""
    journal: str = field(default="", metadata=_OPTIONAL)
    """The client's journal whose experiences the server takes now (`ExperienceBatch.journal`):
    a client takes acks only of its own ("": none taken yet)."""

    def __post_init__(self) -> None:
        _check_journal(self.journal)


@dataclass(frozen=True, kw_only=True, eq=False)
class WeightSnapshot:
    """A think server's weights for `act`: one network, params [1, n_params] (float64)."""

    TYPE: ClassVar[MsgType] = MsgType.WEIGHTS
    server: str
    incarnation: int
    """Increases at every start of the server; a client takes snapshots only of the store,
    incarnation and start the server's status announces, and orders them by version."""
    store: str
    """The identity of the server's store (see `Ack.store`)."""
    started_ns: int
    """The server's start (see `Ack.started_ns`)."""
    version: int = field(metadata=_VERSION)
    spec_hash: str = field(metadata=_SPEC)
    published_ns: int
    """time.time_ns() when published (publish-to-applied latency on one host)."""
    thinks: int
    diverged: bool
    """The server saw divergence and reset; these weights have not relearned yet."""
    learned_through: dict[str, int] = field(metadata=_SEQ)
    """Per client: every experience numbered <= this has had its thinks (lock-step mode)."""
    params: FloatArray = field(metadata=_F8_2)


@dataclass(frozen=True, kw_only=True, eq=False)
class ServerStatus:
    """A think server's heartbeat and figures (namespaced metrics: `think/thinks_per_s`, ...)."""

    TYPE: ClassVar[MsgType] = MsgType.SERVER_STATUS
    server: str
    incarnation: int
    store: str
    """The identity of the server's store (see `Ack.store`)."""
    started_ns: int
    spec_hash: str = field(metadata=_SPEC)
    """Empty until the server has a learner config."""
    learner_config: str
    """The LearnerConfig it learns with, its own overrides applied, as JSON (empty until it has
    one): a client whose settings were not adopted learns so, and records it."""
    weights_version: int = field(metadata=_VERSION)
    stored_through: dict[str, int] = field(metadata=_SEQ)
    rejected: dict[str, int]
    """Frames rejected, by reason."""
    metrics: dict[str, float]
    uptime_ms: int = field(default=-1, metadata=_OPTIONAL)
    """Milliseconds since this start, by the server's monotonic clock (-1: not told). How long a
    server has been alive is told by this, not by `started_ns`: wall clocks are set back and differ
    between hosts."""
    journals: dict[str, str] = field(default_factory=dict, metadata=_OPTIONAL)
    """Per client listed in `stored_through`: the journal whose experiences it takes now. A client
    of another journal under that id numbers past what is stored, but none of it is its own."""

    def __post_init__(self) -> None:
        if self.uptime_ms < -1:
            raise MalformedBody(f"uptime_ms must be -1 or at least 0, got {self.uptime_ms}")
        for journal in self.journals.values():
            _check_journal(journal)


@dataclass(frozen=True, kw_only=True, eq=False)
class ClientStatus:
    """A robot client's heartbeat: its learner config (servers without one adopt it) and figures."""

    TYPE: ClassVar[MsgType] = MsgType.CLIENT_STATUS
    client: str
    spec_hash: str = field(metadata=_SPEC)
    learner_config: str
    """The client's LearnerConfig as JSON."""
    following: str
    """Server whose snapshots `act` uses ("" for none, "local" in-process)."""
    weights_version: int = field(metadata=_VERSION)
    produced_through: int = field(metadata=_SEQ)
    acked: dict[str, int] = field(metadata=_SEQ)
    metrics: dict[str, float]

    journal: str = field(default="", metadata=_OPTIONAL)
    """Its journal's identity (`ExperienceBatch.journal`)."""

    def __post_init__(self) -> None:
        if self.following not in ("", "local") and not _ID_PATTERN.fullmatch(self.following):
            raise MalformedBody(f"following: not a server id, 'local' or '': {self.following[:40]!r}")
        _check_journal(self.journal)


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
MAX_CAMERA_SIDE = 4096
"""Largest width or height of a camera picture (a small PNG can declare a huge image, which a
viewer's browser would then allocate)."""


@dataclass(frozen=True, kw_only=True, eq=False)
class CameraView:
    """What a robot's cameras saw at one tick, side by side, as a PNG file's bytes.

    Sent now and then (with the pictures the client saves) for people watching; never learned.
    """

    TYPE: ClassVar[MsgType] = MsgType.CAMERA_VIEW
    client: str
    tick: int
    png: NDArray[np.uint8] = field(metadata=_U1_1)

    def __post_init__(self) -> None:
        head = bytes(self.png[:24])
        if head[:8] != PNG_SIGNATURE or head[12:16] != b"IHDR":  # the header chunk comes first
            raise MalformedBody("png: not a PNG file")
        width, height = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
        if not (1 <= width <= MAX_CAMERA_SIDE and 1 <= height <= MAX_CAMERA_SIDE):
            raise MalformedBody(
                f"png: {width} x {height} pixels, more than {MAX_CAMERA_SIDE} on a side or none"
            )


Message = ExperienceBatch | Ack | WeightSnapshot | ServerStatus | ClientStatus | CameraView
M = TypeVar("M", ExperienceBatch, Ack, WeightSnapshot, ServerStatus, ClientStatus, CameraView)
MESSAGES: dict[MsgType, type[Any]] = {
    cls.TYPE: cls for cls in (ExperienceBatch, Ack, WeightSnapshot, ServerStatus, ClientStatus, CameraView)
}


def mark_non_finite(batch: ExperienceBatch) -> tuple[ExperienceBatch, int]:
    """`batch` with EXP_NON_FINITE set on experiences holding NaN or infinity; -> (batch, how many).

    They are stored as received, so each client's numbering stays whole, and never learned.
    """
    bad = batch.non_finite() & ((batch.flags & EXP_NON_FINITE) == 0)
    n = int(np.count_nonzero(bad))
    if not n:
        return batch, 0
    return dataclasses.replace(batch, flags=np.where(bad, batch.flags | EXP_NON_FINITE, batch.flags)), n


# --------------------------------------------------------------------------- body codec
def _pack_array(a: NDArray[Any], dtype: str) -> dict[str, Any]:
    arr = np.ascontiguousarray(a, dtype=np.dtype(dtype))
    return {"dtype": dtype, "shape": list(arr.shape), "data": arr.tobytes()}


_ARRAY_KEYS = frozenset({"dtype", "shape", "data"})
_DTYPE_OF = {name: np.dtype(name) for name in _DTYPES}
_NATIVE = {name: dt.newbyteorder("=") for name, dt in _DTYPE_OF.items()}
"""Each dtype taken, made once (not at every array of every frame: a store's restart decodes all)."""


def _unpack_array(name: str, value: Any, dtype: str, ndim: int) -> NDArray[Any]:
    if not isinstance(value, dict) or value.keys() != _ARRAY_KEYS:
        raise MalformedBody(f"{name}: expected an array map {{dtype, shape, data}}")
    found, shape, data = value["dtype"], value["shape"], value["data"]
    if found != dtype or found not in _DTYPES:
        raise MalformedBody(f"{name}: expected dtype {dtype}, found {found!r}")
    if not isinstance(shape, list) or len(shape) != ndim:
        raise MalformedBody(f"{name}: expected {ndim} dimensions, found shape {shape!r}")
    count = 1
    for d in shape:
        if type(d) is not int or not 0 <= d < 1 << 31:
            raise MalformedBody(f"{name}: bad shape {shape!r}")
        count *= d
    if not isinstance(data, bytes):
        raise MalformedBody(f"{name}: data must be bytes")
    dt = _DTYPE_OF[dtype]
    if len(data) != count * dt.itemsize:
        raise MalformedBody(f"{name}: {len(data)} bytes do not hold shape {shape} of {dtype}")
    arr = np.frombuffer(data, dtype=dt).reshape(shape)
    if dtype == "|b1":
        arr = arr.view(np.uint8)
        if arr.size and arr.max() > 1:
            raise MalformedBody(f"{name}: booleans must be 0 or 1")
        arr = arr.view(np.bool_)
    # Native byte order and writable, so receivers may use it as any array.
    return arr.astype(_NATIVE[dtype], copy=True)


def _check_scalar(name: str, kind: str, value: Any) -> Any:
    if kind == "int":
        if type(value) is not int or not -(1 << 63) <= value < 1 << 64:
            raise MalformedBody(f"{name}: expected an integer, found {type(value).__name__}")
        return value
    if kind == "float":
        if type(value) not in (int, float):
            raise MalformedBody(f"{name}: expected a number, found {type(value).__name__}")
        return float(value)
    if kind == "bool":
        if type(value) is not bool:
            raise MalformedBody(f"{name}: expected a boolean, found {type(value).__name__}")
        return value
    if kind == "str":
        if type(value) is not str:
            raise MalformedBody(f"{name}: expected a string, found {type(value).__name__}")
        if len(value) > MAX_STRING:
            raise MalformedBody(f"{name}: {len(value)} characters, more than {MAX_STRING}")
        return value
    raise AssertionError(kind)


MAX_STRING = 1 << 16
"""Longest string field (characters): a learner config's JSON is the longest a status holds."""
MAX_MAP_ENTRIES = 1024
"""Most entries of a map field (figures, per-client numbers): a status lists a few dozen figures
and at most a few hundred clients, and a receiver keeps the newest of each sender's."""
MAX_KEY_CHARS = 256
"""Longest key of a map field."""
MAX_NDIM = 2
"""Most dimensions of an array field (its shape is the only list a body holds)."""
MAX_CONTAINERS = 64
"""Most maps and lists in one body: a body is one map, each array a map and its shape's list,
each map field one more (an experience batch, the most, has 15)."""
UTF8_MAX_BYTES = 4
"""Most bytes of one character in UTF-8 (string limits count characters, msgpack's bytes)."""


def _check_dict(name: str, kind: str, value: Any) -> dict[str, Any]:
    if type(value) is not dict:
        raise MalformedBody(f"{name}: expected a map, found {type(value).__name__}")
    if len(value) > MAX_MAP_ENTRIES:
        raise MalformedBody(f"{name}: {len(value)} entries, more than {MAX_MAP_ENTRIES}")
    if any(type(k) is str and len(k) > MAX_KEY_CHARS for k in value):
        raise MalformedBody(f"{name}: a key longer than {MAX_KEY_CHARS} characters")
    return {
        _check_scalar(f"{name} key", "str", k): _check_scalar(f"{name}[{k!r}]", kind, v)
        for k, v in value.items()
    }


_KINDS = {"int": "int", "float": "float", "bool": "bool", "str": "str", "dict[str, int]": "dict:int",
          "dict[str, float]": "dict:float", "dict[str, str]": "dict:str"}  # fmt: skip


def _check_bounds(name: str, value: Any, meta: dict[str, Any]) -> None:
    """Check a decoded field against the bounds its metadata gives.

    A number's range (each value's, for a map): an acknowledgement below -1 would have its client
    declare experiences lost that were stored. A string's length: receivers keep some of them.
    """
    if "range" in meta:
        low, high = meta["range"]
        for v in value.values() if isinstance(value, dict) else (value,):
            if not low <= v <= high:
                raise MalformedBody(f"{name}: {v} is outside [{low}, {high}]")
    if "max_chars" in meta and len(value) > meta["max_chars"]:
        raise MalformedBody(f"{name}: {len(value)} characters, more than {meta['max_chars']}")


def _fields(cls: type[Any]) -> list[tuple[str, str, dict[str, Any]]]:
    """(name, kind, array metadata) per field of a message class."""
    out = []
    for f in dataclasses.fields(cls):
        kind = "array" if "dtype" in f.metadata else _KINDS[str(f.type)]
        out.append((f.name, kind, dict(f.metadata)))
    return out


_FIELDS = {t: _fields(cls) for t, cls in MESSAGES.items()}
_NAMES = {t: frozenset(name for name, _, _ in fields) for t, fields in _FIELDS.items()}
_REQUIRED = {t: frozenset(name for name, _, meta in fields if not meta.get("optional"))
             for t, fields in _FIELDS.items()}  # fmt: skip
_DEFAULTS = {
    t: {f.name: f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
        for f in dataclasses.fields(cls)}
    for t, cls in MESSAGES.items()
}  # fmt: skip


def to_body(msg: Message) -> dict[str, Any]:
    """The msgpack-ready map of a message; Unsendable where its receivers would refuse it."""
    body = _body(msg)
    try:  # what `from_body` checks, but for the arrays' contents: no frame is sent that all drop
        for name, kind, meta in _FIELDS[msg.TYPE]:
            if name not in body:
                continue
            if kind == "array":
                if len(body[name]["shape"]) != meta["ndim"]:
                    raise MalformedBody(f"{name}: expected {meta['ndim']} dimensions, found shape "
                                        f"{body[name]['shape']}")  # fmt: skip
            else:
                _check_bounds(name, _checked(name, kind, body[name]), meta)
        if isinstance(msg, ExperienceBatch):
            msg.validate()
    except MalformedBody as exc:
        raise Unsendable(f"{msg.TYPE.name} not sent: {exc}") from None
    return body


def _body(msg: Message) -> dict[str, Any]:
    """`to_body` unchecked."""
    body: dict[str, Any] = {}
    for name, kind, meta in _FIELDS[msg.TYPE]:
        value = getattr(msg, name)
        if meta.get("optional") and value == _DEFAULTS[msg.TYPE][name]:
            continue
        if kind == "array":
            body[name] = _pack_array(value, meta["dtype"])
        elif kind == "dict:int":
            body[name] = {str(k): int(v) for k, v in value.items()}
        elif kind == "dict:float":
            body[name] = {str(k): float(v) for k, v in value.items()}
        elif kind == "dict:str":
            body[name] = {str(k): str(v) for k, v in value.items()}
        elif kind == "float":
            body[name] = float(value)
        elif kind == "int":
            body[name] = int(value)
        else:
            body[name] = value
    return body


def _checked(name: str, kind: str, value: Any) -> Any:
    """A decoded map's or scalar's value, checked (MalformedBody where its receivers refuse it)."""
    if kind.startswith("dict:"):
        return _check_dict(name, kind[5:], value)
    return _check_scalar(name, kind, value)


def from_body(msg_type: MsgType, body: Any) -> Message:
    """Check a decoded body against its message type's fields; -> the message."""
    if type(body) is not dict:
        raise MalformedBody(f"body must be a map, found {type(body).__name__}")
    fields, names, required = _FIELDS[msg_type], _NAMES[msg_type], _REQUIRED[msg_type]
    given = body.keys()
    if not (required <= given and given <= names):
        missing, extra = sorted(required - given), set(given) - names
        # By repr: msgpack gives str and bytes keys alike, which do not compare.
        listed = sorted(extra, key=repr)[:8] + ([f"... {len(extra)} in all"] if len(extra) > 8 else [])
        raise MalformedBody(f"{MESSAGES[msg_type].__name__}: missing fields {missing}, unexpected {listed}")
    values: dict[str, Any] = {}
    for name, kind, meta in fields:
        if name not in body:
            continue  # an optional field at its default
        v = body[name]
        if kind == "array":
            values[name] = _unpack_array(name, v, meta["dtype"], meta["ndim"])
        else:
            values[name] = _checked(name, kind, v)
        _check_bounds(name, values[name], meta)
    msg: Message = MESSAGES[msg_type](**values)
    if isinstance(msg, ExperienceBatch):
        msg.validate()
    return msg


# --------------------------------------------------------------------------- frames
class Frame(NamedTuple):
    """A decoded frame."""

    sender: str
    seq: int
    message: Message


def _mac(key: bytes, data: bytes | memoryview) -> bytes:
    return hmac.new(key, data, hashlib.sha256).digest()


def encode(msg: Message, sender: str, seq: int, key: bytes | None = None) -> bytes:
    """One frame holding `msg`; with `key`, an HMAC-SHA256 tag is added."""
    check_id(sender, "sender id")
    return _framed(msg.TYPE, msgpack.packb(to_body(msg), use_bin_type=True), sender, seq, key)


def _framed(msg_type: MsgType, body: bytes, sender: str, seq: int, key: bytes | None) -> bytes:
    """The frame of a packed body (`encode`'s framing, which tests also give hostile bodies)."""
    limit = MAX_BODY[msg_type]
    if len(body) > limit:
        raise FrameTooLarge(f"{msg_type.name} body of {len(body)} bytes exceeds the limit of {limit}")
    header = HEADER.pack(
        MAGIC, PROTOCOL_VERSION, int(msg_type), FLAG_MAC if key else 0, 0, sender.encode("ascii"), seq,
        len(body),
    )  # fmt: skip
    frame = header + body
    if key:
        frame += _mac(key, frame)
    return frame + struct.pack("<I", crc32c(frame))


def peek_type(frame: bytes) -> MsgType | None:
    """The message type in a frame's header, without checking anything else (None if unknown)."""
    if len(frame) < HEADER.size:
        return None
    try:
        return MsgType(frame[5])
    except ValueError:
        return None


MacPolicy = Literal["required", "if_present"]


def decode(
    frame: bytes | bytearray | memoryview,
    key: bytes | None = None,
    expect: type[M] | None = None,
    mac: MacPolicy = "required",
    crc_checked: bool = False,
) -> Frame:
    """Check and decode one frame; raises only `ProtocolError` subclasses.

    Args:
        frame: the bytes received.
        key: the shared key; when given, a frame without a valid HMAC tag is rejected, or with
            `mac="if_present"` (reading logs), only a frame whose tag does not verify.
        expect: the message class this key expression carries; any other type is rejected.
        mac: `required` on the network; `if_present` for stored frames (see the module docstring).
        crc_checked: these very bytes passed `check_frame` already: their CRC is not computed
            again (on a large snapshot, a pass over megabytes holding the interpreter's lock from
            the control tick).
    """
    try:
        return _decode(bytes(frame), key, expect, mac, crc_checked)
    except ProtocolError:
        raise
    except Exception as exc:  # anything a hostile body provokes becomes a rejection
        raise MalformedBody(f"{type(exc).__name__}: {exc}") from exc


def check_frame(
    frame: bytes | bytearray | memoryview, key: bytes | None = None, expect: type[Message] | None = None
) -> tuple[str, int]:
    """Check a frame's header, length, CRC and (with `key`) HMAC tag without unpacking its body.

    Returns the sender id and the frame's number (seq); raises only `ProtocolError` subclasses.
    For a receiver that keeps one frame per key until it is decoded: an unchecked frame must not
    push out a checked one (nor, with a key, a lower-numbered one a higher: a replay).
    """
    try:
        sender, seq, _, _ = _check(bytes(frame), key, expect, "required")
    except ProtocolError:
        raise
    except Exception as exc:
        raise MalformedBody(f"{type(exc).__name__}: {exc}") from exc
    return sender, seq


def _decode(
    frame: bytes, key: bytes | None, expect: type[Any] | None, mac: MacPolicy, crc_checked: bool = False
) -> Frame:
    sender, seq, msg_type, body_len = _check(frame, key, expect, mac, crc_checked)
    # Bounded as the checks after it bound every field (arrays' shapes are the only lists): a
    # forged body of a million map keys otherwise took seconds to unpack, holding the interpreter's
    # lock from a robot's control tick, before its fields were refused; so did one of millions of
    # short lists nested in each other, which the lengths alone do not bound.
    containers = 0

    def counted(container: Any) -> Any:
        nonlocal containers
        containers += 1
        if containers > MAX_CONTAINERS:
            raise MalformedBody(f"more than {MAX_CONTAINERS} maps and lists in the body")
        return container

    body = msgpack.unpackb(
        memoryview(frame)[HEADER.size : HEADER.size + body_len], raw=False, strict_map_key=True,
        use_list=True, max_map_len=MAX_MAP_ENTRIES, max_array_len=MAX_NDIM,
        max_str_len=UTF8_MAX_BYTES * MAX_STRING, max_ext_len=0, object_hook=counted, list_hook=counted,
    )  # fmt: skip
    return Frame(sender, seq, from_body(msg_type, body))


def _check(
    frame: bytes, key: bytes | None, expect: type[Any] | None, mac: MacPolicy, crc_checked: bool = False
) -> tuple[str, int, MsgType, int]:
    """-> (sender, seq, type, body length) of a frame whose header, CRC and tag check out."""
    if len(frame) < MIN_FRAME:
        raise Truncated(f"frame of {len(frame)} bytes is shorter than the minimum {MIN_FRAME}")
    magic, version, type_code, flags, reserved, sender_raw, seq, body_len = HEADER.unpack_from(frame)
    if magic != MAGIC:
        raise BadMagic(f"expected magic {MAGIC!r}, found {magic!r}")
    if not 1 <= version <= PROTOCOL_VERSION:
        raise VersionMismatch(f"expected protocol version {PROTOCOL_VERSION}, found {version}")
    try:
        msg_type = MsgType(type_code)
    except ValueError:
        raise UnknownType(f"unknown message type {type_code}") from None
    if version < SINCE[msg_type]:
        raise VersionMismatch(f"{msg_type.name} frames of protocol version {version} are not read "
                              f"(>= {SINCE[msg_type]})")  # fmt: skip
    if body_len > MAX_BODY[msg_type]:
        raise FrameTooLarge(f"{msg_type.name} body of {body_len} bytes exceeds {MAX_BODY[msg_type]}")
    mac_len = MAC_SIZE if flags & FLAG_MAC else 0
    expected_len = HEADER.size + body_len + mac_len + CRC_SIZE
    if len(frame) != expected_len:
        cls = Truncated if len(frame) < expected_len else MalformedBody
        raise cls(f"frame is {len(frame)} bytes, its header says {expected_len}")
    (crc,) = struct.unpack_from("<I", frame, expected_len - CRC_SIZE)
    if not crc_checked and crc != crc32c(memoryview(frame)[: expected_len - CRC_SIZE]):
        raise CorruptFrame("CRC-32C mismatch")
    if key:
        if not mac_len and mac == "required":
            raise AuthError("a key is configured and the frame carries no HMAC tag")
        end = HEADER.size + body_len
        if mac_len and not hmac.compare_digest(
            frame[end : end + MAC_SIZE], _mac(key, memoryview(frame)[:end])
        ):
            raise AuthError("HMAC tag does not verify with the configured key")
    if flags & ~FLAG_MAC:
        raise MalformedBody(f"unknown flags {flags:#x}")
    if reserved:  # written as 0 by every version: anything else is a frame of no version read here
        raise MalformedBody(f"reserved header byte is {reserved:#x}, not 0")
    if expect is not None and msg_type != expect.TYPE:
        raise UnknownType(f"expected a {expect.TYPE.name} frame, found {msg_type.name}")
    sender = sender_raw.rstrip(b"\0").decode("ascii")
    if not _ID_PATTERN.fullmatch(sender):
        raise MalformedBody(f"bad sender id {sender_raw!r}")
    return sender, seq, msg_type, body_len


def tag_verifies(frame: bytes, key: bytes) -> bool:
    """Whether a frame (one this host wrote: its CRC is not checked) carries a tag `key` verifies."""
    if len(frame) < MIN_FRAME + MAC_SIZE or not frame[6] & FLAG_MAC:
        return False
    end = len(frame) - CRC_SIZE - MAC_SIZE
    return hmac.compare_digest(frame[end : end + MAC_SIZE], _mac(key, memoryview(frame)[:end]))


def take(frame: bytes, handle: Callable[[bytes], object], rejected: Counter[str], what: str,
         prefix: str = "") -> None:  # fmt: skip
    """Hand one received frame to `handle`; what it provokes is counted in `rejected`, never raised.

    Whoever receives frames (client and server alike) takes them this way: a `ProtocolError`
    counts as `prefix` + its reason; an exception no check foresaw counts as "error" (logged the
    first ten times) and the receiving thread goes on. An OSError is raised: it is a fault of this
    host (a store that cannot be written), not of the sender.
    """
    try:
        handle(frame)
    except ProtocolError as exc:
        count_rejected(exc, frame, rejected, what, prefix)
    except OSError:
        raise
    except Exception as exc:
        rejected["error"] += 1
        if rejected["error"] <= 10:
            log.error("a %s could not be handled (%s: %s); counted as rejected 'error'", what,
                      type(exc).__name__, exc, exc_info=exc)  # fmt: skip


def count_rejected(
    exc: ProtocolError, frame: bytes, rejected: Counter[str], what: str, prefix: str = ""
) -> None:
    """Count a refused frame as `prefix` + its reason; the first of another version or tag is told."""
    rejected[prefix + exc.reason] += 1
    if isinstance(exc, VersionMismatch) and _first_told(frame):
        # Told once, as a tag that fails: a peer of another wfnn version is otherwise silent.
        log.warning("a %s was refused (%s): its sender runs another wfnn version; run one version on "
                    "both sides; more are counted as rejected %r", what, exc,
                    prefix + exc.reason)  # fmt: skip
    elif isinstance(exc, AuthError) and rejected[prefix + exc.reason] == 1:
        # Told once: peers with different keys refuse each other's every frame, and a robot
        # then acts on its safe action for the whole run with only counts to show for it.
        log.warning("a %s failed its HMAC tag (%s): its sender has another --key-file or --controller "
                    "than this one, or forged it; more are counted as rejected %r", what, exc,
                    prefix + exc.reason)  # fmt: skip
    else:
        log.debug("rejected %s: %s", what, exc)


_VERSIONS_TOLD: set[int] = set()
"""Protocol versions of refused frames this process has named (`take`)."""


def _first_told(frame: bytes) -> bool:
    """Whether `frame`'s protocol version is one this process has not yet named (now it has)."""
    version = frame[4]
    if version in _VERSIONS_TOLD:
        return False
    _VERSIONS_TOLD.add(version)  # at most 256 values
    return True


def older_peer(frame: bytes, peer: str, told: set[str], what: str) -> None:
    """Say once per peer (at most MAX_TOLD) that `frame` is of an older protocol version than this build's.

    This build reads such frames, but the peer cannot read this build's: `what` says what it misses.
    """
    version = frame[4] if len(frame) > 4 else PROTOCOL_VERSION
    if version < PROTOCOL_VERSION and peer not in told and len(told) < MAX_TOLD:
        told.add(peer)
        log.warning("%s speaks protocol version %d, older than this one's %d: it cannot read %s (run one "
                    "wfnn version on both sides)", peer, version, PROTOCOL_VERSION, what)  # fmt: skip


MAX_TOLD = 256
"""Peers `older_peer` names (ids can be forged)."""


def controller_key(key: bytes, controller: str) -> bytes:
    """The key frames of one controller are tagged with, derived from the shared key.

    A tag made under one controller does not verify under another that shares the key file: a
    frame recorded on one controller's keys and replayed on another's is refused.
    """
    return hmac.new(key, b"wfnn controller\0" + check_id(controller, "controller name").encode(),
                    hashlib.sha256).digest()  # fmt: skip


class Codec:
    """Encodes and decodes frames for one sender with an optional shared key.

    With a `controller`, frames are tagged with that controller's key (`controller_key`). Frame
    sequence numbers count up from 0 per codec (thread-safe: `itertools.count`).
    """

    def __init__(self, sender: str, key: bytes | None = None, controller: str | None = None) -> None:
        import itertools

        self.sender = check_id(sender, "sender id")
        self.key = (controller_key(key, controller) if controller is not None else key) if key else None
        """The key frames are tagged and checked with (the controller's, where one is given)."""
        self._seq = itertools.count()

    def encode(self, msg: Message) -> bytes:
        """Frame `msg` with the next sequence number."""
        return encode(msg, self.sender, next(self._seq), self.key)

    def decode(self, frame: bytes | bytearray | memoryview, expect: type[M]) -> tuple[str, M]:
        """-> (sender, message) of a frame that must carry `expect`."""
        sender, _, msg = decode(frame, self.key, expect)
        return sender, msg  # type: ignore[return-value]  # `expect` checked the type


def load_key(path: str | None) -> bytes | None:
    """Read a shared key file (at least 16 bytes after stripping whitespace); None for no path.

    A leading UTF-8 byte-order mark is not part of the key: an editor that writes one on one host
    would otherwise make every frame fail its tag against the same key written plainly elsewhere.
    A key others may read is taken, with a warning (a read-only deployment may hold it so).
    """
    if not path:
        return None

    from wfnn_io.persist import read_regular  # persist imports the learners: only here

    try:
        data, info = read_regular(path)  # the mode of the file read, not of what the path names later
        key, mode = data.removeprefix(b"\xef\xbb\xbf").strip(), info.st_mode
    except OSError as exc:
        raise ValueError(f"key file {path} cannot be read: {exc.strerror or exc}") from None
    if len(key) < 16:
        raise ValueError(
            f"key file {path} holds {len(key)} bytes; use at least 16 (e.g. 32 random hex chars)"
        )
    if mode & 0o077:
        log.warning("key file %s can be read by others (mode %o); chmod 600 it", path, mode & 0o777)
    return key


# --------------------------------------------------------------------------- key expressions
@dataclass(frozen=True)
class Keys:
    """Every key expression of one controller, under `wfnn/<controller>/`."""

    controller: str

    def __post_init__(self) -> None:
        check_id(self.controller, "controller name")

    @property
    def root(self) -> str:
        """Prefix of all keys of this controller."""
        return f"wfnn/{self.controller}"

    def experiences(self, client: str = "*") -> str:
        """Live experience batches of a client, for every server."""
        return f"{self.root}/exp/live/{client}"

    def resend(self, server: str, client: str = "*") -> str:
        """Experience batches a client re-sends to one server that is missing them."""
        return f"{self.root}/exp/to/{server}/{client}"

    def ack(self, client: str, server: str = "*") -> str:
        """A server's acks to one client."""
        return f"{self.root}/ack/{client}/{server}"

    def weights(self, server: str = "*") -> str:
        """A server's weight snapshots (published, and answered by its queryable)."""
        return f"{self.root}/weights/{server}"

    def server_status(self, server: str = "*") -> str:
        """A server's status heartbeat."""
        return f"{self.root}/status/server/{server}"

    def client_status(self, client: str = "*") -> str:
        """A client's status heartbeat."""
        return f"{self.root}/status/client/{client}"

    def camera_view(self, client: str = "*") -> str:
        """What a client's cameras saw (now and then, for people watching)."""
        return f"{self.root}/camera/{client}"

    def server_alive(self, server: str = "*") -> str:
        """Liveliness token of a server."""
        return f"{self.root}/alive/server/{server}"

    def client_alive(self, client: str = "*") -> str:
        """Liveliness token of a client."""
        return f"{self.root}/alive/client/{client}"

    @staticmethod
    def last(key: str) -> str:
        """The last chunk of a key expression (the id it names)."""
        return str(key).rsplit("/", 1)[-1]
