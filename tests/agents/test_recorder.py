"""Crash-safe recording (agents.recorder): the metrics stream a run writes as it goes, what
a killed writer leaves (readable up to its last complete batch), the run directory of a run
that ended early (complete: false, the reason, the last round) and rse report on both."""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pyarrow.parquet as pq
import pytest

from agents import api
from agents.monitor import Monitor
from agents.recorder import PARTIAL, load_into, read_partial
from tests.conftest import ROOT, SCENARIOS, rse

LKS = str(SCENARIOS / "lee_kim_shim.toml")


@pytest.fixture(scope="module")
def exp():
    return api.load(LKS, set={"run.duration": 10.0, "expect": []})


def test_a_complete_run_writes_the_final_files_and_drops_the_stream(exp, tmp_path):
    res = api.simulate(exp, out=tmp_path / "run")
    d = tmp_path / "run"
    assert not (d / PARTIAL).exists()
    s = json.loads((d / "summary.json").read_text())
    assert s["complete"] is True and s["last_round"] == exp.n_rounds and "reason" not in s
    t = pq.read_table(d / "metrics.parquet")
    assert t.num_rows == (exp.n_rounds + 1) * exp.N * len(exp.blocks)
    assert np.array_equal(t.column("error_2").to_numpy(), res.metrics()["error_2"].to_numpy(), equal_nan=True)


def test_a_run_ended_early_leaves_its_rounds_and_says_so(exp, tmp_path):
    full = api.simulate(exp).metrics()

    def progress(k, worst):
        if k >= 512:
            raise KeyboardInterrupt("SIGTERM")

    with pytest.raises(KeyboardInterrupt):
        api.simulate(exp, out=tmp_path / "run", progress=progress)
    d = tmp_path / "run"
    s = json.loads((d / "summary.json").read_text())
    assert s["complete"] is False and s["reason"] == "interrupted (SIGTERM)"
    assert s["last_round"] == 512  # recorded before the progress callback of round 512 ran
    t = pq.read_table(d / "metrics.parquet").to_pandas()
    assert t["k"].max() == 512 and len(t) == 513 * exp.N * len(exp.blocks)
    want = full[full["k"] <= 512]
    assert np.array_equal(t["error_2"].to_numpy(), want["error_2"].to_numpy(), equal_nan=True)
    assert not (d / PARTIAL).exists()
    p = rse("report", str(d))
    assert p.returncode == 0, p.stderr
    assert "INCOMPLETE: interrupted (SIGTERM), last round recorded 512" in p.stdout.replace("\n", "")


@pytest.mark.parametrize("where", ["design", "stream"])
def test_a_run_ended_while_its_directory_is_begun_says_so_and_leaves_no_stream(exp, tmp_path, monkeypatch, where):
    """A signal after manifest.json, while design.json or the stream's first segment is being
    written (the recorder not up yet): summary.json says so and no partial stream is left
    (seen once in a fresh CI run of `rse simulate` interrupted by SIGTERM at that moment)."""
    import agents.recorder
    import agents.rundir

    def interrupted(*args, **kw):
        (tmp_path / "run" / PARTIAL).mkdir(exist_ok=True)  # what the stream had begun
        raise KeyboardInterrupt("SIGTERM")

    if where == "design":
        monkeypatch.setattr(agents.rundir, "write_design", interrupted)
    else:
        monkeypatch.setattr(agents.recorder.MetricsStream, "__init__", interrupted)
    with pytest.raises(KeyboardInterrupt):
        api.simulate(exp, out=tmp_path / "run")
    d = tmp_path / "run"
    assert (d / "manifest.json").exists()
    s = json.loads((d / "summary.json").read_text())
    assert s["complete"] is False and s["reason"] == "interrupted (SIGTERM)" and s["last_round"] == -1
    assert not (d / PARTIAL).exists()


