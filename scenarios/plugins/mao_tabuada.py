"""Plugin: Mao, Tabuada, "Decentralized resilient state-tracking" (discrete-time version).

Every agent reads one scalar sensor of an autonomous LTI plant, tracks the compressed
measurement windows ``(D (x) I_n) Y`` by dynamic average consensus and decodes the state
with a secure (support-search) decoder; a local sanity check flags (and latches) a node
whose own measurements violate the known dynamics. The numerical core is
:mod:`estimation.mao_tabuada` (with :mod:`estimation.sparse_detectability`,
:mod:`estimation.dynamic_consensus`, :mod:`estimation.secure_decoder`); this module maps the
``[estimator]`` table onto it, checks the setting and reports the conditions.

The plant is the runtime's sampled plant ``x[k+1] = Ad x[k]`` (``plant.time = "discrete"``:
``Ad = A``; a continuous-time plant is used through ``Ad = expm(A dt)``). It must have no
input and no stepper of its own. Agent ``i`` (graph index ``i``) is node ``i`` of the core
and reads exactly one output row.

Long runs: the signals grow like ``||Ad^k||``; the rule is **limit** (see
:mod:`estimation.mao_tabuada`): the horizon must stay within :func:`safe_horizon` for the
largest initial state the sensors report (the plant's ``x0`` and every ``x0_attack`` of a
``trajectory`` sensor attack), otherwise building the run fails naming ``run.rounds``.
"""

from __future__ import annotations

import dataclasses
from math import comb
from typing import TYPE_CHECKING, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from estimation.base import Diagnostics
from estimation.dynamic_consensus import ConsensusGains, design_consensus_gains, disagreement_spectral_radius
from estimation.errors import DesignError, ScenarioError
from estimation.lti import dense
from estimation.mao_tabuada import (
    SIGNAL_LIMIT,
    MaoTabuadaDesign,
    MaoTabuadaEstimator,
    check_report,
    design_mao_tabuada,
    safe_horizon,
)
from estimation.sparse_detectability import design_compression, sparse_detectability

from ..common import Condition, ThreatModel, estimator_section
from ..types import Matrix, Strict

if TYPE_CHECKING:
    from ..build import Experiment


class ConsensusOptions(Strict):
    """Gains of the discrete-time dynamic average consensus (:mod:`estimation.dynamic_consensus`).

    By default they are designed (grid search + Nelder-Mead minimising the spectral radius
    of the disagreement dynamics); ``k_phi``, ``k_I``, ``k_P`` given together are used as
    they are (checked: spectral radius < ``max_spectral_radius``).
    """

    max_spectral_radius: float = Field(default=1.0 - 1e-9, gt=0, le=1)
    k_phi: float | None = Field(default=None, gt=0, lt=2)
    k_I: float | None = Field(default=None, gt=0)
    k_P: float | None = Field(default=None, gt=0)

    @model_validator(mode="after")
    def _all_or_none(self) -> "ConsensusOptions":
        given = [g is not None for g in (self.k_phi, self.k_I, self.k_P)]
        if any(given) and not all(given):
            raise ValueError("give all three of k_phi, k_I, k_P (or none: designed)")
        return self

    @property
    def explicit(self) -> bool:
        return self.k_phi is not None

    @property
    def given(self) -> tuple[float, float, float] | None:
        """``(k_phi, k_I, k_P)`` as given (all three or none, by the validator above)."""
        if self.k_phi is None or self.k_I is None or self.k_P is None:
            return None
        return (self.k_phi, self.k_I, self.k_P)


class SearchOptions(Strict):
    """The search for ``D`` (``D = "search"``, :func:`estimation.sparse_detectability.design_compression`)."""

    n_random: int = Field(default=20, ge=0, description="random candidates per row count v")
    seed: int = Field(default=0, ge=0, description="seed of the candidates (not run.seed: D is a design choice)")


class MaoTabuadaSection(Strict):
    """Mao, Tabuada: dynamic average consensus of compressed windows + secure decoder."""

    algorithm: Literal["mao_tabuada"]
    #: attacked nodes tolerated; (A, C) must be 2s-sparse detectable w.r.t. D (Lemma 2)
    s: int = Field(ge=0)
    #: compression matrix: explicit rows (v x p), "search" (fewest rows), or "identity" (v = p)
    D: Matrix | Literal["search", "identity"] = "search"
    search: SearchOptions = Field(default_factory=SearchOptions)
    #: "secure": exhaustive support search; "least_squares": the non-resilient baseline
    decoder: Literal["secure", "least_squares"] = "secure"
    #: relative tolerance of the local sanity check (Section V)
    sanity_rtol: float = Field(default=1e-9, gt=0)
    consensus: ConsensusOptions = Field(default_factory=ConsensusOptions)

    @field_validator("D", mode="before")
    @classmethod
    def _D_word(cls, v):
        if isinstance(v, str) and v not in ("search", "identity"):
            raise ValueError(f"expected a matrix (list of rows), \"search\" or \"identity\", got {v!r}")
        return v


