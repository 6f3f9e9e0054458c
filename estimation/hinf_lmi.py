"""Offline, central set-up of Ugrinovskii's resilient distributed H-infinity observer.

Ugrinovskii, "Distributed H-infinity estimation resilient to biasing attacks": the LMIs
(49) (LTI plant, noise-free channels, ``W = I``) and their general form (52) (channel
noise ``H_ij``, ``H_c,ij``, general ``W_ij``), minimising ``gamma^2`` (detectors, Theorem 1)
and ``gamma_bar^2`` (observers, Theorem 2); the closed-form fallback of footnote 3; the
graph-selection recursion (50)-(51).

The model is a :class:`ResilientProblem` (plain matrices). Agents are numbered ``0..N-1``;
``neighbours[i]`` lists the in-neighbours ``V_i`` of node ``i`` (nodes it receives from), and
edge-indexed matrices are dicts keyed ``(i, j)`` = "``i`` receives from ``j``".

Per node, with ``F_c,i = [Fbar_i; Gammabar_i]`` the detector attack matrix of (9), ``(17)``
(``Fbar_i``: the part entering ``e_hat_i``, ``Gammabar_i``: the part entering
``eps_hat_i``), the detector error system (20) has the matrices (30) -- derived from (17)
with the attack and its compensation ``F_c,i (f_i - u_i)``::

    bold A_i = [[A, -Fhat_i Ups_i], [0, Omega_i - Gammabar_i Ups_i]],
    bold B_i = [[B, Fhat_i], [0, Gammahat_i]],  Fhat = F + Fbar,  Gammahat = Gamma + Gammabar,
    bold C_i = [C_i 0],  bold W_ij = [W_ij 0],  U_ij = Hhat Hhat' + Z_ij,  Hhat = [H H_c];

with ``F_c,i = 0`` (the paper's example) these are exactly (30). The observer (37) uses
``B_1,i = [B -F_i]`` and ``Ubar_ij = H H' + Zbar_ij`` (38), or ``Hhat Hhat' + Zbar_ij`` with
``observer_channel="H_hat"`` (what reproduces the example's ``gamma_bar^2``).

LMIs solved (strict inequalities as ``<= -margin I``)::

    R + gamma^2 (Phi + Phi' - Delta) > 0,    Rcheck_i > Ups_i' Ups_i,                 (34)
    [[bA' Q + Q bA + bR - gamma^2 S_i, Q bB], [bB' Q, -gamma^2 I]] < 0,  Q > 0     (52)
    Rbar + gamma_bar^2 (Phibar + Phibar' - Deltabar) > P,                            (40)
    [[A' Qb + Qb A + Rbar - gamma_bar^2 Sbar_i, Qb B1], [B1' Qb, -gamma_bar^2 I]] < 0 (52)

with ``S_i = C'(DD')^{-1}C + sum_j W' U^{-1} W`` (for ``W = I``, ``H = 0``, ``Z = I`` this is (49)
with ``d_i I``). The two programmes are independent and solved separately.

Back-off (where the paper is silent). The infimum of ``gamma^2`` sits on the boundary of
the feasible set; the solver's point there gives Riccati solutions whose gains are extremely
stiff (closed-loop eigenvalues to ``-1e5 ... -5e6`` for the example). :func:`design` therefore
solves twice: (1) minimise ``gamma^2``; (2) fix ``gamma^2 = (1 + backoff) * min`` (default
``backoff = 0.05``, 5 %) and solve the feasibility problem (zero objective), whose
interior-point solution is well inside the feasible set (for the example: closed-loop
eigenvalues about ``-275`` at ``t = 0`` and ``-155`` in steady state). Same for
``gamma_bar^2``. The returned ``gamma2`` is the backed-off value; the minimum is kept as
``gamma2_opt``.

The result is a plain ``dict[str, numpy.ndarray]`` (see :func:`design`) so a runtime can store
it with ``numpy.savez`` and pass it back to :func:`design` (``cached=``) or
:func:`check_design`.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from .errors import DesignError, InfeasibleError
from .hinf_problem import ResilientProblem as ResilientProblem
from .hinf_problem import coupling_matrices as coupling_matrices
from .hinf_problem import node_riccati_data as node_riccati_data

__all__ = [
    "ResilientProblem",
    "coupling_matrices",
    "design",
    "closed_form_design",
    "check_design",
    "select_graph",
]



# -- the convex programmes -----------------------------------------------------------------

def _cvxpy():
    try:
        import cvxpy as cp
    except ImportError as exc:  # pragma: no cover - cvxpy is a declared extra
        raise DesignError(
            "the LMIs (49)/(52) need cvxpy (pip install 'resilient-state-estimation[lmi]'); "
            "closed_form_design() is the fallback without it"
        ) from exc
    return cp


def _programme(problem, which, U, Z, *, gamma2, nodes, coupling, margin):
    """cvxpy variables and constraints of (34)+(52) (``det``) or (40)+(52) (``obs``)."""
    cp = _cvxpy()
    n = problem.n
    g = cp.Variable(nonneg=True, name="gamma2") if gamma2 is None else float(gamma2)
    R, Rc, Q, cons = {}, {}, {}, []
    for i in nodes:
        Ab, Bb, S = node_riccati_data(problem, which, U, i)
        m, r = Bb.shape
        R[i] = cp.Variable((n, n), symmetric=True, name=f"R{i}")
        Q[i] = cp.Variable((m, m), symmetric=True, name=f"Q{i}")
        cons += [R[i] >> margin * np.eye(n), Q[i] >> margin * np.eye(m)]
        if which == "det":
            ne = problem.ne(i)
            Rc[i] = cp.Variable((ne, ne), symmetric=True, name=f"Rcheck{i}")
            UU = problem.Upsilon[i].T @ problem.Upsilon[i]
            cons.append(Rc[i] - UU >> margin * np.eye(ne))
            Rb = cp.bmat([[R[i], np.zeros((n, ne))], [np.zeros((ne, n)), Rc[i]]])
        else:
            Rb = R[i]
        blk = cp.bmat([[Ab.T @ Q[i] + Q[i] @ Ab + Rb - g * S, Q[i] @ Bb], [Bb.T @ Q[i], -g * np.eye(r)]])
        cons.append(0.5 * (blk + blk.T) << -margin * np.eye(m + r))
    if coupling:
        M = coupling_matrices(problem, U, Z)
        N = problem.N
        Rdiag = cp.bmat([[R[i] if i == j else np.zeros((n, n)) for j in range(N)] for i in range(N)])
        rhs = problem.P if which == "obs" else np.zeros_like(M)
        cons.append(0.5 * ((Rdiag + g * M - rhs) + (Rdiag + g * M - rhs).T) >> margin * np.eye(n * N))
    return g, R, Rc, Q, cons


_LABEL = {
    "det": ("detector", "gamma^2", "(34)", "(35)"),
    "obs": ("observer", "gamma_bar^2", "(40)", "(41)"),
}


def _solve(problem, which, U, Z, *, gamma2, margin, solver):
    """Solve one programme; ``gamma2=None`` minimises it. Names the failing block on failure."""
    cp = _cvxpy()
    g, R, Rc, Q, cons = _programme(problem, which, U, Z, gamma2=gamma2, nodes=range(problem.N),
                                   coupling=True, margin=margin)
    obj = cp.Minimize(g) if gamma2 is None else cp.Minimize(0)
    prob = cp.Problem(obj, cons)
    try:
        with warnings.catch_warnings():  # "inaccurate" is reported through the status
            warnings.simplefilter("ignore", UserWarning)
            prob.solve(solver=solver)
        status = prob.status
    except cp.error.SolverError as exc:
        status = f"solver error ({exc})"
    if status != cp.OPTIMAL:
        raise InfeasibleError(_diagnose(problem, which, U, Z, status=status, gamma2=gamma2,
                                        margin=margin, solver=solver))
    gv = float(g.value) if gamma2 is None else float(gamma2)
    Rs: dict[int, np.ndarray] = {}
    Qs: dict[int, np.ndarray] = {}
    for i in range(problem.N):
        if which == "det":
            ne = problem.ne(i)
            Rb = np.zeros((problem.n + ne,) * 2)
            Rb[: problem.n, : problem.n] = R[i].value
            Rb[problem.n:, problem.n:] = Rc[i].value
        else:
            Rb = R[i].value
        Rs[i] = 0.5 * (Rb + Rb.T)
        Qs[i] = 0.5 * (Q[i].value + Q[i].value.T)
    return {"gamma2": gv, "R": Rs, "Q": Qs}


def _diagnose(problem, which, U, Z, *, status, gamma2, margin, solver) -> str:
    """Find which block makes the programme infeasible (each node's Riccati LMI alone first)."""
    cp = _cvxpy()
    who, gname, coup, ric = _LABEL[which]
    head = f"{who} LMIs ({gname}) not solved: solver status {status!r}"
    for i in range(problem.N):
        g, _, _, _, cons = _programme(problem, which, U, Z, gamma2=gamma2, nodes=[i],
                                      coupling=False, margin=margin)
        p = cp.Problem(cp.Minimize(0), cons)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)
                p.solve(solver=solver)
            st = p.status
        except cp.error.SolverError as exc:
            st = f"solver error ({exc})"
        if st != cp.OPTIMAL:
            return (f"{head}; the Riccati LMI block of node {i} (the per-node inequality of (52), "
                    f"no conjugate point of {ric}) is infeasible on its own (status {st!r}): node {i} "
                    "cannot see the unstable modes through its measurements and in-neighbours")
    at = "" if gamma2 is None else f" at {gname} = {gamma2:.6g}"
    return (f"{head}; every node's Riccati LMI block is feasible alone, so the coupling condition "
            f"{coup} (R + {gname} (Phi + Phi' - Delta) > {'P' if which == 'obs' else '0'}) cannot be "
            f"met together with them{at}")


