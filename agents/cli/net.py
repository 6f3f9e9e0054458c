"""The networked commands of ``rse``: ``run``, ``plant``, ``agent``, ``monitor``.

Added to the group in :mod:`agents.cli`. Exit statuses
as there: 0 success, 1 failure (the message names the failed process), 2 bad input,
3 an ``[expect]`` bound failed, 130 interrupted.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from estimation.errors import ExpectationFailed, ScenarioError

from .. import api
from .common import (
    EXIT_INTERRUPTED,
    dashboard_options,
    handle_errors,
    load_experiment,
    rerun_options,
    scenario_options,
    secure_files,
    sign_dir,
    sigterm_interrupts,
    wait_while_serving,
    warn_plain,
    warn_threat_model,
)


def _run_options(fn: Callable) -> Callable:
    fn = click.option("--deadline", type=click.FloatRange(min=0.001), default=1.0, show_default=True,
                      help="Lockstep: seconds a round waits for a silent agent or a missing message.")(fn)
    fn = click.option("--rate", type=click.FloatRange(min=0.001), default=None, metavar="HZ",
                      help="Realtime: the plant's tick rate (required). Lockstep: an upper bound on rounds/s.")(fn)
    fn = click.option("--mode", type=click.Choice(["lockstep", "realtime"]), default="lockstep", show_default=True,
                      help="lockstep: equal to rse simulate; realtime: wall-clock ticks, late messages by stamp.")(fn)
    fn = click.option("--warmup", type=click.FloatRange(min=0.0), default=3.0, show_default=True,
                      help="Scenario seconds an agent joining a running team listens before it publishes.")(fn)
    fn = click.option("--startup-timeout", type=click.FloatRange(min=0.1), default=60.0, show_default=True,
                      help="Seconds to wait for the team to assemble.")(fn)
    fn = click.option("--sign", type=click.Path(file_okay=False, path_type=Path), default=None, metavar="DIR",
                      help="Sign every estimate with the keys of `rse certs DIR`: equivocation becomes evidence.")(fn)
    return fn


def _config(mode: str, rate: float | None, deadline: float, startup_timeout: float, save_estimates: bool = False,
            warmup: float = 3.0, sign: str | None = None):
    from ..net.config import RunConfig

    try:
        return RunConfig(mode=mode, rate=rate, deadline=deadline, startup_timeout=startup_timeout,
                         save_estimates=save_estimates, warmup=warmup, sign=sign)
    except ValueError as exc:
        raise ScenarioError(str(exc)) from None


def _endpoints(connect: tuple[str, ...]) -> tuple[str, ...]:
    from transport.zenoh_session import normalize_endpoint

    try:
        return tuple(normalize_endpoint(e) for e in connect)
    except ValueError as exc:
        raise ScenarioError(f"--connect: {exc}") from None


def _print_outcome(summary: dict[str, Any] | None, title: str, run_dir: Path | None = None) -> None:
    from ..console import expectations_table, health_table, summary_table
    from ..console import out as console
    from ..health import rate_line
    from ..summary import ExpectationResult

    if summary is None:
        return
    console.print(summary_table(summary, title=title))
    results = [ExpectationResult.from_dict(e) for e in summary.get("expectations", [])]
    if results:
        console.print(expectations_table(results))
    if "evidence" in summary:
        from .sim import convicted_line
        console.print(convicted_line(summary["evidence"], run_dir or Path("RUN_DIR")), soft_wrap=True)
    rej = summary.get("rejected") or {}
    if rej:
        console.print("rejected messages (sender: total, by reason): " + "; ".join(
            f"{who}: {rec.get('total', 0)} (" + ", ".join(f"{r} {n}" for r, n in rec.items() if r != "total") + ")"
            for who, rec in rej.items()))
    health = health_table(summary) if (summary.get("health") or {}).get("mode") == "realtime" else None
    if health is not None:
        console.print(health)
    perf = summary.get("performance") or {}
    if perf.get("rounds_per_s"):
        console.print(f"{perf['rounds']} rounds in {perf['elapsed_s']:.2f} s: {perf['rounds_per_s']:,.0f} rounds/s")
    line = rate_line(summary)
    if line:
        console.print(line)
    failed = [r for r in results if r.failed]
    if failed:
        raise ExpectationFailed(f"{len(failed)} of {len(results)} expectation(s) failed: " + "; ".join(r.label for r in failed))


@click.command()
@scenario_options
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Run directory (default: runs/NAME-TIMESTAMP).")
@_run_options
@click.option("--connect", multiple=True, metavar="tcp/HOST:PORT",
              help="Zenoh router(s): every process is a client of them (multi-host). Default: peers on loopback.")
@click.option("--router", "with_router", is_flag=True,
              help="Start a Zenoh router on a free loopback port; every process is its client (as across hosts).")
@click.option("--secure", type=click.Path(file_okay=False, path_type=Path), default=None, metavar="DIR",
              help="Mutual TLS on every link, certificates from `rse certs DIR`; every peer enforces its own "
                   "ingress rules (with --router or --connect: the router does).")
@click.option("--run-id", default=None, help="Run id in every key expression (default: NAME-RANDOM).")
@click.option("--agents-per-process", type=click.IntRange(min=1), default=1, show_default=True, metavar="N",
              help="Host N agents in each agent process (one Zenoh session, one task per agent): large teams.")
@click.option("--save-estimates", is_flag=True, help="Also write estimates.npy and truth.npy (every agent's estimate per round).")
@click.option("--progress/--no-progress", default=True, show_default=True, help="Show a progress bar.")
@rerun_options
@handle_errors
def run(scenario: Path, overrides: tuple[str, ...], seed: int | None, out: Path | None, mode: str, rate: float | None,
        deadline: float, startup_timeout: float, warmup: float, connect: tuple[str, ...], with_router: bool,
        secure: Path | None, sign: Path | None, run_id: str | None, agents_per_process: int, save_estimates: bool,
        progress: bool, rrd: Path | None, no_rerun: bool, viewer: bool, serve_web: bool,
        web_port: int | None, grpc_port: int | None) -> None:
    """Run SCENARIO as a team of processes over Zenoh: plant, monitor, one process per agent.

    Writes the same run directory as `rse simulate` (manifest.json, design.json,
    metrics.parquet, summary.json, the Rerun recording recording.rrd streamed by the monitor)
    plus team.json (run id, endpoints: restart a killed agent with
    `rse agent --id I --team RUN_DIR/team.json`). In lockstep mode the estimates equal
    `rse simulate`'s. With --serve-web the monitor keeps serving the recording after the
    run until Ctrl-C.
    """
    from transport.keys import validate_run_id

    from ..console import err
    from ..rundir import default_run_dir

    sigterm_interrupts()
    _config(mode, rate, deadline, startup_timeout, save_estimates, warmup)  # bad values before the experiment is built
    eps = _endpoints(connect)
    warn_plain(eps, secure)
    signing = sign_dir(sign)
    if with_router and eps:
        raise ScenarioError("--router starts a router for the team; --connect names one already running: give one of them")
    if run_id is not None:
        try:
            validate_run_id(run_id)
        except ValueError as exc:
            raise ScenarioError(f"--run-id: {exc}") from None
    from ..net.startup import prestart

    prestart()  # the children's fork server starts while the experiment is built
    exp, _ = load_experiment(scenario, overrides, seed)
    warn_threat_model(exp)
    run_dir = out or default_run_dir(exp.scenario.run.name)
    dopts = dashboard_options(run_dir, rrd, no_rerun, viewer, serve_web, web_port, grpc_port)
    from ..console import out as console

    def title(summary: dict[str, Any]) -> str:
        return (f"{exp.scenario.run.name} (rse run, {mode}): {summary['rounds'] + 1} rounds, "
                f"window t in [{exp.window[0]:g}, {exp.window[1]:g}]")

    served: dict[str, Any] = {}

    def show_urls(urls: dict[str, str]) -> None:
        for what, url in urls.items():
            console.print(f"rerun {what}: {url}", soft_wrap=True)
        served["urls"] = urls

    def while_serving(summary: dict[str, Any] | None) -> None:
        # the run is over, the monitor still serves the recording: report now, then wait
        if summary is not None:
            try:
                _print_outcome(summary, title(summary), run_dir)
            except ExpectationFailed as exc:
                served["failed"] = exc
            served["printed"] = True
        console.print(f"run directory: {run_dir}")
        wait_while_serving(served.get("urls", {}).get("web", ""))

    res = api.run_team(exp, out=run_dir, mode=mode, rate=rate, deadline=deadline, startup_timeout=startup_timeout,
                       warmup=warmup, router=with_router, connect=eps, secure=secure, run_id=run_id, progress=progress, sign=signing,
                       save_estimates=save_estimates, agents_per_process=agents_per_process, dashboard=dopts,
                       on_urls=show_urls, while_serving=while_serving, say=lambda m: err.print(m, soft_wrap=True))
    for leave in res.leaves:
        console.print(f"left during the run: {leave}")
    if served.get("printed"):
        if "failed" in served:
            raise served["failed"]
        return
    _print_outcome(res.summary(), title(res.summary()), run_dir)
    console.print(f"run directory: {run_dir}")


# ----------------------------------------------------------------- single roles


def _role_options(fn: Callable) -> Callable:
    fn = click.option("--verbose", "-v", is_flag=True, help="Log joins, leaves and rounds.")(fn)
    fn = click.option("--identity", default=None, metavar="NAME",
                      help="With --secure: whose certificate to present (default: plant, monitor or agent-ID).")(fn)
    fn = click.option("--secure", type=click.Path(file_okay=False, path_type=Path), default=None, metavar="DIR",
                      help="Mutual TLS with DIR/ca.pem, DIR/IDENTITY.pem and .key (`rse certs`): a secure peer with its "
                           "own ingress rules, or with --client a client of a secure router (tcp/ endpoints are taken "
                           "as tls/). Default: the team file's.")(fn)
    fn = click.option("--listen", default=None, metavar="tcp/HOST:PORT",
                      help="Peer mode: endpoint to listen on (default: the team file's, or a free loopback port).")(fn)
    fn = click.option("--connect", multiple=True, metavar="tcp/HOST:PORT",
                      help="Endpoints of the team's peers, or of a router with --client.")(fn)
    fn = click.option("--client", is_flag=True, help="Be a client of the router(s) given with --connect.")(fn)
    fn = click.option("--run-id", default=None, help="The team's run id (from the team file by default).")(fn)
    fn = click.option("--team", type=click.Path(path_type=Path), default=None,
                      help="team.json written by `rse run` (or its run directory): run id, scenario, endpoints.")(fn)
    fn = _run_options(fn)
    fn = click.option("--set", "overrides", multiple=True, metavar="KEY.PATH=VALUE",
                      help="Override any scenario key (as for rse run; default: the team file's).")(fn)
    fn = click.option("--seed", type=click.IntRange(min=0), default=None, help="Override run.seed.")(fn)
    fn = click.argument("scenario", required=False, type=click.Path(dir_okay=False, path_type=Path))(fn)
    return fn


def _role_spec(role: str, label: str, scenario: Path | None, overrides: tuple[str, ...], seed: int | None,
               team: Path | None, run_id: str | None, client: bool, connect: tuple[str, ...], listen: str | None,
               mode: str, rate: float | None, deadline: float, startup_timeout: float, warmup: float, verbose: bool,
               secure: Path | None = None, identity: str | None = None, _validate: bool = True, **extra: Any):
    from transport.keys import validate_run_id
    from transport.zenoh_session import normalize_endpoint, tcp_endpoint

    from ..net.child import ChildSpec
    from ..net.launcher import load_team, session_for

    sigterm_interrupts()  # a signal before the role's own handlers are up ends it the same way
    ctx = click.get_current_context()
    data: dict[str, Any] = load_team(team) if team is not None else {}
    src = lambda name: ctx.get_parameter_source(name) == click.core.ParameterSource.DEFAULT
    scenario = scenario or (Path(data["scenario"]) if data.get("scenario") else None)
    if scenario is None:
        raise ScenarioError("give SCENARIO (or --team RUN_DIR/team.json)")
    overrides = overrides or tuple(data.get("overrides", ()))
    seed = seed if seed is not None else data.get("seed")
    if data and src("mode"):
        mode = data.get("mode", mode)
    if data and src("rate"):
        rate = data.get("rate", rate)
    if data and src("deadline"):
        deadline = data.get("deadline", deadline)
    run_id = run_id or data.get("run_id")
    if not run_id:
        raise ScenarioError("give --run-id (or --team RUN_DIR/team.json)")
    try:
        validate_run_id(run_id)
    except ValueError as exc:
        raise ScenarioError(f"--run-id: {exc}") from None
    eps = _endpoints(connect)
    tls = None
    secure = secure or (Path(data["secure"]) if data.get("secure") else None)
    if secure is not None:
        from transport.secure import identity_for, validate_identity

        try:
            if extra.get("agent_ids"):
                raise ScenarioError("--secure gives each agent its own identity: run one agent per process")
            me = validate_identity(identity) if identity else identity_for(role, extra.get("agent_id"))
        except ValueError as exc:
            raise ScenarioError(f"--identity: {exc}") from None
        tls = secure_files(secure, me)
        if not (client or data or eps or listen):
            raise ScenarioError("--secure needs --connect tls/PEER:PORT or --listen tls/HOST:PORT (secure peers), "
                                "--client --connect tls/ROUTER:PORT (a secure router), or --team")
        if client and listen is not None:
            raise ScenarioError("--secure: a client of the router does not listen; leave out --listen")
    elif identity is not None:
        raise ScenarioError("--identity only applies with --secure")
    if client:
        if not eps:
            raise ScenarioError("--client needs --connect tcp/HOST:PORT (a Zenoh router)")
        session = _client_options(eps, tls)
    elif data and not eps and listen is None:
        try:
            session = session_for(data, label, tls=tls)
        except ValueError as exc:
            raise ScenarioError(f"--secure: {exc}") from None
    elif tls is not None and data.get("transport") == "client":
        session = _client_options(eps, tls)  # a secure team file: --connect names its router
    else:
        try:
            lst = normalize_endpoint(listen) if listen else (data.get("endpoints", {}).get(label) or tcp_endpoint(0))
        except ValueError as exc:
            raise ScenarioError(f"--listen: {exc}") from None
        others = eps or tuple(v for k, v in data.get("endpoints", {}).items() if k != label)
        session = _peer_options(lst, others, tls, run_id)
    warn_plain((*session.connect, *(session.listen or ())), tls)
    cfg = _config(mode, rate, deadline, startup_timeout, extra.pop("save_estimates", False), warmup,
                  sign_dir(extra.pop("sign", None) or (Path(data["sign"]) if data.get("sign") else None)))
    # built here (a bad scenario is exit status 2 with the usual message) and handed to the
    # role: the role process reads what it is given, it builds nothing
    built = None
    if _validate:
        import pickle

        exp, _ = load_experiment(scenario, overrides, seed)
        built = pickle.dumps(exp)
    return ChildSpec(role=role, scenario=str(scenario), overrides=tuple(overrides), seed=seed, run_id=run_id, cfg=cfg,
                     session=session, log_level=logging.INFO if verbose else logging.WARNING, experiment=built, **extra)


def _peer_options(listen: str, connect: tuple[str, ...], tls: Any, run_id: str) -> Any:
    """A peer on ``listen`` linked to ``connect``; with ``tls`` a secure peer (mutual TLS,
    its own ingress rules for the identities of the certificate directory)."""
    from transport.zenoh_session import SessionOptions

    acl = None
    if tls is not None:
        from ..net.secure_team import peer_acl

        acl = peer_acl(tls.directory, run_id)
    try:
        return SessionOptions(mode="peer", listen=(listen,), connect=connect, tls=tls, acl=acl)
    except ValueError as exc:
        raise ScenarioError(f"--connect/--listen: {exc}") from None


def _client_options(eps: tuple[str, ...], tls: Any) -> Any:
    from transport.zenoh_session import SessionOptions

    try:
        return SessionOptions.client(eps, tls=tls)
    except ValueError as exc:
        raise ScenarioError(f"--connect: {exc}") from None


def _run_single(spec: Any) -> None:
    from ..net.child import run_role

    code = run_role(spec)
    if code == EXIT_INTERRUPTED:
        raise KeyboardInterrupt
    sys.exit(code)


@click.command()
@_role_options
@handle_errors
def plant(**kw: Any) -> None:
    """Run the plant of SCENARIO in this process (one member of a team; see `rse run`).

    With --team (and no SCENARIO, --set or --seed) it reads the plant's slice the team
    directory holds (RUN_DIR/team/plant.pkl): no scenario file, no design."""
    cached = _cached_experiment(kw, "plant.pkl")
    spec = _role_spec("plant", "plant", _validate=cached is None, **kw)
    if cached is not None:
        spec.experiment = cached
    _run_single(spec)


@click.command()
@_role_options
@click.option("--id", "agent_spec", required=True, metavar="I[,J,...|I-J]",
              help="The agent's id (1-based, as in the scenario), or several (1,2,3 or 1-8): one process, one Zenoh "
                   "session, one task per agent.")
@handle_errors
def agent(agent_spec: str, **kw: Any) -> None:
    """Run agent --id I of SCENARIO in this process (or several: --id 1-8); joins (or
    rejoins) a running team.

    Against a team started by `rse run`: `rse agent --id 3 --team RUN_DIR/team.json`
    (reads the agent's slice RUN_DIR/team/agent-3.pkl: no scenario file, no design).
    """
    from ..net.child import group_label

    ids = parse_ids(agent_spec)
    team = kw.get("team")
    cached: bytes | None = None
    if team is not None and not kw.get("overrides") and kw.get("seed") is None and kw.get("scenario") is None:
        # the agents' slices of the launcher's built experiment: no scenario, no design, fast rejoin
        from ..net.slices import find_slices

        cached = find_slices((team if team.is_dir() else team.parent) / "team", ids)
    label = f"agent {ids[0]}" if len(ids) == 1 else group_label(ids)
    extra: dict[str, Any] = {"agent_id": ids[0]} if len(ids) == 1 else {"agent_ids": tuple(ids)}
    extra["rejoin"] = team is not None  # a team that runs: see ChildSpec.rejoin
    if team is not None:  # its delivery record goes to the team's run directory (agents.deliveries)
        extra["out_dir"] = str(team if team.is_dir() else team.parent)
    spec = _role_spec("agent", label, _validate=cached is None, **extra, **kw)
    if cached is None:
        import pickle

        from ..middleware import make_channel, make_nodes
        from ..net.slices import agent_slices, dumps_slices

        exp = pickle.loads(spec.experiment)  # built by _role_spec
        spec.experiment = None  # an agent process reads its slice, not the experiment
        missing = [a for a in ids if a not in exp.agent_ids]
        if missing:
            raise ScenarioError(f"--id {', '.join(map(str, missing))}: no such agent; agents are "
                                f"{', '.join(map(str, exp.agent_ids))}")
        by_id = {s.agent_id: s for s in agent_slices(exp, make_nodes(exp, make_channel(exp)))}  # built here once
        cached = dumps_slices([by_id[a] for a in ids])
    if len(ids) == 1:
        spec.node = cached
    else:
        spec.nodes = (cached,)
    _run_single(spec)


def parse_ids(text: str) -> list[int]:
    """``3``, ``1,2,3``, ``1-8`` or ``1-4,9``: agent ids, in order, without repeats."""
    ids: list[int] = []
    try:
        for part in str(text).split(","):
            a, sep, b = part.strip().partition("-")
            lo, hi = int(a), int(b) if sep else int(a)
            if hi < lo:
                raise ValueError
            ids += [i for i in range(lo, hi + 1) if i not in ids]
    except ValueError:
        raise ScenarioError(f"--id {text!r}: expected an agent id, a list (1,2,3) or a range (1-8)") from None
    if not ids or any(i < 0 for i in ids):
        raise ScenarioError(f"--id {text!r}: expected agent ids >= 0")
    return ids


@click.command()
@_role_options
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Where to write metrics and summary (default with --team: the team's run directory).")
@click.option("--save-estimates", is_flag=True, help="Also write estimates.npy and truth.npy.")
@rerun_options
@handle_errors
def monitor(out: Path | None, save_estimates: bool, rrd: Path | None, no_rerun: bool, viewer: bool, serve_web: bool,
            web_port: int | None, grpc_port: int | None, **kw: Any) -> None:
    """Run the monitor of SCENARIO in this process: writes metrics.parquet (streamed as the
    run goes), summary.json and the Rerun recording recording.rrd (recording id = run id)
    to --out.

    Against a team started by `rse run` (also one whose monitor died: the team goes on
    without it): `rse monitor --team RUN_DIR/team.json` rejoins it, keeps the rounds
    recorded before and records from the round it joins at; the rounds in between are
    listed in summary.json (unrecorded_rounds). Its recording is then recording-2.rrd (-3,
    ...) unless --rrd says otherwise. With --team and an --out that holds no earlier record
    (a team of rse compose) it is the team's first monitor and records from round 0.

    With --serve-web it serves the web viewer (every interface: --web-port, default 9090, and
    the gRPC endpoint the page reads, --grpc-port, default 9876), prints the URL and keeps
    serving after the run until Ctrl-C / SIGTERM.
    """
    team = kw.get("team")
    if out is None:
        if team is None:
            raise ScenarioError("give --out DIR (or --team RUN_DIR/team.json)")
        out = team if team.is_dir() else team.parent
    if team is not None and rrd is None and (out / "recording.rrd").exists():
        n = 2
        while (out / f"recording-{n}.rrd").exists():
            n += 1
        rrd = out / f"recording-{n}.rrd"
    dopts = dashboard_options(out, rrd, no_rerun, viewer, serve_web, web_port, grpc_port)
    cached = _cached_experiment(kw)
    # it rejoins where an earlier monitor of the team recorded (a fresh --out: it is the team's first)
    rejoin = team is not None and any((out / name).exists() for name in ("metrics.partial", "summary.json"))
    spec = _role_spec("monitor", "monitor", out_dir=str(out), save_estimates=save_estimates, dashboard=dopts,
                      conn=_UrlPrinter() if dopts is not None else None, resume=rejoin,
                      _validate=cached is None, **kw)
    if cached is not None:
        spec.experiment = cached
    _run_single(spec)


def _cached_experiment(kw: dict[str, Any], name: str = "experiment.pkl") -> bytes | None:
    """The experiment ``rse run`` (or ``rse compose --write-team``) built for its team
    (``RUN_DIR/team/experiment.pkl``; ``plant.pkl``: the plant's slice of it): a process
    that joins with ``--team`` and no scenario, override or seed of its own starts without
    the offline design."""
    team = kw.get("team")
    if team is None or kw.get("overrides") or kw.get("seed") is not None or kw.get("scenario") is not None:
        return None
    path = (team if team.is_dir() else team.parent) / "team" / name
    return path.read_bytes() if path.is_file() else None


class _UrlPrinter:
    """The monitor's progress channel when it runs alone: prints the dashboard's URLs."""

    def send(self, item: tuple[str, Any]) -> None:
        from ..console import out as console

        kind, data = item
        if kind == "urls":
            for what, url in data.items():
                console.print(f"rerun {what}: {url}", soft_wrap=True)
        elif kind == "serving" and data.get("web"):
            console.print(f"the run is finished; still serving the recording at {data['web']} (Ctrl-C to stop)",
                          soft_wrap=True)