ESTIMATOR = MaoTabuadaSection
THREAT_MODEL = ThreatModel(sensors="s")  # at most s attacked nodes (s-sparse attacks)


def _section(exp: "Experiment") -> MaoTabuadaSection:
    """This plugin's ``[estimator]`` section of ``exp``, typed."""
    return estimator_section(exp, MaoTabuadaSection)


class MaoTabuadaAgent(MaoTabuadaEstimator, Diagnostics):
    """The core estimator with the runtime's optional report hooks (:mod:`agents.monitor`):
    ``flagged`` (the latched local sanity check, inherited) and :meth:`diagnostics`.

    ``agent_ids`` maps node indices to the scenario's agent ids (for the diagnostics).
    """

    def __init__(self, design: MaoTabuadaDesign, *, node: int, decoder: str = "secure",
                 agent_ids: tuple[int, ...] | None = None) -> None:
        super().__init__(design, node=node, decoder=decoder)
        self._ids = tuple(agent_ids) if agent_ids is not None else tuple(range(1, design.p + 1))

    def diagnostics(self) -> dict[str, float]:
        """``sanity_residual``: the last local sanity-check residual relative to the signal
        size (the flag is raised when it exceeds ``sanity_rtol``); ``excluded_1`` ..
        ``excluded_s``: the agent ids of the support the secure decoder chose (the nodes it
        treats as attacked; NaN for the least-squares decoder and before the first decode)."""
        out = {"sanity_residual": float(self._window.last_residual)}
        sup = self.support
        for r in range(self.design.s):
            out[f"excluded_{r + 1}"] = float(self._ids[sup[r]]) if r < len(sup) else float("nan")
        return out


# ----------------------------------------------------------------------------- setting
def _problem(exp: "Experiment") -> tuple[np.ndarray, np.ndarray]:
    """``(A, C)`` of the core (``C[i]``: agent ``i``'s output row); raises for a setting
    the algorithm does not cover (independent of the conditions ``rse check`` reports)."""
    source, sc = exp.source, exp.scenario
    if exp.stepper is not None:
        raise ScenarioError(f"estimator.algorithm: 'mao_tabuada' needs an LTI plant; model {sc.plant.model!r} has its "
                            "own (nonlinear or noisy) step", source=source)
    if exp.Bd.shape[1] > 0 and sc.plant.input.kind != "zero":
        raise ScenarioError("plant.input: 'mao_tabuada' tracks an autonomous plant x[k+1] = A x[k] (eq. (1)); "
                            f"got input kind {sc.plant.input.kind!r}, expected 'zero'", source=source)
    if not exp.static:
        raise ScenarioError("agents: 'mao_tabuada' needs static agents (each reads its own sensor every round)", source=source)
    for i, rows in enumerate(exp.agent_rows):
        if len(rows) != 1:
            raise ScenarioError(f"agents: agent {exp.agent_ids[i]} reads {len(rows)} output rows; 'mao_tabuada' needs "
                                "exactly one scalar sensor per agent (Assumption 5): one [[sensors]] bank with one "
                                "row of C per agent", source=source)
    C = exp.plant.C[np.array([rows[0] for rows in exp.agent_rows], dtype=int)]
    return np.array(dense(exp.Ad), dtype=float), C


def _D_argument(exp: "Experiment", A: np.ndarray, C: np.ndarray) -> np.ndarray:
    """The compression matrix: given, identity, or searched (raises ScenarioError)."""
    est, source = _section(exp), exp.source
    p = C.shape[0]
    if not 0 <= 2 * est.s < p:
        raise ScenarioError(f"estimator.s: need 2s < p (p = {p} agents), got s = {est.s}", source=source)
    if est.D == "identity":
        return np.eye(p)
    if est.D == "search":
        try:
            return design_compression(A, C, s=est.s, n_random=est.search.n_random, seed=est.search.seed).D
        except DesignError as exc:
            raise ScenarioError(f"estimator.s: {exc}", source=source) from None
    try:
        D = np.array(est.D, dtype=float)
    except ValueError:
        raise ScenarioError("estimator.D: rows have different lengths", source=source) from None
    if D.ndim != 2 or D.shape[1] != p or D.shape[0] < 1:
        raise ScenarioError(f"estimator.D: expected rows of length p = {p} (one column per agent), got shape {D.shape}",
                            source=source)
    if not np.all(np.isfinite(D)):
        raise ScenarioError("estimator.D: entries must be finite", source=source)
    return D


