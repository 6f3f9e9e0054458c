"""``rse run``: one process per role of a scenario, supervised.

The launcher builds the experiment once (to validate the scenario and write
``manifest.json`` / ``design.json``, the offline design included), writes each agent's
slice of it (:mod:`agents.net.slices`, ``RUN_DIR/team/agent-I.pkl``), picks one free
loopback port per process, and starts the plant, the monitor and one process per agent
with the ``spawn`` start method (:mod:`agents.net.child`; the children do not re-import
the launching program's ``__main__``, so an agent process imports no CLI library). It
opens no Zenoh session itself: every session lives in a child (:func:`run_role`), which
listens on its port and connects to every other member's port (Zenoh peers on loopback,
multicast scouting off), or is a client of the routers given with ``--connect``.

With ``router=True`` (``rse run --router``) it first starts a Zenoh router as a child
process (:func:`agents.net.router.router_entry`) on a free loopback port and every
process is a client of it. With ``secure`` (``rse run --secure DIR``) each process presents
its own certificate from ``DIR`` on mutual-TLS links: peers that each enforce their own
ingress rules (:mod:`agents.net.secure_team`), or with ``router`` clients of a router that
enforces them.

It writes ``team.json`` to the run directory (run id, endpoints, process ids) so that a
killed agent can be restarted by hand against the running team::

    rse agent --id 3 --team RUN_DIR/team.json

Supervision: the monitor reports progress over a pipe (rounds/s and the worst current
error on the progress bar, joins and leaves); the launcher polls its children. An agent
that is killed by a signal from outside is a *leave*: the team goes on without it. A
process that exits with an error status is a *failure*: named in the final message, and
the exit status is non-zero; a failed plant or monitor stops the run. On SIGINT or
SIGTERM every child gets SIGTERM, then SIGKILL 1 s later; the launcher joins all of them
(no orphan), and children also die with the launcher (``PR_SET_PDEATHSIG`` plus a parent
watch).
"""

from __future__ import annotations

import contextlib
import json
import logging
import signal
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from agents.net.exits import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK
from estimation.errors import RSEError, ScenarioError

from .child import ChildSpec, child_entry, group_label
from .protocol import RunConfig
from .recording import complete_run_dir
from .startup import PEER_RETRY_MS, agent_groups, bare_main, child_env, context, peer_links

log = logging.getLogger("rse.net")

STOP_GRACE_S = 1.0  # SIGTERM -> SIGKILL
END_GRACE_S = 5.0  # after the monitor finished, how long the others may take to exit


def safe_run_id(name: str) -> str:
    stem = "".join(c if c.isalnum() or c in "_.-" else "-" for c in name)[:40].strip("-_.") or "run"
    return f"{stem}-{uuid.uuid4().hex[:8]}"


# ------------------------------------------------------------------------ launcher side


@dataclass
class Team:
    run_id: str
    endpoints: dict[str, str]
    mode: str
    connect: tuple[str, ...]
    scenario: str
    overrides: tuple[str, ...]
    seed: int | None
    cfg: RunConfig
    pids: dict[str, int] = field(default_factory=dict)
    router: str | None = None  # the endpoint of the router started by rse run --router
    secure: str | None = None  # the certificate directory of rse run --secure

    def as_dict(self) -> dict[str, Any]:
        return {
            "run_id": self.run_id, "endpoints": self.endpoints, "transport": self.mode, "connect": list(self.connect),
            "scenario": self.scenario, "overrides": list(self.overrides), "seed": self.seed,
            "mode": self.cfg.mode, "rate": self.cfg.rate, "deadline": self.cfg.deadline, "pids": self.pids,
            "router": self.router, "secure": self.secure,
        }


def load_team(path: Path) -> dict[str, Any]:
    """Read ``team.json`` (written by ``rse run``)."""
    p = Path(path)
    if p.is_dir():
        p = p / "team.json"
    try:
        data = json.loads(p.read_text())
    except FileNotFoundError:
        raise ScenarioError(f"{p}: no such team file (rse run writes RUN_DIR/team.json)") from None
    except (OSError, ValueError) as exc:
        raise ScenarioError(f"{p}: cannot read the team file: {exc}") from None
    if not isinstance(data, dict) or "run_id" not in data or "endpoints" not in data:
        raise ScenarioError(f"{p}: not a team file (no run_id / endpoints)")
    return data


