"""Ctrl-C and SIGTERM at any moment: every command ends within 2 s of the signal, leaves no
process behind and a consistent run directory (a summary.json whenever the run had
begun; complete: false with the reason and the last round when it ended early, and then
metrics.parquet holding exactly the rounds up to it; no partial stream left).

The signal is sent at many moments of each command's life, each one an event the test
waits for (the process started, a file written, a line printed): start-up, the run
directory begun, rounds running, the summary printed, serving the viewer. Whatever the
moment, the outcome must be consistent, so no moment is a race.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path

import psutil
import pyarrow.parquet as pq
import pytest

from tests.conftest import ROOT, SCENARIOS
from tests.procs import child_env, rse_cmd

pytestmark = [pytest.mark.multiprocess, pytest.mark.slow]

LKS = str(SCENARIOS / "lee_kim_shim.toml")
MITRA = str(SCENARIOS / "mitra_cells.toml")
#: the feature: a command ends within this long of the signal (measured 0.1-1.7 s on a
#: loaded two-core machine)
WITHIN_S = 2.0


class Proc:
    """A command in its own process group, its output read on threads."""

    def __init__(self, args: list[str], *, env: dict | None = None) -> None:
        import subprocess

        e = child_env()
        e.update(env or {})
        self.p = subprocess.Popen(args, cwd=ROOT, env=e, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                  start_new_session=True)
        self.lines: list[str] = []
        self.cv = threading.Condition()
        self._open = 2
        for s in (self.p.stdout, self.p.stderr):
            threading.Thread(target=self._read, args=(s,), daemon=True).start()

    def _read(self, stream) -> None:
        for line in stream:
            with self.cv:
                self.lines.append(line)
                self.cv.notify_all()
        with self.cv:
            self._open -= 1
            self.cv.notify_all()

    @property
    def text(self) -> str:
        with self.cv:
            return "".join(self.lines)

    def has(self, text: str) -> bool:
        with self.cv:
            return any(text in ln for ln in self.lines)

    def wait_line(self, text: str, timeout: float) -> bool:
        with self.cv:
            return self.cv.wait_for(lambda: any(text in ln for ln in self.lines) or self._open == 0, timeout) and \
                any(text in ln for ln in self.lines)

    def group(self) -> list[psutil.Process]:
        out = []
        for q in psutil.process_iter(["pid"]):
            try:
                if os.getpgid(q.pid) == self.p.pid and q.status() != psutil.STATUS_ZOMBIE:
                    out.append(q)
            except (ProcessLookupError, psutil.Error, OSError):
                pass
        return out

    def kill(self) -> None:
        try:
            os.killpg(self.p.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass
        self.p.wait(timeout=10)


def loading(p: Proc, timeout: float = 120) -> bool:
    """Start-up: the command runs (numpy is mapped: the scenario is being loaded); before,
    the interpreter itself starts, where a signal's default action ends it."""
    def mapped() -> bool:
        try:
            return any("numpy" in m.path for m in psutil.Process(p.p.pid).memory_maps())
        except (psutil.Error, OSError):
            return p.p.poll() is not None
    return wait_until(mapped, timeout)


def wait_until(pred: Callable[[], bool], timeout: float) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.02)
    return False


def check_run_dir(d: Path) -> str:
    """The run directory is consistent; returns what it says (for the messages)."""
    if not (d / "manifest.json").exists():
        assert not (d / "summary.json").exists() or json.loads((d / "summary.json").read_text())
        return "no run begun"
    s = json.loads((d / "summary.json").read_text())
    assert not (d / "metrics.partial").exists(), "the partial stream was left"
    if s["complete"]:
        assert (d / "metrics.parquet").exists()
        return "complete"
    assert s["reason"] and isinstance(s["last_round"], int)
    if s["last_round"] >= 0:
        k = pq.read_table(d / "metrics.parquet", columns=["k"]).column("k").to_numpy()
        assert k.max() == s["last_round"] and k.min() == 0
    return f"incomplete at round {s['last_round']}: {s['reason']}"


def interrupt(proc: Proc, sig: int, *, ok: tuple[int, ...] = (130,), pids: Callable[[], list[int]] = lambda: []) -> float:
    """Send ``sig``; the command must end within WITHIN_S with status in ``ok`` (0 also when
    it had finished before the signal), leaving no process; returns how long it took."""
    before = [psutil.Process(pid) for pid in pids() if psutil.pid_exists(pid)] + proc.group()
    t0 = time.monotonic()
    try:
        proc.p.send_signal(sig)
    except ProcessLookupError:
        pass
    try:
        rc = proc.p.wait(timeout=30)
    finally:
        took = time.monotonic() - t0
    assert took < WITHIN_S, f"{took:.2f} s after {signal.Signals(sig).name}\n{proc.text}"
    assert rc in ok + (0,), f"exit {rc}\n{proc.text}"
    assert "Traceback" not in proc.text, proc.text
    gone, alive = psutil.wait_procs([q for q in before if q.pid != proc.p.pid], timeout=0.5)
    assert not [q for q in alive if q.status() != psutil.STATUS_ZOMBIE], f"left behind: {alive}"
    return took


