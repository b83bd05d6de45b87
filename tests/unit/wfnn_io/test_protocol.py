import dataclasses
import struct

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from wfnn_io.protocol import (
    CRC_SIZE,
    FLAG_MAC,
    HEADER,
    MAC_SIZE,
    MAGIC,
    MAX_BODY,
    MAX_SEQ,
    MAX_SPEC_CHARS,
    PNG_SIGNATURE,
    PROTOCOL_VERSION,
    Ack,
    AuthError,
    BadMagic,
    CameraView,
    ClientStatus,
    Codec,
    CorruptFrame,
    ExperienceBatch,
    FrameTooLarge,
    Keys,
    MalformedBody,
    MsgType,
    ProtocolError,
    ServerStatus,
    Truncated,
    UnknownType,
    Unsendable,
    VersionMismatch,
    WeightSnapshot,
    check_id,
    crc32c,
    decode,
    encode,
    load_key,
    peek_type,
    to_body,
)

KEY = b"0123456789abcdef0123456789abcdef"
OTHER_KEY = b"fedcba9876543210fedcba9876543210"
FUZZ = settings(max_examples=250, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])


# --------------------------------------------------------------------------- helpers
def make_batch(n=5, s=3, a=2, first_seq=0, client="robot1", seed=0):
    rng = np.random.default_rng(seed)
    return ExperienceBatch(
        client=client,
        spec_hash="abc123",
        first_seq=first_seq,
        weights_source="srv1",
        state=rng.uniform(-1, 1, (n, s)),
        action=rng.uniform(-1, 1, (n, a)),
        next_state=rng.uniform(-1, 1, (n, s)),
        reward=rng.uniform(-2, 0.5, n),
        terminal=rng.random(n) < 0.3,
        weights_version=rng.integers(0, 2**63, n, dtype=np.uint64),
        flags=rng.integers(0, 32, n, dtype=np.uint8),
    )


def make_ack(stored_through=41):
    return Ack(
        client="robot1",
        server="srv1",
        incarnation=3,
        store="9f2c4e",
        started_ns=1_700_000_000_000_000_000,
        stored_through=stored_through,
    )


def make_weights():
    return WeightSnapshot(
        server="srv1",
        incarnation=2,
        store="9f2c4e",
        started_ns=1_699_999_999_000_000_000,
        version=17,
        spec_hash="abc123",
        published_ns=1_700_000_000_123_456_789,
        thinks=12345,
        diverged=True,
        learned_through={"robot1": 9, "robot2": -1},
        params=np.arange(24, dtype=np.float64).reshape(1, 24) / 7,
    )


def make_server_status():
    return ServerStatus(
        server="srv1",
        incarnation=5,
        store="9f2c4e",
        started_ns=123,
        spec_hash="",
        learner_config="",
        weights_version=0,
        stored_through={"robot1": 100},
        rejected={"crc": 2, "auth": 0},
        metrics={"think/thinks_per_s": 1234.5, "store/count": 7.0},
    )


def make_client_status():
    return ClientStatus(
        client="robot1",
        spec_hash="abc123",
        learner_config='{"gamma": 0.8}',
        following="local",
        weights_version=3,
        produced_through=99,
        acked={"srv1": 90, "srv2": -1},
        metrics={},
    )


def _png_head(width, height):
    """A PNG's signature and header chunk (what the protocol reads of it)."""
    ihdr = width.to_bytes(4, "big") + height.to_bytes(4, "big") + bytes([8, 2, 0, 0, 0])
    return PNG_SIGNATURE + len(ihdr).to_bytes(4, "big") + b"IHDR" + ihdr + bytes(4)


def make_camera_view():
    png = np.frombuffer(_png_head(20, 12) + bytes(range(40)), dtype=np.uint8).copy()
    return CameraView(client="robot1", tick=450, png=png)


MAKERS = [make_batch, make_ack, make_weights, make_server_status, make_client_status, make_camera_view]


def assert_same_message(got, want):
    assert type(got) is type(want)
    for f in dataclasses.fields(want):
        g, w = getattr(got, f.name), getattr(want, f.name)
        if isinstance(w, np.ndarray):
            assert isinstance(g, np.ndarray), f.name
            assert g.dtype == w.dtype and g.shape == w.shape, f.name
            np.testing.assert_array_equal(g, w, err_msg=f.name)
        else:
            assert type(g) is type(w) and g == w, f.name


def raw_frame(
    body: bytes, msg_type=MsgType.EXPERIENCES, sender=b"fuzz", seq=0, flags=0, version=None, reserved=0
):
    """A frame with a correct header, length and CRC around any body bytes."""
    v = PROTOCOL_VERSION if version is None else version
    frame = HEADER.pack(MAGIC, v, int(msg_type), flags, reserved, sender, seq, len(body)) + body
    return frame + struct.pack("<I", crc32c(frame))


def with_crc(frame_without_crc: bytes) -> bytes:
    return frame_without_crc + struct.pack("<I", crc32c(frame_without_crc))


# --------------------------------------------------------------------------- round trips
@pytest.mark.parametrize("make", MAKERS, ids=lambda m: m.__name__[5:])
@pytest.mark.parametrize("key", [None, KEY], ids=["nokey", "key"])
def test_every_message_round_trips(make, key):
    msg = make()
    frame = encode(msg, "sender-1", 77, key)
    assert peek_type(frame) is msg.TYPE
    assert ((frame[6] & FLAG_MAC) != 0) == (key is not None)
    sender, seq, got = decode(frame, key)
    assert (sender, seq) == ("sender-1", 77)
    assert_same_message(got, msg)
    _, _, typed = decode(frame, key, expect=type(msg))
    assert_same_message(typed, msg)


def test_frame_layout_and_sizes():
    msg = make_ack()
    plain, keyed = encode(msg, "s", 0), encode(msg, "s", 0, KEY)
    body_len = HEADER.unpack_from(plain)[-1]
    assert len(plain) == HEADER.size + body_len + CRC_SIZE
    assert len(keyed) == len(plain) + MAC_SIZE
    assert plain[:4] == MAGIC and plain[4] == PROTOCOL_VERSION and plain[5] == MsgType.ACK
    assert struct.unpack("<I", plain[-4:])[0] == crc32c(plain[:-4])


