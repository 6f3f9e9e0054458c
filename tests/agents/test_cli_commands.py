"""The command line as a user runs it: ``rse check`` and a shortened ``rse simulate`` on every
scenario file (the click commands in this process: 28 fresh interpreters took half the time;
real ``rse`` processes run both in ``test_cli.py``, ``test_check_and_horizon.py`` and the
scenario tests), and in real ``rse`` processes ``rse sweep`` interrupted and resumed, ``rse bench
simulate --rerun-overhead``, ``rse simulate --rrd PATH`` and ``--viewer``, and an agent that
fails during ``rse run``."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import time
import tomllib
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from tests.conftest import SCENARIOS, scenario_params
from tests.procs import rse_cmd

FILES = sorted(SCENARIOS.glob("*.toml"))
LKS = SCENARIOS / "lee_kim_shim.toml"
MITRA = SCENARIOS / "mitra_cells.toml"
SHORT_LKS = ("--set", "run.duration=2", "--set", "expect=[]", "--set", "output.window=[0, 2]")

# the scenarios whose own comment says a condition of the paper fails (`rse check` exits 1),
# with the condition that fails
CHECK_FAILS = {
    # Fig. 9: p = 0.8, Theorem 2's condition rho^2 pbar < 1 fails
    "mitra_cells_p08": "MSS (Theorem 2): rho^2 pbar < 1 at p = 0.8",
    # Fig. 11: the graph is only strongly (2f+1)-robust (m = 2 < 3): pbar = 1 and the MSS
    # condition fails whatever p
    "mitra_omission": "MSS (Theorem 2): rho^2 pbar < 1 at p = 0.32",
}


def wait_for(what, timeout: float, proc=None, step: float = 0.02) -> None:
    """Wait for the event ``what()``; the timeout is only for a hang (or ``proc`` exiting)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if what():
            return
        if proc is not None and proc.poll() is not None:
            raise AssertionError(f"the process exited ({proc.returncode}) first: {proc.communicate()[1][-2000:]}")
        time.sleep(step)
    raise AssertionError(f"not within {timeout:g} s")


def _invoke(*args: str):
    """``rse ARGS`` through its click command in this process: (exit status, output); an
    exception other than the command's own exit is a traceback a user would see."""
    from click.testing import CliRunner

    from agents.cli import cli
    from agents.console import out

    # rich wraps tables at the console's width, which an earlier command in this process may
    # have fixed (from COLUMNS when the console was made): 200 columns here, as for a process
    saved = out._width
    out.width = 200
    try:
        res = CliRunner().invoke(cli, list(args))
    finally:
        out._width = saved
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    return res.exit_code, res.output


@pytest.mark.parametrize("path", scenario_params(FILES))
def test_rse_check_on_every_scenario_file(path):
    """Exit status as the README says: 0 where every condition holds, 1 where one fails
    (the one the scenario's comment names), never a traceback."""
    code, out = _invoke("check", str(path))
    assert "Traceback" not in out, out
    lines = out.splitlines()
    fails = [line for line in lines if "FAILS" in line]
    assert any("holds" in line for line in lines), out
    if path.stem in CHECK_FAILS:
        assert code == 1, out
        assert len(fails) == 1 and CHECK_FAILS[path.stem] in fails[0], fails
    else:
        assert code == 0, out
        assert fails == []


def _shortened(path: Path, rounds: int = 20) -> list[str]:
    """``--set`` arguments that cut a scenario to its first ``rounds`` rounds (no bounds)."""
    run = tomllib.loads(path.read_text())["run"]
    T = rounds * run["dt"]
    horizon = f"run.rounds={rounds}" if "rounds" in run else f"run.duration={T:g}"
    return [a for ov in (horizon, "expect=[]", f"output.window=[0, {T:g}]") for a in ("--set", ov)]


@pytest.mark.slow
@pytest.mark.parametrize("path", scenario_params(FILES))
def test_rse_simulate_on_every_scenario_file_shortened(path, tmp_path):
    """Every scenario file runs from the command line (its first 20 rounds): exit 0, the run
    directory with its summary, no traceback."""
    out = tmp_path / "run"
    code, text = _invoke("simulate", str(path), "--out", str(out), "--no-progress", "--no-rerun", *_shortened(path))
    assert code == 0 and "Traceback" not in text, text
    assert json.loads((out / "summary.json").read_text())["rounds"] == 20


def _points(out: Path) -> dict[Path, int]:
    return {f: f.stat().st_mtime_ns for f in out.glob("points/*/point.json")}


def _table(out: Path):
    t = pq.read_table(out / "sweep.parquet").to_pandas().drop(columns=["elapsed_s"])
    return t.sort_values(["point", "seed"]).reset_index(drop=True)


