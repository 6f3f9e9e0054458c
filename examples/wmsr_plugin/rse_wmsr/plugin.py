"""The rse plugin module of W-MSR (found through the ``rse.algorithms`` entry point).

The module contract of ``scenarios.plugins``: ``ESTIMATOR`` (the ``[estimator]`` section), ``THREAT_MODEL`` (optional),
``design``, ``make_estimator``, ``conditions`` and ``design_json``. Everything it needs from
rse comes from ``scenarios.helpers`` (imported at module level) and ``estimation``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

import numpy as np
from pydantic import Field

from estimation import graphs
from estimation.errors import DesignError, ScenarioError
from estimation.robustness import is_f_local, strong_robustness
from scenarios.helpers import (
    STREAM_AGENT_X0,
    Condition,
    Init,
    Strict,
    ThreatModel,
    UniformInit,
    checked_design,
    init_vector,
    rng_for,
)

from . import wmsr

if TYPE_CHECKING:  # the built experiment (scenarios.build.Experiment), for annotations only
    from scenarios.build import Experiment


class WmsrEstimator(Strict):
    """``[estimator]`` of ``algorithm = "wmsr"``."""

    algorithm: Literal["wmsr"]
    #: "wmsr": W-MSR on the modes an agent does not observe; "average": the plain average
    #: of the same values (the non-resilient comparison)
    fusion: Literal["wmsr", "average"] = "wmsr"
    #: F: values removed on each side (tolerates F Byzantine in-neighbours per agent)
    f: int = Field(default=1, ge=0)
    #: the local observers' poles: pole * (1, 0.9, 0.8, ...)
    pole: float = Field(default=0.5, gt=0, lt=1)
    x0: Init = Field(default_factory=UniformInit)


ESTIMATOR = WmsrEstimator
#: what W-MSR tolerates (LeBlanc et al., Theorem 2 with the observers): F Byzantine agents in any
#: in-neighbourhood (F-local, ``estimator.f``), whatever values they send; ``rse redteam`` searches
#: within it without --beyond
THREAT_MODEL = ThreatModel(agents="f")


def _agent_C(exp: "Experiment") -> list[np.ndarray]:
    return [exp.plant.C[rows] for rows in exp.agent_rows]


def design(exp: "Experiment", *, check: bool = True) -> wmsr.WmsrDesign | None:
    """The modal design (raises :class:`ScenarioError` naming the key when it cannot be done)."""
    if not exp.discrete:
        raise ScenarioError("estimator.algorithm: 'wmsr' is a discrete-time estimator; set plant.time = 'discrete'",
                            source=exp.source)
    if not exp.static:
        raise ScenarioError("estimator.algorithm: 'wmsr' needs static agents ([[agents]] with sensors)", source=exp.source)
    if exp.plant.B.shape[1] and exp.scenario.plant.input.kind != "zero":
        raise ScenarioError("plant.input: 'wmsr' estimates an autonomous plant (input kind 'zero')", source=exp.source)
    try:
        return wmsr.design(exp.plant.A, _agent_C(exp), pole=exp.scenario.estimator.pole)
    except DesignError as exc:
        if not check:
            return None
        raise ScenarioError(f"estimator: {exc}", source=exp.source) from None


def make_estimator(exp: "Experiment", i: int) -> wmsr.WmsrObserver:
    est = exp.scenario.estimator
    x0 = init_vector(est.x0, exp.n, rng_for(exp.seed, STREAM_AGENT_X0, i), where="estimator.x0")
    return wmsr.WmsrObserver(exp.design, agent=i, x0=x0, f=est.f, fusion=est.fusion)


def conditions(exp: "Experiment") -> list[Condition]:
    """Per mode: eigenvalue, observers, and, for the modes some agent does not observe,
    the claimed range ``|lam| <= 1`` and strong (2F+1)-robustness w.r.t. the observers;
    F-locality of the scenario's Byzantine agents. With ``fusion = "average"`` (not
    resilient) the resilience conditions are information, not requirements."""
    est = exp.scenario.estimator
    des, out = checked_design(exp, design, "modal design (real, diagonalisable A; every mode observed)")
    if des is None:
        return out
    ids = exp.agent_ids
    resilient = est.fusion == "wmsr"
    r = 2 * est.f + 1
    for j, lam in enumerate(des.lam):
        S = des.observers_of(j)
        who = ",".join(str(ids[i]) for i in S)
        out.append(Condition(f"mode {j + 1}: eigenvalue, observers", None, f"lambda = {lam:.6g}; agents {who}"))
        if len(S) == exp.N:
            continue
        rob = strong_robustness(exp.Adj, S)
        note = "" if resilient else f" (information: fusion {est.fusion!r} is not resilient)"
        out.append(Condition(f"mode {j + 1}: strongly (2F+1) = {r}-robust w.r.t. its observers{note}",
                             (rob >= r) if resilient else None, f"strong robustness {rob}"))
        out.append(Condition(f"mode {j + 1}: |lambda| <= 1 (the range W-MSR is claimed for)",
                             bool(abs(lam) <= 1 + 1e-12) if resilient else None, f"|lambda| = {abs(lam):.6g}"))
    byz = sorted(exp.byzantine)
    local = is_f_local(exp.Adj, byz, f=est.f)
    out.append(Condition(f"at most F = {est.f} Byzantine in-neighbour(s) per agent (F-local)",
                         local if resilient else None,
                         "Byzantine agents " + (", ".join(str(ids[i]) for i in byz) or "none")))
    return out


def graph_conditions(exp: "Experiment") -> list[Condition]:
    """The graph needs no symmetry (W-MSR works on directed graphs); connectivity is
    implied by the robustness conditions."""
    comps = graphs.components(exp.Adj)
    return [Condition("network connected", len(comps) == 1,
                      f"{'undirected' if graphs.is_undirected(exp.Adj) else 'directed'}, {len(comps)} component(s)")]


def design_json(exp: "Experiment") -> dict:
    d = exp.design
    if d is None:
        return {}
    return {
        "eigenvalues": d.lam, "V": d.V,
        "observers": [{"agent": aid, "modes": (ob.observed + 1).tolist(), "L": ob.L}
                      for aid, ob in zip(exp.agent_ids, d.observers)],
    }
