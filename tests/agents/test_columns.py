"""Arrow columns built from numpy buffers (agents.columns) equal pyarrow.array's, and a
process that builds and writes them never imports pandas."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pyarrow as pa
import pytest

from agents.columns import column, repeated_strings, strings, table


@pytest.mark.parametrize("dtype", [np.int32, np.int64, np.uint8, np.float32, np.float64])
def test_numeric_columns_equal_pyarrow_array(dtype):
    x = (np.arange(12).reshape(3, 4) * 7 - 5).astype(dtype)[:, ::2]  # not contiguous, 2-D
    got = column(x)
    assert got.type == pa.from_numpy_dtype(np.dtype(dtype))
    assert got.equals(pa.array(x.reshape(-1)))


def test_bools_nulls_and_strings_equal_pyarrow_array():
    b = np.array([True, False, True, True, False, False, True, False, True])
    assert column(b).equals(pa.array(b))
    f = np.array([1.0, np.nan, 0.0, np.nan, 1.0])
    got = column(f == 1.0, mask=np.isnan(f))
    assert got.null_count == 2 and got.to_pylist() == [True, None, False, None, True]
    names = ["x1", "", "é", "block 3"]
    assert strings(names).equals(pa.array(names))
    idx = np.array([3, 0, 0, 2, 1])
    assert repeated_strings(names, idx).equals(pa.array([names[i] for i in idx]))
    t = table({"k": np.arange(3), "s": strings(["a", "b", "c"])})
    assert t.column_names == ["k", "s"] and t.column("k").to_pylist() == [0, 1, 2]


def test_object_arrays_are_refused():
    with pytest.raises(TypeError, match="dtype object"):
        column(np.array(["a"], dtype=object))


def test_a_process_that_writes_columns_does_not_import_pandas(tmp_path):
    code = (
        "import sys, numpy as np, pyarrow.parquet as pq\n"
        "from agents.columns import column, strings, table\n"
        f"pq.write_table(table({{'k': np.arange(4), 'ok': column(np.arange(4) > 1), 's': strings('abcd')}}), {str(tmp_path / 'x.parquet')!r})\n"
        "print('pandas' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"
