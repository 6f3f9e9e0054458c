"""Injecting the faults of a schedule into a running team (:mod:`agents.chaos.schedule`).

The :class:`Injector` runs on the main thread of ``rse chaos`` while the team's supervisor
runs on another. It reads the team's process ids from ``team.json``, keeps the team's
clock (round 0's wall time, from the rounds ``status.json`` reports), and at each fault's
time: SIGKILLs a process and restarts it against the team (``rse agent --id I --team``,
``rse monitor --team``: the plug-and-play a user does by hand), SIGSTOPs then SIGCONTs an
agent, or starts CPU hogs that spin and are reaped. A link cut needs no action here: it is
a loss window of the channel model, in the scenario every process was given. Every action
is an event (``fault``, ``what``, wall time) for :mod:`agents.chaos.measure`.

:meth:`Injector.close` leaves nothing behind on every path: a stopped agent gets SIGCONT,
hogs are killed, restarted processes get SIGTERM and SIGKILL :data:`GRACE_S` later, all
reaped. A hog also ends by itself at its end time, should ``rse chaos`` itself be killed.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from .schedule import Fault

__all__ = ["Injector", "GRACE_S", "hog_command"]

GRACE_S = 1.0  # SIGTERM -> SIGKILL of a restarted process
STEP_S = 0.02  # how finely the injector waits


def hog_command(seconds: float) -> list[str]:
    """A process that spins one core for ``seconds`` and exits by itself."""
    code = f"import time\nend = time.monotonic() + {seconds!r}\nwhile time.monotonic() < end:\n    pass\n"
    return [sys.executable, "-c", code]


def rse_command(*args: str) -> list[str]:
    """``rse ARGS`` with this interpreter (the restarted processes run this tree's code)."""
    return [sys.executable, "-m", "agents.cli", *args]


class Injector:
    """Injects faults into the team of ``run_dir`` ticking at ``rate`` Hz (see the module)."""

    def __init__(self, run_dir: Path, rate: float, *, stop: threading.Event, rerun: bool = True,
                 warmup: float = 3.0) -> None:
        self.run_dir, self.rate, self.stop = run_dir, rate, stop
        self.rerun, self.warmup = rerun, warmup
        self.pids: dict[str, int] = {}
        self.events: list[dict[str, Any]] = []
        self.restarted: list[tuple[str, subprocess.Popen]] = []
        self.hogs: list[subprocess.Popen] = []
        self.frozen: set[int] = set()
        self._t0: float | None = None
        self._restarts = 0
        (run_dir / "chaos-logs").mkdir(parents=True, exist_ok=True)

    # ------------------------------------------------------------------ the team's clock
    def _look(self) -> None:
        """Round 0's wall time, from status.json (the earliest ``time - round / rate``: the
        monitor's lag only makes it later)."""
        try:
            st = json.loads((self.run_dir / "status.json").read_text())
            r, t = int(st["round"]), float(st["time"])
        except (OSError, ValueError, KeyError, TypeError):
            return
        if r >= 0:
            t0 = t - r / self.rate
            self._t0 = t0 if self._t0 is None else min(self._t0, t0)

    def wait_started(self, alive: Any) -> bool:
        """Wait until the team runs (team.json and a first round); False when ``stop`` was
        set or ``alive()`` turned False first."""
        while not self.stop.is_set() and alive():
            if not self.pids:
                with contextlib.suppress(OSError, ValueError, KeyError):
                    self.pids = {k: int(v) for k, v in json.loads((self.run_dir / "team.json").read_text())["pids"].items()}
            self._look()
            if self.pids and self._t0 is not None:
                return True
            time.sleep(0.1)
        return False

    def _sleep_until(self, when: float, alive: Any) -> bool:
        """Sleep until wall time ``when``; False when stopped (or the team ended) first."""
        while time.time() < when:
            if self.stop.is_set() or not alive():
                return False
            self._look()
            self._reap()
            time.sleep(min(STEP_S * 5, max(0.0, when - time.time())))
        return not self.stop.is_set()

    # ------------------------------------------------------------------ faults
    def run(self, faults: list[Fault], alive: Any) -> None:
        """Inject ``faults`` (one episode's) in turn, each at its time; returns early when
        ``stop`` is set or ``alive()`` turns False (the team ended)."""
        for f in faults:
            if self._t0 is None or not self._sleep_until(self._t0 + f.at, alive):
                return
            self._begin(f)
            end_ok = self._sleep_until(time.time() + f.lasts, alive)
            self._end(f)
            if not end_ok:
                return

    def note(self, f: Fault | None, what: str, **extra: Any) -> None:
        self.events.append({"fault": None if f is None else f.index, "what": what, "time": time.time(), **extra})

    def _begin(self, f: Fault) -> None:
        if f.kind in ("kill-agent", "kill-monitor"):
            name = "monitor" if f.kind == "kill-monitor" else f"agent {f.agents[0]}"
            pid = self.pids.get(name)
            self._signal(pid, signal.SIGKILL)
            self.note(f, "begin", pid=pid)
        elif f.kind == "freeze-agent":
            pid = self.pids.get(f"agent {f.agents[0]}")
            if pid is not None and self._signal(pid, signal.SIGSTOP):
                self.frozen.add(pid)
            self.note(f, "begin", pid=pid)
        elif f.kind == "cpu-hog":
            log = self.run_dir / "chaos-logs" / "hogs.log"
            with open(log, "ab") as out:
                self.hogs += [subprocess.Popen(hog_command(f.lasts + 0.5), stdout=out, stderr=out) for _ in range(f.hogs)]
            self.note(f, "begin", pids=[h.pid for h in self.hogs])
        else:  # cut-link: the channel's loss window (every process knows it)
            self.note(f, "begin")

    def _end(self, f: Fault) -> None:
        if f.kind in ("kill-agent", "kill-monitor"):
            name = "monitor" if f.kind == "kill-monitor" else f"agent {f.agents[0]}"
            if self.stop.is_set():
                return
            self._restart(f, name)
        elif f.kind == "freeze-agent":
            pid = self.pids.get(f"agent {f.agents[0]}")
            if pid in self.frozen:
                self._signal(pid, signal.SIGCONT)
                self.frozen.discard(pid)
            self.note(f, "end")
        elif f.kind == "cpu-hog":
            self._kill_hogs()
            self.note(f, "end")
        else:
            self.note(f, "end")

    def _restart(self, f: Fault, name: str) -> None:
        team = str(self.run_dir / "team.json")
        self._restarts += 1
        if name == "monitor":
            args = rse_command("monitor", "--team", team, "--verbose", *(() if self.rerun else ("--no-rerun",)))
        else:
            args = rse_command("agent", "--id", name.split()[1], "--team", team, "--warmup", repr(self.warmup),
                               "--verbose")
        log = self.run_dir / "chaos-logs" / f"{name.replace(' ', '-')}-{self._restarts}.log"
        with open(log, "wb") as out:
            p = subprocess.Popen(args, stdout=out, stderr=out, stdin=subprocess.DEVNULL)
        self.restarted.append((name, p))
        self.pids[name] = p.pid
        self.note(f, "end", pid=p.pid, log=log.name)

    # ------------------------------------------------------------------ processes
    @staticmethod
    def _signal(pid: int | None, sig: int) -> bool:
        if pid is None:
            return False
        try:
            os.kill(pid, sig)
            return True
        except (ProcessLookupError, PermissionError):
            return False

    def _reap(self) -> None:
        """Collect the exit status of restarted processes that ended (no zombie)."""
        for name, p in self.restarted:
            if p.returncode is None and p.poll() is not None:
                self.note(None, "exited", name=name, pid=p.pid, status=p.returncode)
        self.hogs = [h for h in self.hogs if h.poll() is None]

    def _kill_hogs(self) -> None:
        for h in self.hogs:
            with contextlib.suppress(OSError):
                h.kill()
        for h in self.hogs:
            with contextlib.suppress(subprocess.TimeoutExpired):
                h.wait(1.0)
        self.hogs = []

    def wait_restarted(self, timeout: float) -> None:
        """Give the restarted processes ``timeout`` seconds to end with the team."""
        end = time.monotonic() + timeout
        for _, p in self.restarted:
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(max(0.0, end - time.monotonic()))
        self._reap()

    def close(self) -> None:
        """Leave nothing behind (see the module): SIGCONT, hogs, restarted processes."""
        for pid in list(self.frozen):
            self._signal(pid, signal.SIGCONT)
        self.frozen.clear()
        self._kill_hogs()
        live = [p for _, p in self.restarted if p.poll() is None]
        for p in live:
            with contextlib.suppress(OSError):
                p.terminate()
        end = time.monotonic() + GRACE_S
        for p in live:
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(max(0.0, end - time.monotonic()))
        for p in live:
            if p.poll() is None:
                with contextlib.suppress(OSError):
                    p.kill()
                p.wait()
        self._reap()

    @property
    def t0(self) -> float | None:
        return self._t0
