"""The model of Ugrinovskii's resilient distributed H-infinity design (:mod:`estimation.hinf_lmi`):
the plain-matrix :class:`ResilientProblem`, its coupling matrices and each node's Riccati data.

Agents are numbered ``0..N-1``; ``neighbours[i]`` lists the in-neighbours ``V_i`` of node ``i``
(nodes it receives from), and edge-indexed matrices are dicts keyed ``(i, j)`` = "``i`` receives
from ``j``". The matrices (30), (37), (38) are documented in :mod:`estimation.hinf_lmi`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from .errors import DesignError

Edge = tuple[int, int]


def _mat(x, name: str, shape: tuple[int | None, int | None] | None = None) -> np.ndarray:
    a = np.asarray(x, dtype=float)
    if a.ndim == 1:
        a = a.reshape(-1, 1)
    if a.ndim != 2 or not np.all(np.isfinite(a)):
        raise DesignError(f"{name} must be a finite 2-D matrix, got shape {np.shape(x)}")
    if shape is not None:
        for want, got in zip(shape, a.shape):
            if want is not None and want != got:
                raise DesignError(f"{name} must have shape {shape} (None = any), got {a.shape}")
    return a


@dataclass(frozen=True)
class ResilientProblem:
    """Plant, sensors, network and attack model of the resilient observer (all plain matrices).

    Attributes
    ----------
    A : (n, n); B : (n, m)                plant (1), LTI.
    C : tuple of (p_i, n); D : tuple of (p_i, q_i)   sensors (2); ``D_i D_i'`` invertible.
    neighbours : tuple of tuples of int   in-neighbours ``V_i`` (directed graph allowed).
    W : dict (i, j) -> (p_ij, n)          shared information (3).
    H, Hc : dict (i, j) -> (p_ij, r)      channel noise of (3) and of the controllers' (18).
    Z, Zbar : dict (i, j) -> (p_ij, p_ij) design weights of (33) and (38), positive definite.
    F : tuple of (n, nf_i)                observer attack matrices (5).
    Fc : tuple of (n + ne_i, nf_i)        detector attack matrices ``[Fbar_i; Gammabar_i]`` (9).
    Omega, Gamma, Upsilon : tuples of (ne_i, ne_i), (ne_i, nf_i), (nf_i, ne_i)
                                          minimal realisation (13) of ``-G_i(s)/s``.
    P : (n N, n N)                        performance weight of (40), positive semidefinite.
    """

    A: np.ndarray
    B: np.ndarray
    C: tuple
    D: tuple
    neighbours: tuple
    W: Mapping[Edge, np.ndarray]
    H: Mapping[Edge, np.ndarray]
    Hc: Mapping[Edge, np.ndarray]
    Z: Mapping[Edge, np.ndarray]
    Zbar: Mapping[Edge, np.ndarray]
    F: tuple
    Fc: tuple
    Omega: tuple
    Gamma: tuple
    Upsilon: tuple
    P: np.ndarray
    edges: tuple = field(init=False)

    def __post_init__(self) -> None:
        set_ = lambda k, v: object.__setattr__(self, k, v)  # frozen dataclass
        A = _mat(self.A, "A")
        n = A.shape[0]
        if A.shape != (n, n):
            raise DesignError(f"A must be square, got {A.shape}")
        set_("A", A)
        set_("B", _mat(self.B, "B", (n, None)))
        N = len(self.neighbours)
        if N < 1:
            raise DesignError("the network needs at least one node")
        for name in ("C", "D", "F", "Fc", "Omega", "Gamma", "Upsilon"):
            if len(getattr(self, name)) != N:
                raise DesignError(f"{name} must have one entry per node ({N}), got {len(getattr(self, name))}")
        nb = []
        for i, Vi in enumerate(self.neighbours):
            Vi = tuple(int(j) for j in Vi)
            if any(not 0 <= j < N or j == i for j in Vi) or len(set(Vi)) != len(Vi):
                raise DesignError(f"neighbours[{i}] = {Vi}: in-neighbours must be distinct nodes 0..{N - 1}, not {i}")
            nb.append(Vi)
        set_("neighbours", tuple(nb))
        C = tuple(_mat(c, f"C[{i}]", (None, n)) for i, c in enumerate(self.C))
        D = tuple(_mat(d, f"D[{i}]", (C[i].shape[0], None)) for i, d in enumerate(self.D))
        for i, d in enumerate(D):
            if np.linalg.matrix_rank(d @ d.T) < d.shape[0]:
                raise DesignError(f"D[{i}] D[{i}]' must be invertible")
        set_("C", C)
        set_("D", D)
        Om = tuple(_mat(o, f"Omega[{i}]") for i, o in enumerate(self.Omega))
        Ups = tuple(_mat(u, f"Upsilon[{i}]", (None, Om[i].shape[0])) for i, u in enumerate(self.Upsilon))
        Gam = tuple(_mat(g, f"Gamma[{i}]", (Om[i].shape[0], Ups[i].shape[0])) for i, g in enumerate(self.Gamma))
        F = tuple(_mat(f, f"F[{i}]", (n, Ups[i].shape[0])) for i, f in enumerate(self.F))
        Fc = tuple(_mat(f, f"Fc[{i}]", (n + Om[i].shape[0], Ups[i].shape[0])) for i, f in enumerate(self.Fc))
        for i, o in enumerate(Om):
            if o.shape[0] != o.shape[1]:
                raise DesignError(f"Omega[{i}] must be square, got {o.shape}")
        set_("Omega", Om)
        set_("Upsilon", Ups)
        set_("Gamma", Gam)
        set_("F", F)
        set_("Fc", Fc)
        edges = tuple((i, j) for i in range(N) for j in nb[i])
        for name in ("W", "H", "Hc", "Z", "Zbar"):
            d = getattr(self, name)
            missing = [e for e in edges if e not in d]
            if missing:
                raise DesignError(f"{name} has no matrix for edge(s) {missing} ((i, j): i receives from j)")
        W = {e: _mat(self.W[e], f"W{e}", (None, n)) for e in edges}
        H = {e: _mat(self.H[e], f"H{e}", (W[e].shape[0], None)) for e in edges}
        Hc = {e: _mat(self.Hc[e], f"Hc{e}", (W[e].shape[0], None)) for e in edges}
        Z = {e: _mat(self.Z[e], f"Z{e}", (W[e].shape[0], W[e].shape[0])) for e in edges}
        Zb = {e: _mat(self.Zbar[e], f"Zbar{e}", (W[e].shape[0], W[e].shape[0])) for e in edges}
        for name, zs in (("Z", Z), ("Zbar", Zb)):
            for e, z in zs.items():
                if np.linalg.eigvalsh(0.5 * (z + z.T))[0] <= 0:
                    raise DesignError(f"{name}{e} must be symmetric positive definite")
        for k, v in (("W", W), ("H", H), ("Hc", Hc), ("Z", Z), ("Zbar", Zb)):
            set_(k, v)
        P = _mat(self.P, "P", (n * N, n * N))
        if np.linalg.eigvalsh(0.5 * (P + P.T))[0] < -1e-12 * max(1.0, np.abs(P).max()):
            raise DesignError("P must be positive semidefinite")
        set_("P", 0.5 * (P + P.T))
        set_("edges", edges)

    # -- sizes and per-node matrices (30), (37) ---------------------------------------
    @property
    def n(self) -> int:
        return self.A.shape[0]

    @property
    def N(self) -> int:
        return len(self.neighbours)

    def ne(self, i: int) -> int:
        """Order of the realisation (13) at node ``i``."""
        return self.Omega[i].shape[0]

    def detector_matrices(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[np.ndarray]]:
        """``(bold A_i, bold B_i, bold C_i, [bold W_ij for j in V_i])`` of (30), with ``F_c,i``."""
        n, ne = self.n, self.ne(i)
        Fbar, Gbar = self.Fc[i][:n], self.Fc[i][n:]
        Fhat, Ghat = self.F[i] + Fbar, self.Gamma[i] + Gbar
        Ups = self.Upsilon[i]
        Ab = np.block([[self.A, -Fhat @ Ups], [np.zeros((ne, n)), self.Omega[i] - Gbar @ Ups]])
        Bb = np.block([[self.B, Fhat], [np.zeros((ne, self.B.shape[1])), Ghat]])
        Cb = np.hstack([self.C[i], np.zeros((self.C[i].shape[0], ne))])
        Wb = [np.hstack([self.W[(i, j)], np.zeros((self.W[(i, j)].shape[0], ne))]) for j in self.neighbours[i]]
        return Ab, Bb, Cb, Wb

    def observer_input_matrix(self, i: int) -> np.ndarray:
        """``B_1,i = [B  -F_i]`` of (37)."""
        return np.hstack([self.B, -self.F[i]])

    def channel_weights(self, *, observer_channel: str = "H") -> tuple[dict, dict]:
        """``(U, Ubar)``: ``U_ij = Hhat Hhat' + Z_ij`` (33) and ``Ubar_ij`` (38).

        ``observer_channel="H"``: ``Ubar = H H' + Zbar`` (38); ``"H_hat"``: ``Hhat Hhat' + Zbar``.
        """
        if observer_channel not in ("H", "H_hat"):
            raise DesignError(f"observer_channel must be 'H' or 'H_hat', got {observer_channel!r}")
        U, Ub = {}, {}
        for e in self.edges:
            Hh = np.hstack([self.H[e], self.Hc[e]])
            U[e] = Hh @ Hh.T + self.Z[e]
            Hb = Hh if observer_channel == "H_hat" else self.H[e]
            Ub[e] = Hb @ Hb.T + self.Zbar[e]
        return U, Ub


def coupling_matrices(problem: ResilientProblem, U: Mapping[Edge, np.ndarray], Z: Mapping[Edge, np.ndarray]) -> np.ndarray:
    """``M = Phi + Phi' - Delta`` of (32)-(33) (or (38)-(39) with ``Ubar``, ``Zbar``), (nN, nN).

    ``Delta_i = sum_j W' U^-1 Z U^-1 W``; ``Phi_ii = Delta_i``, ``Phi_ij = -W' U^-1 W``.
    For ``W = I``, ``H = 0``, ``Z = I`` this is ``(L + L' - D) (x) I`` of (47).
    """
    n, N = problem.n, problem.N
    Phi = np.zeros((n * N, n * N))
    Delta = np.zeros_like(Phi)
    for i, j in problem.edges:
        W = problem.W[(i, j)]
        UiW = np.linalg.solve(U[(i, j)], W)
        d = UiW.T @ Z[(i, j)] @ UiW
        Delta[i * n:(i + 1) * n, i * n:(i + 1) * n] += d
        Phi[i * n:(i + 1) * n, i * n:(i + 1) * n] += d
        Phi[i * n:(i + 1) * n, j * n:(j + 1) * n] -= W.T @ UiW
    M = Phi + Phi.T - Delta
    return 0.5 * (M + M.T)


def node_riccati_data(problem: ResilientProblem, which: str, U: Mapping, i: int):
    """``(A_i, B_i, S_i, row sizes)`` of node ``i``'s Riccati LMI for ``which`` in {det, obs}."""
    from .hinf_riccati import information_matrix

    nb = problem.neighbours[i]
    if which == "det":
        Ab, Bb, Cb, Wb = problem.detector_matrices(i)
        S = information_matrix(Cb, problem.D[i], Wb, [U[(i, j)] for j in nb])
        return Ab, Bb, S
    W = [problem.W[(i, j)] for j in nb]
    S = information_matrix(problem.C[i], problem.D[i], W, [U[(i, j)] for j in nb])
    return problem.A, problem.observer_input_matrix(i), S
