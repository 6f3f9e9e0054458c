"""The message codec: what goes over the wire, and strict decoding of untrusted bytes.

A message is a msgpack map (never ``msgpack-numpy``, which unpickles)::

    {"v": 1,                      # wire version, :data:`VERSION`
     "kind": "est",               # one of :data:`KINDS`
     "from": 3,                   # sender id (agents 0.., roles negative, see PLANT_ID)
     "k": 17,                     # round stamp
     "to": 5,                     # optional: receiver id of an addressed message
     "meta": {"cmd": "stop"},     # optional: small scalars (str / int / float / bool)
     "arr": {"x": [[4], b"..."]}} # named float64 arrays: [shape, little-endian bytes]

Decoding is strict because the bytes come from the network (a Byzantine agent or an
outside process may send anything). :func:`decode` checks, in this order, and raises
:class:`~estimation.errors.MessageError` with the ``reason`` tag in brackets:

1. the size, before anything is parsed (``size``);
2. msgpack with tight limits: no ext types, bounded strings / arrays / maps, UTF-8
   strings, string map keys only, no trailing bytes (``decode``);
3. a map with ``v`` equal to :data:`VERSION` (``type``, ``keys``, ``version``);
4. exactly the known keys (``keys``), each with its type and integer range (``type``);
5. the sender (and receiver) that the key expression implies, when given (``sender``);
6. the array names the schema lists for this kind (``keys``), their shapes (``shape``)
   and finite values (``nonfinite``).

A decoded :class:`Message`'s arrays are read-only views of the immutable bytes msgpack copies
out of the input (never views into the caller's buffer, never writeable again). A
:class:`Message` built locally is validated the same way when it is constructed, so
:func:`encode` never puts an invalid message on the wire.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import msgpack
import numpy as np

__all__ = [
    "VERSION", "KINDS", "DEFAULT_MAX_BYTES", "PLANT_ID", "MONITOR_ID", "LAUNCHER_ID", "MIN_ID", "MAX_ID", "MAX_STAMP",
    "Message", "Schema", "encode", "encode_fields", "decode", "to_wire",
]

from .wire import (
    _ALLOWED,
    _EMPTY,
    _F8,
    _K_ARR,
    _K_FROM,
    _K_KIND,
    _K_META,
    _K_STAMP,
    _K_TO,
    _K_VERSION,
    _LITTLE,
    _MAX_ARRAY_LEN,
    _MAX_MAP_LEN,
    _NAME_RE,
    _REQUIRED,
    DEFAULT_MAX_BYTES,
    KINDS,
    LAUNCHER_ID,
    MAX_DIM,
    MAX_FIELDS,
    MAX_ID,
    MAX_NDIM,
    MAX_STAMP,
    MAX_STR_LEN,
    MIN_ID,
    MONITOR_ID,
    PLANT_ID,
    VERSION,
    MetaValue,
    ShapeSpec,
    _all_finite,
    _check_id,
    _check_kind,
    _check_meta,
    _check_stamp,
    _fail,
    _freeze_array,
    _is_int,
)


# ------------------------------------------------------------------------------ message
@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class Message:
    """One message on the wire (all fields keyword-only, validated on construction).

    Parameters
    ----------
    kind : str
        One of :data:`KINDS`.
    sender : int
        Agent id ``0 .. MAX_ID``, or a role id (:data:`PLANT_ID`, :data:`MONITOR_ID`,
        :data:`LAUNCHER_ID`).
    stamp : int
        The round ``k`` the content belongs to, ``0 .. 2**53 - 1``.
    arrays : mapping of name -> float array
        Copied to C-contiguous float64, finite, read-only; stored in a read-only mapping.
    receiver : int, optional
        The addressed receiver (``rse/{run}/agent/{i}/est/{j}`` carries ``j``).
    meta : mapping of name -> str | int | float | bool, optional
        Small scalar metadata (at most :data:`MAX_META` entries), e.g. a control command.
        Always a read-only mapping after construction (empty when not given).
    version : int
        Wire version; only :data:`VERSION` exists.
    """

    kind: str
    sender: int
    stamp: int
    arrays: Mapping[str, np.ndarray]
    receiver: int | None = None
    meta: Mapping[str, MetaValue] = field(default_factory=dict)  # None is taken as empty
    version: int = VERSION

    def __post_init__(self) -> None:
        if self.version != VERSION or not _is_int(self.version):
            raise _fail("version", f"version must be {VERSION}, got {self.version!r}")
        _check_kind(self.kind)
        _check_id(self.sender, "sender")
        _check_stamp(self.stamp)
        if self.receiver is not None:
            _check_id(self.receiver, "receiver")
        if type(self.arrays) is not dict and not isinstance(self.arrays, Mapping):
            raise _fail("type", f"arrays must be a mapping, got {type(self.arrays).__name__}")
        if len(self.arrays) > MAX_FIELDS:
            raise _fail("keys", f"{len(self.arrays)} arrays, at most {MAX_FIELDS}")
        arrays = {name: _freeze_array(name, value) for name, value in self.arrays.items()}
        if self.meta is None:  # an untyped caller's None
            meta: Mapping[str, MetaValue] = _EMPTY
        elif isinstance(self.meta, Mapping):
            meta = MappingProxyType(dict(_check_meta(dict(self.meta))))
        else:
            raise _fail("type", f"meta must be a mapping, got {type(self.meta).__name__}")
        object.__setattr__(self, "arrays", MappingProxyType(arrays))
        object.__setattr__(self, "meta", meta)

    @classmethod
    def _trusted(
        cls,
        kind: str,
        sender: int,
        stamp: int,
        arrays: dict[str, np.ndarray],
        receiver: int | None,
        meta: dict[str, MetaValue],
    ) -> "Message":
        # Used by decode(), which has already validated every field: skip the checks.
        self = _new(cls)
        _set_kind(self, kind)
        _set_sender(self, sender)
        _set_stamp(self, stamp)
        _set_arrays(self, MappingProxyType(arrays))
        _set_receiver(self, receiver)
        _set_meta(self, MappingProxyType(meta) if meta else _EMPTY)
        _set_version(self, VERSION)
        return self

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Message):
            return NotImplemented
        return (
            (self.version, self.kind, self.sender, self.stamp, self.receiver)
            == (other.version, other.kind, other.sender, other.stamp, other.receiver)
            and dict(self.meta or {}) == dict(other.meta or {})
            and self.arrays.keys() == other.arrays.keys()
            and all(
                self.arrays[n].shape == other.arrays[n].shape
                and np.array_equal(self.arrays[n], other.arrays[n])
                for n in self.arrays
            )
        )

    __hash__ = None  # type: ignore[assignment]


# The slot descriptors of the frozen dataclass: setting through them bypasses the frozen
# __setattr__ (for Message._trusted only).
_new = object.__new__
_set_kind = Message.__dict__["kind"].__set__
_set_sender = Message.__dict__["sender"].__set__
_set_stamp = Message.__dict__["stamp"].__set__
_set_arrays = Message.__dict__["arrays"].__set__
_set_receiver = Message.__dict__["receiver"].__set__
_set_meta = Message.__dict__["meta"].__set__
_set_version = Message.__dict__["version"].__set__


# ------------------------------------------------------------------------------- schema


class Schema:
    """The expected array names and shapes per message kind.

    Built once per scenario (and per key family, e.g. a schema that accepts only ``est``
    on estimate keys) and handed to :func:`decode`::

        schema = Schema({"est": {"x": (4,)}, "ctl": {}})
        schema = Schema({"meas": {"y": (None,)}})   # None: any length on that axis

    A kind that is not listed is rejected (reason ``"type"``); a message must carry
    exactly the listed arrays (reason ``"keys"``) with matching shapes (``"shape"``).
    """

    __slots__ = ("_kinds",)

    def __init__(self, kinds: Mapping[str, Mapping[str, Sequence[int | None]]]) -> None:
        if isinstance(kinds, Schema):
            self._kinds: dict[str, dict[str, ShapeSpec]] = kinds._kinds
            return
        if not isinstance(kinds, Mapping):
            raise TypeError(f"Schema expects a mapping kind -> {{name: shape}}, got {type(kinds).__name__}")
        built: dict[str, dict[str, ShapeSpec]] = {}
        for kind, fields in kinds.items():
            if kind not in KINDS:
                raise ValueError(f"Schema: unknown kind {kind!r}; valid kinds are {sorted(KINDS)}")
            if not isinstance(fields, Mapping):
                raise ValueError(f"Schema[{kind!r}] must map array names to shapes, got {fields!r}")
            if len(fields) > MAX_FIELDS:
                raise ValueError(f"Schema[{kind!r}] lists {len(fields)} arrays, at most {MAX_FIELDS}")
            built[kind] = {}
            for name, shape in fields.items():
                if type(name) is not str or not _NAME_RE.match(name):
                    raise ValueError(f"Schema[{kind!r}]: array name {name!r} is not a name")
                spec = tuple(shape) if not isinstance(shape, (str, bytes)) else None
                if spec is None or len(spec) > MAX_NDIM or not all(
                    d is None or (_is_int(d) and 0 <= d <= MAX_DIM) for d in spec
                ):
                    raise ValueError(
                        f"Schema[{kind!r}][{name!r}] must be a shape of at most {MAX_NDIM} "
                        f"ints in [0, {MAX_DIM}] or None, got {shape!r}"
                    )
                built[kind][name] = spec
        self._kinds = built

    def __contains__(self, kind: object) -> bool:
        return kind in self._kinds

    def __repr__(self) -> str:
        return f"Schema({self._kinds!r})"

    @property
    def kinds(self) -> frozenset[str]:
        """The kinds this schema accepts."""
        return frozenset(self._kinds)

    def fields(self, kind: str) -> Mapping[str, ShapeSpec]:
        """The expected ``{name: shape}`` of ``kind`` (KeyError if not accepted)."""
        return MappingProxyType(self._kinds[kind])

    def only(self, *kinds: str) -> "Schema":
        """A schema accepting only ``kinds`` (each must be in this one)."""
        missing = [k for k in kinds if k not in self._kinds]
        if missing:
            raise ValueError(f"Schema.only: kinds {missing} are not in {sorted(self._kinds)}")
        return Schema({k: self._kinds[k] for k in kinds})

    def check(self, msg: Message) -> None:
        """Raise :class:`MessageError` unless ``msg`` matches this schema."""
        fields = self._kinds.get(msg.kind)
        if fields is None:
            raise _fail("type", f"kind {msg.kind!r} is not accepted here (expected {sorted(self._kinds)})")
        if msg.arrays.keys() != fields.keys():
            raise _fail("keys", f"{msg.kind!r} arrays {sorted(msg.arrays)} != expected {sorted(fields)}")
        for name, spec in fields.items():
            _check_shape(name, msg.arrays[name].shape, spec)


_ANY1 = (None,)  # the shape spec of any 1-D array


def _as_schema(schema: Schema | Mapping[str, Mapping[str, Sequence[int | None]]]) -> Schema:
    return schema if isinstance(schema, Schema) else Schema(schema)


def _check_shape(name: str, shape: tuple[int, ...], spec: ShapeSpec) -> None:
    if shape == spec or (len(shape) == len(spec) and (spec == _ANY1 or all(e is None or e == d for d, e in zip(shape, spec)))):
        return
    expected = "(" + ", ".join("*" if e is None else str(e) for e in spec) + ("," if len(spec) == 1 else "") + ")"
    raise _fail("shape", f"array {name!r} has shape {shape}, expected {expected}")


# ------------------------------------------------------------------------------- encode


def to_wire(msg: Message) -> dict[str, Any]:
    """The plain msgpack map of ``msg`` (what :func:`encode` packs).

    Public so that tests and fault injectors can corrupt a valid message field by field.
    """
    return _wire(msg.version, msg.kind, msg.sender, msg.stamp, msg.arrays, msg.receiver, msg.meta)


def _wire(version: int, kind: str, sender: int, stamp: int, arrays: Mapping[str, np.ndarray], receiver: int | None,
          meta: Mapping[str, MetaValue] | None) -> dict[str, Any]:
    """The msgpack map of checked fields (:func:`to_wire`, :func:`encode_fields`)."""
    arr = {name: [list(a.shape), a.tobytes() if _LITTLE else a.astype(_F8).tobytes()] for name, a in arrays.items()}
    wire: dict[str, Any] = {_K_VERSION: version, _K_KIND: kind, _K_FROM: sender, _K_STAMP: stamp, _K_ARR: arr}
    if receiver is not None:
        wire[_K_TO] = receiver
    if meta:
        wire[_K_META] = dict(meta)
    return wire


def _packed(wire: dict[str, Any], max_bytes: int) -> bytes:
    data = msgpack.packb(wire, use_bin_type=True)
    if len(data) > max_bytes:
        raise _fail("size", f"encoded message is {len(data)} bytes, more than max_bytes={max_bytes}")
    return data


def encode(
    msg: Message,
    *,
    schema: Schema | Mapping[str, Mapping[str, Sequence[int | None]]] | None = None,
    max_bytes: int = DEFAULT_MAX_BYTES,
) -> bytes:
    """Encode ``msg`` to bytes.

    Raises :class:`MessageError` if the message does not match ``schema`` (when given),
    if an array was made non-finite after construction (``"nonfinite"``), or if the
    encoding is larger than ``max_bytes`` (``"size"``): a sender fails loudly rather than
    have every receiver drop its messages.
    """
    if not isinstance(msg, Message):
        raise TypeError(f"encode expects a Message, got {type(msg).__name__}")
    if schema is not None:
        _as_schema(schema).check(msg)
    for name, a in msg.arrays.items():
        # Read-only arrays that own their data can be made writeable again; re-check.
        if not _all_finite(a):
            raise _fail("nonfinite", f"array {name!r} has non-finite values")
    return _packed(to_wire(msg), max_bytes)


def encode_fields(
    kind: str,
    sender: int,
    stamp: int,
    arrays: Mapping[str, Any],
    *,
    receiver: int | None = None,
    meta: Mapping[str, MetaValue] | None = None,
    max_bytes: int = DEFAULT_MAX_BYTES,
) -> bytes:
    """``encode(Message(kind=..., ...))`` without building the :class:`Message`: the same
    checks (each array converted and checked once, not copied when it already is float64)
    and the same bytes. For a sender's hot path (every message of a round)."""
    _check_kind(kind)
    _check_id(sender, "sender")
    _check_stamp(stamp)
    if receiver is not None:
        _check_id(receiver, "receiver")
    if type(arrays) is not dict and not isinstance(arrays, Mapping):
        raise _fail("type", f"arrays must be a mapping, got {type(arrays).__name__}")
    if len(arrays) > MAX_FIELDS:
        raise _fail("keys", f"{len(arrays)} arrays, at most {MAX_FIELDS}")
    checked = {name: _freeze_array(name, value, copy=False) for name, value in arrays.items()}
    if meta is not None and not isinstance(meta, Mapping):
        raise _fail("type", f"meta must be a mapping, got {type(meta).__name__}")
    return _packed(_wire(VERSION, kind, sender, stamp, checked, receiver, _check_meta(dict(meta)) if meta else None), max_bytes)


