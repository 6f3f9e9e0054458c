"""TLS identities and the router's access control (``--secure DIR``).

A secure team is a star: every process (plant, monitor, agents) is a client of one Zenoh
router over TLS with mutual authentication; each process presents its own certificate,
whose common name is its *identity* (``router``, ``plant``, ``monitor``, ``agent-3``).
``rse certs DIR`` writes them (:mod:`transport.certs`)::

    DIR/ca.pem                       the certificate authority (everyone trusts it)
    DIR/{identity}.pem, .key         one certificate and private key per process

The router enforces Zenoh's ``access_control`` (:func:`access_control`): default deny;
each identity may put, declare, subscribe to and receive only what its role needs, so an
agent cannot speak for another agent or for the plant, and nobody but the monitor hears
the true state. Without credentials a process cannot open a session at all.

Zenoh's configuration keys (zenoh 1.x): ``transport/link/tls/{root_ca_certificate,
listen_certificate, listen_private_key, connect_certificate, connect_private_key,
enable_mtls}`` and ``access_control/{enabled, default_permission, rules, subjects,
policies}``; a rule's key expression must *include* a message's key expression to apply.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = [
    "CA_FILE",
    "TlsFiles",
    "identity_for",
    "validate_identity",
    "tls_files",
    "tls_settings",
    "secure_endpoint",
    "agent_ids_in",
    "access_control",
    "ROLE_RULES",
    "OPEN_ESTIMATES",
]

CA_FILE = "ca.pem"
_IDENTITY_RE = re.compile(r"(?:router|plant|monitor|agent-(?:0|[1-9][0-9]{0,4}))\Z")
_AGENT_PEM_RE = re.compile(r"agent-(0|[1-9][0-9]{0,4})\.pem\Z")


def identity_for(role: str, agent_id: int | None = None) -> str:
    """The default identity of a role: ``plant``, ``monitor``, ``router``, ``agent-{id}``."""
    if role == "agent":
        if type(agent_id) is not int or agent_id < 0:
            raise ValueError(f"an agent's identity needs its id, got {agent_id!r}")
        return f"agent-{agent_id}"
    return validate_identity(role)


def validate_identity(name: str) -> str:
    """Return ``name`` if it is an identity (``router``, ``plant``, ``monitor``,
    ``agent-{i}``), else raise ``ValueError`` (it names files and certificate subjects)."""
    if not isinstance(name, str) or not _IDENTITY_RE.match(name):
        raise ValueError(f"invalid identity {name!r}: expected router, plant, monitor or agent-I (I a canonical integer)")
    return name


@dataclass(frozen=True)
class TlsFiles:
    """The three files of one identity (absolute paths; picklable for spawned children).

    Attributes
    ----------
    ca, cert, key : str
        ``DIR/ca.pem``, ``DIR/{identity}.pem``, ``DIR/{identity}.key``.
    identity : str
        The common name of ``cert``.
    """

    ca: str
    cert: str
    key: str
    identity: str

    @property
    def directory(self) -> Path:
        return Path(self.cert).parent


def tls_files(directory: str | Path, identity: str) -> TlsFiles:
    """The files of ``identity`` in ``directory``, checked to exist and be readable.

    Raises ``ValueError`` naming the directory and every missing file (and the command
    that writes them).
    """
    validate_identity(identity)
    d = Path(directory).expanduser()
    if not d.is_dir():
        raise ValueError(f"--secure {d}: no such directory (write one with `rse certs {d} --scenario SCENARIO`)")
    paths = [d / CA_FILE, d / f"{identity}.pem", d / f"{identity}.key"]
    missing = [p.name for p in paths if not p.is_file()]
    if missing:
        raise ValueError(f"--secure {d}: missing {', '.join(missing)} for identity {identity!r} "
                         f"(write them with `rse certs {d} --scenario SCENARIO`)")
    unreadable = [p.name for p in paths if not _readable(p)]
    if unreadable:
        raise ValueError(f"--secure {d}: cannot read {', '.join(unreadable)} (permissions?)")
    ca, cert, key = (str(p.resolve()) for p in paths)
    return TlsFiles(ca=ca, cert=cert, key=key, identity=identity)


def _readable(p: Path) -> bool:
    try:
        with open(p, "rb") as f:
            f.read(1)
        return True
    except OSError:
        return False


def tls_settings(files: TlsFiles, *, listen: bool = True, connect: bool = True) -> dict[str, Any]:
    """Zenoh configuration keys (for ``Config.insert_json5``) of mutual TLS with ``files``:
    the CA both sides check against, this process's certificate and key for the links it
    accepts (``listen``) and opens (``connect``)."""
    out: dict[str, Any] = {
        "transport/link/tls/root_ca_certificate": files.ca,
        "transport/link/tls/enable_mtls": True,
    }
    if listen:
        out["transport/link/tls/listen_certificate"] = files.cert
        out["transport/link/tls/listen_private_key"] = files.key
    if connect:
        out["transport/link/tls/connect_certificate"] = files.cert
        out["transport/link/tls/connect_private_key"] = files.key
    return out


def secure_endpoint(endpoint: str) -> str:
    """``tcp/HOST:PORT`` -> ``tls/HOST:PORT``; ``tls/...`` unchanged; anything else is a
    ``ValueError`` (a secure team speaks TLS only)."""
    proto, sep, addr = endpoint.partition("/")
    if sep and proto == "tls":
        return endpoint
    if sep and proto == "tcp":
        return f"tls/{addr}"
    raise ValueError(f"{endpoint!r}: with --secure every endpoint is tls/HOST:PORT (or tcp/HOST:PORT, taken as tls)")


def agent_ids_in(directory: str | Path) -> list[int]:
    """The agent ids ``i`` of the ``agent-{i}.pem`` certificates in ``directory``, sorted."""
    d = Path(directory)
    try:
        names = [p.name for p in d.iterdir()]
    except OSError:
        return []
    return sorted(int(m.group(1)) for m in map(_AGENT_PEM_RE.match, names) if m)


#: What each role may do, for the documentation table and :func:`access_control`:
#: (message kinds, flow, key expressions under ``rse/{run}``), ``{i}`` the agent's id.
ROLE_RULES: dict[str, list[tuple[tuple[str, ...], str, tuple[str, ...]]]] = {
    "plant": [
        (("put",), "ingress", ("plant/**", "ctl/*/plant")),
        (("liveliness_token",), "ingress", ("alive/plant/0",)),
        (("declare_subscriber",), "ingress", ("ctl/**",)),
        (("put",), "egress", ("ctl/**",)),
    ],
    "monitor": [
        (("put",), "ingress", ("ctl/*/monitor",)),
        (("liveliness_token",), "ingress", ("alive/monitor/0",)),
        (("declare_subscriber",), "ingress", ("plant/truth", "ctl/**")),
        (("put",), "egress", ("plant/truth", "ctl/**")),
    ],
    "agent": [
        (("put",), "ingress", ("agent/{i}/**", "ctl/*/{i}")),
        (("liveliness_token",), "ingress", ("alive/agent/{i}",)),
        (("declare_subscriber",), "ingress", ("plant/loc/{i}", "agent/**", "ctl/done/*")),
        (("put",), "egress", ("plant/loc/{i}", "agent/**", "ctl/done/*")),
    ],
    # every identity: watch who is alive, see the tokens, learn where the subscribers are
    # (a declared publisher of a client sends only where it knows of a subscriber)
    "everyone": [
        (("declare_liveliness_subscriber", "liveliness_query"), "ingress", ("alive/**",)),
        (("liveliness_token", "declare_subscriber"), "egress", ("**",)),
    ],
}


#: a secure peer's ingress of estimates and done reports: from any agent of the team, each
#: receiver then checking who sealed it (:mod:`transport.linkauth`) and counting what it rejects
OPEN_ESTIMATES = ("agent/**", "ctl/done/*", "ctl/*/{i}")


def access_control(agent_ids: Iterable[int], *, run_id: str = "*", open_estimates: bool = False) -> dict[str, Any]:
    """The router's ``access_control`` section: default deny, and :data:`ROLE_RULES` for
    the identities ``plant``, ``monitor`` and ``agent-{i}`` (``i`` in ``agent_ids``).

    Parameters
    ----------
    agent_ids : iterable of int
        The agents that may join.
    run_id : str
        The run the rules are for; ``*`` (default) is any run (one chunk of the key).
    open_estimates : bool
        A secure peer's rules: every agent may put estimates and done reports
        (:data:`OPEN_ESTIMATES`) on whosever keys, for the receiver to authenticate and
        count (:mod:`transport.linkauth`); the router's rules bind them to the certificate.

    Notes
    -----
    Each identity is a subject matched by its certificate's common name (``cert_common_names``).
    A put is checked twice at the router: ``ingress`` from the sender, ``egress`` to each
    receiver; a subscription must be included in an allowed key expression to be declared.
    """
    if run_id != "*":
        from transport.keys import validate_run_id

        validate_run_id(run_id)
    root = f"rse/{run_id}"
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []

    def add(identity: str, role: str, i: int | None = None) -> None:
        ids = []
        for n, (messages, flow, keys) in enumerate(ROLE_RULES[role]):
            if open_estimates and role == "agent" and flow == "ingress" and messages == ("put",):
                keys = OPEN_ESTIMATES
            rid = f"{identity}-{n}"
            ids.append(rid)
            rules.append({"id": rid, "permission": "allow", "flows": [flow], "messages": list(messages),
                          "key_exprs": [f"{root}/{k}".replace("{i}", str(i)) for k in keys]})
        subjects.append({"id": identity, "cert_common_names": [identity]})
        policies.append({"id": f"{identity}-policy", "rules": ids + everyone, "subjects": [identity]})

    everyone = []
    for n, (messages, flow, keys) in enumerate(ROLE_RULES["everyone"]):
        rid = f"everyone-{n}"
        everyone.append(rid)
        rules.append({"id": rid, "permission": "allow", "flows": [flow], "messages": list(messages),
                      "key_exprs": [f"{root}/{k}" for k in keys]})
    add("plant", "plant")
    add("monitor", "monitor")
    for i in sorted(set(int(a) for a in agent_ids)):
        add(f"agent-{i}", "agent", i)
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}