def session_for(team: dict[str, Any], me: str, *, connect: tuple[str, ...] = (), tls: Any = None) -> Any:
    """Session options of process ``me`` (e.g. ``"agent 3"``) joining ``team``; ``tls``
    (a :class:`transport.secure.TlsFiles`) for a secure team."""
    from transport.zenoh_session import SessionOptions, any_port, tcp_endpoint

    if connect or team.get("transport") == "client":
        return SessionOptions.client(connect or tuple(team.get("connect", ())), tls=tls)
    acl = None
    if tls is not None:  # a secure peer-to-peer team: its own ingress rules, as the others'
        from .secure_team import peer_acl

        acl = peer_acl(tls.directory, team["run_id"])
    eps = team["endpoints"]
    listen = eps.get(me, tcp_endpoint(0))
    if me == "monitor":
        # A monitor that joins a running team listens on a port of its own host that the OS
        # chooses, not on its endpoint in the team file: it connects out to every process,
        # and nobody dials its new port, so no pair of processes links twice. (It was chosen
        # while the restarted monitor's missing reports were thought to be its own doing;
        # they came from agents whose measurements had stopped: see
        # AgentProcess._measurements_stopped.) A restarted agent stays on its endpoint: the
        # linked processes started after it dial that one again (on a port of its own, 5 of
        # 20 never heard the plant).
        listen = any_port(listen)
    # connect to every process of the team (each link that this process does not use costs
    # little), retrying soon those that are not listening yet; unlike the sessions rse run
    # opens (gossip off, each linked pair connecting one way), Zenoh's gossip stays on here
    return SessionOptions(mode="peer", listen=(listen,), connect=tuple(v for k, v in eps.items() if k != me),
                          retry_ms=PEER_RETRY_MS, small_links=True, tls=tls, acl=acl)


@dataclass
class LaunchResult:
    status: int
    run_dir: Path
    run_id: str
    summary: dict[str, Any] | None
    failures: list[str]
    leaves: list[str]


def _distinct_ports(n: int) -> list[int]:
    from transport.zenoh_session import free_tcp_port

    ports: list[int] = []
    while len(ports) < n:
        p = free_tcp_port()
        if p not in ports:
            ports.append(p)
    return ports


def _describe_exit(code: int | None) -> str:
    if code is None:
        return "still running"
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit status {code}"