def test_the_reader_stops_at_a_torn_last_batch(exp, tmp_path):
    """A writer killed in the middle of a batch: every complete batch is read."""
    mon = Monitor(exp)
    from agents.recorder import MetricsStream, regular_mask

    stream = MetricsStream(tmp_path, exp, regular_mask(exp))
    x = np.ones(exp.n)
    sizes = []
    for start in (0, 10, 20):
        for k in range(start, start + 10):
            mon.record(k, x, np.zeros((exp.N, exp.n)))
        mon.flush()
        stream.write(mon, np.arange(start, start + 10))
        sizes.append(stream.path.stat().st_size)
    stream.close()
    data = stream.path.read_bytes()
    for cut, rounds in ((sizes[1] + 7, 20), (sizes[2] - 1, 20), (sizes[0] - 3, 0), (5, None)):
        stream.path.write_bytes(data[:cut])
        t = read_partial(tmp_path)
        got = 0 if t is None or t.num_rows == 0 else int(t.column("k").to_numpy().max()) + 1
        assert got == (rounds or 0), cut
    # a restarted monitor resumes from it
    stream.path.write_bytes(data)
    mon2 = Monitor(exp)
    load_into(mon2, read_partial(tmp_path))
    assert mon2.last_round == 29
    assert np.array_equal(mon2.error_2[:30], mon.error_2[:30])


CHILD = """
import sys, time
from agents import api
exp = api.load({scenario!r}, set={{"run.duration": 5000.0, "expect": []}})
def progress(k, worst):
    print(k, time.monotonic(), flush=True)
api.simulate(exp, out={out!r}, progress=progress)
"""


@pytest.mark.multiprocess
def test_a_killed_writer_leaves_every_round_up_to_a_second_before_the_kill(tmp_path):
    d = tmp_path / "run"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    p = subprocess.Popen([sys.executable, "-c", CHILD.format(scenario=LKS, out=str(d))], cwd=ROOT, env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    seen: list[tuple[int, float]] = []
    try:
        end = time.monotonic() + 180
        while time.monotonic() < end:
            line = p.stdout.readline()
            if not line:
                break
            k, _ = line.split()
            seen.append((int(k), time.monotonic()))
            if seen[-1][0] >= 6000 and seen[-1][1] - seen[0][1] > 3.0:
                break
        assert seen and seen[-1][0] >= 6000, p.stderr.read() if p.poll() is not None else "too slow"
        t_kill = time.monotonic()
        p.send_signal(signal.SIGKILL)
        p.wait(timeout=30)
    finally:
        if p.poll() is None:
            p.kill()
    assert not (d / "summary.json").exists() and not (d / "metrics.parquet").exists()
    t = read_partial(d)
    ks = np.unique(t.column("k").to_numpy())
    # every round the child had recorded 1.5 s before the kill (1 s flush interval + 0.5 s
    # margin for a loaded machine) is in the stream, with no gap
    due = max(k for k, t_seen in seen if t_seen <= t_kill - 1.5)
    assert ks[-1] >= due and np.array_equal(ks, np.arange(ks[-1] + 1))
    out = rse("report", str(d))
    assert out.returncode == 0, out.stderr
    assert "INCOMPLETE: no summary.json" in out.stdout.replace("\n", "")


def test_the_readers_columns_come_from_the_arrow_buffers_without_pandas():
    """A restarted monitor reads the earlier record without pyarrow's ``to_numpy`` (it imports
    pandas: seconds of a start on a busy machine): sliced, empty and null columns alike."""
    import pyarrow as pa

    from agents.columns import to_numpy as _array

    assert _array(pa.array(np.arange(6, dtype=np.int32)).slice(2, 3)).tolist() == [2, 3, 4]
    assert _array(pa.array(np.array([], dtype=np.int64))).dtype == np.int64
    got = _array(pa.array([1.5, None]))
    assert got[0] == 1.5 and np.isnan(got[1])
    code = ("import sys, numpy as np, pyarrow as pa\nfrom agents.recorder import _np\n"
            "t = pa.Table.from_batches([pa.RecordBatch.from_arrays([pa.Array.from_buffers(pa.int64(), 3, "
            "[None, pa.py_buffer(np.arange(3))])], names=['k'])] * 2)\n"
            "assert _np(t, 'k').tolist() == [0, 1, 2, 0, 1, 2]\nprint('pandas' in sys.modules)")
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip() == "False"