def test_decoded_arrays_are_native_writable_copies():
    batch = make_batch()
    got = decode(encode(batch, "s", 0)).message
    for name in ("state", "reward", "terminal", "weights_version", "flags"):
        arr = getattr(got, name)
        assert arr.flags.writeable and arr.dtype.isnative, name
    got.state[0, 0] = 99.0
    assert batch.state[0, 0] != 99.0


def test_experience_batch_round_trip_handles_other_input_dtypes():
    batch = dataclasses.replace(
        make_batch(n=3, s=1, a=1),
        state=np.array([[1], [2], [3]], dtype=np.int32),
        terminal=np.array([0, 1, 0]),
        flags=np.array([1, 2, 255]),
    )
    got = decode(encode(batch, "s", 0)).message
    assert got.state.dtype == np.float64 and got.state.tolist() == [[1.0], [2.0], [3.0]]
    assert got.terminal.dtype == np.bool_ and got.terminal.tolist() == [False, True, False]
    assert got.flags.dtype == np.uint8 and got.flags.tolist() == [1, 2, 255]


def test_codec_sequence_numbers_count_up_and_decode_checks_type():
    codec = Codec("robot1", KEY)
    frames = [codec.encode(make_ack(i)) for i in range(5)]
    assert [decode(f, KEY).seq for f in frames] == [0, 1, 2, 3, 4]
    other = Codec("srv1", KEY)
    sender, ack = other.decode(frames[3], Ack)
    assert sender == "robot1" and isinstance(ack, Ack) and ack.stored_through == 3
    with pytest.raises(UnknownType):
        other.decode(frames[0], ExperienceBatch)
    assert Codec("x", b"").key is None
    with pytest.raises(ValueError):
        Codec("bad/id")


# --------------------------------------------------------------------------- authentication
def test_receiver_with_key_rejects_unkeyed_frame():
    frame = encode(make_ack(), "robot1", 0)
    with pytest.raises(AuthError) as info:
        decode(frame, KEY)
    assert info.value.reason == "auth"
    with pytest.raises(AuthError):
        Codec("srv1", KEY).decode(Codec("robot1").encode(make_ack()), Ack)


def test_a_frame_tagged_for_one_controller_is_refused_by_another_sharing_the_key():
    frame = Codec("robot1", KEY, "arm").encode(make_ack())
    assert isinstance(Codec("srv1", KEY, "arm").decode(frame, Ack)[1], Ack)
    for other in (Codec("srv1", KEY, "base"), Codec("srv1", KEY)):
        with pytest.raises(AuthError):
            other.decode(frame, Ack)


def test_receiver_with_key_rejects_frame_with_other_key():
    with pytest.raises(AuthError):
        decode(encode(make_batch(), "robot1", 0, OTHER_KEY), KEY)


def test_receiver_without_key_accepts_keyed_frame():
    msg = make_batch()
    sender, seq, got = decode(encode(msg, "robot1", 9, KEY))
    assert (sender, seq) == ("robot1", 9)
    assert_same_message(got, msg)


def test_forged_tag_with_recomputed_crc_is_rejected():
    frame = bytearray(encode(make_ack(), "robot1", 0, KEY))
    tag_start = len(frame) - CRC_SIZE - MAC_SIZE
    frame[tag_start] ^= 0xFF
    with pytest.raises(AuthError):
        decode(with_crc(bytes(frame[:-CRC_SIZE])), KEY)


def test_stripping_the_tag_and_flag_is_rejected():
    frame = encode(make_ack(), "robot1", 0, KEY)
    magic, ver, typ, _, res, sender, seq, body_len = HEADER.unpack_from(frame)
    body = frame[HEADER.size : HEADER.size + body_len]
    stripped = with_crc(HEADER.pack(magic, ver, typ, 0, res, sender, seq, body_len) + body)
    assert decode(stripped).message.stored_through == 41
    with pytest.raises(AuthError):
        decode(stripped, KEY)


def test_tampered_body_with_recomputed_crc_is_rejected_by_key():
    frame = bytearray(encode(make_ack(), "robot1", 0, KEY))
    body_len = HEADER.unpack_from(frame)[-1]
    # change the stored_through value (the last byte of the body: a positive fixint 41)
    assert frame[HEADER.size + body_len - 1] == 41
    frame[HEADER.size + body_len - 1] = 42
    forged = with_crc(bytes(frame[:-CRC_SIZE]))
    assert decode(forged).message.stored_through == 42  # without a key only the CRC protects it
    with pytest.raises(AuthError):
        decode(forged, KEY)