# -- public entry points --------------------------------------------------------------------

def _pack(problem, *, method, det, obs, U, Ub, observer_channel, extra) -> dict[str, np.ndarray]:
    res = {"method": np.array(method), "observer_channel": np.array(observer_channel),
           "n": np.array(problem.n), "N": np.array(problem.N),
           "gamma2": np.array(det["gamma2"]), "gamma2_bar": np.array(obs["gamma2"])}
    res.update({k: np.array(float(v)) for k, v in extra.items()})
    for i in range(problem.N):
        res[f"R_{i}"], res[f"Q_{i}"] = det["R"][i], det["Q"][i]
        res[f"Rbar_{i}"], res[f"Qbar_{i}"] = obs["R"][i], obs["Q"][i]
    for i, j in problem.edges:
        res[f"U_{i}_{j}"], res[f"Ubar_{i}_{j}"] = U[(i, j)], Ub[(i, j)]
    return res


def design(
    problem: ResilientProblem,
    *,
    backoff: float = 0.05,
    observer_channel: str = "H",
    margin: float = 1e-7,
    solver: str = "CLARABEL",
    cached: Mapping[str, np.ndarray] | None = None,
) -> dict[str, np.ndarray]:
    """Solve the LMIs (34), (40) with (52) for ``gamma^2``, ``gamma_bar^2`` and the weights.

    Parameters
    ----------
    problem : ResilientProblem
    backoff : float, keyword-only, >= 0
        Relative back-off from the minimum (module docstring); ``0`` returns the solver's
        boundary point (very stiff gains).
    observer_channel : {"H", "H_hat"}, keyword-only
        Channel noise in ``Ubar`` of the observer programme (38); see the module docstring.
    margin : float, keyword-only
        Strictness margin: every ``> 0`` is imposed as ``>= margin I``.
    solver : str, keyword-only
        cvxpy solver name (open-source conic: ``"CLARABEL"``, ``"SCS"``).
    cached : dict, keyword-only
        A previous result: it is checked against ``problem`` (:func:`check_design`) and
        returned without solving.

    Returns
    -------
    dict of numpy arrays (all ``numpy.savez``-able, no pickling):
        ``gamma2``, ``gamma2_bar`` (backed-off values used online), ``gamma2_opt``,
        ``gamma2_bar_opt`` (minima), ``backoff``, ``method`` (``"lmi"``),
        ``observer_channel``, ``n``, ``N``; per node ``R_i`` ((n + ne_i)-square, bold
        ``R_i = diag(R_i, Rcheck_i)``), ``Q_i`` (same size), ``Rbar_i``, ``Qbar_i`` ((n, n));
        per edge ``U_i_j``, ``Ubar_i_j``. The Riccati equations start at
        ``Y_i(0) = gamma2 Q_i^-1``, ``Ybar_i(0) = gamma2_bar Qbar_i^-1``.

    Raises
    ------
    InfeasibleError
        A programme is infeasible or the solver failed; the message names the failing block
        (a node's Riccati LMI, or the coupling condition (34)/(40)).
    """
    if cached is not None:
        check_design(problem, cached)
        return {k: np.array(v) for k, v in cached.items()}
    if not backoff >= 0:
        raise DesignError(f"backoff must be >= 0, got {backoff}")
    U, Ub = problem.channel_weights(observer_channel=observer_channel)
    Z, Zb = problem.Z, problem.Zbar
    det = _solve(problem, "det", U, Z, gamma2=None, margin=margin, solver=solver)
    obs = _solve(problem, "obs", Ub, Zb, gamma2=None, margin=margin, solver=solver)
    g_opt, gb_opt = det["gamma2"], obs["gamma2"]
    if backoff > 0:
        det = _solve(problem, "det", U, Z, gamma2=(1 + backoff) * g_opt, margin=margin, solver=solver)
        obs = _solve(problem, "obs", Ub, Zb, gamma2=(1 + backoff) * gb_opt, margin=margin, solver=solver)
    res = _pack(problem, method="lmi", det=det, obs=obs, U=U, Ub=Ub, observer_channel=observer_channel,
                extra={"gamma2_opt": g_opt, "gamma2_bar_opt": gb_opt, "backoff": backoff})
    check_design(problem, res)
    return res