# ------------------------------------------------------------------------------- decode


def decode(
    data: bytes | bytearray | memoryview,
    *,
    schema: Schema | Mapping[str, Mapping[str, Sequence[int | None]]],
    expected_sender: int | None = None,
    expected_receiver: int | None = None,
    max_bytes: int = DEFAULT_MAX_BYTES,
) -> Message:
    """Decode untrusted bytes into a :class:`Message`, or raise :class:`MessageError`.

    Parameters
    ----------
    data : bytes-like
        The payload as received.
    schema : Schema or mapping kind -> {name: shape}
        The kinds accepted here and their array shapes (pass a prebuilt :class:`Schema`
        in hot paths; a mapping is converted on every call).
    expected_sender : int, optional
        The sender the key expression implies (``ParsedKey.sender``); a message whose
        ``from`` differs is rejected with reason ``"sender"``.
    expected_receiver : int, optional
        The receiver an addressed key implies (``ParsedKey.receiver``); a message whose
        ``to`` differs (or is missing) is rejected with reason ``"sender"``.
    max_bytes : int
        Size cap, checked before anything is parsed (reason ``"size"``).

    Every failure is a :class:`MessageError` whose ``reason`` is one of ``"size"``,
    ``"decode"``, ``"type"``, ``"keys"``, ``"version"``, ``"sender"``, ``"shape"``,
    ``"nonfinite"``; nothing else escapes for any input bytes.
    """
    schema = _as_schema(schema)
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise _fail("type", f"payload must be bytes, got {type(data).__name__}")
    size = data.nbytes if isinstance(data, memoryview) else len(data)
    if size > max_bytes:
        raise _fail("size", f"payload is {size} bytes, more than max_bytes={max_bytes}")
    try:
        obj = msgpack.unpackb(
            data,
            raw=False,
            strict_map_key=True,
            use_list=True,
            max_bin_len=max_bytes,
            max_str_len=MAX_STR_LEN,
            max_array_len=_MAX_ARRAY_LEN,
            max_map_len=_MAX_MAP_LEN,
            max_ext_len=0,
        )
    except Exception as exc:  # any failure to parse untrusted bytes is a decode error
        raise _fail("decode", f"not a valid msgpack message: {type(exc).__name__}: {exc}"[:200]) from exc

    if type(obj) is not dict:
        raise _fail("type", f"message must be a map, got {type(obj).__name__}")
    if _K_VERSION not in obj:
        raise _fail("keys", "message has no version field 'v'")
    version = obj[_K_VERSION]
    if not _is_int(version) or version != VERSION:
        raise _fail("version", f"unsupported version {version!r:.40} (this codec reads {VERSION})")
    keys = obj.keys()
    if not (keys >= _REQUIRED and keys <= _ALLOWED):
        raise _fail(
            "keys",
            f"message keys {sorted(map(repr, keys))} (required {sorted(_REQUIRED)}, allowed {sorted(_ALLOWED)})"[:300],
        )

    kind = _check_kind(obj[_K_KIND])
    fields = schema._kinds.get(kind)
    if fields is None:
        raise _fail("type", f"kind {kind!r} is not accepted here (expected {sorted(schema._kinds)})")
    sender = _check_id(obj[_K_FROM], "sender")
    if expected_sender is not None and sender != expected_sender:
        raise _fail("sender", f"message claims sender {sender}, its key says {expected_sender}")
    stamp = _check_stamp(obj[_K_STAMP])
    receiver = obj.get(_K_TO)
    if receiver is not None:
        _check_id(receiver, "receiver")
    elif _K_TO in obj:
        raise _fail("type", "receiver must be an int, got None")
    if expected_receiver is not None and receiver != expected_receiver:
        raise _fail("sender", f"message is addressed to {receiver}, its key says {expected_receiver}")
    meta = _check_meta(obj[_K_META]) if _K_META in obj else None

    arr = obj[_K_ARR]
    if type(arr) is not dict:
        raise _fail("type", f"'arr' must be a map, got {type(arr).__name__}")
    if arr.keys() != fields.keys():
        raise _fail("keys", f"{kind!r} arrays {sorted(map(repr, arr))} != expected {sorted(fields)}"[:300])
    arrays: dict[str, np.ndarray] = {}
    raws: list[bytes] = []
    for name, spec in fields.items():
        arrays[name] = _decode_array(name, arr[name], spec, raws)
    # finite values last, after every shape: all arrays' bytes in one check (a bad one named after)
    if raws and not _all_finite(np.frombuffer(raws[0] if len(raws) == 1 else b"".join(raws), dtype=_F8)):
        bad = next(n for n, a in arrays.items() if not _all_finite(a))
        raise _fail("nonfinite", f"array {bad!r} has non-finite values")
    return Message._trusted(kind, sender, stamp, arrays, receiver, dict(meta) if meta else {})


