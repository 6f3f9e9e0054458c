"""The message codec: round trips, strict rejection of bad bytes, and a property test
that no input makes ``decode`` raise anything but ``MessageError``."""

from __future__ import annotations

import math
import struct
import time

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from estimation.errors import MessageError
from transport.codec import (
    DEFAULT_MAX_BYTES,
    MAX_ID,
    MAX_STAMP,
    MIN_ID,
    PLANT_ID,
    VERSION,
    Message,
    Schema,
    decode,
    encode,
    encode_fields,
    to_wire,
)

SCHEMA = Schema(
    {
        "est": {"x": (4,)},
        "meas": {"y": (None,)},
        "truth": {"x": (4,), "P": (4, 4)},
        "ctl": {},
        "done": {"err": ()},
    }
)


def est(x=(1.0, -2.0, 3.5, 1e300), **kw) -> Message:
    kw.setdefault("kind", "est")
    kw.setdefault("sender", 3)
    kw.setdefault("stamp", 17)
    return Message(arrays={"x": np.asarray(x, dtype=float)}, **kw)


def reason_of(data, **kw) -> str:
    kw.setdefault("schema", SCHEMA)
    with pytest.raises(MessageError) as info:
        decode(data, **kw)
    return info.value.reason


def packed(wire) -> bytes:
    return msgpack.packb(wire, use_bin_type=True)


# ----------------------------------------------------------------------------- round trip


def test_round_trip_est():
    msg = est()
    out = decode(encode(msg), schema=SCHEMA, expected_sender=3)
    assert out == msg
    assert (out.version, out.kind, out.sender, out.stamp, out.receiver) == (VERSION, "est", 3, 17, None)
    assert out.arrays["x"].dtype == np.float64
    np.testing.assert_array_equal(out.arrays["x"], [1.0, -2.0, 3.5, 1e300])


def test_round_trip_all_fields():
    rng = np.random.default_rng(0)
    msg = Message(
        kind="truth",
        sender=PLANT_ID,
        stamp=MAX_STAMP,
        receiver=MAX_ID,
        arrays={"x": rng.normal(size=4), "P": rng.normal(size=(4, 4))},
        meta={"cmd": "go", "n": -5, "gain": 0.25, "flag": True},
    )
    out = decode(encode(msg), schema=SCHEMA, expected_sender=PLANT_ID, expected_receiver=MAX_ID)
    assert out == msg
    assert dict(out.meta) == {"cmd": "go", "n": -5, "gain": 0.25, "flag": True}
    assert type(out.meta["flag"]) is bool and type(out.meta["n"]) is int


def test_round_trip_empty_and_scalar_and_wildcard():
    ctl = Message(kind="ctl", sender=MIN_ID, stamp=0, arrays={}, meta={"cmd": "stop"})
    assert decode(encode(ctl), schema=SCHEMA) == ctl
    done = Message(kind="done", sender=0, stamp=1, arrays={"err": 0.5})
    assert decode(encode(done), schema=SCHEMA).arrays["err"].shape == ()
    for p in (0, 1, 7):
        meas = Message(kind="meas", sender=PLANT_ID, stamp=2, arrays={"y": np.arange(p, dtype=float)})
        assert decode(encode(meas), schema=SCHEMA).arrays["y"].shape == (p,)


def test_decoded_arrays_are_read_only_and_independent_of_the_input():
    data = bytearray(encode(est()))
    out = decode(data, schema=SCHEMA)
    x = out.arrays["x"]
    assert not x.flags.writeable
    with pytest.raises(ValueError):
        x[0] = 0.0
    with pytest.raises(ValueError):  # a view of immutable bytes (decoding copies nothing else): never writeable again
        x.setflags(write=True)
    data[:] = b"\x00" * len(data)  # the input buffer is reused: the message is unaffected
    assert x[0] == 1.0
    with pytest.raises(TypeError):
        out.arrays["x"] = np.zeros(4)  # type: ignore[index]
    with pytest.raises(AttributeError):
        out.stamp = 3  # type: ignore[misc]


