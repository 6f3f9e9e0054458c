"""Plugin: Lee, Kim, Shim (IEEE TAC 2020), the distributed median solver."""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

import numpy as np
from pydantic import Field

from estimation import graphs
from estimation.errors import DesignError, ScenarioError
from estimation.lee_kim_shim import LeeKimShim, LKSDesign, theorem3_bound
from estimation.lee_kim_shim import design as lks_design
from estimation.lti import dense
from estimation.median_solver import theorem1_bound
from estimation.observability import redundancy_violations

from ..common import STREAM_AGENT_X0, Condition, ThreatModel, estimator_section, rng_for
from ..helpers import init_vector
from ..types import Init, Strict, UniformInit

if TYPE_CHECKING:
    from ..build import Experiment


class ObserverPoles(Strict):
    real_part: float = Field(default=-1.0, lt=0)
    gain: Literal["place", "kalman"] = Field(
        default="place", description="pole placement, or the sampled system's Kalman gain (large plants)")


class LeeKimShimEstimator(Strict):
    algorithm: Literal["lee_kim_shim"]
    variant: Literal["median", "lyapunov", "linear"] = "median"
    kappa: float = Field(gt=0)
    gamma: float = Field(gt=0)
    q: int = Field(default=1, ge=0, description="number of attacked sensor banks tolerated")
    observer: ObserverPoles = Field(default_factory=ObserverPoles)
    sign: Literal["implicit", "held"] = "implicit"
    max_age: int = Field(default=3, ge=0)
    x0: Init = Field(default_factory=UniformInit)


ESTIMATOR = LeeKimShimEstimator
THREAT_MODEL = ThreatModel(sensors="q")  # Theorem 1: at most q attacked sensor banks


def _section(exp: "Experiment") -> LeeKimShimEstimator:
    """This plugin's ``[estimator]`` section of ``exp``, typed."""
    return estimator_section(exp, LeeKimShimEstimator)


def _agent_C(exp: "Experiment") -> list[np.ndarray]:
    return [exp.plant.C[rows] for rows in exp.agent_rows]


def design(exp: "Experiment", *, check: bool = True) -> LKSDesign | None:
    est, source = _section(exp), exp.source
    if exp.discrete:
        raise ScenarioError("estimator.algorithm: 'lee_kim_shim' is a continuous-time observer; the plant is discrete-time", source=source)
    if not exp.static:
        raise ScenarioError("estimator.algorithm: 'lee_kim_shim' needs static agents ([[agents]] with sensors)", source=source)
    agent_C = _agent_C(exp)
    if check:
        bad = redundancy_violations(dense(exp.plant.A), agent_C, est.q)
        if bad:
            subset, dim = bad[0]
            who = ", ".join(str(exp.agent_ids[i]) for i in subset) or "(none)"
            raise ScenarioError(
                f"estimator.q: the sensor set is not {2 * est.q}-redundantly observable (Assumption 2): "
                f"agents {who} alone leave a {dim}-dimensional unobservable subspace "
                f"({len(bad)} such set(s) of {exp.N - 2 * est.q} agents); lower q or add sensors",
                source=source,
            )
    try:
        return _design(exp, agent_C, est)
    except DesignError as exc:
        if not check:
            return None
        raise ScenarioError(f"estimator: {exc}", source=source) from None


def _design(exp: "Experiment", agent_C: list[np.ndarray], est: LeeKimShimEstimator) -> LKSDesign:
    return lks_design(dense(exp.plant.A), exp.plant.B, agent_C, real_part=est.observer.real_part,
                      gains=est.observer.gain, dt=exp.dt)


def make_estimator(exp: "Experiment", i: int) -> LeeKimShim:
    est = _section(exp)
    x0 = init_vector(est.x0, exp.n, rng_for(exp.seed, STREAM_AGENT_X0, i), where="estimator.x0")
    return LeeKimShim(exp.design, agent=i, kappa=est.kappa, gamma=est.gamma, dt=exp.dt, variant=est.variant,
                      sign=est.sign, input_fn=exp.input, x0=x0, max_age=est.max_age,
                      max_degree=int(exp.Adj[i].sum()))