def closed_form_design(
    problem: ResilientProblem,
    *,
    gamma2: float,
    gamma2_bar: float,
    alpha: float = 1e-3,
    observer_channel: str = "H",
) -> dict[str, np.ndarray]:
    """Footnote-3 fallback without an LMI solver, same result format as :func:`design`.

    ``R_i = (gamma2 * lambda_max(-(Phi + Phi' - Delta)) + alpha) I``,
    ``Rcheck_i = (lambda_max(Ups_i' Ups_i) + alpha) I`` and
    ``Rbar_i = (lambda_max(P - gamma2_bar (Phibar + Phibar' - Deltabar)) + alpha) I`` satisfy
    (34) and (40). (The footnote prints ``lambda_max(Phi + Phi' - Delta)``; the sign used
    here is the one that makes (34) hold for every graph.) As the footnote warns, (35)/(41)
    must still have bounded solutions: each Riccati equation is started at its stabilising
    stationary solution (so ``Y(t)`` is constant), and a node without a positive definite
    stabilising solution raises :class:`DesignError` naming it. ``Q_i = gamma2 Y_s^-1``.
    """
    from .errors import NumericalError
    from .hinf_riccati import stabilizing_solution

    if not (gamma2 > 0 and gamma2_bar > 0 and alpha > 0):
        raise DesignError(f"gamma2, gamma2_bar and alpha must be > 0, got {gamma2}, {gamma2_bar}, {alpha}")
    n = problem.n
    U, Ub = problem.channel_weights(observer_channel=observer_channel)
    M = coupling_matrices(problem, U, problem.Z)
    Mb = coupling_matrices(problem, Ub, problem.Zbar)
    r = gamma2 * max(np.linalg.eigvalsh(-M)[-1], 0.0) + alpha
    rb = max(np.linalg.eigvalsh(problem.P - gamma2_bar * Mb)[-1], 0.0) + alpha
    det: dict[str, Any] = {"gamma2": gamma2, "R": {}, "Q": {}}
    obs: dict[str, Any] = {"gamma2": gamma2_bar, "R": {}, "Q": {}}
    for i in range(problem.N):
        ne = problem.ne(i)
        rc = np.linalg.eigvalsh(problem.Upsilon[i].T @ problem.Upsilon[i])[-1] + alpha
        det["R"][i] = np.diag(np.r_[np.full(n, r), np.full(ne, rc)])
        obs["R"][i] = rb * np.eye(n)
        for which, d, UU, g in (("det", det, U, gamma2), ("obs", obs, Ub, gamma2_bar)):
            A_, B_, S = node_riccati_data(problem, which, UU, i)
            try:
                Ys = stabilizing_solution(A=A_, B=B_, S=S, R=d["R"][i], gamma2=g)
            except NumericalError as exc:
                raise DesignError(f"closed-form design: {_LABEL[which][0]} Riccati equation "
                                  f"{_LABEL[which][3]} of node {i}: {exc}") from exc
            if np.linalg.eigvalsh(Ys)[0] <= 0:
                raise DesignError(f"closed-form design: {_LABEL[which][0]} Riccati equation "
                                  f"{_LABEL[which][3]} of node {i} has no positive definite "
                                  "stabilising solution at this gamma")
            d["Q"][i] = g * np.linalg.inv(Ys)
    return _pack(problem, method="closed_form", det=det, obs=obs, U=U, Ub=Ub,
                 observer_channel=observer_channel, extra={"alpha": alpha})


