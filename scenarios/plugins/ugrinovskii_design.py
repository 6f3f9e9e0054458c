"""The Ugrinovskii plugin's offline design (:mod:`scenarios.plugins.ugrinovskii`): the problem of
an experiment, the LMI design (34), (40), (52) and its cache."""


from __future__ import annotations

import hashlib
import json
import math
import re
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from estimation.errors import DesignError, ScenarioError
from estimation.hinf_lmi import ResilientProblem, closed_form_design
from estimation.hinf_lmi import design as lmi_design
from estimation.lti import dense
from estimation.ugrinovskii import first_order_attack_model

from ..common import estimator_section
from ..helpers import matrix
from ..types import Matrix

if TYPE_CHECKING:
    from ..build import Experiment

from .ugrinovskii_plants import AttackSignal, DisturbanceSignal, HinfPlant
from .ugrinovskii_schema import BiasingAttack, UgrinovskiiEstimator

Amplitude = float | list[float]


def _section(exp: "Experiment") -> UgrinovskiiEstimator:
    """This plugin's ``[estimator]`` section of ``exp``, typed."""
    return estimator_section(exp, UgrinovskiiEstimator)


# ============================================================================ design
@dataclass
class UgrinovskiiDesign:
    """``exp.design``: the problem (plain matrices), the LMI (or closed-form) result
    (a dict of arrays, ``numpy.savez``-able) and where the result came from."""

    problem: ResilientProblem
    result: dict[str, np.ndarray]
    source: str  # "solved", "memory" or "file <path>"
    key: str


#: results solved in this process, by problem and options (a run builds once; tests and
#: ``rse agent``, which validates then builds, do not solve twice)
_MEMO: "OrderedDict[str, dict[str, np.ndarray]]" = OrderedDict()
_MEMO_SIZE = 8


def _matrix_opt(rows: Matrix | None, default: np.ndarray, where: str, source: str, *, nrows: int | None = None,
                cols: int | None = None) -> np.ndarray:
    if rows is None:
        return default
    return matrix(rows, where, source, nrows=nrows, cols=cols)


def _plant_data(exp: "Experiment") -> HinfPlant:
    st = exp.stepper
    if not isinstance(st, HinfPlant):
        raise ScenarioError(f"estimator.algorithm: 'ugrinovskii' needs plant.model 'ugrinovskii_example' or 'hinf' (they carry "
                            f"the disturbance matrices B and D_i), got {exp.scenario.plant.model!r}", source=exp.source)
    return st


def problem_of(exp: "Experiment") -> ResilientProblem:
    """The :class:`~estimation.hinf_lmi.ResilientProblem` of a scenario (node ``i`` = agent
    index ``i``; ``V_i`` = its in-neighbours in ``network.graph``)."""
    est, source = _section(exp), exp.source
    st = _plant_data(exp)
    if not exp.static:
        raise ScenarioError("estimator.algorithm: 'ugrinovskii' needs static agents ([[agents]] with sensors)", source=source)
    n, N = exp.n, exp.N
    C = tuple(exp.plant.C[rows] for rows in exp.agent_rows)
    D = tuple(st.D[np.ix_(rows, rows)] for rows in exp.agent_rows)
    for i, c in enumerate(C):
        if c.shape[0] == 0:
            raise ScenarioError(f"agents: agent {exp.agent_ids[i]} reads no sensor", source=source)
    F = _matrix_opt(est.F, np.ones((n, 1)), "estimator.F", source, nrows=n)
    nf = F.shape[1]
    Om, Ga, Up = first_order_attack_model(gain=est.attack_gain, pole=est.attack_pole)
    if nf > 1:  # G_i(s) = g/(s+p) I: one realisation per attack component
        Om, Ga, Up = (np.kron(np.eye(nf), M) for M in (Om, Ga, Up))
    ne = Om.shape[0]
    Fc = np.vstack([F, np.zeros((ne, nf))]) if est.detector_attack_matrix == "F" else np.zeros((n + ne, nf))
    W = _matrix_opt(est.W, np.eye(n), "estimator.W", source, cols=n)
    pW = W.shape[0]
    H = _matrix_opt(est.H, (0.1 / math.sqrt(2.0)) * np.ones((pW, 1)), "estimator.H", source, nrows=pW)
    Hc = _matrix_opt(est.Hc, H, "estimator.Hc", source, nrows=pW)
    neighbours = tuple(tuple(exp.in_neighbours(i)) for i in range(N))
    edges = [(i, j) for i in range(N) for j in neighbours[i]]
    Adj = (np.asarray(exp.Adj) != 0).astype(float)
    Lap = np.diag(Adj.sum(axis=1)) - Adj
    LapT = np.diag(Adj.T.sum(axis=1)) - Adj.T
    try:
        return ResilientProblem(
            A=dense(exp.plant.A), B=st.B, C=C, D=D, neighbours=neighbours,
            W={e: W for e in edges}, H={e: H for e in edges}, Hc={e: Hc for e in edges},
            Z={e: est.Z * np.eye(pW) for e in edges}, Zbar={e: est.Zbar * np.eye(pW) for e in edges},
            F=(F,) * N, Fc=(Fc,) * N, Omega=(Om,) * N, Gamma=(Ga,) * N, Upsilon=(Up,) * N,
            P=np.kron(Lap + LapT, np.eye(n)),
        )
    except DesignError as exc:
        raise ScenarioError(f"estimator: {exc}", source=source) from None


