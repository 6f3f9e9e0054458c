"""``rse sweep --cluster``: a real Dask scheduler and two real workers on loopback.

The cluster's table equals the process pool's run by run; a worker killed in the middle
of a sweep loses no run and writes none twice (the client writes each result once);
an address where no scheduler answers is a one-line error, exit status 2.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest

pytest.importorskip("distributed")

from tests.conftest import SCENARIOS

pytestmark = pytest.mark.multiprocess

SC = str(SCENARIOS / "mitra_cells.toml")
TIMING = {"elapsed_s"}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def dask_cmd(*args: str) -> list[str]:
    import sys

    return [sys.executable, "-m", "distributed.cli.dask_" + args[0], *args[1:]]


def start_cluster(procs, workers: int = 2) -> tuple[str, list]:
    """``dask scheduler`` and ``workers`` x ``dask worker`` (one thread, no nanny: a killed
    worker stays dead); returns the address once every worker has registered."""
    from distributed import Client

    port = free_port()
    addr = f"tcp://127.0.0.1:{port}"
    procs.start(dask_cmd("scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"))
    ws = [procs.start(dask_cmd("worker", addr, "--nthreads", "1", "--no-nanny", "--no-dashboard",
                               "--name", f"w{i}")) for i in range(workers)]
    with Client(addr, timeout=60, set_as_default=False) as c:
        c.wait_for_workers(workers, timeout=90)
    return addr, ws


def table(path: Path) -> list[dict]:
    rows = pq.read_table(path).to_pylist()
    return [{k: v for k, v in r.items() if k not in TIMING} for r in rows]


def test_cluster_sweep_equals_the_process_pool_run_by_run(tmp_path, procs, run_rse):
    addr, _ = start_cluster(procs)
    args = ["--grid", "network.channel.drop_p=0.1,0.6", "--seeds", "2", "--set", "run.rounds=60",
            "--set", "expect=[]", "--no-png"]
    r = run_rse("sweep", SC, *args, "--cluster", addr, "--out", str(tmp_path / "dask"), cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    r = run_rse("sweep", SC, *args, "--jobs", "2", "--out", str(tmp_path / "pool"), cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    dask, pool = table(tmp_path / "dask" / "sweep.parquet"), table(tmp_path / "pool" / "sweep.parquet")
    assert len(dask) == 4 and all(row["status"] == "ok" for row in dask)
    assert dask == pool
    # the recordings were built on the workers and written here, one per run
    assert len(list((tmp_path / "dask").glob("points/*/run.rrd"))) == 4


@pytest.mark.slow
def test_a_worker_killed_mid_sweep_loses_no_run_and_writes_none_twice(tmp_path, procs):
    addr, workers = start_cluster(procs)
    out = tmp_path / "sweep"
    from tests.procs import rse_cmd

    sweep = procs.start(rse_cmd("sweep", SC, "--grid", "network.channel.drop_p=0:0.55:0.05", "--seeds", "2",
                                "--set", "run.rounds=80", "--set", "expect=[]", "--no-png", "--no-rrd",
                                "--cluster", addr, "--out", str(out)))
    deadline = time.monotonic() + 240
    while len(list(out.glob("points/*/point.json"))) < 3:
        assert sweep.poll() is None, sweep.communicate()
        assert time.monotonic() < deadline, "the sweep made no progress"
        time.sleep(0.05)
    os.kill(workers[0].pid, signal.SIGKILL)  # busy: one thread, a queue of 24 tasks
    done_at_kill = len(list(out.glob("points/*/point.json")))
    assert done_at_kill < 24
    stdout, stderr = sweep.communicate(timeout=300)
    assert sweep.returncode == 0, stdout + stderr
    rows = pq.read_table(out / "sweep.parquet").to_pylist()
    assert len(rows) == 24 and len({r["point"] for r in rows}) == 24
    assert all(r["status"] == "ok" for r in rows)
    assert sorted({(r["network.channel.drop_p"], r["seed"]) for r in rows}) == sorted(
        {(round(0.05 * i, 12), s) for i in range(12) for s in (3, 4)})
    assert len(list(out.glob("points/*/point.json"))) == 24
    assert all(json.loads(f.read_text())["status"] == "ok" for f in out.glob("points/*/point.json"))
    assert workers[0].poll() is not None and workers[1].poll() is None


def test_unreachable_cluster_is_a_one_line_error(tmp_path, run_rse):
    port = free_port()  # nothing listens there
    r = run_rse("sweep", SC, "--grid", "network.channel.drop_p=0.1", "--set", "expect=[]", "--no-png",
                "--cluster", f"tcp://127.0.0.1:{port}", "--out", str(tmp_path / "s"), cwd=tmp_path, timeout=120)
    assert r.returncode == 2, r.stdout + r.stderr
    assert f"no Dask scheduler answers at tcp://127.0.0.1:{port}" in r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("grid, words", [
    ("network.channel.nope=0.1,0.2", "nope"),
    ("network.channel.drop_p=0.5:0.1:0.1", "STOP >= START"),
])
def test_bad_grid_is_a_one_line_error(tmp_path, run_rse, grid, words):
    r = run_rse("sweep", SC, "--grid", grid, "--no-png", "--out", str(tmp_path / "s"), cwd=tmp_path)
    assert r.returncode == 2, r.stdout + r.stderr
    assert words in r.stderr and "Traceback" not in r.stderr