def test_message_copies_and_freezes_its_arrays():
    x = np.array([1.0, 2.0, 3.0, 4.0])
    msg = est(x)
    x[0] = 99.0
    assert msg.arrays["x"][0] == 1.0
    assert not msg.arrays["x"].flags.writeable


def test_decode_accepts_memoryview():
    assert decode(memoryview(encode(est())), schema=SCHEMA) == est()


def test_wire_format_is_plain_msgpack_little_endian():
    wire = msgpack.unpackb(encode(est(stamp=5)), raw=False)
    assert wire["v"] == VERSION and wire["kind"] == "est" and wire["from"] == 3 and wire["k"] == 5
    shape, raw = wire["arr"]["x"]
    assert shape == [4] and raw == struct.pack("<4d", 1.0, -2.0, 3.5, 1e300)
    assert "to" not in wire and "meta" not in wire


# ------------------------------------------------------------------ construction / encode


@pytest.mark.parametrize(
    "kw, reason",
    [
        ({"kind": "nope"}, "type"),
        ({"sender": True}, "type"),
        ({"sender": MAX_ID + 1}, "type"),
        ({"sender": MIN_ID - 1}, "type"),
        ({"stamp": -1}, "type"),
        ({"stamp": 1.0}, "type"),
        ({"stamp": MAX_STAMP + 1}, "type"),
        ({"receiver": "2"}, "type"),
        ({"meta": {"bad key": 1}}, "keys"),
        ({"meta": {"v": [1]}}, "type"),
        ({"meta": {"v": math.nan}}, "nonfinite"),
        ({"version": 2}, "version"),
    ],
)
def test_invalid_message_is_rejected_at_construction(kw, reason):
    with pytest.raises(MessageError) as info:
        est(**kw)
    assert info.value.reason == reason


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_array_cannot_be_built_or_encoded(bad):
    with pytest.raises(MessageError) as info:
        est((1.0, bad, 0.0, 0.0))
    assert info.value.reason == "nonfinite"
    msg = est()
    x = msg.arrays["x"]
    x.flags.writeable = True  # deliberate tampering after construction
    x[2] = bad
    with pytest.raises(MessageError) as info:
        encode(msg)
    assert info.value.reason == "nonfinite"


def test_encode_checks_schema_and_size():
    with pytest.raises(MessageError) as info:
        encode(est((1.0, 2.0)), schema=SCHEMA)
    assert info.value.reason == "shape"
    with pytest.raises(MessageError) as info:
        encode(Message(kind="meas", sender=0, stamp=0, arrays={"y": np.zeros(1000)}), max_bytes=1000)
    assert info.value.reason == "size"


def test_schema_validation():
    with pytest.raises(ValueError, match="unknown kind"):
        Schema({"bogus": {}})
    with pytest.raises(ValueError, match="shape"):
        Schema({"est": {"x": (-1,)}})
    with pytest.raises(ValueError, match="not a name"):
        Schema({"est": {"x y": (1,)}})
    assert SCHEMA.only("est").kinds == {"est"}
    assert reason_of(encode(est()), schema=SCHEMA.only("ctl")) == "type"
    # a plain mapping works too
    assert decode(encode(est()), schema={"est": {"x": [4]}}) == est()


# ----------------------------------------------------------------------- strict decoding


def test_size_is_checked_before_decoding():
    data = encode(est())
    assert reason_of(data, max_bytes=len(data) - 1) == "size"
    assert decode(data, schema=SCHEMA, max_bytes=len(data)) == est()
    assert reason_of(b"\xff" * (DEFAULT_MAX_BYTES + 1)) == "size"