@pytest.mark.multiprocess
@pytest.mark.slow
def test_rse_sweep_interrupted_then_resumed_equals_an_uninterrupted_sweep(procs, run_rse, tmp_path):
    """Ctrl-C (SIGINT to the process group, as a terminal sends it) once a run has finished:
    exit 130, no traceback; the same command with the same --out runs only what is missing
    (the finished runs are not run again) and its table equals an uninterrupted sweep's."""
    args = ("sweep", str(MITRA), "--grid", "network.channel.drop_p=0.0,0.3,0.6", "--seeds", "4", "--jobs", "1",
            "--set", "run.rounds=100", "--set", "expect=[]", "--no-png")
    total = 12
    out = tmp_path / "sweep"
    p = procs.start(rse_cmd(*args, "--out", str(out)))
    wait_for(lambda: len(_points(out)) >= 1, 600, p)
    os.killpg(p.pid, signal.SIGINT)
    so, se = p.communicate(timeout=60)
    assert p.returncode == 130, se
    assert "Traceback" not in so + se, se
    before = _points(out)
    assert 1 <= len(before) < total, "the sweep was not interrupted in the middle"
    res = run_rse(*args, "--out", str(out), timeout=900)
    assert res.returncode == 0 and "Traceback" not in res.stderr, res.stderr
    assert f"{total} runs in {out}" in " ".join(res.stdout.split())
    after = _points(out)
    assert len(after) == total and {f: after[f] for f in before} == before  # not run again
    table = _table(out)
    assert len(table) == total and not table.duplicated(["point", "seed"]).any()
    assert (table["status"] == "ok").all()
    ref = run_rse(*args, "--out", str(tmp_path / "ref"), timeout=900)
    assert ref.returncode == 0, ref.stderr
    assert table.equals(_table(tmp_path / "ref"))


def test_rse_bench_simulate_prints_the_rerun_overhead(run_rse):
    res = run_rse("bench", "simulate", str(LKS), "--repeat", "2", "--rerun-overhead", *SHORT_LKS)
    assert res.returncode == 0 and "Traceback" not in res.stderr, res.stderr
    out = " ".join(res.stdout.split())
    m = re.search(r"with the Rerun dashboard: median ([0-9,]+) agent-rounds/s; logging overhead in the rounds: "
                  r"median (-?[0-9.]+)% \(min (-?[0-9.]+)%, max (-?[0-9.]+)%\)", out)
    assert m, out
    rate, med, lo, hi = (float(g.replace(",", "")) for g in m.groups())
    assert rate > 0 and lo <= med <= hi and lo > -100


def test_rse_simulate_rrd_path_writes_the_recording_there(run_rse, tmp_path):
    """--rrd PATH: the recording at PATH (its directory created), none in the run directory."""
    rr = pytest.importorskip("rerun")
    out, rrd = tmp_path / "run", tmp_path / "elsewhere" / "lks.rrd"
    res = run_rse("simulate", str(LKS), "--out", str(out), "--no-progress", "--rrd", str(rrd), *SHORT_LKS)
    assert res.returncode == 0, res.stderr
    assert rrd.is_file() and not (out / "recording.rrd").exists()
    assert json.loads((out / "summary.json").read_text())["rounds"] == 200  # rounds 0 to 200
    pytest.importorskip("datafusion", reason="reading .rrd files needs rerun-sdk[catalog] (the test extra)")
    with rr.server.Server(datasets={"run": [str(rrd)]}) as srv:
        client = srv.client()
        df = client.get_dataset("run").reader(index="k").to_pandas()
        del client
    assert len(df[["k", "/errors/x:Scalars:scalars"]].dropna()) == 201  # every round


@pytest.mark.multiprocess
def test_rse_simulate_viewer_spawns_the_native_viewer(run_rse, tmp_path):
    """--viewer spawns Rerun's native viewer and streams to it (the recording is written too)."""
    import psutil

    if not shutil.which("rerun"):
        pytest.skip("no `rerun` viewer binary on PATH (rerun-sdk installs it)")
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        pytest.skip("no display (DISPLAY / WAYLAND_DISPLAY unset): the native viewer cannot open a window")
    t0 = time.time()
    out = tmp_path / "run"
    try:
        res = run_rse("simulate", str(LKS), "--out", str(out), "--no-progress", "--viewer", *SHORT_LKS)
        assert res.returncode == 0 and "Traceback" not in res.stderr, res.stderr
        assert (out / "recording.rrd").is_file()
        viewers = [p for p in psutil.process_iter(["name", "create_time"])
                   if p.info["name"] and p.info["name"].startswith("rerun") and p.info["create_time"] >= t0 - 1]
        assert viewers, "no viewer process was started"
    finally:
        for p in psutil.process_iter(["name", "create_time"]):
            if p.info["name"] and p.info["name"].startswith("rerun") and p.info["create_time"] >= t0 - 1:
                p.kill()


@pytest.mark.multiprocess
@pytest.mark.slow
def test_an_agent_that_fails_during_rse_run_fails_the_run_and_is_named(run_rse, tmp_path):
    """An agent process that ends with an error is a failure, not a leave: exit 1, the
    final message names it, the agent's own error is one line (no traceback).

    The failure is a real I/O error in one agent only: with ``RSE_PROFILE=DIR`` every
    process writes its profile to ``DIR/<role>.prof`` when it ends, and here
    ``agent-3.prof`` is a directory."""
    prof = tmp_path / "prof"
    (prof / "agent-3.prof").mkdir(parents=True)
    out = tmp_path / "run"
    res = run_rse("run", str(LKS), "--out", str(out), "--no-progress", "--no-rerun", "--deadline", "30",
                  "--set", "run.duration=1", "--set", "expect=[]", "--set", "output.window=[0, 1]",
                  env={"RSE_PROFILE": str(prof)}, timeout=600)
    assert res.returncode == 1, res.stdout + res.stderr
    err = res.stderr
    assert "Traceback" not in err, err
    assert f"agent 3: Is a directory: {prof / 'agent-3.prof'}" in err
    assert "agent 3 failed (exit status 1)" in err
    assert not re.search(r"agent [1245] failed|plant failed|monitor failed", err), err
    assert {p.name for p in prof.glob("*.prof") if p.is_file()} == {"plant.prof", "monitor.prof", "agent-1.prof",
                                                                   "agent-2.prof", "agent-4.prof", "agent-5.prof"}