def launch(
    scenario: Path,
    overrides: tuple[str, ...],
    seed: int | None,
    run_dir: Path,
    cfg: RunConfig,
    *,
    connect: tuple[str, ...] = (),
    progress: bool = True,
    run_id: str | None = None,
    exp: Any = None,
    frozen: dict | None = None,
    say: Any = None,
    dashboard: Any = None,
    show_urls: Any = None,
    while_serving: Any = None,
    router: bool = False,
    secure: Path | None = None,
    agents_per_process: int = 1,
) -> LaunchResult:
    """Start and supervise the team; returns when every child has exited.

    agents_per_process : agents hosted by each agent process (one Zenoh session, one
        asyncio task and node per agent, the same keys and messages); 1: one process each

    router : start a Zenoh router child on a free loopback port; every process is its client
    secure : a directory of ``rse certs``: mutual TLS, each process with its own identity;
        peers with their own ingress rules, or clients of the router of ``connect`` / ``router``

    dashboard : the monitor's :class:`agents.dashboard.DashboardOptions` (None: no Rerun output)
    show_urls : called with the dashboard's URLs once the monitor serves them
    while_serving : with ``dashboard.serve_web``, called with the summary once the run is
        over while the monitor still serves the recording; the monitor stops when it returns
    """
    from agents.console import err, round_progress
    from agents.rundir import write_design, write_json, write_manifest
    from transport.zenoh_session import SessionOptions, tcp_endpoint

    say = say or (lambda msg: err.print(msg, soft_wrap=True))
    if exp is None:
        from agents.runs import load_experiment

        exp, frozen = load_experiment(scenario, overrides, seed)
    from agents.simulate import make_channel, make_nodes

    from .slices import agent_slices, plant_slice, write_slices

    # the nodes built once, as the simulator does; each agent gets its own slice
    slices = agent_slices(exp, make_nodes(exp, make_channel(exp)))
    run_id = run_id or safe_run_id(exp.scenario.run.name)
    run_dir.mkdir(parents=True, exist_ok=True)
    groups = agent_groups(exp.agent_ids, agents_per_process)
    group_of = {group_label(g): g for g in groups}
    host = {a: nm for nm, g in group_of.items() for a in g}
    names = ["plant", "monitor"] + list(group_of)
    tls: dict[str, Any] = {nm: None for nm in names}
    if secure is not None and agents_per_process > 1:
        raise ScenarioError("--secure gives each agent its own identity: it cannot share a process (--agents-per-process)")
    acl = None
    if secure is not None:
        from .secure_team import identities, peer_acl

        tls = identities(secure, names, router=router)
        acl = None if router or connect else peer_acl(secure, run_id, exp.agent_ids)
    router_ep = None
    if router:
        if connect:
            raise ScenarioError("--router starts a router for the team: leave out --connect (or use --connect alone)")
        from transport.secure import secure_endpoint
        from transport.zenoh_session import free_tcp_port

        router_ep = tcp_endpoint(free_tcp_port())
        if secure is not None:
            router_ep = secure_endpoint(router_ep)
        connect = (router_ep,)
    if connect:
        endpoints: dict[str, str] = {}
        sessions = {nm: SessionOptions.client(connect, tls=tls[nm]) for nm in names}
    else:
        ports = _distinct_ports(len(names))
        endpoints = {nm: tcp_endpoint(p) for nm, p in zip(names, ports)}
        if secure is not None:  # secure peer-to-peer: TLS links, each peer's own ingress rules
            endpoints = {nm: ep.replace("tcp/", "tls/", 1) for nm, ep in endpoints.items()}
        # each process linked to the ones it talks to (not a full mesh): it connects to
        # those that listen before it, the later ones connect to it; the monitor, which
        # reads the whole experiment first, listens last (it connects to all of its links)
        links = peer_links(slices, host)
        order = {nm: i for i, nm in enumerate([nm for nm in names if nm != "monitor"] + ["monitor"])}
        # a session opens at once (scout_delay_ms=0), not after Zenoh's 500 ms wait for a
        # connect endpoint that is not listening yet: the processes start together, their
        # links come up in the background, and each waits for the others' liveliness
        sessions = {nm: SessionOptions(mode="peer", listen=(endpoints[nm],), gossip=False, retry_ms=PEER_RETRY_MS,
                                       small_links=True, scout_delay_ms=0, tls=tls[nm], acl=acl,
                                       connect=tuple(endpoints[o] for o in names if o in links[nm] and order[o] < order[nm]))
                    for nm in names}
    team = Team(run_id, endpoints, "client" if connect else "peer", tuple(connect), str(scenario), tuple(overrides), seed, cfg,
                router=router_ep, secure=str(Path(secure).resolve()) if secure is not None else None)
    write_manifest(run_dir, exp, frozen or {}, driver="run", run_id=run_id,
                   extra={"mode": cfg.mode, "rate": cfg.rate, "deadline": cfg.deadline, "endpoints": endpoints,
                          "connect": list(connect), "router": router_ep, "secure": secure is not None})
    write_design(run_dir, exp)

    ctx = context()
    recv_conn, send_conn = ctx.Pipe(duplex=False)
    import pickle

    base = dict(scenario=str(scenario), overrides=tuple(overrides), seed=seed, run_id=run_id, cfg=cfg, watch_parent=True,
                experiment=pickle.dumps(exp))
    cache = run_dir / "team"
    cache.mkdir(exist_ok=True)
    (cache / "experiment.pkl").write_bytes(base["experiment"])
    base["experiment"] = str((cache / "experiment.pkl").resolve())
    child_env()
    plant_pkl = cache / "plant.pkl"  # the plant's slice: no scenario schema in the plant process
    plant_pkl.write_bytes(pickle.dumps(plant_slice(exp), protocol=pickle.HIGHEST_PROTOCOL))
    specs = {
        "plant": ChildSpec(role="plant", session=sessions["plant"], **{**base, "experiment": str(plant_pkl.resolve())}),
        "monitor": ChildSpec(role="monitor", session=sessions["monitor"], out_dir=str(run_dir), conn=send_conn,
                             dashboard=dashboard, **base),
    }
    # each agent reads its slice (as does `rse agent --team`, for a fast rejoin), not the experiment
    paths = write_slices(cache, slices, groups)  # one file per agent process
    agent_base = {k: v for k, v in base.items() if k != "experiment"} | ({"out_dir": str(run_dir)} if cfg.deliveries else {})
    for nm, g in group_of.items():
        if len(g) == 1:
            specs[nm] = ChildSpec(role="agent", agent_id=g[0], session=sessions[nm], node=str(paths[g[0]]), **agent_base)
        else:
            specs[nm] = ChildSpec(role="agent", agent_ids=g, nodes=(str(paths[g[0]]),), session=sessions[nm],
                                  **agent_base)
    procs: dict[str, Any] = {}
    failures: list[str] = []
    leaves: list[str] = []
    noted: set[str] = set()
    stopping: list[int] = []
    prev_handlers: dict[int, Any] = {}
    serving = False

    def on_signal(signum: int, frame: Any) -> None:
        stopping.append(signum)

    in_main = _is_main_thread()
    if in_main:
        for sig in (signal.SIGINT, signal.SIGTERM):
            prev_handlers[sig] = signal.signal(sig, on_signal)
    status = EXIT_OK
    router_proc = None
    plant_failed: str | None = None
    try:
        if router_ep is not None:
            router_proc = _start_router(ctx, router_ep, tls.get("router"), exp.agent_ids, run_id, stopping)
            if router_proc is None:  # interrupted while it started
                return LaunchResult(EXIT_INTERRUPTED, run_dir, run_id, None, failures, leaves)
        for name in ["monitor", *(nm for nm in names if nm != "monitor")]:  # the slowest to start first
            p = ctx.Process(target=child_entry, args=(specs[name],), name=f"rse-{name.replace(' ', '-')}", daemon=True)
            with bare_main():
                p.start()
            procs[name] = p
        send_conn.close()  # the monitor holds the writing end now
        team.pids = {nm: p.pid for nm, p in procs.items()}
        if router_proc is not None:
            team.pids["router"] = router_proc.pid
        write_json(run_dir / "team.json", team.as_dict())
        say(f"run {run_id}: {exp.N} agents, {cfg.mode}"
            + (f" at {cfg.rate:g} Hz" if cfg.rate else "") + f"; team file {run_dir / 'team.json'}")
        status_path = run_dir / "status.json"
        last_status = 0.0
        monitor_done_at: float | None = None
        k_now, worst = -1, float("nan")
        with round_progress(exp.n_rounds + 1, exp.scenario.run.name, enabled=progress) as update:
            while True:
                if stopping:
                    break
                try:
                    ready = recv_conn.poll(0.1)
                except (OSError, EOFError):
                    ready = False
                while ready:
                    try:
                        kind, data = recv_conn.recv()
                    except (EOFError, OSError):
                        break
                    if kind == "round":
                        k_now, worst = data
                        update(k_now, worst)
                    elif kind == "urls" and show_urls is not None:
                        show_urls(data)
                    elif kind == "serving":
                        serving = True
                        noted.add("monitor")
                        monitor_done_at = monitor_done_at or time.monotonic()
                    elif (kind == "member" and data["role"] == "agent" and 0 < data["round"]
                          and k_now < exp.n_rounds):  # not the processes leaving after the last round
                        say(f"agent {data['id']} {'joined' if data['event'] == 'join' else 'left'} (round {data['round']})")
                    try:
                        ready = recv_conn.poll(0)
                    except (OSError, EOFError):
                        ready = False
                now = time.monotonic()
                if now - last_status > 0.5:
                    last_status = now
                    with contextlib.suppress(OSError):
                        write_json(status_path, {"run_id": run_id, "round": k_now, "worst_error_inf": worst, "time": time.time()})
                fatal = False
                for name, p in procs.items():
                    if name in noted or p.exitcode is None:
                        continue
                    noted.add(name)
                    code = p.exitcode
                    if code == 0:
                        if name == "monitor":
                            monitor_done_at = now
                        continue
                    if name.startswith("agent") and code < 0 and monitor_done_at is None:
                        leaves.append(f"{name} ({_describe_exit(code)})")
                        say(f"{name} was {_describe_exit(code)}; the team goes on without it")
                        continue
                    if name == "monitor" and code < 0:
                        # the monitor only records: the team goes on, and a monitor restarted
                        # against the team rejoins (the rounds in between are not recorded)
                        leaves.append(f"{name} ({_describe_exit(code)})")
                        say(f"the monitor was {_describe_exit(code)}; the team goes on without it "
                            f"(rejoin: rse monitor --team {run_dir / 'team.json'})")
                        continue
                    failures.append(f"{name} failed ({_describe_exit(code)})")
                    if name == "plant":  # the plant is the physics: the run ends
                        fatal = True
                        plant_failed = f"the plant failed ({_describe_exit(code)})"
                if router_proc is not None and router_proc.exitcode is not None:
                    failures.append(f"the router failed ({_describe_exit(router_proc.exitcode)})")
                    fatal = True
                if fatal:
                    break
                if all(p.exitcode is not None for nm, p in procs.items() if not (serving and nm == "monitor")):
                    if serving and while_serving is not None and not failures:
                        summary = None
                        with contextlib.suppress(OSError, ValueError):
                            summary = json.loads((run_dir / "summary.json").read_text())
                        while_serving(summary)
                    break
                if monitor_done_at is not None and now - monitor_done_at > END_GRACE_S:
                    late = [nm for nm, p in procs.items() if p.exitcode is None and not (serving and nm == "monitor")]
                    failures.append(f"{', '.join(late)} did not stop after the end of the run")
                    break
    finally:
        # the router within the same grace period (it is last: the others leave first)
        _stop_all(procs if router_proc is None else {**procs, "router": router_proc})
        if router_proc is not None:
            with contextlib.suppress(Exception):
                router_proc.close()
        for name, p in procs.items():
            if name not in noted and p.exitcode not in (None, 0) and not stopping:
                if not (name.startswith("agent") and p.exitcode < 0):
                    failures.append(f"{name} failed ({_describe_exit(p.exitcode)})")
        for p in procs.values():
            with contextlib.suppress(Exception):
                p.close()
        for c in (recv_conn, send_conn):
            with contextlib.suppress(OSError):
                c.close()
        if in_main:
            for sig, h in prev_handlers.items():
                signal.signal(sig, h)
    if stopping:
        status = EXIT_INTERRUPTED
    elif failures:
        status = EXIT_FAILED
    complete_run_dir(run_dir, exp, plant_failed=plant_failed, stopping=bool(stopping), children=set(team.pids.values()))
    summary = None
    with contextlib.suppress(OSError, ValueError):
        summary = json.loads((run_dir / "summary.json").read_text())
    if summary is None and status == EXIT_OK:
        failures.append("the monitor wrote no summary")
        status = EXIT_FAILED
    elif summary is not None and summary.get("complete") is False and status == EXIT_OK:
        # the team finished, but its record did not: no monitor ran at the end
        failures.append(f"the run's record is incomplete: {summary.get('reason')} (rounds recorded up to "
                        f"{summary.get('last_round')}; {run_dir / 'metrics.parquet'})")
        status = EXIT_FAILED
    return LaunchResult(status, run_dir, run_id, summary, failures, leaves)


