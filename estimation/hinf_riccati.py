"""Riccati differential equations of Ugrinovskii's resilient distributed H-infinity observer.

Every node ``i`` solves, by itself and without communication, two Riccati differential
equations of the same shape (Ugrinovskii, "Distributed H-infinity estimation resilient
to biasing attacks", eqs. (25), (35) and (41))::

    Y' = A Y + Y A' + B B' - Y (S - R / gamma^2) Y,      Y(0) = Y0,          (*)
    S  = C' (D D')^{-1} C + sum_j W_j' U_j^{-1} W_j,

* (35): the attack detector's equation, ``A = bold A_i``, ``B = bold B_i``,
  ``C = [C_i 0]``, ``W_j = [W_ij 0]``, ``R = diag(R_i, R~_i)``, ``gamma^2``;
* (41): the observer's equation, ``A``, ``B = B_1,i = [B -F_i]``, ``C_i``, ``W_ij``,
  ``Ubar_ij``, ``Rbar_i``, ``gamma_bar^2``.

Their gains are (36) ``L = Y C' (D D')^{-1}``, ``K_j = Y W_j' U_j^{-1}`` (split along the
partition (31) for the detector) and (42); the detector's remaining gains are the
differences (44).

Integration (time-invariant coefficients, the case the offline LMIs (49)/(52) cover).
The equations are stiff (for the paper's example the closed-loop matrix
``A - Y S`` has eigenvalues down to about ``-1e5``), so they are not integrated by an
explicit scheme. :class:`RiccatiFlow` uses the exact solution of (*): with ``Y_s`` the
stabilising solution of the algebraic equation (``Ric(Y_s) = 0``, ``A_s = A - Y_s S~``
Hurwitz, ``S~ = S - R / gamma^2``) the deviation ``Delta = Y - Y_s`` obeys
``Delta' = A_s Delta + Delta A_s' - Delta S~ Delta`` whose flow over a step ``h`` is::

    Delta(t + h) = E Delta(t) (I + G Delta(t))^{-1} E',
    E = expm(A_s h),   G = int_0^h expm(A_s' s) S~ expm(A_s s) ds        (Van Loan).

``E`` is contracting, so the map is well conditioned at any step ``h`` (an exponential of
the Hamiltonian matrix itself would overflow at ``h = 1e-3`` for the example); it is exact
up to rounding, whatever ``h``. A singular ``I + G Delta`` is a finite escape time.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .errors import DesignError, NumericalError

__all__ = [
    "information_matrix",
    "riccati_rhs",
    "filter_gains",
    "split_detector_gains",
    "difference_gains",
    "stabilizing_solution",
    "check_riccati_solution",
    "RiccatiFlow",
]


def _sym(M: np.ndarray) -> np.ndarray:
    return 0.5 * (M + M.T)


def information_matrix(
    C: np.ndarray, D: np.ndarray, W: Sequence[np.ndarray], U: Sequence[np.ndarray]
) -> np.ndarray:
    """``S = C' (D D')^{-1} C + sum_j W_j' U_j^{-1} W_j`` (the bracket of (25), (35), (41)).

    Parameters
    ----------
    C : (p, m) array
        Measurement matrix (``[C_i 0]`` for the detector).
    D : (p, q) array
        Measurement-noise matrix; ``D D'`` must be invertible.
    W : sequence of (p_j, m) arrays
        One per in-neighbour ``j``.
    U : sequence of (p_j, p_j) arrays
        ``U_ij = H H' + Z_ij`` (positive definite), same order as ``W``.

    Returns
    -------
    S : (m, m) array, symmetric positive semidefinite.
    """
    C = np.atleast_2d(np.asarray(C, dtype=float))
    D = np.atleast_2d(np.asarray(D, dtype=float))
    if len(W) != len(U):
        raise DesignError(f"information_matrix: {len(W)} matrices W but {len(U)} matrices U")
    DD = D @ D.T
    try:
        S = C.T @ np.linalg.solve(DD, C)
        for Wj, Uj in zip(W, U):
            Wj = np.atleast_2d(np.asarray(Wj, dtype=float))
            S = S + Wj.T @ np.linalg.solve(np.asarray(Uj, dtype=float), Wj)
    except np.linalg.LinAlgError as exc:
        raise DesignError(f"information_matrix: D D' or some U_ij is singular ({exc})") from exc
    return _sym(S)


def riccati_rhs(
    Y: np.ndarray, *, A: np.ndarray, B: np.ndarray, S: np.ndarray, R: np.ndarray, gamma2: float
) -> np.ndarray:
    """Right-hand side of the Riccati differential equations (35) / (41).

    ``A Y + Y A' + B B' - Y (S - R / gamma2) Y``.

    Parameters
    ----------
    Y : (m, m) symmetric array
    A : (m, m) array
    B : (m, r) array
    S : (m, m) array, from :func:`information_matrix`
    R : (m, m) array, the weight ``R_i`` (bold ``R_i`` for (35), ``Rbar_i`` for (41))
    gamma2 : float, > 0
        ``gamma^2`` or ``gamma_bar^2``.

    Returns
    -------
    (m, m) symmetric array.
    """
    if not gamma2 > 0:
        raise DesignError(f"riccati_rhs: gamma2 must be > 0, got {gamma2}")
    Y = np.asarray(Y, dtype=float)
    St = np.asarray(S, dtype=float) - np.asarray(R, dtype=float) / gamma2
    return _sym(A @ Y + Y @ A.T + B @ B.T - Y @ St @ Y)


def filter_gains(
    Y: np.ndarray,
    *,
    C: np.ndarray,
    D: np.ndarray,
    W: Sequence[np.ndarray],
    U: Sequence[np.ndarray],
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Gains (36) / (42): ``L = Y C' (D D')^{-1}``, ``K_j = Y W_j' U_j^{-1}``.

    Parameters
    ----------
    Y : (m, m) array
    C : (p, m) array; D : (p, q) array
    W, U : sequences of (p_j, m) and (p_j, p_j) arrays, one per in-neighbour.

    Returns
    -------
    L : (m, p) array
    K : list of (m, p_j) arrays, same order as ``W``.
    """
    Y = np.asarray(Y, dtype=float)
    C = np.atleast_2d(np.asarray(C, dtype=float))
    D = np.atleast_2d(np.asarray(D, dtype=float))
    L = np.linalg.solve(D @ D.T, C @ Y.T).T  # Y C' (DD')^{-1}, (DD') symmetric
    K = [np.linalg.solve(np.asarray(Uj, float), np.atleast_2d(Wj) @ Y.T).T for Wj, Uj in zip(W, U)]
    return L, K


