"""The child side of ``rse run``: one role in this process (:func:`run_role`).

The launcher (:mod:`agents.net.launcher`) starts each child with :func:`child_entry` and a
:class:`ChildSpec`. An agent child reads its slice of the built experiment
(:mod:`agents.net.slices`) and imports only its role's module (:mod:`agents.net.agent`):
numpy, Zenoh, msgpack, its estimator and the round logic; the plant and the monitor read the
pickled experiment. The same function runs a role in the foreground for ``rse plant``,
``rse agent`` and ``rse monitor``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import signal
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from agents.net.exits import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK, describe, exit_status
from estimation.errors import RSEError, ScenarioError, TransportError
from transport.event_loop import run as run_loop

from .config import RunConfig
from .parent import die_with_parent as _die_with_parent
from .recording import claim, release

if TYPE_CHECKING:
    from multiprocessing.connection import Connection

    from agents.dashboard import DashboardOptions
    from agents.rounds import Team
    from scenarios.build import Experiment
    from transport.keys import Keys
    from transport.linkauth import LinkAuth
    from transport.zenoh_bus import Bus
    from transport.zenoh_session import SessionOptions

    from .slices import AgentSlice, PlantSlice

log = logging.getLogger("rse.net")


@dataclass
class ChildSpec:
    """Everything a role process needs (picklable; sessions are opened in the child)."""

    role: str  # "plant", "monitor" or "agent"
    scenario: str
    overrides: tuple[str, ...]
    seed: int | None
    run_id: str
    cfg: RunConfig
    session: SessionOptions
    agent_id: int | None = None
    out_dir: str | None = None
    conn: Connection | None = None  # the monitor's progress pipe to the launcher
    log_level: int = logging.WARNING
    watch_parent: bool = False
    # the launcher's built experiment, pickled (no rebuild), or the path of that pickle: a
    # path keeps the spec small, so that starting a child does not wait for it to read it
    experiment: bytes | str | None = None
    # an agent's slice of the built experiment (agents.net.slices: its node, neighbours, the
    # channel's seeds), pickled, or its path: an agent process reads this and no experiment
    node: bytes | str | None = None
    dashboard: DashboardOptions | None = None  # the monitor's Rerun output (None: none)
    resume: bool = False  # a monitor rejoining a running team (rse monitor --team)
    # several agents in this process (one session, one asyncio task and node each):
    # their ids and slices (as agent_id and node for one agent)
    agent_ids: tuple[int, ...] = ()
    nodes: tuple[bytes | str, ...] = ()
    # the agent(s) of this process rejoining a running team (rse agent --team): see
    # AgentProcess.rejoin; several agents share the session and its reconnects
    rejoin: bool = False

    @property
    def label(self) -> str:
        if self.role == "agent" and self.agent_ids:
            return group_label(self.agent_ids)
        return f"agent {self.agent_id}" if self.role == "agent" else self.role


def group_label(ids: tuple[int, ...] | list[int]) -> str:
    """``agents 1-8`` (a run of ids) or ``agents 1,3,5``: the name of a process hosting several agents."""
    ids = sorted(ids)
    if len(ids) == 1:
        return f"agent {ids[0]}"
    if ids == list(range(ids[0], ids[-1] + 1)):
        return f"agents {ids[0]}-{ids[-1]}"
    return "agents " + ",".join(map(str, ids))



def _open(opts: SessionOptions) -> Any:
    from transport.zenoh_session import SessionOptions, one_zenoh_thread, open_session, tcp_endpoint

    one_zenoh_thread()  # before the process's first session (ZENOH_RUNTIME)
    try:
        return open_session(opts)
    except TransportError:
        if opts.mode != "peer" or not opts.listen or opts.listen == (tcp_endpoint(0),):
            raise
        # our port was taken meanwhile: listen on any port; we still connect to the others
        return open_session(SessionOptions(mode="peer", listen=(tcp_endpoint(0),), connect=opts.connect))


#: niceness increment of the monitor process (0: none)
MONITOR_NICE = 10


async def _role_main(spec: ChildSpec, exp: Any) -> Any:
    """The role of ``spec`` on this process's event loop: signals and the parent watch, the
    session and its bus (closed on every path), then the role itself."""
    from transport.keys import Keys
    from transport.zenoh_bus import ZenohBus
    from transport.zenoh_session import close_session

    loop = asyncio.get_running_loop()
    log.debug("event loop: %s", type(loop).__module__.partition(".")[0])  # uvloop or asyncio (transport.event_loop)
    watcher = _stop_on_signals(loop, spec.watch_parent)
    session = await asyncio.to_thread(_open, spec.session)
    log.debug("session open")
    bus = None
    try:
        bus = ZenohBus(session, loop, opener=lambda: _open(spec.session))
        bus.auth = _link_auth(spec.session, exp)
        keys = Keys(spec.run_id)
        if spec.role == "plant":
            from .plant import run_plant

            return await run_plant(exp, bus, keys, spec.cfg)
        if spec.role == "agent":
            return await _agents(spec, exp, bus, keys)
        return await _monitor(spec, exp, bus, keys)
    finally:
        if watcher is not None:
            watcher.cancel()
        if bus is not None:
            bus.close()
            session = bus.session  # a new one after bus.reconnect()
        close_session(session)


def _link_auth(opts: SessionOptions, exp: Team | list[AgentSlice]) -> LinkAuth | None:
    """A secure peer's pairwise message keys (:mod:`transport.linkauth`), else None (a
    router team's router binds the estimate keys to the certificates)."""
    tls = opts.tls
    if tls is None or opts.acl is None:
        return None
    from transport.linkauth import load_link_auth, team_identities

    team = exp[0] if isinstance(exp, list) else exp
    try:
        return load_link_auth(tls.directory, tls.identity, team_identities(team.agent_ids))
    except ValueError as exc:
        raise ScenarioError(str(exc)) from None