@pytest.mark.parametrize(
    "data",
    [
        b"",
        b"\xc1",  # never-used msgpack byte
        b"\x82",  # truncated map
        packed({"v": 1}) + b"\x00",  # trailing bytes
        packed(msgpack.ExtType(1, b"x")),
        packed({1: 2}),  # non-string map key
        packed("x" * 1000),  # string longer than allowed
        packed(list(range(100))),  # array longer than allowed
        packed({str(i): i for i in range(100)}),  # map larger than allowed
        b"\x91" * 10000,  # deep nesting
    ],
)
def test_malformed_msgpack_is_a_decode_error(data):
    assert reason_of(data) == "decode"


def test_wrong_top_level_and_version():
    assert reason_of(packed([1, 2])) == "type"
    assert reason_of(packed(42)) == "type"
    wire = to_wire(est())
    assert reason_of(packed({**wire, "v": 2})) == "version"
    assert reason_of(packed({**wire, "v": "1"})) == "version"
    assert reason_of(packed({**wire, "v": True})) == "version"
    no_v = dict(wire)
    del no_v["v"]
    assert reason_of(packed(no_v)) == "keys"


@pytest.mark.parametrize("field", ["kind", "from", "k", "arr"])
def test_missing_field(field):
    wire = to_wire(est())
    del wire[field]
    assert reason_of(packed(wire)) == "keys"


def test_unknown_field():
    assert reason_of(packed({**to_wire(est()), "extra": 1})) == "keys"
    assert reason_of(packed({**to_wire(est()), b"to": 1})) == "keys"


@pytest.mark.parametrize(
    "field, value",
    [
        ("kind", "bogus"),
        ("kind", 1),
        ("from", "3"),
        ("from", 3.0),
        ("from", True),
        ("from", 1 << 40),
        ("from", -(1 << 40)),
        ("k", -1),
        ("k", 1 << 60),
        ("k", None),
        ("to", None),
        ("to", 2.5),
        ("meta", [1]),
        ("meta", {"x": [1]}),
        ("meta", {"x": None}),
        ("arr", [1]),
        ("arr", {"x": [[4], "text"]}),
        ("arr", {"x": [[4.0], b"\x00" * 32]}),
        ("arr", {"x": [[-4], b""]}),
        ("arr", {"x": [[True], b"\x00" * 8]}),
        ("arr", {"x": {"shape": [4]}}),
        ("arr", {"x": [[4], b"\x00" * 32, 1]}),
    ],
)
def test_wrong_types(field, value):
    assert reason_of(packed({**to_wire(est()), field: value})) == "type"


def test_kind_not_in_schema_is_rejected():
    msg = Message(kind="ctl", sender=0, stamp=0, arrays={})
    assert reason_of(encode(msg), schema=SCHEMA.only("est")) == "type"


def test_wrong_array_names():
    wire = to_wire(est())
    assert reason_of(packed({**wire, "arr": {}})) == "keys"
    assert reason_of(packed({**wire, "arr": {"y": wire["arr"]["x"]}})) == "keys"
    assert reason_of(packed({**wire, "arr": {**wire["arr"], "z": wire["arr"]["x"]}})) == "keys"


@pytest.mark.parametrize("x", [np.zeros(3), np.zeros(5), np.zeros((2, 2)), np.zeros((4, 1)), np.float64(1.0)])
def test_wrong_shape(x):
    assert reason_of(encode(est(x))) == "shape"


def test_bytes_that_do_not_match_the_shape():
    wire = to_wire(est())
    wire["arr"]["x"] = [[4], b"\x00" * 31]
    assert reason_of(packed(wire)) == "shape"
    wire["arr"]["x"] = [[4], b"\x00" * 40]
    assert reason_of(packed(wire)) == "shape"


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_values_are_rejected(bad):
    wire = to_wire(est())
    wire["arr"]["x"] = [[4], struct.pack("<4d", 0.0, bad, 0.0, 0.0)]
    assert reason_of(packed(wire)) == "nonfinite"
    wire = to_wire(est())
    wire["meta"] = {"g": bad}
    assert reason_of(packed(wire)) == "nonfinite"