def split_detector_gains(
    L_bold: np.ndarray, K_bold: Sequence[np.ndarray], *, n: int
) -> tuple[np.ndarray, np.ndarray, list[np.ndarray], list[np.ndarray]]:
    """Partition the detector gains (36) along (31): ``bold L = [L_hat; L_check]``.

    Parameters
    ----------
    L_bold : (n + n_eps, p) array; K_bold : list of (n + n_eps, p_j) arrays
    n : int, plant order.

    Returns
    -------
    L_hat (n, p), L_check (n_eps, p), K_hat list of (n, p_j), K_check list of (n_eps, p_j).
    """
    return (
        L_bold[:n],
        L_bold[n:],
        [Kj[:n] for Kj in K_bold],
        [Kj[n:] for Kj in K_bold],
    )


def difference_gains(
    L_hat: np.ndarray, K_hat: Sequence[np.ndarray], L: np.ndarray, K: Sequence[np.ndarray]
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Eq. (44): ``L_bar = L_hat - L``, ``K_bar_j = K_hat_j - K_j``."""
    if len(K_hat) != len(K):
        raise DesignError(f"difference_gains: {len(K_hat)} vs {len(K)} neighbour gains")
    return L_hat - L, [a - b for a, b in zip(K_hat, K)]


def stabilizing_solution(
    *, A: np.ndarray, B: np.ndarray, S: np.ndarray, R: np.ndarray, gamma2: float
) -> np.ndarray:
    """Stabilising solution ``Y_s`` of ``A Y + Y A' + B B' - Y (S - R/gamma2) Y = 0``.

    ``S - R/gamma2`` may be indefinite (H-infinity case), so this uses the ordered real
    Schur form of the Hamiltonian ``[[A', -S~], [-B B', -A]]`` directly.

    Returns
    -------
    Y_s : (m, m) symmetric array with ``A - Y_s S~`` Hurwitz.

    Raises
    ------
    NumericalError
        The Hamiltonian has eigenvalues on (or numerically near) the imaginary axis, or its
        stable subspace is not a graph: there is no stabilising solution.
    """
    A = np.asarray(A, dtype=float)
    m = A.shape[0]
    St = np.asarray(S, dtype=float) - np.asarray(R, dtype=float) / gamma2
    Ham = np.block([[A.T, -St], [-B @ B.T, -A]])
    scale = max(1.0, np.abs(Ham).max())
    from scipy.linalg import schur  # here, not at import: a node's process unpickles this module

    T, Zs, sdim = schur(Ham, output="real", sort=lambda re, im: re < -1e-10 * scale)
    if sdim != m:
        raise NumericalError(
            f"no stabilising Riccati solution: the Hamiltonian has {2 * m - 2 * sdim} "
            "eigenvalues on the imaginary axis"
        )
    U1, U2 = Zs[:m, :m], Zs[m:, :m]
    if np.linalg.cond(U1) > 1e12:
        raise NumericalError("no stabilising Riccati solution: stable subspace is not a graph")
    Ys = _sym(np.linalg.solve(U1.T, U2.T).T)
    return Ys


def check_riccati_solution(Y: np.ndarray, *, bound: float, name: str = "Y", t: float | None = None) -> None:
    """Raise :class:`NumericalError` unless ``Y`` is finite, positive definite and bounded.

    Positive definiteness is tested by a Cholesky factorisation, boundedness by
    ``trace(Y) <= bound`` (for a positive definite ``Y`` this bounds every eigenvalue).

    Parameters
    ----------
    Y : (m, m) symmetric array
    bound : float
        Largest admissible trace (the "bounded" of Theorems 1-2, made concrete).
    name : str
        Used in the message, e.g. ``"detector Riccati (35) of node 2"``.
    t : float, optional
        Time, used in the message.
    """
    when = "" if t is None else f" at t = {t:.6g}"
    if not np.all(np.isfinite(Y)):
        raise NumericalError(f"{name}{when}: solution is not finite (finite escape time)")
    try:
        np.linalg.cholesky(Y)
    except np.linalg.LinAlgError:
        lam = np.linalg.eigvalsh(_sym(Y))[0]
        raise NumericalError(
            f"{name}{when}: solution stopped being positive definite (smallest eigenvalue {lam:.3g})"
        ) from None
    tr = float(np.trace(Y))
    if tr > bound:
        raise NumericalError(
            f"{name}{when}: solution left the bound trace(Y) <= {bound:.3g} (trace {tr:.3g}); "
            "finite escape time"
        )


class RiccatiFlow:
    """Exact step-by-step solution of a time-invariant Riccati equation (35) / (41).

    Parameters
    ----------
    A : (m, m) array; B : (m, r) array; S : (m, m) array; R : (m, m) array
        Coefficients of (*) in the module docstring.
    gamma2 : float
    Y0 : (m, m) array
        Initial value (for the design of :mod:`estimation.hinf_lmi`, ``gamma^2 Q^-1``).
    dt : float
        Step of :meth:`step`.
    bound : float, keyword-only
        Largest admissible ``trace(Y)``; default ``1e3 * max(trace Y0, trace Y_s)``.
    name : str, keyword-only
        Used in error messages.

    Notes
    -----
    Every :meth:`step` applies the exact flow map of the module docstring and then
    :func:`check_riccati_solution`, so a solution that stops being positive definite or
    bounded stops the node with :class:`NumericalError` at the first step where it does.
    """

    def __init__(
        self,
        *,
        A: np.ndarray,
        B: np.ndarray,
        S: np.ndarray,
        R: np.ndarray,
        gamma2: float,
        Y0: np.ndarray,
        dt: float,
        bound: float | None = None,
        name: str = "Riccati equation",
    ) -> None:
        if not dt > 0:
            raise DesignError(f"{name}: dt must be > 0, got {dt}")
        A = np.asarray(A, dtype=float)
        m = A.shape[0]
        Y0 = np.asarray(Y0, dtype=float)
        if Y0.shape != (m, m):
            raise DesignError(f"{name}: Y0 must have shape {(m, m)}, got {Y0.shape}")
        self.name = name
        self.dt = float(dt)
        self._t = 0.0
        Ys = stabilizing_solution(A=A, B=B, S=S, R=R, gamma2=gamma2)
        St = np.asarray(S, dtype=float) - np.asarray(R, dtype=float) / gamma2
        As = A - Ys @ St
        # Van Loan: expm([[-As', St], [0, As]] h) = [[*, F12], [0, E]], G = E' F12.
        from scipy.linalg import expm

        V = expm(np.block([[-As.T, St], [np.zeros((m, m)), As]]) * self.dt)
        self._E = V[m:, m:]
        self._G = _sym(self._E.T @ V[:m, m:])
        self._Ys = Ys
        self._Delta = _sym(Y0) - Ys
        self._Et = self._E.T.copy()
        self._I = np.eye(m)
        tr_max = max(float(np.trace(Y0)), float(np.trace(Ys)))
        self.bound = float(bound) if bound is not None else 1e3 * abs(tr_max)
        check_riccati_solution(self.Y, bound=self.bound, name=name, t=0.0)

    @property
    def Y(self) -> np.ndarray:
        """Current solution, (m, m) copy."""
        return _sym(self._Ys + self._Delta)

    @property
    def Y_stationary(self) -> np.ndarray:
        """The stabilising algebraic solution the flow converges to, (m, m) copy."""
        return self._Ys.copy()

    @property
    def t(self) -> float:
        return self._t

    @property
    def deviation(self) -> np.ndarray:
        """``Y - Y_s`` (read-only view, for cheap change tests)."""
        v = self._Delta.view()
        v.flags.writeable = False
        return v

    def step(self) -> np.ndarray:
        """Advance by ``dt`` and return the new ``Y`` (checked; see class notes)."""
        t_new = self._t + self.dt
        # (I + Delta G)^-1 Delta by LAPACK gesv; det(I + Delta G_s) is 1 at s = 0 and vanishes
        # exactly at an escape time, so a non-positive determinant means the solution went
        # through infinity within this step.
        from scipy.linalg.lapack import dgesv as _gesv  # imported once, then a dict look-up

        lu, piv, X, info = _gesv(self._I + self._Delta @ self._G, self._Delta)
        d = np.diag(lu)
        sign = np.prod(np.sign(d)) * (-1.0) ** np.count_nonzero(piv != np.arange(len(piv)))
        if info != 0 or sign <= 0 or not np.all(np.isfinite(X)):
            raise NumericalError(f"{self.name} at t = {t_new:.6g}: solution escapes to infinity (finite escape time)")
        D = self._E @ X @ self._Et
        self._Delta = 0.5 * (D + D.T)
        self._t = t_new
        Y = self._Ys + self._Delta
        check_riccati_solution(Y, bound=self.bound, name=self.name, t=self._t)
        return Y



class FlowStack:
    """Several :class:`RiccatiFlow` stepped together (the batched round).

    :meth:`step` is :meth:`RiccatiFlow.step` of every flow, stacked: ``X = (I + Delta G)^-1
    Delta`` by one batched solve, the escape test on the sign of ``det(I + Delta G)``,
    ``Delta+ = sym(E X E^T)`` and the checks of :func:`check_riccati_solution` (Cholesky,
    trace bound) for all of them; each flow's ``Delta`` and time are written back by
    :meth:`sync` (the stack runs ahead of its flows until then). Where any flow
    fails a test, every flow takes its own :meth:`~RiccatiFlow.step` instead, which raises
    the per-flow error. Flows of different sizes ``m`` are stacked at the largest size ``m_max``:
    ``Delta``, ``G``, ``E`` padded with zeros and ``Y_s`` with the identity (so the padded
    block of ``I + Delta G`` is ``I``, of ``Delta`` stays 0 and of ``Y`` is ``I``: the
    determinant's sign and the Cholesky test are the flow's; the trace bound is raised by
    ``m_max - m``). Two sufficient conditions spare LAPACK calls once the deviations are
    small: ``|Delta|_F |G|_F < 1/2`` gives ``det(I + Delta G) > 0``, and ``|Delta+|_F <
    lambda_min(Y_s) / 2`` (for a well-conditioned ``Y_s``) a positive definite ``Y``. The batched LAPACK calls may round differently from the per-flow ones:
    equal within 1e-12 relative.
    """

    def __init__(self, flows: "list[RiccatiFlow]") -> None:
        self.flows = list(flows)
        fl = self.flows
        self.sizes = [f._G.shape[0] for f in fl]
        F, m = len(fl), max(self.sizes)
        self.m = m
        self._G = np.zeros((F, m, m))
        self._E = np.zeros((F, m, m))
        self._Ys = np.tile(np.eye(m), (F, 1, 1))
        for i, (f, mi) in enumerate(zip(fl, self.sizes)):
            self._G[i, :mi, :mi], self._E[i, :mi, :mi], self._Ys[i, :mi, :mi] = f._G, f._E, f._Ys
        self._Et = self._E.transpose(0, 2, 1).copy()
        self._bound = np.array([f.bound + (m - mi) for f, mi in zip(fl, self.sizes)])
        # sufficient conditions that spare the determinant and the Cholesky factorisation
        # (see step): |G|_F, and half the smallest eigenvalue of Y_s where Y_s is well conditioned
        self._Gnorm = np.sqrt(np.einsum("fij,fij->f", self._G, self._G))
        lam = [np.linalg.eigvalsh(f._Ys) for f in fl]
        self._margin = np.array([0.5 * v[0] if v[0] > 1e-8 * abs(v[-1]) else 0.0 for v in lam])
        self._I = np.eye(m)
        self._dt = np.array([f.dt for f in fl])
        self._D: np.ndarray | None = None  # the stacked (padded) deviations after the last stacked step
        self._rows: list[np.ndarray] = []  # ... each flow's Delta (a view into it) once written back
        self._T = np.array([f._t for f in fl])  # every flow's time
        self._synced = True  # the flows hold the stack's Delta and time (else the stack is ahead)

    def sync(self) -> None:
        """Write the stacked deviations and times back into the flows (after stacked steps,
        before anything reads or steps a flow by itself)."""
        if self._synced or self._D is None:
            return
        D = self._D
        self._rows = [D[i, :mi, :mi] for i, mi in enumerate(self.sizes)]
        for f, d, t in zip(self.flows, self._rows, self._T.tolist()):
            f._Delta, f._t = d, t
        self._synced = True

    @property
    def deviations(self) -> np.ndarray:
        """``(F, m_max, m_max)``: every flow's ``Delta``, zero-padded (read-only use): the
        stack's own after stacked steps, else gathered from the flows (which may have been
        stepped alone)."""
        D = self._D
        if D is not None and not self._synced:
            return D
        if D is None or any(f._Delta is not d for f, d in zip(self.flows, self._rows)):
            D = np.zeros((len(self.flows), self.m, self.m))
            for i, (f, mi) in enumerate(zip(self.flows, self.sizes)):
                D[i, :mi, :mi] = f._Delta
            self._D = D
            self._rows = [D[i, :mi, :mi] for i, mi in enumerate(self.sizes)]
            for f, d in zip(self.flows, self._rows):
                f._Delta = d
            self._T = np.array([f._t for f in self.flows])
        return D

    def step(self) -> None:
        fl = self.flows
        Delta = self.deviations
        Amat = self._I + Delta @ self._G
        X = np.linalg.solve(Amat, Delta)
        # det(I + Delta G) > 0 without the determinant where |Delta G|_2 <= |Delta|_F |G|_F < 1/2
        # (then det(I + s Delta G) has no zero for s in [0, 1]); else its sign
        small = np.sqrt(np.einsum("fij,fij->f", Delta, Delta)) * self._Gnorm < 0.5
        ok = bool(small.all()) or bool((np.linalg.slogdet(Amat)[0] > 0).all())
        ok = ok and bool(np.isfinite(X).all())
        if ok:
            D = self._E @ X @ self._Et
            Dn = 0.5 * (D + D.transpose(0, 2, 1))
            Y = self._Ys + Dn
            ok = bool(np.isfinite(Y).all()) and bool((np.trace(Y, axis1=1, axis2=2) <= self._bound).all())
            # Y = Y_s + Delta is positive definite without Cholesky where |Delta|_F < lambda_min(Y_s) / 2
            if ok and not bool((np.sqrt(np.einsum("fij,fij->f", Dn, Dn)) < self._margin).all()):
                try:
                    np.linalg.cholesky(Y)
                except np.linalg.LinAlgError:
                    ok = False
        if not ok:
            self.sync()
            self._D = None
            for f in fl:
                f.step()
            return
        self._D, self._synced = Dn, False
        self._T = self._T + self._dt
