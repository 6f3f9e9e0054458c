"""The wire format's constants and limits, and the checks each field of a message passes
(:mod:`transport.codec` builds and decodes the messages with them)."""

from __future__ import annotations

import math
import re
import sys
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

import numpy as np

from estimation.errors import MessageError

# ---------------------------------------------------------------------------- constants

VERSION = 1
"""Wire version written in ``v``; any other value is rejected (reason ``"version"``)."""

KINDS = frozenset({"est", "meas", "truth", "ctl", "done"})
"""Message kinds: an agent's estimate, a plant measurement, the true state (monitor
only), a control message (round start, stop, ...), an agent's end-of-round report."""

DEFAULT_MAX_BYTES = 1 << 20
"""Default cap on an encoded message (1 MiB), checked before any parsing."""

PLANT_ID = -1
MONITOR_ID = -2
LAUNCHER_ID = -3
"""Sender ids of the roles that are not agents (agents are ``0 .. MAX_ID``)."""

MIN_ID = -16  # ids -16 .. -1 are reserved for roles
MAX_ID = (1 << 16) - 1
MAX_STAMP = (1 << 53) - 1  # round stamps are 0 .. 2**53 - 1 (exact as a float64 too)
_INT64_MIN, _INT64_MAX = -(1 << 63), (1 << 63) - 1

MAX_NDIM = 4
MAX_DIM = 1 << 24
MAX_FIELDS = 32  # arrays per message
MAX_META = 16  # metadata entries per message
MAX_STR_LEN = 256  # any string on the wire (kind, names, metadata values)

_NAME_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]{0,31}\Z")

# Keys of the wire map.
_K_VERSION, _K_KIND, _K_FROM, _K_STAMP, _K_TO, _K_META, _K_ARR = (
    "v", "kind", "from", "k", "to", "meta", "arr",
)
_REQUIRED = frozenset({_K_VERSION, _K_KIND, _K_FROM, _K_STAMP, _K_ARR})
_ALLOWED = _REQUIRED | {_K_TO, _K_META}

_LITTLE = sys.byteorder == "little"
_isfinite = np.isfinite
_count_nonzero = np.count_nonzero
_F8 = np.dtype("<f8")

# Limits handed to the msgpack unpacker (the byte cap is per call).
_MAX_ARRAY_LEN = 2 * MAX_NDIM  # the longest msgpack array is a shape (or a [shape, data] pair)
_MAX_MAP_LEN = max(MAX_FIELDS, MAX_META, len(_ALLOWED))

ShapeSpec = tuple[int | None, ...]
"""An expected shape: ints are exact, ``None`` accepts any length along that axis."""

MetaValue = str | int | float | bool

_EMPTY: Mapping[str, Any] = MappingProxyType({})


def _fail(reason: str, message: str) -> MessageError:
    return MessageError(message, reason=reason)


def _is_int(x: object) -> bool:
    # bool is a subclass of int; a bool is never a valid id, stamp or dimension.
    return type(x) is int




def _check_id(value: object, what: str) -> int:
    if not _is_int(value) or not MIN_ID <= value <= MAX_ID:  # type: ignore[operator]
        raise _fail("type", f"{what} must be an int in [{MIN_ID}, {MAX_ID}], got {value!r:.40}")
    return value  # type: ignore[return-value]


def _check_stamp(value: object) -> int:
    if not _is_int(value) or not 0 <= value <= MAX_STAMP:  # type: ignore[operator]
        raise _fail("type", f"stamp must be an int in [0, 2**53 - 1], got {value!r:.40}")
    return value  # type: ignore[return-value]


def _check_kind(value: object) -> str:
    if type(value) is not str or value not in KINDS:
        raise _fail("type", f"kind must be one of {sorted(KINDS)}, got {value!r:.40}")
    return value


def _check_meta(meta: object) -> Mapping[str, MetaValue]:
    if not isinstance(meta, dict) or type(meta) is not dict:
        raise _fail("type", f"meta must be a map, got {type(meta).__name__}")
    if len(meta) > MAX_META:
        raise _fail("keys", f"meta has {len(meta)} entries, at most {MAX_META}")
    for key, value in meta.items():
        if type(key) is not str or not _NAME_RE.match(key):
            raise _fail("keys", f"meta key {key!r:.40} is not a name")
        tv = type(value)
        if tv is float:
            if not math.isfinite(value):
                raise _fail("nonfinite", f"meta[{key!r}] is not finite")
        elif tv is int:
            if not _INT64_MIN <= value <= _INT64_MAX:
                raise _fail("type", f"meta[{key!r}] is out of the int64 range")
        elif tv is str:
            if len(value) > MAX_STR_LEN:
                raise _fail("type", f"meta[{key!r}] is longer than {MAX_STR_LEN} characters")
        elif tv is not bool:
            raise _fail("type", f"meta[{key!r}] must be str, int, float or bool, got {tv.__name__}")
    return meta


def _all_finite(a: np.ndarray) -> bool:
    # Exact, never warns (a sum or a dot product would warn on inf / overflow), and
    # about twice as fast as ``np.isfinite(a).all()`` on small arrays.
    return _count_nonzero(_isfinite(a)) == a.size


def _freeze_array(name: object, value: object, *, copy: bool = True) -> np.ndarray:
    """``value`` as a checked float64 array: a read-only C-contiguous copy, or with
    ``copy=False`` the value itself when it already is a float64 array (never made
    read-only then: it is the caller's; for encoding it at once)."""
    if type(name) is not str or not _NAME_RE.match(name):
        raise _fail("keys", f"array name {name!r:.40} is not a name")
    if isinstance(value, (str, bytes)):
        raise _fail("type", f"array {name!r} is a string, not numbers")
    try:
        a = np.array(value, dtype=np.float64, copy=True, order="C") if copy else np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as exc:
        raise _fail("type", f"array {name!r} is not convertible to float64: {exc}") from exc
    if a.ndim > MAX_NDIM or (a.ndim and max(a.shape) > MAX_DIM):
        raise _fail("shape", f"array {name!r} has shape {a.shape}, beyond the wire limits")
    if not _all_finite(a):
        raise _fail("nonfinite", f"array {name!r} has non-finite values")
    if copy:
        a.setflags(write=False)
    return a