def test_each_array_of_a_message_is_checked_for_finite_values_after_every_shape():
    """The finite values of all arrays are checked in one pass after the shapes: a bad value
    in any array is rejected and named; a bad shape is reported before a bad value."""
    truth = Message(kind="truth", sender=PLANT_ID, stamp=2, arrays={"x": np.zeros(4), "P": np.zeros((4, 4))})
    for name, count in (("x", 4), ("P", 16)):
        for at in (0, count - 1):
            wire = to_wire(truth)
            values = [0.0] * count
            values[at] = math.nan
            wire["arr"][name] = [wire["arr"][name][0], struct.pack(f"<{count}d", *values)]
            with pytest.raises(MessageError, match=f"array '{name}' has non-finite") as info:
                decode(packed(wire), schema=SCHEMA)
            assert info.value.reason == "nonfinite"
    wire = to_wire(truth)
    wire["arr"]["x"] = [[4], struct.pack("<4d", math.inf, 0.0, 0.0, 0.0)]
    wire["arr"]["P"] = [[4, 3], b"\x00" * 96]
    assert reason_of(packed(wire)) == "shape"
    wire["arr"]["P"] = [[4, 4], b"\x00" * 128]
    assert reason_of(packed(wire)) == "nonfinite"
    wire["arr"]["x"] = [[4], b"\x00" * 32]
    assert decode(packed(wire), schema=SCHEMA) == truth


def test_sender_and_receiver_must_match_the_key():
    data = encode(est(sender=3))
    assert reason_of(data, expected_sender=4) == "sender"
    assert decode(data, schema=SCHEMA, expected_sender=3).sender == 3
    addressed = encode(est(receiver=5))
    assert reason_of(addressed, expected_receiver=6) == "sender"
    assert reason_of(data, expected_receiver=5) == "sender"  # not addressed at all
    assert decode(addressed, schema=SCHEMA, expected_receiver=5).receiver == 5


def test_decode_rejects_non_bytes():
    assert reason_of("a string") == "type"  # type: ignore[arg-type]
    assert reason_of(None) == "type"  # type: ignore[arg-type]


# -------------------------------------------------------------------- property: no escape

ALLOWED_REASONS = {"size", "decode", "keys", "type", "nonfinite", "shape", "sender", "version"}
PROP_MAX_BYTES = 4096


def check_decode_contract(data, expected_sender=None):
    """decode either returns a valid Message or raises MessageError, nothing else."""
    try:
        msg = decode(data, schema=SCHEMA, expected_sender=expected_sender, max_bytes=PROP_MAX_BYTES)
    except MessageError as exc:
        assert exc.reason in ALLOWED_REASONS, exc.reason
        return None
    assert isinstance(msg, Message)
    assert msg.kind in SCHEMA.kinds
    assert MIN_ID <= msg.sender <= MAX_ID and 0 <= msg.stamp <= MAX_STAMP
    if expected_sender is not None:
        assert msg.sender == expected_sender
    fields = SCHEMA.fields(msg.kind)
    assert set(msg.arrays) == set(fields)
    for name, a in msg.arrays.items():
        spec = fields[name]
        assert a.dtype == np.float64 and a.dtype.isnative and not a.flags.writeable
        assert len(a.shape) == len(spec) and all(e is None or e == d for d, e in zip(a.shape, spec))
        assert np.isfinite(a).all()
    for v in msg.meta.values():
        assert type(v) in (str, int, float, bool)
    return msg


finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
anything = st.floats(allow_nan=True, allow_infinity=True, width=64)