def _gains(exp: "Experiment") -> ConsensusGains:
    """Designed or given consensus gains (raises DesignError)."""
    opt = _section(exp).consensus
    designed = design_consensus_gains(exp.Adj, max_spectral_radius=1.0 if opt.explicit else opt.max_spectral_radius)
    if opt.given is None:
        return designed
    k_phi, k_I, k_P = opt.given
    L = np.diag(exp.Adj.sum(axis=1)) - exp.Adj
    ev = np.sort(np.linalg.eigvalsh(L))
    rho = disagreement_spectral_radius(ev[1:], k_phi=k_phi, k_I=k_I, k_P=k_P)
    if not rho < opt.max_spectral_radius:
        raise DesignError(f"the given gains k_phi = {k_phi:g}, k_I = {k_I:g}, k_P = {k_P:g} give "
                          f"disagreement spectral radius {rho:.9f}, not < {opt.max_spectral_radius:g} (unstable); "
                          f"the designed gains reach {designed.spectral_radius:.6g}")
    return ConsensusGains(float(k_phi), float(k_I), float(k_P), float(rho), designed.lambda_2,
                          designed.lambda_max)


def _gain_key(exc: DesignError) -> str:
    msg = str(exc)
    return "network.graph" if ("not connected" in msg or "undirected" in msg) else "estimator.consensus"


def signal_x0_norm(exp: "Experiment") -> float:
    """The largest initial state the sensors report: the plant's ``x0`` and every
    ``x0_attack`` (``x0 + d0``) of a ``trajectory`` sensor attack."""
    norms = [float(np.linalg.norm(exp.x0))]
    for a in exp.sensor_attacks:
        if a.kind == "trajectory" and a.d0 is not None:
            norms.append(float(np.linalg.norm(exp.x0 + a.d0)))
    return max(max(norms), 1e-300)


def horizon(exp: "Experiment", A: np.ndarray, *, cap: int | None = None) -> int:
    """The safe horizon (capped: ``cap`` rounds means "at least")."""
    cap = cap if cap is not None else max(10 * exp.n_rounds, 20_000)
    return safe_horizon(A, x0_norm=signal_x0_norm(exp), max_rounds=cap)


def design(exp: "Experiment", *, check: bool = True) -> MaoTabuadaDesign | None:
    est, source = _section(exp), exp.source
    A, C = _problem(exp)
    try:
        D = _D_argument(exp, A, C)
    except ScenarioError:
        if not check:
            return None
        raise
    if est.D not in ("search", "identity") and check:
        rep = sparse_detectability(A, C, k=2 * est.s, D=D)
        if not rep.holds:
            raise ScenarioError(_not_detectable(A, C, est.s, rep, exp.agent_ids), source=source)
    opt = est.consensus
    try:
        des = design_mao_tabuada(A, C, exp.Adj, s=est.s, D=D, rtol=est.sanity_rtol,
                                 max_spectral_radius=1.0 if opt.explicit else opt.max_spectral_radius)
        if opt.explicit:
            des = dataclasses.replace(des, gains=_gains(exp))
    except DesignError as exc:
        if not check:
            return None
        key = "estimator.D" if "sparse detectable" in str(exc) else _gain_key(exc)
        raise ScenarioError(f"{key}: {exc}", source=source) from None
    if check:
        h = horizon(exp, A, cap=exp.n_rounds)
        if h < exp.n_rounds:
            raise ScenarioError(
                f"run.rounds: the horizon {exp.n_rounds} passes the safe horizon {h} of this plant: by then the "
                f"signals (|x0| up to {signal_x0_norm(exp):.3g}, growing like ||A^k||) would pass {SIGNAL_LIMIT:g}, "
                "the limit that keeps every product of two signals finite in float64 (numerical rule: limit, "
                f"not rescale); shorten the run to at most {h} rounds", source=source)
    return des


def _not_detectable(A: np.ndarray, C: np.ndarray, s: int, rep, ids: list[int]) -> str:
    """The message for a D w.r.t. which (A, C) is not 2s-sparse detectable."""
    ident = sparse_detectability(A, C, k=2 * s)
    who = ", ".join(str(ids[i]) for i in rep.worst_support)
    if not ident.holds:
        return (f"estimator.s: (A, C) is not {2 * s}-sparse detectable (Corollary 1): without the sensors of agents "
                f"{', '.join(str(ids[i]) for i in ident.worst_support)} an unstable mode is unobservable, so no D works "
                f"(Lemma 1); lower s or add sensors")
    return (f"estimator.D: (A, C) is not {2 * s}-sparse detectable w.r.t. the given D (v = {rep.v}, Lemma 2): removing "
            f"the range of D's columns of agents {who} hides an unstable mode; the identity (or D = \"search\") works")


def make_estimator(exp: "Experiment", i: int) -> MaoTabuadaAgent:
    return MaoTabuadaAgent(exp.design, node=i, decoder=_section(exp).decoder, agent_ids=tuple(exp.agent_ids))