SIGS = (signal.SIGINT, signal.SIGTERM)


# ------------------------------------------------------------------------ rse simulate


def _simulate_moments(tmp_path: Path, serve: bool) -> list[tuple[str, Callable[[Proc, Path], bool]]]:
    """Without a viewer: start-up, the run directory begun, the rounds; with --serve-web:
    the rounds (a dashboard open), the summary printed, serving."""
    rounds = ("rounds", lambda p, d: wait_until(lambda: any((d / "metrics.partial").glob("*.arrows")), 120))
    if not serve:
        return [("start-up", lambda p, d: loading(p)),
                ("run directory begun", lambda p, d: wait_until((d / "manifest.json").exists, 120)), rounds]
    return [rounds, ("summary printed", lambda p, d: p.wait_line("run directory:", 240)),
            ("serving", lambda p, d: p.wait_line("still serving", 240))]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("serve", [False, True], ids=["plain", "serve-web"])
def test_rse_simulate_at_any_moment(tmp_path, serve):
    took = []
    for n, (name, reach) in enumerate(_simulate_moments(tmp_path, serve)):
        d = tmp_path / f"run{n}"
        args = ["simulate", LKS, "--set", "run.duration=400", "--set", "expect=[]", "--no-progress", "--out", str(d)]
        if serve:
            args += ["--serve-web", "--web-port", str(free_port()), "--grpc-port", str(free_port())]
        else:
            args += ["--no-rerun"]
        if name == "summary printed":  # a short run: the moment after the rounds
            args[args.index("run.duration=400")] = "run.duration=5"
        p = Proc(rse_cmd(*args))
        try:
            assert reach(p, d), f"{name}: never reached\n{p.text}"
            ok = (0, 130) if name == "serving" else (130,)
            took.append(interrupt(p, SIGS[n % 2], ok=ok))
            what = check_run_dir(d)
            if name == "rounds":
                assert what.startswith("incomplete"), what
            if name == "serving":
                assert p.p.returncode == 0 and what == "complete", what
        finally:
            p.kill()
    print(f"rse simulate{' --serve-web' if serve else ''}: ended {', '.join(f'{t:.2f}' for t in took)} s after the signal")


# -------------------------------------------------------------------------- rse sweep


def test_rse_sweep_at_any_moment(tmp_path):
    took = []
    out = tmp_path / "sweep"
    seen: set[Path] = set()  # what the earlier (interrupted) invocations left: a moment waits for something new

    def new(pattern: str) -> Callable[[], bool]:
        return lambda: bool(set((out / "points").glob(pattern)) - seen)

    moments = [
        ("start-up", lambda p: loading(p)),
        ("runs under way", lambda p: loading(p) and wait_until(new("*/"), 120)),
        ("a point done", lambda p: loading(p) and wait_until(new("*/point.json"), 240)),
    ]
    for n, (name, reach) in enumerate(moments):
        seen = set((out / "points").glob("*/")) | set((out / "points").glob("*/point.json"))
        p = Proc(rse_cmd("sweep", LKS, "--grid", "run.seed=1,2,3,4,5,6", "--set", "run.duration=100", "--set",
                         "expect=[]", "-j", "2", "--out", str(out), "--no-png"))
        try:
            assert reach(p), f"{name}: never reached\n{p.text}"
            took.append(interrupt(p, SIGS[n % 2]))
            # consistent: every point with its point.json has its summary (a resumed sweep
            # skips exactly those); a table, when written, lists them
            done = sorted(q.parent.name for q in (out / "points").glob("*/point.json")) if out.exists() else []
            for pid in done:
                assert (out / "points" / pid / "summary.json").exists()
            if (out / "sweep.parquet").exists():
                assert sorted(pq.read_table(out / "sweep.parquet").column("point").to_pylist()) == done
        finally:
            p.kill()
    print(f"rse sweep: ended {', '.join(f'{t:.2f}' for t in took)} s after the signal")


# ---------------------------------------------------------------------------- rse run


def _status_round(d: Path) -> int:
    try:
        return json.loads((d / "status.json").read_text())["round"]
    except (OSError, ValueError, KeyError):
        return -1