def _key(problem: ResilientProblem, est: UgrinovskiiEstimator) -> str:
    """A digest of everything the design depends on."""
    h = hashlib.sha256()

    def add(a: Any) -> None:
        a = np.ascontiguousarray(np.asarray(a, dtype=float))
        h.update(str(a.shape).encode())
        h.update(a.tobytes())

    for name in ("A", "B", "P"):
        add(getattr(problem, name))
    for name in ("C", "D", "F", "Fc", "Omega", "Gamma", "Upsilon"):
        for a in getattr(problem, name):
            add(a)
    h.update(repr(problem.neighbours).encode())
    for name in ("W", "H", "Hc", "Z", "Zbar"):
        for e in problem.edges:
            add(getattr(problem, name)[e])
    opts = (est.method, est.backoff, est.observer_channel, est.solver, est.gamma2, est.gamma2_bar)
    h.update(repr(opts).encode())
    return h.hexdigest()[:32]


def _load_cache(path: Path) -> dict[str, np.ndarray]:
    if path.suffix == ".json":
        data = json.loads(path.read_text())
        res = data.get("lmi", data)
        return {k: np.asarray(v) for k, v in res.items()}
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _solve(problem: ResilientProblem, est: UgrinovskiiEstimator) -> dict[str, np.ndarray]:
    if est.method == "closed_form":
        if est.gamma2 is None or est.gamma2_bar is None:  # the section's validator already says so
            raise ScenarioError("estimator.method = 'closed_form' needs estimator.gamma2 and estimator.gamma2_bar")
        return closed_form_design(problem, gamma2=est.gamma2, gamma2_bar=est.gamma2_bar,
                                  observer_channel=est.observer_channel)
    return lmi_design(problem, backoff=est.backoff, observer_channel=est.observer_channel, solver=est.solver)


def design(exp: "Experiment", *, check: bool = True) -> UgrinovskiiDesign | None:
    """The problem, and the LMI design done once: from this process's memo, from
    ``estimator.design_cache`` (checked against the problem by
    :func:`estimation.hinf_lmi.check_design`) or solved (then written to the cache file)."""
    est, source = _section(exp), exp.source
    if exp.discrete:
        raise ScenarioError("estimator.algorithm: 'ugrinovskii' is a continuous-time observer; the plant is discrete-time",
                            source=source)
    problem = problem_of(exp)
    for (i, _), specs in _attack_specs(exp).items():  # validate the attacks and noise before the (slow) design
        AttackSignal(specs, problem.F[i].shape[1], dt=exp.dt, seed=exp.seed, source=source)
    for name, mats in (("channel_noise", problem.H), ("controller_noise", problem.Hc)):
        for _e, M in list(mats.items())[:1]:
            DisturbanceSignal(getattr(est, name), M.shape[1], dt=exp.dt, seed=exp.seed, stream=(), where=f"estimator.{name}",
                              source=source)
    key = _key(problem, est)
    path = Path(est.design_cache) if est.design_cache else None
    origin = "memory"
    try:
        res = _MEMO.get(key)
        if res is not None:
            _MEMO.move_to_end(key)
            res = {k: v.copy() for k, v in res.items()}
        elif path is not None and path.exists():
            try:
                cached = _load_cache(path)
            except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
                raise ScenarioError(f"estimator.design_cache: cannot read {path}: {exc}", source=source) from None
            if str(cached.get("cache_key", "")) == key:
                res = lmi_design(problem, cached=cached)  # checked against the problem (check_design)
                origin = f"file {path}"
            elif path.suffix == ".json":
                raise ScenarioError(f"estimator.design_cache: {path} holds the design of another problem or other "
                                    "design options", source=source)
        if res is None:
            res = _solve(problem, est)
            res["cache_key"] = np.array(key)
            origin = "solved"
    except DesignError as exc:
        if not check:
            return None
        raise ScenarioError(f"estimator: {_agent_names(str(exc), exp.agent_ids)}", source=source) from None
    if path is not None and path.suffix != ".json" and not origin.startswith("file"):
        path.parent.mkdir(parents=True, exist_ok=True)
        with path.open("wb") as fh:
            np.savez(fh, **res)  # type: ignore[arg-type]  # numpy's stub matches **res against allow_pickle
    _MEMO[key] = {k: v.copy() for k, v in res.items()}
    while len(_MEMO) > _MEMO_SIZE:
        _MEMO.popitem(last=False)
    return UgrinovskiiDesign(problem, res, origin, key)


def _agent_names(msg: str, ids: list[int]) -> str:
    """The core numbers nodes 0..N-1; scenario files use agent ids."""
    return re.sub(r"\bnode (\d+)", lambda m: f"agent {ids[int(m.group(1))]}" if int(m.group(1)) < len(ids) else m.group(0), msg)


def _attack_specs(exp: "Experiment") -> dict[tuple[int, str], list[tuple[int, BiasingAttack]]]:
    est, source = _section(exp), exp.source
    out: dict[tuple[int, str], list[tuple[int, BiasingAttack]]] = {}
    for k, a in enumerate(est.biasing):
        if a.node not in exp.agent_ids:
            raise ScenarioError(f"estimator.biasing[{k}].node: no agent {a.node}; agents are "
                                f"{', '.join(map(str, exp.agent_ids))}", source=source)
        if a.target == "detector" and est.detector_attack_matrix == "zero" and est.controlled:
            raise ScenarioError(f"estimator.biasing[{k}].target: an attack on the detector enters through F_c,i, which is 0 "
                                "with detector_attack_matrix = 'zero'; set detector_attack_matrix = 'F'", source=source)
        out.setdefault((exp.agent_ids.index(a.node), a.target), []).append((k, a))
    return out
