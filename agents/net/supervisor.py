"""The supervisor of ``rse run``: starts the processes of a team plan and watches them.

The monitor reports progress over a pipe (rounds/s and the worst current error on the
progress bar, joins and leaves, the dashboard's URLs, "serving" once the run is over); the
supervisor polls it and its children. An agent that is killed by a signal from outside is a
*leave*: the team goes on without it; so is a killed monitor (a restarted one rejoins). A
process that exits with an error status is a *failure*, named in the outcome; a failed
plant or router ends the run. On SIGINT or SIGTERM (main thread) every child gets SIGTERM,
then SIGKILL :data:`STOP_GRACE_S` later; every child is joined on every path (no orphan).
"""

from __future__ import annotations

import contextlib
import json
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from estimation.errors import RSEError

from .child import child_entry
from .startup import bare_main, context

if TYPE_CHECKING:
    from multiprocessing.process import BaseProcess

    from transport.secure import TlsFiles

    from .child import ChildSpec

__all__ = ["Supervisor", "Outcome", "describe_exit", "stop_all", "STOP_GRACE_S", "END_GRACE_S", "ROUTER_START_S"]

STOP_GRACE_S = 1.0  # SIGTERM -> SIGKILL
END_GRACE_S = 5.0  # after the monitor finished, how long the others may take to exit
ROUTER_START_S = 15.0  # how long the router child may take to open


@dataclass
class Outcome:
    """How the team ended: ``failures`` and ``leaves`` (one line each), ``stopping`` (a
    signal ended it), ``plant_failed`` (the plant's failure, which ends the run), the pids."""

    failures: list[str] = field(default_factory=list)
    leaves: list[str] = field(default_factory=list)
    stopping: bool = False
    plant_failed: str | None = None
    pids: dict[str, int] = field(default_factory=dict)


def describe_exit(code: int | None) -> str:
    if code is None:
        return "still running"
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit status {code}"