def _stop_on_signals(loop: asyncio.AbstractEventLoop, watch_parent: bool) -> asyncio.Future[None] | None:
    """SIGINT and SIGTERM cancel the running task (and so does the parent's death, with
    ``watch_parent``: returns that watch's task, else None)."""
    task = asyncio.current_task()
    assert task is not None  # called from the role's coroutine

    def stop() -> None:
        # cancelled until it is done: asyncio.wait_for of Python 3.11 can swallow a
        # cancellation that meets its inner future's completion (then a loop waiting for
        # the team would go on)
        if not task.done():
            task.cancel()
            loop.call_later(0.1, stop)

    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
            loop.add_signal_handler(sig, stop)
    if not watch_parent:
        return None
    parent = os.getppid()

    async def watch() -> None:
        while os.getppid() == parent:
            await asyncio.sleep(0.5)
        stop()

    return asyncio.ensure_future(watch())


async def _agents(spec: ChildSpec, exp: AgentSlice | list[AgentSlice], bus: Bus, keys: Keys) -> Any:
    """The agent (or the agents: one task each over this one session) of this process,
    recording their deliveries (agents.deliveries, one file per agent) where there is a run directory."""
    from .agent import run_agent_slice

    parts = exp if isinstance(exp, list) else [exp]
    writers = []
    if spec.out_dir:
        from agents.deliveries import attach

        writers = attach([p.node for p in parts], spec.out_dir)
    try:
        if isinstance(exp, list):
            return await asyncio.gather(*(run_agent_slice(part, bus, keys, spec.cfg, rejoin=spec.rejoin) for part in exp))
        return await run_agent_slice(exp, bus, keys, spec.cfg, rejoin=spec.rejoin)
    finally:
        for w in writers:
            w.close()


async def _monitor(spec: ChildSpec, exp: Experiment, bus: Bus, keys: Keys) -> Any:
    """The monitor: its dashboard, its claim on the run directory, the rounds, and with a
    served viewer the wait after the run until SIGINT / SIGTERM."""
    from .monitor import run_monitor

    # lockstep: once it records, the monitor yields the CPU to the plant and agents, whose
    # rounds it must not slow down (its lag is bounded by the plant's MAX_AHEAD window); not
    # before: a monitor restarted on a busy machine would take tens of seconds to import,
    # read the earlier record and rejoin. Realtime: never (a starved monitor's bounded
    # queue drops the reports it cannot take: rounds lost from the record)
    conn, niced = spec.conn, spec.cfg.mode != "lockstep"

    def progress(kind: str, data: Any) -> None:
        nonlocal niced
        if kind == "round" and not niced and MONITOR_NICE:
            niced = True
            with contextlib.suppress(OSError):
                os.nice(MONITOR_NICE)
        if conn is not None:
            try:
                conn.send((kind, data))
            except (OSError, ValueError):
                pass

    out = Path(spec.out_dir) if spec.out_dir else None
    dash, options = None, spec.dashboard
    try:
        if options is not None:
            from agents.dashboard import Dashboard

            # one recording per run: its id is the run id
            dash = Dashboard(exp, run_id=spec.run_id, options=options)
            progress("urls", dict(options.urls))
        if out is not None:  # who records this run now (the launcher waits for a rejoined monitor)
            claim(out)
        res = await run_monitor(exp, bus, keys, spec.cfg, out_dir=out, progress=progress, dashboard=dash,
                                resume=spec.resume)
        if dash is not None and options is not None and options.serve_web:
            # the run is over: keep serving the recording until SIGINT / SIGTERM
            bus.close()
            progress("serving", dict(options.urls))
            await asyncio.Event().wait()
        return res
    finally:
        if dash is not None:
            dash.close()
        if out is not None:
            release(out, exp)


