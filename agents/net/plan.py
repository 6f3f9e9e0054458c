"""The team plan of ``rse run``: who runs where, as data.

:func:`plan_team` decides, from a built experiment and the command's choices, which
processes the team has (the plant, the monitor, one process per agent or per group of
agents), where each listens (a free loopback port per process in peer mode) or which
routers they are clients of, the Zenoh session of each, and the identities of a secure
team. It starts nothing and opens nothing; :mod:`agents.net.supervisor` starts what the
plan says and :func:`agents.net.launcher.launch` composes the two.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from estimation.errors import ScenarioError

from .child import group_label
from .startup import PEER_RETRY_MS, agent_groups, peer_links

if TYPE_CHECKING:
    from scenarios.build import Experiment
    from transport.secure import TlsFiles

    from .slices import AgentSlice

__all__ = ["TeamPlan", "plan_team", "distinct_ports"]


@dataclass(frozen=True)
class TeamPlan:
    """Who runs where (see the module docstring)."""

    run_id: str
    names: tuple[str, ...]  # every process: "plant", "monitor", then the agent processes
    groups: dict[str, tuple[int, ...]]  # agent process name -> the ids of its agents
    endpoints: dict[str, str]  # peer mode: where each process listens ({} for clients of routers)
    connect: tuple[str, ...]  # the routers every process is a client of (() in peer mode)
    sessions: dict[str, Any]  # process name -> transport.zenoh_session.SessionOptions
    router: str | None = None  # the endpoint of the router the team starts (rse run --router)
    tls: dict[str, Any] = field(default_factory=dict)  # identities (transport.secure.TlsFiles), router included
    secure: Path | None = None  # the certificate directory of a secure team

    @property
    def transport(self) -> str:
        return "client" if self.connect else "peer"


def distinct_ports(n: int) -> list[int]:
    """``n`` different free TCP ports of this host."""
    from transport.zenoh_session import free_tcp_port

    ports: list[int] = []
    while len(ports) < n:
        p = free_tcp_port()
        if p not in ports:
            ports.append(p)
    return ports


def plan_team(exp: Experiment, slices: list[AgentSlice], *, run_id: str, agents_per_process: int = 1, connect: tuple[str, ...] = (),
              router: bool = False, secure: Path | None = None) -> TeamPlan:
    """The plan of a team for ``exp`` (``slices``: the agents' slices, whose links decide
    which peers connect to which). ``router``: the team starts a router on a free loopback
    port and every process is its client; ``connect``: clients of those routers; ``secure``:
    a directory of ``rse certs`` (mutual TLS, each process its own identity; peers enforce
    their own ingress rules, or the router does)."""
    groups = {group_label(g): g for g in agent_groups(exp.agent_ids, agents_per_process)}
    names = ("plant", "monitor", *groups)
    if secure is not None and agents_per_process > 1:
        raise ScenarioError("--secure gives each agent its own identity: it cannot share a process (--agents-per-process)")
    if router and connect:
        raise ScenarioError("--router starts a router for the team: leave out --connect (or use --connect alone)")
    tls, acl = _identities(exp, names, run_id=run_id, router=router, connect=connect, secure=secure)
    router_ep = _router_endpoint(secure) if router else None
    if router_ep is not None:
        connect = (router_ep,)
    if connect:
        from transport.zenoh_session import SessionOptions

        sessions = {nm: SessionOptions.client(connect, tls=tls.get(nm)) for nm in names}
        return TeamPlan(run_id, names, groups, {}, tuple(connect), sessions, router_ep, tls, secure)
    host = {a: nm for nm, g in groups.items() for a in g}
    endpoints, sessions = _peer_sessions(names, peer_links(slices, host), tls, acl, tls_links=secure is not None)
    return TeamPlan(run_id, names, groups, endpoints, (), sessions, None, tls, secure)


def _identities(exp: Experiment, names: tuple[str, ...], *, run_id: str, router: bool, connect: tuple[str, ...],
                secure: Path | None) -> tuple[dict[str, TlsFiles], dict[str, Any] | None]:
    """The TLS identity of each process (and of the router) and a secure peer's ingress rules."""
    if secure is None:
        return {}, None
    from .secure_team import identities, peer_acl

    tls = identities(secure, list(names), router=router)
    return tls, (None if router or connect else peer_acl(secure, run_id, exp.agent_ids))


def _router_endpoint(secure: Path | None) -> str:
    from transport.secure import secure_endpoint
    from transport.zenoh_session import free_tcp_port, tcp_endpoint

    ep = tcp_endpoint(free_tcp_port())
    return secure_endpoint(ep) if secure is not None else ep


def _peer_sessions(names: tuple[str, ...], links: dict[str, set[str]], tls: dict[str, TlsFiles], acl: dict[str, Any] | None, *,
                   tls_links: bool) -> tuple[dict[str, str], dict[str, Any]]:
    """Peer mode: a loopback endpoint per process and its session.

    Each process is linked to the ones it talks to (not a full mesh): it connects to those
    that listen before it, the later ones connect to it; the monitor, which reads the whole
    experiment first, listens last (it connects to all of its links). A session opens at
    once (``scout_delay_ms=0``), not after Zenoh's 500 ms wait for a connect endpoint that is
    not listening yet: the processes start together, their links come up in the background,
    and each waits for the others' liveliness. A secure team's links are TLS, each peer
    enforcing its own ingress rules (``acl``).
    """
    from transport.zenoh_session import SessionOptions, tcp_endpoint

    endpoints = {nm: tcp_endpoint(p) for nm, p in zip(names, distinct_ports(len(names)))}
    if tls_links:
        endpoints = {nm: ep.replace("tcp/", "tls/", 1) for nm, ep in endpoints.items()}
    order = {nm: i for i, nm in enumerate([nm for nm in names if nm != "monitor"] + ["monitor"])}
    sessions = {nm: SessionOptions(mode="peer", listen=(endpoints[nm],), gossip=False, retry_ms=PEER_RETRY_MS,
                                   small_links=True, scout_delay_ms=0, tls=tls.get(nm), acl=acl,
                                   connect=tuple(endpoints[o] for o in names if o in links[nm] and order[o] < order[nm]))
                for nm in names}
    return endpoints, sessions