def test_rse_run_at_any_moment(tmp_path):
    took = []
    moments = [
        ("start-up", lambda p, d: loading(p)),
        ("team started", lambda p, d: wait_until((d / "team.json").exists, 120)),
        ("rounds", lambda p, d: wait_until(lambda: _status_round(d) > 200, 120)),
        ("serving", lambda p, d: p.wait_line("still serving", 240)),
    ]
    for n, (name, reach) in enumerate(moments):
        d = tmp_path / f"run{n}"
        args = ["run", LKS, "--set", "run.dt=0.01", "--set", "run.duration=60", "--set", "expect=[]", "--rate", "100",
                "--no-progress", "--out", str(d)]
        if name == "serving":
            args[args.index("run.duration=60")] = "run.duration=3"
            args += ["--serve-web", "--web-port", str(free_port()), "--grpc-port", str(free_port())]
        else:
            args += ["--no-rerun"]

        def pids(d=d) -> list[int]:
            try:
                return list(json.loads((d / "team.json").read_text())["pids"].values())
            except (OSError, ValueError):
                return []

        p = Proc(rse_cmd(*args))
        try:
            assert reach(p, d), f"{name}: never reached\n{p.text}"
            took.append(interrupt(p, SIGS[n % 2], ok=(0, 130) if name == "serving" else (130,), pids=pids))
            if (d / "team.json").exists():
                what = check_run_dir(d)
                if name == "rounds":
                    assert what.startswith("incomplete"), what
        finally:
            p.kill()
    print(f"rse run: ended {', '.join(f'{t:.2f}' for t in took)} s after the signal")


# ----------------------------------------------------------------------- single roles


@pytest.mark.parametrize("role", ["plant", "monitor", "agent"])
def test_a_single_role_at_start_up_and_waiting_for_its_team(tmp_path, role):
    """A role started alone: the signal once its session is open while it waits for the
    rest of the team (and, for the monitor, at start-up: the command's path is the same
    for the three roles until then)."""
    took = []
    names = ("start-up", "waiting for the team") if role == "monitor" else ("waiting for the team",)
    for n, name in enumerate(names, start=0 if role == "monitor" else 1):
        args = [role, LKS, "--run-id", f"sig-{role}-{n}", "--set", "run.dt=0.01"]
        args += {"monitor": ["--out", str(tmp_path / f"mon{n}"), "--no-rerun"], "agent": ["--id", "2"], "plant": []}[role]
        p = Proc(rse_cmd(*args), env={"RSE_NET_DEBUG": "1"})
        try:
            assert loading(p) if name == "start-up" else p.wait_line("session open", 120), p.text
            took.append(interrupt(p, SIGS[n % 2]))
            if role == "monitor" and (tmp_path / f"mon{n}").exists():
                s = json.loads((tmp_path / f"mon{n}" / "summary.json").read_text())
                assert s["complete"] is False and s["last_round"] == -1
        finally:
            p.kill()
    print(f"rse {role}: ended {', '.join(f'{t:.2f}' for t in took)} s after the signal")


def test_single_roles_in_a_running_team(tmp_path):
    """An agent and a monitor that rejoined a running team (rse agent / rse monitor --team):
    the signal while they run rounds ends each within 2 s, the monitor's run directory
    says where it stopped, and the team goes on."""
    d = tmp_path / "run"
    team_proc = Proc(rse_cmd("run", LKS, "--set", "run.dt=0.01", "--set", "run.duration=600", "--set", "expect=[]",
                             "--rate", "100", "--mode", "realtime", "--no-progress", "--no-rerun", "--out", str(d)))
    try:
        assert wait_until(lambda: _status_round(d) > 100, 120), team_proc.text
        team = json.loads((d / "team.json").read_text())
        os.kill(team["pids"]["agent 3"], signal.SIGKILL)
        os.kill(team["pids"]["monitor"], signal.SIGKILL)
        assert team_proc.wait_line("the monitor was killed", 60), team_proc.text
        agent = Proc(rse_cmd("agent", "--id", "3", "--team", str(d / "team.json"), "--verbose", "--startup-timeout", "30"))
        mon = Proc(rse_cmd("monitor", "--team", str(d / "team.json"), "--no-rerun", "--verbose"))
        try:
            def both() -> bool:
                return mon.has("rejoined the team at round") and agent.has("joined")

            # both lines, or either process ended; a rejoining process that does not hear a
            # peer reconnects (7 of 32 scripted rejoins needed it: 3 s, at most 5 times)
            wait_until(lambda: both() or agent.p.poll() is not None or mon.p.poll() is not None, 120)
            rejoined = both()
            assert rejoined, (mon.text, agent.text, team_proc.text)
            t_agent = interrupt(agent, signal.SIGTERM)
            t_mon = interrupt(mon, signal.SIGINT)
        finally:
            agent.kill()
            mon.kill()
        s = json.loads((d / "summary.json").read_text())
        assert s["complete"] is False and s["reason"] == "interrupted" and s["last_round"] > 100
        assert team_proc.p.poll() is None  # the team goes on
        print(f"rse agent / rse monitor in a running team: ended {t_agent:.2f} / {t_mon:.2f} s after the signal")
    finally:
        team_proc.kill()