# --------------------------------------------------------------------------- corruption
@pytest.mark.parametrize("key", [None, KEY], ids=["nokey", "key"])
def test_every_single_bit_flip_of_an_ack_frame_is_rejected(key):
    frame = encode(make_ack(), "robot1", 5, key)
    decode(frame, key)  # intact frame is fine
    reasons = set()
    for bit in range(len(frame) * 8):
        bad = bytearray(frame)
        bad[bit // 8] ^= 1 << (bit % 8)
        with pytest.raises(ProtocolError) as info:
            decode(bytes(bad), key)
        reasons.add(info.value.reason)
    assert {"bad_magic", "version", "crc"} <= reasons


def test_random_bit_flips_of_an_experience_batch_frame_are_rejected():
    frame = encode(make_batch(n=20), "robot1", 5)
    rng = np.random.default_rng(1234)
    nbits = len(frame) * 8
    for i in range(2000):
        k = 1 if i % 2 == 0 else int(rng.integers(2, 9))
        bits = rng.choice(nbits, size=k, replace=False)
        bad = bytearray(frame)
        for bit in bits:
            bad[bit // 8] ^= 1 << (bit % 8)
        with pytest.raises(ProtocolError):
            decode(bytes(bad))


def test_bit_flip_in_crc_field_is_corrupt_frame():
    frame = bytearray(encode(make_batch(), "robot1", 0))
    frame[-1] ^= 0x10
    with pytest.raises(CorruptFrame) as info:
        decode(bytes(frame))
    assert info.value.reason == "crc"


@pytest.mark.parametrize("key", [None, KEY], ids=["nokey", "key"])
def test_truncation_at_every_length_is_rejected(key):
    frame = encode(make_ack(), "robot1", 0, key)
    for n in range(len(frame)):
        with pytest.raises(Truncated):
            decode(frame[:n], key)


def test_trailing_bytes_are_rejected():
    frame = encode(make_ack(), "robot1", 0)
    with pytest.raises(MalformedBody):
        decode(frame + b"\0")


def test_oversized_body_len_in_header_is_frame_too_large():
    for msg_type, limit in MAX_BODY.items():
        header = HEADER.pack(MAGIC, PROTOCOL_VERSION, int(msg_type), 0, 0, b"x", 0, limit + 1)
        with pytest.raises(FrameTooLarge) as info:
            decode(header + b"\0" * CRC_SIZE)
        assert info.value.reason == "oversized"
    header = HEADER.pack(MAGIC, PROTOCOL_VERSION, int(MsgType.ACK), 0, 0, b"x", 0, 2**32 - 1)
    with pytest.raises(FrameTooLarge):
        decode(header + b"\0" * 100)


def test_encoding_body_over_the_limit_is_frame_too_large():
    limit = MAX_BODY[MsgType.ACK]
    empty = len(msgpack.packb(to_body(dataclasses.replace(make_ack(), server="")), use_bin_type=True))
    length = limit - empty - 2  # a str16 header is 2 bytes longer than the empty fixstr's
    exact = dataclasses.replace(make_ack(), server="s" * length)
    assert len(msgpack.packb(to_body(exact), use_bin_type=True)) == limit
    assert decode(encode(exact, "x", 0)).message.server == "s" * length
    with pytest.raises(FrameTooLarge):
        encode(dataclasses.replace(exact, server="s" * (length + 1)), "x", 0)


def test_encoding_an_oversized_experience_batch_is_frame_too_large():
    n = (MAX_BODY[MsgType.EXPERIENCES] // 16) + 1000  # state and next_state alone exceed the limit
    big = make_batch(n=n, s=1, a=1)
    with pytest.raises(FrameTooLarge):
        encode(big, "robot1", 0)
    with pytest.raises(FrameTooLarge):
        Codec("robot1").encode(big)


# --------------------------------------------------------------------------- header checks
def test_expect_mismatch_is_unknown_type():
    frame = encode(make_ack(), "robot1", 0)
    with pytest.raises(UnknownType) as info:
        decode(frame, expect=ExperienceBatch)
    assert info.value.reason == "type"
    assert isinstance(decode(frame, expect=Ack).message, Ack)


def test_unknown_type_code_is_unknown_type():
    body = msgpack.packb(to_body(make_ack()), use_bin_type=True)
    for code in (0, 7, 255):
        with pytest.raises(UnknownType):
            decode(raw_frame(body, msg_type=code))
        assert peek_type(raw_frame(body, msg_type=code)) is None


def test_wrong_magic_is_bad_magic():
    frame = bytearray(encode(make_ack(), "robot1", 0))
    frame[:4] = b"WFNM"
    with pytest.raises(BadMagic) as info:
        decode(with_crc(bytes(frame[:-CRC_SIZE])))
    assert info.value.reason == "bad_magic"


def test_wrong_version_is_version_mismatch():
    body = msgpack.packb(to_body(make_ack()), use_bin_type=True)
    for version in (0, 1, 2, 3, PROTOCOL_VERSION + 1, 255):  # version 1 acks had no store, 3 no start
        with pytest.raises(VersionMismatch) as info:
            decode(raw_frame(body, MsgType.ACK, version=version))
        assert info.value.reason == "version"
    assert isinstance(decode(raw_frame(body, MsgType.ACK)).message, Ack)


def test_experience_batches_of_protocol_version_1_stay_readable():
    """Logs written before version 2 hold version 1 batches, whose body has not changed."""
    batch = make_batch()
    body = msgpack.packb(to_body(batch), use_bin_type=True)
    got = decode(raw_frame(body, MsgType.EXPERIENCES, version=1)).message
    np.testing.assert_array_equal(got.state, batch.state)


def test_unknown_flags_and_a_reserved_byte_that_is_not_zero_are_rejected():
    body = msgpack.packb(to_body(make_ack()), use_bin_type=True)
    assert isinstance(decode(raw_frame(body, MsgType.ACK)).message, Ack)
    with pytest.raises(MalformedBody, match="flags"):
        decode(raw_frame(body, MsgType.ACK, flags=0x02))
    with pytest.raises(MalformedBody, match="reserved"):
        decode(raw_frame(body, MsgType.ACK, reserved=1))


@pytest.mark.parametrize("sender", [b"", b"a/b", b"a*", b"\xff\xfe", b"ab\0cd"])
def test_bad_sender_ids_in_frames_are_rejected(sender):
    body = msgpack.packb(to_body(make_ack()), use_bin_type=True)
    with pytest.raises(MalformedBody):
        decode(raw_frame(body, MsgType.ACK, sender=sender))


def test_sender_id_with_trailing_newline_is_rejected():
    body = msgpack.packb(to_body(make_ack()), use_bin_type=True)
    with pytest.raises(MalformedBody):
        decode(raw_frame(body, MsgType.ACK, sender=b"robot1\n"))


def test_error_reasons_and_hierarchy():
    errors = {
        Truncated: "truncated", BadMagic: "bad_magic", VersionMismatch: "version", UnknownType: "type",
        FrameTooLarge: "oversized", CorruptFrame: "crc", AuthError: "auth", MalformedBody: "malformed",
    }  # fmt: skip
    for cls, reason in errors.items():
        assert issubclass(cls, ProtocolError) and cls.reason == reason


# --------------------------------------------------------------------------- fuzzing
@FUZZ
@given(st.binary(max_size=400), st.sampled_from([None, KEY]))
def test_fuzz_arbitrary_bytes_raise_only_protocol_errors(data, key):
    with pytest.raises(ProtocolError):
        decode(data, key)


@FUZZ
@given(st.binary(max_size=300))
def test_fuzz_arbitrary_bytes_after_a_valid_header_prefix(tail):
    prefix = encode(make_ack(), "robot1", 0)[:8]
    with pytest.raises(ProtocolError):
        decode(prefix + tail)


msgpack_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(min_value=-(2**63), max_value=2**64 - 1)
    | st.floats(allow_nan=True)
    | st.text(max_size=20)
    | st.binary(max_size=40),
    lambda children: (
        st.lists(children, max_size=6) | st.dictionaries(st.text(max_size=12), children, max_size=6)
    ),
    max_leaves=12,
)


@FUZZ
@given(body=msgpack_values, msg_type=st.sampled_from(list(MsgType)))
def test_fuzz_well_formed_frames_with_arbitrary_bodies(body, msg_type):
    frame = raw_frame(msgpack.packb(body, use_bin_type=True), msg_type)
    try:
        result = decode(frame)
    except ProtocolError:
        return
    assert result.message.TYPE == msg_type  # by chance a valid body


@FUZZ
@given(st.data(), st.sampled_from(list(MsgType)))
def test_fuzz_well_formed_frames_with_right_field_names_and_arbitrary_values(data, msg_type):
    proto = next(m() for m in MAKERS if m().TYPE == msg_type)
    body = {f.name: data.draw(msgpack_values, label=f.name) for f in dataclasses.fields(proto)}
    try:
        result = decode(raw_frame(msgpack.packb(body, use_bin_type=True), msg_type))
    except ProtocolError:
        return
    assert result.message.TYPE == msg_type


@FUZZ
@given(st.binary(min_size=1, max_size=200), st.sampled_from(list(MsgType)))
def test_fuzz_well_formed_frames_with_arbitrary_body_bytes(body, msg_type):
    try:
        result = decode(raw_frame(body, msg_type))
    except ProtocolError:
        return
    assert result.message.TYPE == msg_type


BATCH_BODY = to_body(make_batch(n=4, s=3, a=2))
ARRAY_FIELDS = ["state", "action", "next_state", "reward", "terminal", "weights_version", "flags"]
SCALAR_FIELDS = {"client": str, "spec_hash": str, "first_seq": int, "weights_source": str}
small_ints = st.integers(-(2**63), 2**64 - 1)
scalar_junk = st.one_of(
    st.none(),
    st.booleans(),
    small_ints,
    st.floats(),
    st.text(max_size=8),
    st.binary(max_size=8),
    st.lists(small_ints, max_size=3),
    st.dictionaries(st.text(max_size=3), small_ints, max_size=2),
)


def decode_batch_body(body):
    return decode(raw_frame(msgpack.packb(body, use_bin_type=True), MsgType.EXPERIENCES))


def test_unchanged_batch_body_decodes():
    batch = decode_batch_body(BATCH_BODY).message
    assert isinstance(batch, ExperienceBatch) and len(batch) == 4


@FUZZ
@given(st.data())
def test_fuzz_batch_scalar_field_with_wrong_type(data):
    name = data.draw(st.sampled_from(sorted(SCALAR_FIELDS)))
    want = SCALAR_FIELDS[name]
    value = data.draw(scalar_junk.filter(lambda v: type(v) is not want))
    with pytest.raises(MalformedBody):
        decode_batch_body({**BATCH_BODY, name: value})


@FUZZ
@given(st.sampled_from(ARRAY_FIELDS), scalar_junk)
def test_fuzz_batch_array_field_with_wrong_type(name, value):
    with pytest.raises(MalformedBody):
        decode_batch_body({**BATCH_BODY, name: value})


@FUZZ
@given(st.sampled_from(ARRAY_FIELDS), st.text(max_size=6) | st.binary(max_size=6) | st.integers(-5, 5))
def test_fuzz_batch_array_with_wrong_dtype(name, dtype):
    if dtype == BATCH_BODY[name]["dtype"]:
        dtype = dtype + "x"
    with pytest.raises(MalformedBody):
        decode_batch_body({**BATCH_BODY, name: {**BATCH_BODY[name], "dtype": dtype}})


@FUZZ
@given(st.sampled_from(ARRAY_FIELDS), st.lists(st.integers(-3, 2**33), max_size=4))
def test_fuzz_batch_array_with_inconsistent_shape(name, shape):
    if shape == BATCH_BODY[name]["shape"]:
        shape = [*shape, 1]
    with pytest.raises(MalformedBody):
        decode_batch_body({**BATCH_BODY, name: {**BATCH_BODY[name], "shape": shape}})


@FUZZ
@given(st.sampled_from(ARRAY_FIELDS), st.integers(1, 3), st.booleans())
def test_fuzz_batch_array_length_disagrees_with_the_others(name, extra, longer):
    # shape and data agree with each other, but not with the batch length N = 4
    arr = BATCH_BODY[name]
    itemsize = len(arr["data"]) // int(np.prod(arr["shape"]))
    row = itemsize * int(np.prod(arr["shape"][1:]))
    rows = arr["shape"][0] + (extra if longer else -extra)
    data = (arr["data"] * 2)[: rows * row]
    with pytest.raises(MalformedBody):
        decode_batch_body({**BATCH_BODY, name: {**arr, "shape": [rows, *arr["shape"][1:]], "data": data}})


@FUZZ
@given(st.lists(st.integers(0, 255), min_size=4, max_size=4).filter(lambda b: max(b) > 1))
def test_fuzz_bool_array_bytes_other_than_0_or_1(values):
    terminal = {**BATCH_BODY["terminal"], "data": bytes(values)}
    with pytest.raises(MalformedBody, match="booleans"):
        decode_batch_body({**BATCH_BODY, "terminal": terminal})


@pytest.mark.parametrize(
    "change",
    [
        {"first_seq": -1},
        {"reward": {"dtype": "<f8", "shape": [0], "data": b""}},
        {"extra": 1},
        {"state": {"dtype": "<f8", "shape": [4, 3], "data": b"\0" * 96, "more": 1}},
    ],
)
def test_batch_body_edge_cases_are_malformed(change):
    with pytest.raises(MalformedBody):
        decode_batch_body({**BATCH_BODY, **change})


def test_batch_body_missing_field_is_malformed():
    body = dict(BATCH_BODY)
    del body["flags"]
    with pytest.raises(MalformedBody, match="missing"):
        decode_batch_body(body)


def test_dict_fields_are_checked():
    body = to_body(make_server_status())

    def status_frame(**change):
        return raw_frame(msgpack.packb({**body, **change}, use_bin_type=True), MsgType.SERVER_STATUS)

    for bad in ({"a": 1.5}, {"a": "x"}, [1, 2], {"a": True}, {"a": None}):
        with pytest.raises(MalformedBody):
            decode(status_frame(rejected=bad))
    with pytest.raises(MalformedBody):  # binary map keys are not strings
        decode(status_frame(metrics={b"k": 1.0}))
    ok = decode(status_frame(metrics={"k": 3}))
    assert ok.message.metrics == {"k": 3.0} and type(ok.message.metrics["k"]) is float


# --------------------------------------------------------------------------- batch helpers, keys, ids
def test_slice_and_last_seq():
    batch = make_batch(n=6, first_seq=10)
    assert len(batch) == 6 and batch.last_seq == 15
    tail = batch.slice(2)
    assert tail.first_seq == 12 and tail.last_seq == 15 and len(tail) == 4
    assert tail.client == batch.client and tail.weights_source == batch.weights_source
    for name in ARRAY_FIELDS:
        np.testing.assert_array_equal(getattr(tail, name), getattr(batch, name)[2:])
    tail.validate()
    assert batch.slice(0).first_seq == 10 and len(batch.slice(0)) == 6
    assert make_batch(n=1, first_seq=0).last_seq == 0


def test_validate_rejects_inconsistent_shapes():
    batch = make_batch(n=4)
    with pytest.raises(MalformedBody):
        dataclasses.replace(batch, terminal=batch.terminal[:3]).validate()
    with pytest.raises(MalformedBody):
        dataclasses.replace(batch, next_state=batch.next_state[:, :2]).validate()
    with pytest.raises(MalformedBody):
        dataclasses.replace(batch, first_seq=-1).validate()
    batch.validate()


def test_keys_produce_the_documented_key_expressions():
    k = Keys("arm")
    assert k.root == "wfnn/arm"
    assert k.experiences() == "wfnn/arm/exp/live/*"
    assert k.experiences("robot1") == "wfnn/arm/exp/live/robot1"
    assert k.resend("srv1") == "wfnn/arm/exp/to/srv1/*"
    assert k.resend("srv1", "robot1") == "wfnn/arm/exp/to/srv1/robot1"
    assert k.ack("robot1") == "wfnn/arm/ack/robot1/*"
    assert k.ack("robot1", "srv1") == "wfnn/arm/ack/robot1/srv1"
    assert k.weights() == "wfnn/arm/weights/*"
    assert k.weights("srv1") == "wfnn/arm/weights/srv1"
    assert k.server_status() == "wfnn/arm/status/server/*"
    assert k.server_status("srv1") == "wfnn/arm/status/server/srv1"
    assert k.client_status() == "wfnn/arm/status/client/*"
    assert k.client_status("robot1") == "wfnn/arm/status/client/robot1"
    assert k.server_alive("srv1") == "wfnn/arm/alive/server/srv1"
    assert k.client_alive() == "wfnn/arm/alive/client/*"
    assert Keys.last(k.ack("robot1", "srv1")) == "srv1"
    assert Keys.last("plain") == "plain"
    with pytest.raises(ValueError):
        Keys("a/b")


@pytest.mark.parametrize("name", ["a", "robot-1.x_Y", "x" * 16, "0"])
def test_check_id_accepts_valid_ids(name):
    assert check_id(name) == name


@pytest.mark.parametrize("name", ["a/b", "*", "", "x" * 17, "a b", "é", None, 5])
def test_check_id_rejects_invalid_ids(name):
    with pytest.raises(ValueError, match="controller name"):
        check_id(name, "controller name")


@pytest.mark.parametrize("name", ["robot1\n", "x" * 16 + "\n"])
def test_check_id_rejects_trailing_newline(name):
    with pytest.raises(ValueError):
        check_id(name)


def test_a_camera_view_must_carry_a_png():
    view = make_camera_view()
    body = to_body(view)
    body["png"]["data"] = b"GIF89a" + body["png"]["data"][6:]
    with pytest.raises(MalformedBody, match="not a PNG"):
        decode(raw_frame(msgpack.packb(body, use_bin_type=True), msg_type=MsgType.CAMERA_VIEW))


@pytest.mark.parametrize("size", [(20000, 20000), (0, 12), (20, 0), (4097, 1)])
def test_a_camera_view_declaring_a_huge_or_empty_picture_is_refused(size):
    # A few hundred bytes can declare 20,000 x 20,000 pixels, which a viewer's browser would allocate.
    with pytest.raises(MalformedBody, match="pixels"):
        CameraView(client="robot1", tick=1, png=np.frombuffer(_png_head(*size), dtype=np.uint8).copy())
    CameraView(client="robot1", tick=1, png=np.frombuffer(_png_head(4096, 1), dtype=np.uint8).copy())


@pytest.mark.parametrize("following", ["x" * 65536, "s1/../..", "<script>"])
def test_a_client_status_following_anything_but_a_server_id_is_refused(following):
    with pytest.raises(MalformedBody, match="following"):
        dataclasses.replace(make_client_status(), following=following)
    for fine in ("", "local", "srv1"):
        dataclasses.replace(make_client_status(), following=fine)


def test_take_counts_what_a_frame_provokes_and_raises_only_a_local_fault():
    from collections import Counter

    from wfnn_io.protocol import Codec, take

    rejected: Counter[str] = Counter()
    codec = Codec("srv1")
    good = codec.encode(make_ack())
    got = []
    take(good, lambda f: got.append(codec.decode(f, Ack)[1]), rejected, "ack", "ack_")
    take(good[:-1] + bytes([good[-1] ^ 1]), lambda f: codec.decode(f, Ack), rejected, "ack", "ack_")
    take(good, lambda f: 1 / 0, rejected, "ack", "ack_")
    assert len(got) == 1 and rejected == Counter({"ack_crc": 1, "error": 1})

    def disk_full(frame):
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError):
        take(good, disk_full, rejected, "ack")


def test_maps_of_too_many_entries_or_long_keys_are_refused():
    """A status's figures are a few dozen; a receiver keeps each sender's newest, so they are bounded."""
    from wfnn_io.protocol import MAX_KEY_CHARS, MAX_MAP_ENTRIES, ClientStatus

    def status(metrics):
        return ClientStatus(client="c1", spec_hash="h", learner_config="", following="", weights_version=0,
                            produced_through=-1, acked={}, metrics=metrics)  # fmt: skip

    codec = Codec("c1")
    ok = status({f"m{i}": float(i) for i in range(MAX_MAP_ENTRIES)})
    assert codec.decode(codec.encode(ok), ClientStatus)[1].metrics == ok.metrics
    for bad in ({f"m{i}": 0.0 for i in range(MAX_MAP_ENTRIES + 1)}, {"k" * (MAX_KEY_CHARS + 1): 0.0}):
        with pytest.raises(ProtocolError, match="metrics"):
            codec.decode(codec.encode(status(bad)), ClientStatus)


def test_lost_from_travels_only_where_a_batch_declares_from_where_and_is_checked():
    """A declaration names from where it gives experiences up; frames that declare nothing are as
    before (their bodies lack the field), so journals and stores written before read as they were."""
    plain = make_batch(first_seq=10)
    assert "lost_from" not in to_body(plain)
    assert decode(Codec("robot1").encode(plain)).message.lost_from == -1
    named = dataclasses.replace(plain, lost_from=4)
    assert to_body(named)["lost_from"] == 4
    assert decode(Codec("robot1", KEY).encode(named), KEY).message.lost_from == 4
    assert named.slice(2).lost_from == 4
    for bad in (10, 11, -2):  # at or after its first experience, or below -1
        body = {**to_body(plain), "lost_from": bad}
        with pytest.raises(MalformedBody, match="lost_from"):
            decode(raw_frame(msgpack.packb(body, use_bin_type=True)))
    body = {**to_body(plain), "lost_from": "4"}
    with pytest.raises(MalformedBody, match="lost_from"):
        decode(raw_frame(msgpack.packb(body, use_bin_type=True)))
    body = {**to_body(plain), "lost_since": 4}  # any other name is still refused
    with pytest.raises(MalformedBody, match="unexpected"):
        decode(raw_frame(msgpack.packb(body, use_bin_type=True)))


def test_a_servers_uptime_travels_in_its_status_and_is_checked():
    """Clients order servers by how long they have been alive, which wall clocks cannot tell."""
    plain = make_server_status()
    assert "uptime_ms" not in to_body(plain) and plain.uptime_ms == -1  # a version 5 server's
    frame = raw_frame(msgpack.packb(to_body(plain), use_bin_type=True), msg_type=MsgType.SERVER_STATUS,
                      version=5)  # fmt: skip
    assert decode(frame).message.uptime_ms == -1
    told = dataclasses.replace(plain, uptime_ms=90_061)
    assert decode(Codec("srv1", KEY).encode(told), KEY).message.uptime_ms == 90_061
    for bad in (-2, "5", 1.5):
        body = {**to_body(plain), "uptime_ms": bad}
        with pytest.raises(MalformedBody, match="uptime_ms"):
            decode(raw_frame(msgpack.packb(body, use_bin_type=True), msg_type=MsgType.SERVER_STATUS))


def test_a_key_file_reads_the_same_with_or_without_a_byte_order_mark(tmp_path, caplog):
    """An editor's UTF-8 BOM on one host's copy made every frame fail its tag on the other's."""
    plain, marked = tmp_path / "plain.key", tmp_path / "marked.key"
    plain.write_bytes(b"0123456789abcdef0123456789abcdef\n")
    marked.write_bytes(b"\xef\xbb\xbf0123456789abcdef0123456789abcdef\r\n")
    plain.chmod(0o600)
    marked.chmod(0o600)
    with caplog.at_level("WARNING", logger="wfnn_io.protocol"):
        assert load_key(str(marked)) == load_key(str(plain))
    assert not caplog.records  # private keys: nothing to warn of
    short = tmp_path / "short.key"
    short.write_bytes(b"\xef\xbb\xbf" + b"x" * 14)  # 17 bytes, 14 of them key: refused
    with pytest.raises(ValueError, match="holds 14 bytes"):
        load_key(str(short))


def test_a_key_file_others_can_read_is_taken_with_a_warning(tmp_path, caplog):
    path = tmp_path / "shared.key"
    path.write_bytes(b"0123456789abcdef0123456789abcdef")
    path.chmod(0o644)
    with caplog.at_level("WARNING", logger="wfnn_io.protocol"):
        assert load_key(str(path)) == b"0123456789abcdef0123456789abcdef"
    assert any("can be read by others (mode 644)" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize(
    ("make", "field", "bad"),
    [(make_ack, "stored_through", -2), (make_ack, "stored_through", MAX_SEQ + 1),
     (make_server_status, "stored_through", {"robot1": -999}), (make_client_status, "acked", {"srv1": -2}),
     (make_client_status, "produced_through", -5), (make_weights, "learned_through", {"robot1": -2}),
     (make_weights, "version", -1), (make_server_status, "weights_version", -1),
     (make_client_status, "weights_version", -3)],
)  # fmt: skip
def test_experience_numbers_out_of_their_range_are_refused(make, field, bad):
    """An acknowledgement below -1 (none) would have a client declare stored experiences lost; a
    snapshot of a negative version, applied, stopped the client's uplink (batches record versions
    unsigned)."""
    good = make()
    frame = raw_frame(msgpack.packb({**to_body(good), field: bad}, use_bin_type=True), msg_type=good.TYPE)
    with pytest.raises(MalformedBody, match=field):
        decode(frame)
    assert_same_message(decode(raw_frame(msgpack.packb(to_body(good), use_bin_type=True),
                                         msg_type=good.TYPE)).message, good)  # fmt: skip


@pytest.mark.parametrize("make", [make_batch, make_weights, make_server_status, make_client_status])
def test_a_spec_hash_longer_than_any_spec_gives_is_refused(make):
    """Receivers keep each heard sender's newest spec hash: thousands of forged ids must not hold
    a 64 KiB string each."""
    good = make()
    for spec, ok in (("0" * MAX_SPEC_CHARS, True), ("0" * (MAX_SPEC_CHARS + 1), False)):
        frame = raw_frame(msgpack.packb({**to_body(good), "spec_hash": spec}, use_bin_type=True),
                          msg_type=good.TYPE)  # fmt: skip
        if ok:
            assert decode(frame).message.spec_hash == spec
        else:
            with pytest.raises(MalformedBody, match="spec_hash"):
                decode(frame)


def test_a_frame_whose_receivers_would_refuse_a_string_is_not_sent():
    """A status holding a config of 72,687 characters was encoded and sent twice a second, and
    every receiver refused it as malformed: the sender counted nothing."""
    from wfnn_common.config import MAX_CONFIG_JSON
    from wfnn_io.protocol import MAX_STRING

    assert MAX_STRING == MAX_CONFIG_JSON  # a config that a config check passes, a status carries
    for status in (make_server_status(), make_client_status()):
        fits = dataclasses.replace(status, learner_config="x" * MAX_STRING)
        assert decode(encode(fits, "srv1", 1)).message.learner_config == fits.learner_config
        with pytest.raises(Unsendable, match="learner_config: 65537 characters, more than 65536"):
            encode(dataclasses.replace(status, learner_config="x" * (MAX_STRING + 1)), "srv1", 1)


HOSTILE = {
    "int": [-(1 << 63), -2, -1, 0, (1 << 62), (1 << 63), (1 << 64) - 1],
    "float": [float("nan"), float("inf"), -1e308],
    "str": ["", "x" * 65, "x" * 65_537],
    "dict:int": [{"k" * 257: 1}, {str(i): i for i in range(1025)}, {"a": 1 << 63}, {"a": -2}],
    "dict:float": [{"k" * 257: 1.0}, {str(i): 1.0 for i in range(1025)}],
}


def test_a_message_is_sent_only_where_its_receivers_take_it():
    """Encoding refuses (Unsendable) every field value that decoding refuses, so no sender puts a
    frame on the bus that every receiver drops as malformed (a spec hash of 65 characters, a map of
    1,025 figures or a key of 257 characters, an experience number beyond MAX_SEQ were sent)."""
    from wfnn_io.protocol import _FIELDS, MESSAGES

    makers = {MsgType.EXPERIENCES: make_batch, MsgType.ACK: make_ack, MsgType.WEIGHTS: make_weights,
              MsgType.SERVER_STATUS: make_server_status, MsgType.CLIENT_STATUS: make_client_status,
              MsgType.CAMERA_VIEW: make_camera_view}  # fmt: skip
    checked = 0
    for msg_type, make in makers.items():
        for name, kind, _meta in _FIELDS[msg_type]:
            for value in HOSTILE.get(kind, []):
                try:
                    msg = dataclasses.replace(make(), **{name: value})
                except (MalformedBody, ValueError):
                    continue  # refused where it is made
                try:
                    frame = encode(msg, "srv1", 1)
                except (Unsendable, FrameTooLarge):
                    continue
                got = decode(frame).message  # anything sent is taken
                assert type(got) is MESSAGES[msg_type]
                checked += 1
    assert checked > 20  # most hostile values that are sendable are taken, not skipped


def test_an_experience_batch_of_mismatched_shapes_is_not_sent():
    bad = dataclasses.replace(make_batch(n=5), reward=np.zeros(4))
    with pytest.raises(Unsendable, match="expected shape"):
        encode(bad, "robot1", 0)
    with pytest.raises(Unsendable, match="dimensions"):
        encode(dataclasses.replace(make_batch(n=5), reward=np.zeros((5, 1))), "robot1", 0)


def test_a_body_larger_than_any_field_allows_is_refused_as_it_is_unpacked():
    """A forged status of 100,000 map keys (about 1 MiB) took a quarter of a second to unpack, and
    an experience body of a million several seconds, holding the interpreter's lock from a robot's
    control tick, before its fields were refused; the refusal then listed every key."""
    from wfnn_io.protocol import _FIELDS, MAX_MAP_ENTRIES, MAX_NDIM, MAX_STRING

    status = to_body(make_client_status())
    hostile = [
        {**status, **{f"k{i:06d}": None for i in range(100_000)}},  # a huge map
        {**status, "metrics": {f"m{i}": 1.0 for i in range(MAX_MAP_ENTRIES + 1)}},
        {**status, "spec_hash": "x" * (4 * MAX_STRING + 1)},  # a string beyond any field's characters
        {**status, "junk": [None] * 200_000},  # a list (only arrays' shapes are lists)
    ]
    for body in hostile:
        frame = raw_frame(msgpack.packb(body, use_bin_type=True), msg_type=MsgType.CLIENT_STATUS)
        with pytest.raises(MalformedBody, match="exceeds max_") as refused:
            decode(frame)
        assert len(str(refused.value)) < 300
    # Unexpected fields within the limits are named, at most 8 of them, and counted.
    body = {**status, **{f"k{i:03d}": None for i in range(500)}}
    with pytest.raises(MalformedBody, match=r"unexpected \['k000'.*'k007', '\.\.\. 500 in all'\]"):
        decode(raw_frame(msgpack.packb(body, use_bin_type=True), msg_type=MsgType.CLIENT_STATUS))
    # Keys of both kinds msgpack gives (str and bytes, which do not compare) are listed all the same.
    with pytest.raises(MalformedBody, match="unexpected"):
        decode(raw_frame(msgpack.packb({**status, b"zz": 1, "yy": 2}, use_bin_type=True),
                         msg_type=MsgType.CLIENT_STATUS))  # fmt: skip
    # What the fields allow still unpacks: the longest string in characters of 4 bytes each, the
    # most map entries, and every array field's dimensions.
    longest = dataclasses.replace(make_client_status(), learner_config="\U0001f600" * MAX_STRING)
    assert decode(Codec("robot1").encode(longest)).message.learner_config == longest.learner_config
    full = dataclasses.replace(make_client_status(), metrics={f"m{i}": 1.0 for i in range(MAX_MAP_ENTRIES)})
    assert decode(Codec("robot1").encode(full)).message.metrics == full.metrics
    assert max(meta["ndim"] for f in _FIELDS.values() for _, kind, meta in f if kind == "array") <= MAX_NDIM


def test_a_body_of_many_short_lists_nested_in_each_other_is_refused_as_it_is_unpacked():
    """Within every length limit, a complete binary tree of 2-element lists (1 MiB) took about a
    second to unpack, and 16 MiB seven, holding the interpreter's lock from the control tick."""
    from wfnn_io.protocol import _FIELDS, MAX_CONTAINERS

    tree = b"\xc0"  # nil
    while len(tree) < 256 << 10:  # within every message's body limit
        tree = b"\x92" + tree + tree  # a list of two of the tree
    for msg_type, message in [
        (MsgType.CLIENT_STATUS, make_client_status()),
        (MsgType.WEIGHTS, make_weights()),
    ]:
        packed = msgpack.packb({**to_body(message), "junk": 0}, use_bin_type=True)
        body = packed[:-1] + tree  # "junk": the tree in place of its 0 (one byte)
        with pytest.raises(MalformedBody, match=f"more than {MAX_CONTAINERS} maps and lists"):
            decode(raw_frame(body, msg_type=msg_type))
    # The most a message holds: an experience batch, one map, and a map and a list per array.
    arrays = max(sum(kind == "array" for _, kind, _ in f) for f in _FIELDS.values())
    maps = max(sum(kind.startswith("dict") for _, kind, _ in f) for f in _FIELDS.values())
    assert 1 + 2 * arrays + maps <= MAX_CONTAINERS
    batch = make_batch(n=5)
    assert decode(Codec("robot1").encode(batch)).message.reward.shape == (5,)


def test_a_journals_identity_travels_in_batches_acks_and_statuses_and_is_checked():
    """Two runs under one client id are told apart by it; frames that name none are as before."""
    plain = make_batch(first_seq=10)
    assert "journal" not in to_body(plain)
    named = dataclasses.replace(plain, journal="0123456789abcdef")
    assert decode(Codec("robot1", KEY).encode(named), KEY).message.journal == "0123456789abcdef"
    assert named.slice(2).journal == "0123456789abcdef"
    ack = Ack(client="robot1", server="s1", incarnation=1, store="st", started_ns=1, stored_through=3,
              journal="j1")  # fmt: skip
    assert decode(Codec("s1").encode(ack)).message.journal == "j1"
    status = ServerStatus(
        server="s1", incarnation=1, store="st", started_ns=1, spec_hash="", learner_config="",
        weights_version=0, stored_through={"robot1": 3}, rejected={}, metrics={}, journals={"robot1": "j1"},
    )  # fmt: skip
    assert decode(Codec("s1").encode(status)).message.journals == {"robot1": "j1"}
    assert "journals" not in to_body(dataclasses.replace(status, journals={}))
    for bad in ("a/b", "x" * 17, 5):
        body = {**to_body(plain), "journal": bad}
        with pytest.raises(MalformedBody, match="journal"):
            decode(raw_frame(msgpack.packb(body, use_bin_type=True)))
    with pytest.raises(MalformedBody, match="journal"):
        dataclasses.replace(status, journals={"robot1": "../x"})


def test_a_peer_of_another_protocol_version_is_named_once(caplog, monkeypatch):
    """Peers of two wfnn versions refused each other's every frame, or read only one way, silently."""
    from collections import Counter

    from wfnn_io import protocol
    from wfnn_io.protocol import older_peer, take

    monkeypatch.setattr(protocol, "_VERSIONS_TOLD", set())  # named once per process: none yet here

    status = ClientStatus(client="robot1", spec_hash="", learner_config="", following="", weights_version=0,
                          produced_through=-1, acked={}, metrics={})  # fmt: skip
    newer = raw_frame(msgpack.packb(to_body(status), use_bin_type=True), MsgType.CLIENT_STATUS,
                      version=PROTOCOL_VERSION + 1)  # fmt: skip
    rejected: Counter[str] = Counter()
    with caplog.at_level("WARNING", logger="wfnn_io.protocol"):
        for prefix in ("", "status_", "ack_"):  # a client takes frames of several kinds
            take(newer, lambda frame: decode(frame, expect=ClientStatus), rejected, "frame", prefix)
    assert rejected["version"] == rejected["status_version"] == rejected["ack_version"] == 1
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 1 and "another wfnn version" in said[0]
    caplog.clear()
    older = raw_frame(msgpack.packb(to_body(status), use_bin_type=True), MsgType.CLIENT_STATUS,
                      version=PROTOCOL_VERSION - 1)  # fmt: skip
    assert decode(older).message.client == "robot1"  # read, as before
    told: set[str] = set()
    with caplog.at_level("WARNING", logger="wfnn_io.protocol"):
        for peer in ("client a", "client a", "client b"):
            older_peer(older, peer, told, "its acks")
        older_peer(Codec("robot1").encode(status), "client c", told, "its acks")  # this version: nothing
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 2 and all(f"older than this one's {PROTOCOL_VERSION}" in m for m in said)
