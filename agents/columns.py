"""Arrow columns from numpy arrays, built from their buffers.

``pyarrow.array`` (and ``pyarrow.table`` of numpy arrays) imports pandas on its first call,
to check whether its argument is a pandas object: about 45 MB in a process that never uses
pandas. The monitor writes every record through these functions instead, so that its
process stays lean (`rse bench run` prints its peak RSS). The values are the same as
``pyarrow.array``'s (``tests/agents/test_columns.py``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pyarrow as pa


def _validity(mask: np.ndarray | None) -> tuple[pa.Buffer | None, int]:
    """The validity bitmap of ``mask`` (True: null) and the null count."""
    if mask is None or not mask.any():
        return None, 0
    return pa.py_buffer(np.packbits(~mask, bitorder="little")), int(mask.sum())


def column(values: np.ndarray, *, mask: np.ndarray | None = None) -> pa.Array:
    """A numeric or boolean numpy array as an Arrow array (``mask``: True where null)."""
    x = np.ascontiguousarray(values).reshape(-1)
    valid, nulls = _validity(None if mask is None else np.asarray(mask, dtype=bool).reshape(-1))
    if x.dtype == np.bool_:
        return pa.Array.from_buffers(pa.bool_(), len(x), [valid, pa.py_buffer(np.packbits(x, bitorder="little"))], nulls)
    if x.dtype.kind not in "iuf":
        raise TypeError(f"no Arrow column for numpy dtype {x.dtype}")
    typ = pa.from_numpy_dtype(x.dtype)
    return pa.Array.from_buffers(typ, len(x), [valid, pa.py_buffer(x)], nulls)


def strings(values: Sequence[str] | np.ndarray) -> pa.Array:
    """A sequence of Python strings as an Arrow ``string`` array."""
    data = [str(v).encode() for v in values]
    offsets = np.zeros(len(data) + 1, dtype=np.int32)
    np.cumsum([len(b) for b in data], out=offsets[1:])
    return pa.Array.from_buffers(pa.string(), len(data), [None, pa.py_buffer(offsets), pa.py_buffer(b"".join(data))])


def repeated_strings(names: Sequence[str], index: np.ndarray) -> pa.Array:
    """``names[index]`` for every entry of ``index``, as a ``string`` array (taken from the
    dictionary of the distinct names, not encoded once per row)."""
    return strings(names).take(column(np.asarray(index, dtype=np.int32)))


def table(columns: dict[str, np.ndarray | pa.Array]) -> pa.Table:
    """``pyarrow.table(columns)`` with the numpy arrays built by :func:`column`."""
    arrays = [c if isinstance(c, pa.Array) else column(c) for c in columns.values()]
    return pa.Table.from_arrays(arrays, names=list(columns))


def to_numpy(a: pa.Array) -> np.ndarray:
    """A numeric Arrow array as numpy, read from its buffer (the way back of :func:`column`):
    pyarrow's own ``to_numpy`` imports pandas, seconds of a restarted monitor's start on a
    busy machine. An array with nulls, or not numeric, goes through pyarrow."""
    if a.null_count or not (pa.types.is_integer(a.type) or pa.types.is_floating(a.type)):
        return a.to_numpy(zero_copy_only=False)
    dt = np.dtype(f"{'f' if pa.types.is_floating(a.type) else 'i' if pa.types.is_signed_integer(a.type) else 'u'}"
                  f"{a.type.bit_width // 8}")
    if len(a) == 0:
        return np.empty(0, dtype=dt)
    return np.frombuffer(a.buffers()[1], dtype=dt, count=len(a), offset=a.offset * dt.itemsize)