def _blob(b: bytes | str) -> bytes:
    return Path(b).read_bytes() if isinstance(b, str) else b


def _name_process(name: str) -> None:
    """Show the role in ``ps`` and ``top`` (the main thread's name, at most 15 bytes, on
    Linux; elsewhere nothing)."""
    with contextlib.suppress(OSError):
        with open("/proc/self/comm", "w") as f:
            f.write(name[:15])


def run_role(spec: ChildSpec) -> int:
    """Run one role in this process until the team stops; returns an exit status.

    Errors are one line on stderr naming the role: 2 bad scenario, 1 failure, 130
    interrupted (SIGINT / SIGTERM).
    """
    _name_process("rse " + spec.label)
    level = logging.DEBUG if os.environ.get("RSE_NET_DEBUG") else spec.log_level
    logging.basicConfig(level=level, format=f"%(relativeCreated)6.0f ms rse {spec.label}: %(message)s",
                        stream=sys.stderr, force=True)
    for noisy in ("zenoh", "transport"):
        logging.getLogger(noisy).setLevel(max(level, logging.INFO))
    try:
        # what the role was handed: an agent its slice(s), the plant and the monitor the
        # built experiment (or the plant's slice), pickled or in a file; nothing is built here
        exp = _agent_slice(spec) if spec.role == "agent" else _experiment(spec)
        log.debug("scenario built")
        prof_dir = os.environ.get("RSE_PROFILE")  # a directory: one cProfile dump per process
        if prof_dir:
            import cProfile

            prof = cProfile.Profile(time.thread_time)  # CPU of this thread, not waits
            try:
                prof.runcall(run_loop, _role_main(spec, exp))
            finally:
                prof.dump_stats(os.path.join(prof_dir, spec.label.replace(" ", "-") + ".prof"))
        else:
            run_loop(_role_main(spec, exp))  # on uvloop where installed (transport.event_loop)
        return EXIT_OK
    except (KeyboardInterrupt, asyncio.CancelledError):
        return EXIT_INTERRUPTED
    except (RSEError, OSError) as exc:
        _error(f"{spec.label}: {describe(exc)}")
        return exit_status(exc)
    except Exception as exc:
        if os.environ.get("RSE_DEBUG"):
            raise
        _error(f"{spec.label}: {describe(exc)}")
        return EXIT_FAILED


def _experiment(spec: ChildSpec) -> Experiment | PlantSlice:
    """The built experiment (or the plant's slice of it) handed to a plant or monitor process."""
    import pickle

    if spec.experiment is None:
        raise ScenarioError(f"{spec.label}: no experiment was handed to the process (a bug of its launcher)")
    return pickle.loads(_blob(spec.experiment))


def _agent_slice(spec: ChildSpec) -> AgentSlice | list[AgentSlice]:
    """The slice of the agent of ``spec`` (a list with several agents)."""
    from .slices import read_slice, read_slices

    if spec.agent_ids:
        parts = [p for n in spec.nodes for p in read_slices(n)]
        if [p.agent_id for p in parts] != list(spec.agent_ids):
            raise ScenarioError(f"the slices of agents {[p.agent_id for p in parts]} given to agents {list(spec.agent_ids)}")
        return parts
    if spec.node is None:
        raise ScenarioError(f"{spec.label}: no slice was handed to the process (a bug of its launcher)")
    part = read_slice(spec.node)
    if spec.agent_id is not None and part.agent_id != spec.agent_id:
        raise ScenarioError(f"the slice of agent {part.agent_id} given to agent {spec.agent_id}")
    return part


def _error(msg: str) -> None:
    """One line on stderr (Rich's styling when the process has it loaded already: a lean
    agent process does not import it for this)."""
    if "rich" in sys.modules:
        from agents.console import error

        error(msg)
    else:
        print(f"error: {msg}", file=sys.stderr, flush=True)


def child_entry(spec: ChildSpec) -> None:
    """Target of the spawned processes."""
    _die_with_parent()
    signal.signal(signal.SIGINT, signal.default_int_handler)
    code = run_role(spec)
    sys.stderr.flush()
    os._exit(code)  # multiprocessing's own exit path would try to join feeder threads