def check_design(problem: ResilientProblem, result: Mapping[str, np.ndarray], *, tol: float = 1e-9) -> None:
    """Check a (possibly cached) result against ``problem``; raise naming the failed block.

    Checks sizes, ``R_i > 0``, ``Q_i > 0``, ``Rcheck_i > Ups' Ups``, the coupling conditions
    (34), (40) and, for ``method == "lmi"``, each node's Riccati LMI of (52), all with
    eigenvalue tolerance ``tol`` (relative to the block's scale).

    Raises
    ------
    DesignError
        Missing keys or wrong sizes (``result`` is from another problem).
    InfeasibleError
        An inequality does not hold.
    """
    try:
        n, N = int(result["n"]), int(result["N"])
    except KeyError as exc:
        raise DesignError(f"design result lacks key {exc}") from exc
    if (n, N) != (problem.n, problem.N):
        raise DesignError(f"design result is for n = {n}, N = {N}; the problem has n = {problem.n}, N = {problem.N}")
    try:
        g, gb = float(result["gamma2"]), float(result["gamma2_bar"])
        method = str(result["method"])
        oc = str(result["observer_channel"])
        R = [np.asarray(result[f"R_{i}"]) for i in range(problem.N)]
        Q = [np.asarray(result[f"Q_{i}"]) for i in range(problem.N)]
        Rb = [np.asarray(result[f"Rbar_{i}"]) for i in range(problem.N)]
        Qb = [np.asarray(result[f"Qbar_{i}"]) for i in range(problem.N)]
        U = {e: np.asarray(result[f"U_{e[0]}_{e[1]}"]) for e in problem.edges}
        Ub = {e: np.asarray(result[f"Ubar_{e[0]}_{e[1]}"]) for e in problem.edges}
    except KeyError as exc:
        raise DesignError(f"design result lacks key {exc}; was it made for this problem?") from exc
    U0, Ub0 = problem.channel_weights(observer_channel=oc)
    for e in problem.edges:
        if not (np.allclose(U[e], U0[e]) and np.allclose(Ub[e], Ub0[e])):
            raise DesignError(f"design result's U/Ubar of edge {e} do not match the problem")

    def neg(name, X):  # X must be negative definite
        X = 0.5 * (X + X.T)
        lam = np.linalg.eigvalsh(X)[-1]
        if lam >= tol * max(1.0, np.abs(X).max()):
            raise InfeasibleError(f"design check: {name} fails (largest eigenvalue {lam:.3g} must be < 0)")

    for i in range(problem.N):
        m = n + problem.ne(i)
        if R[i].shape != (m, m) or Q[i].shape != (m, m) or Rb[i].shape != (n, n) or Qb[i].shape != (n, n):
            raise DesignError(f"design result: matrices of node {i} have the wrong size")
        neg(f"R_{i} > 0", -R[i][:n, :n])
        neg(f"Rbar_{i} > 0", -Rb[i])
        neg(f"Q_{i} > 0", -Q[i])
        neg(f"Qbar_{i} > 0", -Qb[i])
        UU = problem.Upsilon[i].T @ problem.Upsilon[i]
        neg(f"Rcheck_{i} > Ups' Ups (34)", UU - R[i][n:, n:])
        if method == "lmi":
            for which, Rw, Qw, gw, UUw in (("det", R[i], Q[i], g, U), ("obs", Rb[i], Qb[i], gb, Ub)):
                A_, B_, S = node_riccati_data(problem, which, UUw, i)
                blk = np.block([[A_.T @ Qw + Qw @ A_ + Rw - gw * S, Qw @ B_], [B_.T @ Qw, -gw * np.eye(B_.shape[1])]])
                neg(f"{_LABEL[which][0]} Riccati LMI (52) of node {i}", blk)
    Rd = np.zeros((n * N, n * N))
    Rbd = np.zeros_like(Rd)
    for i in range(N):
        Rd[i * n:(i + 1) * n, i * n:(i + 1) * n] = R[i][:n, :n]
        Rbd[i * n:(i + 1) * n, i * n:(i + 1) * n] = Rb[i]
    neg("coupling condition (34)", -(Rd + g * coupling_matrices(problem, U, problem.Z)))
    neg("coupling condition (40)", problem.P - Rbd - gb * coupling_matrices(problem, Ub, problem.Zbar))


