"""Whether a scenario's own attacks stay inside the threat model its algorithm tolerates.

The threat model is what the algorithm's plugin declares (``THREAT_MODEL``, a
:class:`scenarios.helpers.ThreatModel`, the one ``rse redteam`` searches; docs/redteam.md):
Lee-Kim-Shim tolerates ``estimator.q`` attacked sensor banks, the median bank of van der
Horst et al. ``estimator.M``, Mao-Tabuada ``estimator.s``; Mitra et al.'s LFRE
``estimator.f`` Byzantine agents among the in-neighbours of any regular agent, with trusted
sensors. A plugin that declares no threat model (Ugrinovskii's observers) is not judged. ``rse check``, ``rse simulate`` and ``rse run`` print the one line
:func:`beyond_threat_model` returns as a warning; nothing is refused (the paper scenarios
that show what happens beyond the model are meant to run).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from scenarios.build import Experiment

__all__ = ["beyond_threat_model"]


def _ids(values: list[int]) -> str:
    return ", ".join(str(v) for v in sorted(values))


def beyond_threat_model(exp: Experiment) -> str | None:
    """One line saying how ``exp``'s ``[[attacks]]`` exceed its algorithm's threat model, or None.

    Parameters
    ----------
    exp : a built :class:`~scenarios.build.Experiment`

    Returns
    -------
    ``"... : the paper's guarantee does not cover this run"`` naming the attacked banks or
    agents and the budget key, or None when the attacks are within the model (or the
    algorithm declares none).
    """
    from scenarios import plugins

    sc = exp.scenario
    alg = sc.estimator.algorithm
    tm = getattr(plugins.algorithm(alg), "THREAT_MODEL", None)
    if tm is None:
        return None
    qkey, fkey = tm.sensors, tm.agents
    banks = sorted({b for a in sc.attacks if a.target == "sensor" for b in a.sensors})
    byz = sorted({g for a in sc.attacks if a.target == "agent" for g in a.agents})
    problems: list[str] = []
    kinds = sorted({a.kind for a in sc.attacks if a.target == "agent"} - set(tm.strategies or ()))
    if byz and fkey is not None and tm.strategies is not None and kinds:
        problems.append(f"Byzantine strategy {', '.join(kinds)} is not one {alg}'s proof covers "
                        f"({', '.join(tm.strategies)})")
    if banks and qkey is None:
        problems.append(f"sensor bank(s) {_ids(banks)} attacked, but {alg} assumes trusted sensors")
    elif qkey is not None and len(banks) > int(getattr(sc.estimator, qkey)):
        q = int(getattr(sc.estimator, qkey))
        problems.append(f"{len(banks)} sensor banks attacked ({_ids(banks)}), but {alg} tolerates "
                        f"estimator.{qkey} = {q}")
    if byz and fkey is None:
        problems.append(f"Byzantine agent(s) {_ids(byz)}, but {alg} assumes every agent follows the protocol")
    elif fkey is not None and byz:
        f = int(getattr(sc.estimator, fkey))
        worst = _most_byzantine_in_neighbours(exp, byz)
        if worst is not None and worst[1] > f:
            problems.append(f"agent {worst[0]} hears {worst[1]} Byzantine in-neighbours, but {alg} tolerates "
                            f"estimator.{fkey} = {f} in any neighbourhood")
    if not problems:
        return None
    return "attacks beyond the threat model: " + "; ".join(problems) + ": the paper's guarantee does not cover this run"


def _most_byzantine_in_neighbours(exp: Experiment, byz: list[int]) -> tuple[int, int] | None:
    """(regular agent id, its number of Byzantine in-neighbours) for the agent that hears most."""
    index = {a: i for i, a in enumerate(exp.agent_ids)}
    bad = {index[a] for a in byz if a in index}
    best: tuple[int, int] | None = None
    for i, agent in enumerate(exp.agent_ids):
        if i in bad:
            continue
        n = sum(1 for j in exp.in_neighbours(i) if j in bad and j != i)
        if best is None or n > best[1]:
            best = (agent, n)
    return best