# ----------------------------------------------------------------------------- rse check
def conditions(exp: "Experiment") -> list[Condition]:
    """Sparse detectability (identity and D), v, consensus gains and spectral radius,
    decoder size, sanity-check tolerance, safe horizon."""
    est = _section(exp)
    out: list[Condition] = []
    try:
        A, C = _problem(exp)
    except ScenarioError as exc:
        out.append(Condition("setting: autonomous LTI plant, one scalar sensor per static agent", False, exc.detail))
        return out
    p, s = C.shape[0], est.s
    mods = np.sort(np.abs(np.linalg.eigvals(A)))
    out.append(Condition("eigenvalue moduli of A (Assumption 6, discrete time: all > 1; not necessary)", None,
                         ", ".join(f"{m:.6g}" for m in mods)))
    ident = sparse_detectability(A, C, k=2 * s) if 2 * s < p else None
    out.append(Condition(f"(A, C) {2 * s}-sparse detectable, s = {s} (Corollary 1: some D exists)",
                         bool(ident is not None and ident.holds),
                         f"margin {ident.margin:.3g}, {ident.supports_checked} supports" if ident is not None
                         else f"2s = {2 * s} >= p = {p}"))
    try:
        D = _D_argument(exp, A, C)
    except ScenarioError as exc:
        out.append(Condition(f"compression D (estimator.D = {est.D if isinstance(est.D, str) else 'explicit'})", False,
                             exc.detail))
        D = None
    if D is not None:
        rep = sparse_detectability(A, C, k=2 * s, D=D)
        out.append(Condition(f"(A, C) {2 * s}-sparse detectable w.r.t. D (Lemma 2)", bool(rep.holds),
                             f"v = {rep.v}, margin {rep.margin:.3g} (worst support: agents "
                             f"{', '.join(str(exp.agent_ids[i]) for i in rep.worst_support)}), cond(D) = "
                             f"{rep.cond_D:.6g}, {rep.supports_checked} supports checked"))
        out.append(Condition(f"v >= 2s + 1 = {2 * s + 1} (necessary)", rep.v >= 2 * s + 1, f"v = {rep.v}"))
        out.append(Condition("compression v < p", None, f"v = {rep.v}, p = {p}: payload 2 v n = {2 * rep.v * A.shape[0]} "
                                                        f"floats per message"))
    try:
        g = _gains(exp)
        src = "given" if est.consensus.explicit else "designed"
        out.append(Condition(f"consensus gains ({src})", None, f"k_phi = {g.k_phi:.6g}, k_I = {g.k_I:.6g}, "
                                                               f"k_P = {g.k_P:.6g}; lambda_2 = {g.lambda_2:.6g}, "
                                                               f"lambda_max = {g.lambda_max:.6g}"))
        demand = est.consensus.max_spectral_radius
        out.append(Condition("spectral radius of the disagreement dynamics < 1", bool(g.spectral_radius < 1),
                             f"{g.spectral_radius:.9g}" + (f" (demanded < {demand:g})" if demand < 1 - 1e-9 else "")))
    except DesignError as exc:
        out.append(Condition("spectral radius of the disagreement dynamics < 1 (stable consensus gains)", False, str(exc)))
    out.append(Condition(f"decoder: {est.decoder}", None,
                         f"exhaustive support search, C(p, s) = {comb(p, s)} supports per round"
                         if est.decoder == "secure" else "plain least squares (not resilient)"))
    out.append(Condition("local sanity check tolerance (relative)", None, f"{est.sanity_rtol:g}"))
    h = horizon(exp, A)
    cap = max(10 * exp.n_rounds, 20_000)
    out.append(Condition(f"horizon {exp.n_rounds} <= safe horizon (signals <= {SIGNAL_LIMIT:g}, rule: limit)",
                         exp.n_rounds <= h, f"safe horizon {'>= ' if h >= cap else ''}{h} rounds for |x0| <= "
                                            f"{signal_x0_norm(exp):.6g}"))
    return out


def design_json(exp: "Experiment") -> dict:
    d = exp.design
    if d is None:
        return {}
    rep = check_report(d)
    rep["sparse_detectability"]["worst_support"] = [exp.agent_ids[i] for i in d.detectability.worst_support]
    rep["consensus"]["given"] = _section(exp).consensus.explicit
    rep["decoder"]["used"] = _section(exp).decoder
    rep["numerics"]["safe_horizon"] = horizon(exp, d.A)
    rep["numerics"]["x0_norm"] = signal_x0_norm(exp)
    return {**rep, "D": d.D, "alpha": d.alpha, "Ahat": d.Ahat, "sanity_rtol": d.rtol,
            "node_of_agent": {str(aid): i for i, aid in enumerate(exp.agent_ids)}}
