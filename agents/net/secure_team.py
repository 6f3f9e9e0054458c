"""The identities and ingress rules of a secure team (``rse run --secure DIR``).

Two topologies, one set of certificates (``rse certs DIR``):

* **secure peer-to-peer** (the default): every process is a Zenoh peer; every link is
  mutual TLS under the team's CA, and every process enforces its own ingress rules bound
  to the certificate names of its peers (:func:`peer_acl`, the rules of
  :data:`transport.secure.ROLE_RULES`): agent ``i`` may put only under agent ``i``'s keys,
  only the plant publishes measurements and the truth, only the monitor receives the truth.
  Peers are linked directly (gossip off) and a peer forwards for nobody, so there is no
  process whose death ends the run.
* **secure with a router** (``--router`` or ``--connect tls/ROUTER:PORT``): every process
  is a client of the router, which enforces the same rules (:mod:`agents.net.router`).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from estimation.errors import ScenarioError

if TYPE_CHECKING:
    from transport.secure import TlsFiles

__all__ = ["identities", "tls_identity", "peer_acl"]


def tls_identity(directory: Path, name: str) -> TlsFiles:
    """The TLS identity of process ``name`` (``"agent 3"`` -> ``agent-3``) in ``directory``;
    a missing file is a :class:`ScenarioError` naming it."""
    from transport.secure import tls_files

    try:
        return tls_files(directory, name.replace(" ", "-"))
    except ValueError as exc:
        raise ScenarioError(str(exc)) from None


def identities(directory: Path, names: list[str], *, router: bool) -> dict[str, TlsFiles]:
    """The identity of each process of ``names`` (and of ``router`` if the team has one)."""
    return {nm: tls_identity(directory, nm) for nm in (["router"] if router else []) + names}


def peer_acl(directory: Path | str, run_id: str = "*", agent_ids: Iterable[int] | None = None) -> dict[str, Any]:
    """Zenoh's ``access_control`` of one secure peer: default deny, and for each identity of
    the team (``plant``, ``monitor``, ``agent-i`` for ``i`` in ``agent_ids``, default: the
    ``agent-i.pem`` certificates in ``directory``) what this peer accepts from it (ingress)
    and sends to it (egress). Zenoh enforces it on this peer's own links, matching the
    certificate's common name of the peer at the other end (eclipse-zenoh/zenoh#2137).
    Estimates and done reports are accepted from every agent of the team and authenticated
    by the receiver (:mod:`transport.linkauth`), which counts what it rejects."""
    from transport.secure import access_control, agent_ids_in

    ids = list(agent_ids) if agent_ids is not None else agent_ids_in(directory)
    if not ids:
        raise ScenarioError(f"--secure {directory}: no agent-I.pem certificates there (write them with "
                            f"`rse certs {directory} --scenario SCENARIO`)")
    try:
        return access_control(ids, run_id=run_id, open_estimates=True)
    except ValueError as exc:
        raise ScenarioError(f"--run-id: {exc}") from None