def conditions(exp: "Experiment") -> list[Condition]:
    est = _section(exp)
    out: list[Condition] = []
    agent_C = _agent_C(exp)
    bad = redundancy_violations(dense(exp.plant.A), agent_C, est.q)
    detail = (f"every set of {exp.N - 2 * est.q} agents observes x" if not bad else
              f"{len(bad)} set(s) of {exp.N - 2 * est.q} agents do not, e.g. agents "
              + ", ".join(str(exp.agent_ids[i]) for i in bad[0][0]))
    out.append(Condition(f"{2 * est.q}-redundant observability, q = {est.q} (Assumption 2)", not bad, detail))
    des = exp.design
    if des is None:
        try:
            des = _design(exp, agent_C, est)
        except DesignError as exc:
            out.append(Condition("common basis (Assumption 4)", False, str(exc)))
            return out
    per_agent = des.basis.S.sum(axis=1)
    out.append(Condition("observability per agent (directions w_l^T x each bank observes)", None,
                         ", ".join(f"{aid}: {int(o)} of {exp.n}" for aid, o in zip(exp.agent_ids, per_agent))
                         if exp.N <= 12 else f"{int(per_agent.min())} to {int(per_agent.max())} of {exp.n}"))
    counts = des.basis.S.sum(axis=0)
    per_dir = (f"banks observing each basis direction: {counts.tolist()}" if counts.size <= 24 else
               f"each of the {counts.size} basis directions observed by {int(counts.min())} to {int(counts.max())} banks")
    out.append(Condition("common basis (Assumption 4)", True, f"{des.basis.method} basis; {per_dir}"))
    out.append(Condition(f"each direction observed by >= 2q+1 = {2 * est.q + 1} agents (Lemma 1)",
                         bool(np.all(counts >= 2 * est.q + 1)), f"min {int(counts.min())}"))
    Adj = exp.Adj
    if graphs.is_undirected(Adj) and len(graphs.components(Adj)) == 1:
        out.append(Condition(f"Theorem 1 bound 2 sqrt(N)/(gamma lambda_2), gamma = {est.gamma:g}", None,
                             f"{theorem1_bound(Adj, est.gamma):.6g}"))
        stable = des.sqrt_Pbar is not None
        detail = "P_bar = I in the modal basis" if stable and np.allclose(des.sqrt_Pbar, np.eye(exp.n)) else ""
        if est.variant == "lyapunov":  # eq. (11) needs it; eq. (6) and the linear baseline do not
            out.append(Condition("plant Lyapunov stable (Theorem 3 / eq. 11)", stable, detail))
        else:
            detail = ("yes" if stable else "no") + (f"; {detail}" if detail else "")
            out.append(Condition("plant Lyapunov stable (Theorem 3 / eq. 11; not needed by variant "
                                 f"{est.variant!r})", None, detail))
        r = graphs.r_robustness(Adj)
        if r is not None:  # the Byzantine-agent condition of the papers' LFRE, not this solver's
            out.append(Condition("graph r-robustness (information: Byzantine agents need it, "
                                 "falsified sensors do not)", None, f"{r}-robust"))
        b3 = theorem3_bound(des, Adj, est.gamma)
        if b3 is not None:
            out.append(Condition("Theorem 3 steady-state bound on |x_hat_i - x|", None, f"{b3:.6g}"))
    return out


def design_json(exp: "Experiment") -> dict:
    d = exp.design
    if d is None:
        return {}
    return {
        "basis_method": d.basis.method, "V": d.basis.V, "W": d.basis.W, "S": d.basis.S,
        "observers": [
            {"agent": aid, "observable": ob.observable, "L": ob.L,
             "poles_real": np.real(ob.poles), "poles_imag": np.imag(ob.poles),
             **({"Ld": ob.Ld} if ob.Ld is not None else {})}  # the sampled gain the agent runs
            for aid, ob in zip(exp.agent_ids, d.observers)
        ],
    }