@st.composite
def valid_messages(draw) -> Message:
    kind = draw(st.sampled_from(sorted(SCHEMA.kinds)))
    arrays = {}
    for name, spec in SCHEMA.fields(kind).items():
        shape = tuple(draw(st.integers(0, 6)) if d is None else d for d in spec)
        n = int(np.prod(shape, dtype=int))
        arrays[name] = np.array(draw(st.lists(finite, min_size=n, max_size=n)), dtype=float).reshape(shape)
    meta = draw(
        st.dictionaries(
            st.from_regex(r"[a-z_][a-z0-9_]{0,5}", fullmatch=True),
            st.one_of(st.text(max_size=8), st.integers(-(2**63), 2**63 - 1), finite, st.booleans()),
            max_size=3,
        )
    )
    return Message(
        kind=kind,
        sender=draw(st.integers(MIN_ID, MAX_ID)),
        stamp=draw(st.integers(0, MAX_STAMP)),
        receiver=draw(st.none() | st.integers(MIN_ID, MAX_ID)),
        arrays=arrays,
        meta=meta,
    )


@given(valid_messages())
@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_encode_fields_writes_the_bytes_of_encode(msg):
    fields = dict(msg.arrays)
    fields = {name: (a.tolist() if i % 2 else a) for i, (name, a) in enumerate(fields.items())}  # lists too
    data = encode_fields(msg.kind, msg.sender, msg.stamp, fields, receiver=msg.receiver, meta=dict(msg.meta))
    assert data == encode(msg)


@pytest.mark.parametrize(
    "kw, reason",
    [
        ({"kind": "nope"}, "type"),
        ({"sender": True}, "type"),
        ({"sender": MAX_ID + 1}, "type"),
        ({"stamp": -1}, "type"),
        ({"stamp": MAX_STAMP + 1}, "type"),
        ({"receiver": "2"}, "type"),
        ({"meta": {"bad key": 1}}, "keys"),
        ({"meta": {"v": math.nan}}, "nonfinite"),
        ({"arrays": {"x": np.array([1.0, np.inf])}}, "nonfinite"),
        ({"arrays": {"x": "1.0"}}, "type"),
        ({"arrays": {"bad name": np.zeros(1)}}, "keys"),
        ({"arrays": {"x": np.zeros(4)}, "max_bytes": 16}, "size"),
    ],
)
def test_encode_fields_rejects_what_message_rejects(kw, reason):
    args = {"kind": "est", "sender": 1, "stamp": 3, "arrays": {"x": np.zeros(4)}, **kw}
    with pytest.raises(MessageError) as info:
        encode_fields(args.pop("kind"), args.pop("sender"), args.pop("stamp"), args.pop("arrays"), **args)
    assert info.value.reason == reason


def test_encode_fields_leaves_the_callers_array_alone():
    x = np.arange(4.0)
    encode_fields("est", 1, 3, {"x": x})
    assert x.flags.writeable

# Values of every msgpack type, to put where they do not belong.
wire_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**64), 2**64 - 1).filter(lambda i: -(2**63) <= i < 2**64)
    | anything
    | st.text(max_size=20)
    | st.binary(max_size=40),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=5), inner, max_size=4),
    max_leaves=8,
)


@given(st.binary(max_size=600))
@settings(max_examples=400, deadline=None)
def test_property_random_bytes(data):
    check_decode_contract(data)


