"""``rse run`` when a process dies: the plant ends the run with everything recorded up to
it; the monitor is not a single point of failure (the team goes on, a restarted monitor
rejoins, the run directory covers every round but the gap).

Lockstep paced at 100 Hz (dt = 0.01): a round is at least 10 ms of wall clock, and every
agent's estimate of every round is recorded (realtime on a loaded machine leaves an agent
late for a round now and then: NaN there, up to most rounds at a load average of 40 on two
cores). Every wait is for an event (a file, a line printed), with generous timeouts.
"""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from pathlib import Path

import numpy as np
import psutil
import pyarrow.parquet as pq
import pytest

from tests.conftest import SCENARIOS
from tests.procs import rse_cmd
from tests.procs import wait_json as _wait_file

pytestmark = [pytest.mark.multiprocess, pytest.mark.slow]

LKS = SCENARIOS / "lee_kim_shim.toml"
# paced at 200 rounds/s (at most): the rounds of the kills below come within a poll or two
# of status.json, and the runs take half the wall time they took at 100 (the suite's budget)
RUN = ("--set", "run.dt=0.01", "--set", "run.duration=41", "--set", "output.window=[40.0, 41.0]",
       "--rate", "200", "--no-progress", "--no-rerun")


class Status:
    """The rounds the launcher reports in status.json, with when they were seen."""

    def __init__(self, out: Path, proc) -> None:
        self.out, self.proc = out, proc
        self.seen: list[tuple[int, float]] = []

    def wait_round(self, k: int, timeout: float = 60) -> None:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            try:
                r = json.loads((self.out / "status.json").read_text())["round"]
                self.seen.append((r, time.monotonic()))
                if r >= k:
                    return
            except (OSError, ValueError, KeyError):
                pass
            assert self.proc.poll() is None, self.proc.communicate()[1]
            time.sleep(0.02)
        raise AssertionError(f"round {k} not reached")

    def recorded_before(self, t: float) -> int:
        """The last round the monitor had recorded at time ``t`` (as the launcher saw it)."""
        return max((r for r, seen in self.seen if seen <= t), default=-1)


class Lines:
    """A stream's lines, read on a thread; :meth:`wait_for` waits for one with ``text``."""

    def __init__(self, stream) -> None:
        self.lines: list[str] = []
        self.cv = threading.Condition()
        threading.Thread(target=self._read, args=(stream,), daemon=True).start()

    def _read(self, stream) -> None:
        for line in stream:
            with self.cv:
                self.lines.append(line)
                self.cv.notify_all()

    def wait_for(self, text: str, timeout: float) -> bool:
        with self.cv:
            return self.cv.wait_for(lambda: any(text in ln for ln in self.lines), timeout)

    @property
    def text(self) -> str:
        with self.cv:
            return "".join(self.lines)


def test_a_killed_plant_ends_the_run_with_everything_recorded(procs, tmp_path):
    out = tmp_path / "run"
    p = procs.start(rse_cmd("run", str(LKS), *RUN, "--mode", "lockstep", "--out", str(out)))
    team = _wait_file(out / "team.json", 60)
    status = Status(out, p)
    status.wait_round(1500)
    t_kill = time.monotonic()
    os.kill(team["pids"]["plant"], signal.SIGKILL)
    so, se = p.communicate(timeout=30)
    assert p.returncode == 1, se
    assert "plant failed (killed by SIGKILL)" in se and "Traceback" not in se
    children = [psutil.Process(pid) for name, pid in team["pids"].items() if name != "plant" and psutil.pid_exists(pid)]
    assert not psutil.wait_procs(children, timeout=1)[1]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["complete"] is False and summary["reason"].startswith("the plant failed (killed by SIGKILL)")
    m = pq.read_table(out / "metrics.parquet").to_pandas()
    assert m["k"].max() == summary["last_round"]
    # every round the monitor had recorded a second before the kill (1 s flush interval;
    # the launcher sees the monitor's rounds within 0.5 s: that is the margin) is there,
    # with every agent's error
    due = status.recorded_before(t_kill - 1.0)
    assert due >= 1000
    x = m[(m["block"] == "x") & (m["k"] <= due)]
    assert sorted(set(x["k"])) == list(range(due + 1))
    assert np.isfinite(x["error_2"]).all()  # every agent's estimate of every round
    assert not (out / "metrics.partial").exists()


def test_the_team_goes_on_without_its_monitor_and_a_restarted_one_rejoins(procs, tmp_path):
    out = tmp_path / "run"
    # lockstep: a rejoining monitor goes through the plant's flow control
    p = procs.start(rse_cmd("run", str(LKS), *RUN, "--mode", "lockstep", "--out", str(out)))
    err = Lines(p.stderr)
    team = _wait_file(out / "team.json", 60)
    status = Status(out, p)
    status.wait_round(1300)  # after t = 10 s, where the scenario has a bound
    t_kill = time.monotonic()
    os.kill(team["pids"]["monitor"], signal.SIGKILL)
    assert err.wait_for("the team goes on without it", 30), err.text
    # the team goes on: the plant and the agents are alive a while later, rounds still tick
    # (the agents' liveliness is what the restarted monitor sees below)
    assert p.poll() is None
    m = procs.start(rse_cmd("monitor", "--team", str(out / "team.json"), "--no-rerun", "--verbose"))
    mon_err = Lines(m.stderr)
    assert mon_err.wait_for("rejoined the team at round", 60), mon_err.text
    p.wait(timeout=60)
    m.wait(timeout=60)
    assert p.returncode == 0, err.text
    assert m.returncode == 0, mon_err.text
    summary = json.loads((out / "summary.json").read_text())
    assert summary["complete"] is True and summary["last_round"] == 4100
    gaps = summary["unrecorded_rounds"]
    assert len(gaps) == 1
    first, last = gaps[0]
    due = status.recorded_before(t_kill - 1.0)
    assert 1000 <= due < first <= last < 4100
    metrics = pq.read_table(out / "metrics.parquet").to_pandas()
    x = metrics[metrics["block"] == "x"]
    assert sorted(set(x["k"])) == list(range(4101))
    inside = (x["k"] >= first) & (x["k"] <= last)
    assert x[inside]["error_2"].isna().all()
    assert np.isfinite(x[~inside]["error_2"]).all()  # every other round, every agent
    assert np.nanmax(x[x["k"] >= 4000]["error_inf"]) <= 0.25  # the run's own bound held
    assert not (out / "metrics.partial").exists()