class Supervisor:
    """Start the children of a plan and watch them until the run is over (see the module).

    ``say(line)``: one-line notes (joins, leaves); ``update(k, worst)``: the progress bar;
    ``show_urls(urls)``: the dashboard's URLs; ``while_serving(summary)``: called once the
    run is over while the monitor still serves the recording (it stops when this returns);
    ``stop_when()``: polled while the team runs, True stops it as a signal would (a
    supervisor on another thread than the main one, which catches no signal: ``rse chaos``).
    """

    def __init__(self, run_dir: Path, n_rounds: int, run_id: str, *, say: Callable[[str], None],
                 show_urls: Callable[[dict], None] | None = None,
                 while_serving: Callable[[dict | None], None] | None = None,
                 stop_when: Callable[[], bool] | None = None) -> None:
        self.run_dir, self.n_rounds, self.run_id = run_dir, n_rounds, run_id
        self.say, self.show_urls, self.while_serving = say, show_urls, while_serving
        self.stop_when = stop_when
        self.ctx = context()
        self.recv_conn, self.send_conn = self.ctx.Pipe(duplex=False)  # the monitor's end: send_conn
        self.procs: dict[str, BaseProcess] = {}
        self.router: BaseProcess | None = None
        self.out = Outcome()
        self._stopping: list[int] = []
        self._noted: set[str] = set()
        self._serving = False
        self._monitor_done_at: float | None = None
        self._k, self._worst = -1, float("nan")

    # ------------------------------------------------------------------ the whole run
    def run(self, specs: dict[str, ChildSpec], *, router: tuple[str, TlsFiles | None, dict[str, Any]] | None = None,
            on_started: Callable[[dict[str, int]], None] = lambda pids: None,
            update: Callable[[int, float], None] = lambda k, w: None) -> Outcome:
        """Start the router (``(endpoint, its TLS identity, its access-control args)``) and the
        children of ``specs``, call ``on_started(pids)``, supervise; returns the outcome."""
        prev = self._catch_signals()
        try:
            if router is not None and not self._start_router(*router):
                return self.out  # interrupted while it started
            for name in ["monitor", *(nm for nm in specs if nm != "monitor")]:  # the slowest to start first
                p = self.ctx.Process(target=child_entry, args=(specs[name],), name=f"rse-{name.replace(' ', '-')}",
                                     daemon=True)
                with bare_main():
                    p.start()
                self.procs[name] = p
            self.send_conn.close()  # the monitor holds the writing end now
            started = {**self.procs, **({"router": self.router} if self.router is not None else {})}
            self.out.pids = {nm: p.pid for nm, p in started.items() if p.pid is not None}  # each started
            on_started(self.out.pids)
            self._watch(update)
        finally:
            self._stop()
            for sig, h in prev.items():
                signal.signal(sig, h)
        return self.out

    def _catch_signals(self) -> dict[int, Any]:
        def on_signal(signum: int, frame: Any) -> None:
            self._stopping.append(signum)
            self.out.stopping = True

        if threading.current_thread() is not threading.main_thread():
            return {}
        return {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}

    def _watch(self, update: Callable[[int, float], None]) -> None:
        status_path = self.run_dir / "status.json"
        last_status = 0.0
        while not self._stopping:
            if self.stop_when is not None and self.stop_when():
                self._stopping.append(signal.SIGTERM)
                self.out.stopping = True
                return
            self._read_pipe(update)
            now = time.monotonic()
            if now - last_status > 0.5:
                last_status = now
                from agents.rundir import write_json

                with contextlib.suppress(OSError):
                    write_json(status_path, {"run_id": self.run_id, "round": self._k, "worst_error_inf": self._worst,
                                             "time": time.time()})
            if self._exits(now) or self._over(now):
                return

    # ------------------------------------------------------------------ the monitor's pipe
    def _read_pipe(self, update: Callable[[int, float], None]) -> None:
        try:
            ready = self.recv_conn.poll(0.1)
        except (OSError, EOFError):
            ready = False
        while ready:
            try:
                kind, data = self.recv_conn.recv()
            except (EOFError, OSError):
                return
            self._on_message(kind, data, update)
            try:
                ready = self.recv_conn.poll(0)
            except (OSError, EOFError):
                ready = False

    def _on_message(self, kind: str, data: Any, update: Callable[[int, float], None]) -> None:
        if kind == "round":
            self._k, self._worst = data
            update(self._k, self._worst)
        elif kind == "urls" and self.show_urls is not None:
            self.show_urls(data)
        elif kind == "serving":
            self._serving = True
            self._noted.add("monitor")
            self._monitor_done_at = self._monitor_done_at or time.monotonic()
        elif (kind == "member" and data["role"] == "agent" and 0 < data["round"]
              and self._k < self.n_rounds):  # not the processes leaving after the last round
            self.say(f"agent {data['id']} {'joined' if data['event'] == 'join' else 'left'} (round {data['round']})")

    # ------------------------------------------------------------------ exits
    def _exits(self, now: float) -> bool:
        """Note the children that exited since the last look; True when the run must end."""
        fatal = False
        for name, p in self.procs.items():
            if name in self._noted or p.exitcode is None:
                continue
            self._noted.add(name)
            fatal = self._exited(name, p.exitcode, now) or fatal
        if self.router is not None and self.router.exitcode is not None:
            self.out.failures.append(f"the router failed ({describe_exit(self.router.exitcode)})")
            fatal = True
        return fatal

    def _exited(self, name: str, code: int, now: float) -> bool:
        """One child's exit: a normal end, a leave, or a failure (True: the run ends)."""
        if code == 0:
            if name == "monitor":
                self._monitor_done_at = now
            return False
        if name.startswith("agent") and code < 0 and self._monitor_done_at is None:
            self.out.leaves.append(f"{name} ({describe_exit(code)})")
            self.say(f"{name} was {describe_exit(code)}; the team goes on without it")
            return False
        if name == "monitor" and code < 0:
            # the monitor only records: the team goes on, and a monitor restarted against the
            # team rejoins (the rounds in between are not recorded)
            self.out.leaves.append(f"{name} ({describe_exit(code)})")
            self.say(f"the monitor was {describe_exit(code)}; the team goes on without it "
                     f"(rejoin: rse monitor --team {self.run_dir / 'team.json'})")
            return False
        self.out.failures.append(f"{name} failed ({describe_exit(code)})")
        if name == "plant":  # the plant is the physics: the run ends
            self.out.plant_failed = f"the plant failed ({describe_exit(code)})"
            return True
        return False

    def _over(self, now: float) -> bool:
        """Every child has exited (a serving monitor aside), or the stragglers overstayed."""
        live = [nm for nm, p in self.procs.items() if p.exitcode is None and not (self._serving and nm == "monitor")]
        if not live:
            if self._serving and self.while_serving is not None and not self.out.failures:
                summary = None
                with contextlib.suppress(OSError, ValueError):
                    summary = json.loads((self.run_dir / "summary.json").read_text())
                self.while_serving(summary)
            return True
        if self._monitor_done_at is not None and now - self._monitor_done_at > END_GRACE_S:
            self.out.failures.append(f"{', '.join(live)} did not stop after the end of the run")
            return True
        return False

    # ------------------------------------------------------------------ start and stop
    def _start_router(self, endpoint: str, tls: TlsFiles | None, acl: dict[str, Any]) -> bool:
        """Start the router child and wait until its session is open (False: a signal came
        meanwhile); raises :class:`RSEError` if it exits or does not open within
        :data:`ROUTER_START_S`."""
        from .router import router_entry

        ready = self.ctx.Event()
        args = {"listen": (endpoint,), "secure": tls, **acl}
        p = self.ctx.Process(target=router_entry, args=(args, ready), name="rse-router", daemon=True)
        with bare_main():
            p.start()
        end = time.monotonic() + ROUTER_START_S
        while not ready.wait(0.05):
            if self._stopping or p.exitcode is not None or time.monotonic() > end:
                why = None if self._stopping else ("it exited with " + describe_exit(p.exitcode) if p.exitcode is not None
                                                   else f"it did not open within {ROUTER_START_S:g} s")
                stop_all({"router": p})
                if why is None:
                    return False
                raise RSEError(f"the router on {endpoint} did not start: {why}")
        self.router = p
        return True

    def _stop(self) -> None:
        """Stop every child (the router within the same grace, last), note late failures, join, close."""
        procs = self.procs if self.router is None else {**self.procs, "router": self.router}
        stop_all(procs)
        for name, p in self.procs.items():
            if name not in self._noted and p.exitcode not in (None, 0) and not self._stopping:
                if not (name.startswith("agent") and p.exitcode < 0):
                    self.out.failures.append(f"{name} failed ({describe_exit(p.exitcode)})")
        for p in procs.values():
            with contextlib.suppress(Exception):
                p.close()
        for c in (self.recv_conn, self.send_conn):
            with contextlib.suppress(OSError):
                c.close()


def stop_all(procs: dict[str, BaseProcess]) -> None:
    """SIGTERM every live child, SIGKILL what is left after STOP_GRACE_S, join all."""
    alive = [p for p in procs.values() if p.exitcode is None]
    for p in alive:
        with contextlib.suppress(Exception):
            p.terminate()
    end = time.monotonic() + STOP_GRACE_S
    for p in alive:
        p.join(max(0.0, end - time.monotonic()))
    for p in alive:
        if p.exitcode is None:
            with contextlib.suppress(Exception):
                p.kill()
    for p in procs.values():
        p.join(1.0)