ROUTER_START_S = 15.0  # how long the router child may take to open


def _start_router(ctx: Any, endpoint: str, tls: Any, agent_ids: Any, run_id: str, stopping: list[int]) -> Any:
    """Start the router child of ``rse run --router`` and wait until its session is open.

    Returns the process (``None`` if a signal arrived meanwhile); raises
    :class:`RSEError` if it exits or does not open within :data:`ROUTER_START_S`.
    """
    ready = ctx.Event()
    args = {"listen": (endpoint,), "secure": tls, "agent_ids": tuple(agent_ids), "run_id": run_id}
    from .router import router_entry

    p = ctx.Process(target=router_entry, args=(args, ready), name="rse-router", daemon=True)
    with bare_main():
        p.start()
    end = time.monotonic() + ROUTER_START_S
    while not ready.wait(0.05):
        if stopping or p.exitcode is not None or time.monotonic() > end:
            why = None if stopping else ("it exited with " + _describe_exit(p.exitcode) if p.exitcode is not None
                                         else f"it did not open within {ROUTER_START_S:g} s")
            _stop_all({"router": p})
            if why is None:
                return None
            raise RSEError(f"the router on {endpoint} did not start: {why}")
    return p


def _is_main_thread() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()


def _stop_all(procs: dict[str, Any]) -> None:
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