def _decode_array(name: str, entry: object, spec: ShapeSpec, raws: list[bytes]) -> np.ndarray:
    # a read-only view of its bytes, shape checked; the bytes go to ``raws`` (finiteness: decode)
    if type(entry) is not list or len(entry) != 2:
        raise _fail("type", f"array {name!r} must be [shape, bytes]")
    shape_list, raw = entry
    if type(shape_list) is not list or type(raw) is not bytes:
        raise _fail("type", f"array {name!r} must be [list of ints, bytes]")
    count = 1
    for d in shape_list:
        if type(d) is not int or not 0 <= d <= MAX_DIM:  # _is_int, inlined (hot)
            raise _fail("type", f"array {name!r} has an invalid dimension {d!r:.40}")
        count *= d
    shape = tuple(shape_list)
    if shape != spec:
        _check_shape(name, shape, spec)
    if len(raw) != 8 * count:
        raise _fail("shape", f"array {name!r} has {len(raw)} bytes, shape {shape} needs {8 * count}")
    # A view of the immutable bytes, not a copy (native float64 on a little-endian host):
    # read-only, as a view of bytes always is (a vector needs no reshape).
    a = np.frombuffer(raw, dtype=_F8)
    if len(shape) != 1:
        a = a.reshape(shape)
    if not _LITTLE:
        a = a.astype(np.float64)
        a.setflags(write=False)
    if count:
        raws.append(raw)
    return a