def select_graph(
    candidates: Sequence[ResilientProblem],
    *,
    criterion: str = "gamma2",
    **design_kwargs,
) -> dict[str, np.ndarray]:
    """Recursion (50) (``criterion="gamma2"``) or (51) (``"gamma2_bar"``) over candidate graphs.

    ``gamma_m = inf gamma^2`` over the LMIs for graph ``m`` (``+inf`` if infeasible) and
    ``gamma_m^o = min(gamma_m, gamma_{m-1}^o)``, ``gamma_0^o = +inf``. The candidates are the
    same plant and sensors over different graphs (different ``neighbours``, edge matrices).

    Returns
    -------
    dict of numpy arrays: ``best`` (index of the first graph attaining the minimum),
    ``gamma_m`` (M,), ``gamma_running`` (M,), and the full :func:`design` result of the best
    graph under its usual keys.

    Raises
    ------
    InfeasibleError
        No candidate graph is feasible.
    """
    if criterion not in ("gamma2", "gamma2_bar"):
        raise DesignError(f"criterion must be 'gamma2' or 'gamma2_bar', got {criterion!r}")
    if len(candidates) == 0:
        raise DesignError("select_graph needs at least one candidate graph")
    which = "det" if criterion == "gamma2" else "obs"
    oc = design_kwargs.get("observer_channel", "H")
    margin = design_kwargs.get("margin", 1e-7)
    solver = design_kwargs.get("solver", "CLARABEL")
    gam: list[float] = []
    run: list[float] = []
    reasons: list[str] = []
    best = None
    for m, pb in enumerate(candidates):
        U, Ub = pb.channel_weights(observer_channel=oc)
        UU, ZZ = (U, pb.Z) if which == "det" else (Ub, pb.Zbar)
        try:
            gm = _solve(pb, which, UU, ZZ, gamma2=None, margin=margin, solver=solver)["gamma2"]
        except InfeasibleError as exc:
            gm = np.inf
            reasons.append(f"graph {m}: {exc}")
        prev = run[-1] if run else np.inf
        run.append(min(gm, prev))
        if gm < prev:
            best = m
        gam.append(gm)
    if best is None:
        raise InfeasibleError("no candidate graph is feasible: " + " | ".join(reasons))
    res = design(candidates[best], **design_kwargs)
    res.update({"best": np.array(best), "gamma_m": np.array(gam), "gamma_running": np.array(run)})
    return res
