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

:func:`launch` composes three parts: the team plan (:mod:`agents.net.plan`: which processes,
where each listens, their sessions and identities), the children's specs and the run
directory's first files (:func:`_child_specs`), and the supervisor
(:mod:`agents.net.supervisor`: starting, the monitor's progress pipe, exits, leaves and
failures, signals). A process that exits with an error status is a *failure*: named in the
final message, and the exit status is non-zero; an agent or the monitor killed from outside
is a *leave*. Children also die with the launcher (``PR_SET_PDEATHSIG`` plus a parent watch).
"""

from __future__ import annotations

import contextlib
import json
import logging
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from agents.net.exits import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK
from estimation.errors import ScenarioError

from .child import ChildSpec
from .config import RunConfig
from .plan import TeamPlan, plan_team
from .recording import complete_run_dir
from .startup import PEER_RETRY_MS, child_env
from .supervisor import Outcome, Supervisor

if TYPE_CHECKING:
    from multiprocessing.connection import Connection

    from agents.dashboard import DashboardOptions
    from scenarios.build import Experiment
    from transport.secure import TlsFiles
    from transport.zenoh_session import SessionOptions

    from .slices import AgentSlice

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
            "router": self.router, "secure": self.secure, "sign": self.cfg.sign,
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


def session_for(team: dict[str, Any], me: str, *, connect: tuple[str, ...] = (), tls: TlsFiles | None = None) -> SessionOptions:
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


@dataclass(frozen=True)
class Hooks:
    """What the caller sees of a running team: ``say(line)`` the one-line notes (joins,
    leaves; None: the console's stderr), the progress bar, ``show_urls(urls)`` once the
    monitor serves the dashboard, ``while_serving(summary)`` after the run while a served
    viewer is still up (the monitor stops when it returns), ``stop_when()`` True stops the
    team as a signal would (a launch on another thread than the main one: ``rse chaos``)."""

    say: Callable[[str], None] | None = None
    progress: bool = True
    show_urls: Callable[[dict[str, str]], None] | None = None
    while_serving: Callable[[dict[str, Any] | None], None] | None = None
    stop_when: Callable[[], bool] | None = None


def launch(exp: Experiment, run_dir: Path, cfg: RunConfig, *, run_id: str | None = None, connect: tuple[str, ...] = (),
           router: bool = False, secure: Path | None = None, agents_per_process: int = 1,
           dashboard: DashboardOptions | None = None,
           hooks: Hooks = Hooks()) -> LaunchResult:
    """Start and supervise a team for the built experiment ``exp``; returns when every child
    has exited. It composes the team plan (:func:`agents.net.plan.plan_team`: ``connect``,
    ``router``, ``secure``, ``agents_per_process``), the run directory's first files and the
    children's specs (:func:`_child_specs`; ``dashboard`` the monitor's
    :class:`agents.dashboard.DashboardOptions`), the supervisor
    (:class:`agents.net.supervisor.Supervisor`) and the completed run directory (:func:`_finish`).
    """
    from agents.console import err, round_progress
    from agents.rundir import write_json
    from agents.simulate import make_channel, make_nodes

    from .slices import agent_slices

    say = hooks.say or (lambda msg: err.print(msg, soft_wrap=True))
    slices = agent_slices(exp, make_nodes(exp, make_channel(exp)))  # the nodes built once, as the simulator does
    plan = plan_team(exp, slices, run_id=run_id or safe_run_id(exp.scenario.run.name),
                     agents_per_process=agents_per_process, connect=connect, router=router, secure=secure)
    run_dir.mkdir(parents=True, exist_ok=True)
    team = Team(plan.run_id, plan.endpoints, plan.transport, plan.connect, str(exp.source), tuple(exp.overrides), None,
                cfg, router=plan.router, secure=str(Path(secure).resolve()) if secure is not None else None)
    sup = Supervisor(run_dir, exp.n_rounds, plan.run_id, say=say, show_urls=hooks.show_urls,
                     while_serving=hooks.while_serving, stop_when=hooks.stop_when)
    base = dict(scenario=team.scenario, overrides=team.overrides, seed=None, run_id=plan.run_id, cfg=cfg, watch_parent=True)
    specs = _child_specs(run_dir, exp, plan, cfg, slices, base=base, conn=sup.send_conn, dashboard=dashboard)

    def started(pids: dict[str, int]) -> None:
        team.pids = pids
        write_json(run_dir / "team.json", team.as_dict())
        say(f"run {plan.run_id}: {exp.N} agents, {cfg.mode}"
            + (f" at {cfg.rate:g} Hz" if cfg.rate else "") + f"; team file {run_dir / 'team.json'}")

    router_args = None if plan.router is None else (
        plan.router, plan.tls.get("router"), {"agent_ids": tuple(exp.agent_ids), "run_id": plan.run_id})
    with round_progress(exp.n_rounds + 1, exp.scenario.run.name, enabled=hooks.progress) as update:
        out = sup.run(specs, router=router_args, on_started=started, update=update)
    if not out.pids:  # interrupted while the router started: nothing ran
        return LaunchResult(EXIT_INTERRUPTED, run_dir, plan.run_id, None, out.failures, out.leaves)
    return _finish(run_dir, exp, plan.run_id, out)


def _child_specs(run_dir: Path, exp: Experiment, plan: TeamPlan, cfg: RunConfig, slices: list[AgentSlice], *,
                 base: dict[str, Any], conn: Connection, dashboard: DashboardOptions | None) -> dict[str, ChildSpec]:
    """Write the run directory's first files (``manifest.json``, ``design.json``) and what the
    children read (``team/``: the pickled experiment for the monitor, the plant's slice, one
    slice file per agent process), and return each process's :class:`ChildSpec`."""
    import pickle

    from agents.rundir import write_design, write_manifest

    from .slices import plant_slice, write_slices

    write_manifest(run_dir, exp, exp.frozen or {}, driver="run", run_id=plan.run_id,
                   extra={"mode": cfg.mode, "rate": cfg.rate, "deadline": cfg.deadline, "endpoints": plan.endpoints,
                          "connect": list(plan.connect), "router": plan.router, "secure": plan.secure is not None})
    write_design(run_dir, exp)
    cache = run_dir / "team"
    cache.mkdir(exist_ok=True)
    (cache / "experiment.pkl").write_bytes(pickle.dumps(exp))
    child_env()
    plant_pkl = cache / "plant.pkl"  # the plant's slice: no scenario schema in the plant process
    plant_pkl.write_bytes(pickle.dumps(plant_slice(exp), protocol=pickle.HIGHEST_PROTOCOL))
    sessions = plan.sessions
    specs = {
        "plant": ChildSpec(role="plant", session=sessions["plant"], experiment=str(plant_pkl.resolve()), **base),
        "monitor": ChildSpec(role="monitor", session=sessions["monitor"], out_dir=str(run_dir), conn=conn,
                             dashboard=dashboard, experiment=str((cache / "experiment.pkl").resolve()), **base),
    }
    # each agent reads its slice (as does `rse agent --team`, for a fast rejoin), not the experiment
    paths = write_slices(cache, slices, list(plan.groups.values()))  # one file per agent process
    agent_base = base | ({"out_dir": str(run_dir)} if cfg.deliveries else {})
    for nm, g in plan.groups.items():
        if len(g) == 1:
            specs[nm] = ChildSpec(role="agent", agent_id=g[0], session=sessions[nm], node=str(paths[g[0]]), **agent_base)
        else:
            specs[nm] = ChildSpec(role="agent", agent_ids=g, nodes=(str(paths[g[0]]),), session=sessions[nm],
                                  **agent_base)
    return specs


def _finish(run_dir: Path, exp: Experiment, run_id: str, out: Outcome) -> LaunchResult:
    """Complete the run directory after the team ended and decide the exit status."""
    status = EXIT_INTERRUPTED if out.stopping else (EXIT_FAILED if out.failures else EXIT_OK)
    complete_run_dir(run_dir, exp, plant_failed=out.plant_failed, stopping=out.stopping, children=set(out.pids.values()))
    summary = None
    with contextlib.suppress(OSError, ValueError):
        summary = json.loads((run_dir / "summary.json").read_text())
    if summary is None and status == EXIT_OK:
        out.failures.append("the monitor wrote no summary")
        status = EXIT_FAILED
    elif summary is not None and summary.get("complete") is False and status == EXIT_OK:
        # the team finished, but its record did not: no monitor ran at the end
        out.failures.append(f"the run's record is incomplete: {summary.get('reason')} (rounds recorded up to "
                            f"{summary.get('last_round')}; {run_dir / 'metrics.parquet'})")
        status = EXIT_FAILED
    return LaunchResult(status, run_dir, run_id, summary, out.failures, out.leaves)