@given(valid_messages(), st.data())
@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_property_mutated_bytes(msg, data):
    raw = encode(msg)
    assert decode(raw, schema=SCHEMA, expected_sender=msg.sender) == msg  # valid before mutation
    mutation = data.draw(st.sampled_from(["flip", "truncate", "insert", "oversize", "splice"]))
    if mutation == "flip":
        buf = bytearray(raw)
        for _ in range(data.draw(st.integers(1, 4))):
            i = data.draw(st.integers(0, len(buf) - 1))
            buf[i] ^= data.draw(st.integers(1, 255))
        mutated = bytes(buf)
    elif mutation == "truncate":
        mutated = raw[: data.draw(st.integers(0, len(raw) - 1))]
    elif mutation == "insert":
        i = data.draw(st.integers(0, len(raw)))
        mutated = raw[:i] + data.draw(st.binary(min_size=1, max_size=16)) + raw[i:]
    elif mutation == "oversize":
        mutated = raw + b"\x00" * (PROP_MAX_BYTES + 1 - len(raw))
    else:
        mutated = raw[: len(raw) // 2] + data.draw(st.binary(max_size=64))
    out = check_decode_contract(mutated, expected_sender=data.draw(st.sampled_from([None, msg.sender])))
    if mutation == "oversize":
        assert out is None


@given(valid_messages(), st.data())
@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_property_structural_mutations(msg, data):
    """Corrupt one field of a valid message's map; the reason must name the damage."""
    wire = to_wire(msg)
    fields = SCHEMA.fields(msg.kind)
    mutation = data.draw(
        st.sampled_from(["wrong_type", "nonfinite", "wrong_shape", "wrong_sender", "drop_key", "add_key"])
    )
    expected: set[str]
    if mutation == "wrong_type":
        key = data.draw(st.sampled_from(["kind", "from", "k", "to", "meta", "arr"]))
        value = data.draw(wire_values)
        wire[key] = value
        expected = set()  # may even still be valid (e.g. another stamp): the contract only
    elif mutation == "nonfinite":
        assume(any(np.prod(s, dtype=int) > 0 for s in (a.shape for a in msg.arrays.values())))
        name = data.draw(st.sampled_from([n for n, a in msg.arrays.items() if a.size > 0]))
        a = np.array(msg.arrays[name])
        a.flat[data.draw(st.integers(0, a.size - 1))] = data.draw(st.sampled_from([np.nan, np.inf, -np.inf]))
        wire["arr"][name] = [list(a.shape), a.astype("<f8").tobytes()]
        expected = {"nonfinite"}
    elif mutation == "wrong_shape":
        assume(fields)
        name = data.draw(st.sampled_from(sorted(fields)))
        spec = fields[name]
        shape = data.draw(st.lists(st.integers(0, 5), max_size=3).map(tuple))
        assume(len(shape) != len(spec) or any(e is not None and e != d for d, e in zip(shape, spec)))
        n = int(np.prod(shape, dtype=int))
        wire["arr"][name] = [list(shape), np.zeros(n).astype("<f8").tobytes()]
        expected = {"shape"}
    elif mutation == "wrong_sender":
        wire["from"] = data.draw(st.integers(MIN_ID, MAX_ID).filter(lambda s: s != msg.sender))
        expected = {"sender"}
    elif mutation == "drop_key":
        del wire[data.draw(st.sampled_from(["v", "kind", "from", "k", "arr"]))]
        expected = {"keys"}
    else:
        known = {"v", "kind", "from", "k", "to", "meta", "arr"}
        wire[data.draw(st.text(min_size=1, max_size=8).filter(lambda k: k not in known))] = 1
        expected = {"keys"}
    check_decode_contract(packed(wire), expected_sender=msg.sender)
    if expected:
        with pytest.raises(MessageError) as info:
            decode(packed(wire), schema=SCHEMA, expected_sender=msg.sender, max_bytes=PROP_MAX_BYTES)
        assert info.value.reason in expected, (mutation, info.value.reason, str(info.value))


# ------------------------------------------------------------------------------- speed


def test_encode_decode_speed_80_floats():
    """A generous bound (the measured figure is a few microseconds; see the report)."""
    schema = Schema({"est": {"x": (80,)}})
    msg = Message(kind="est", sender=1, stamp=2, arrays={"x": np.random.default_rng(1).normal(size=80)})
    n = 2000
    best = math.inf
    for _ in range(5):
        t0 = time.perf_counter()
        for _ in range(n):
            decode(encode(msg), schema=schema, expected_sender=1)
        best = min(best, (time.perf_counter() - t0) / n)
    assert best < 200e-6, f"encode+decode took {best * 1e6:.1f} us"
