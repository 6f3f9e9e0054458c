"""Discrete-time dynamic average consensus of signals with known dynamics, eqs. (6)-(10).

Mao, Tabuada, "Decentralized resilient state-tracking", Section VI. Every node ``i`` has
a signal ``phi_i[k]`` (here a ``(v, m)`` array: one copy of the algorithm per row of the
compression ``D``, Section V) that obeys ``phi_i[k+1] = phi_i[k] Ahat^T`` row by row
(``Ahat`` the ``(m, m)`` companion matrix of eq. (5)). Each node tracks the average
``(1/p) sum_i phi_i[k]``.

Discrete-time algorithm (this module's choice; the paper states (6) in continuous time).
In the rotating frame ``J~[k] = J[k] Ahat^{-k}`` (and likewise ``b``, ``eta``, ``phi``)
every ``Ahat``-consistent signal is constant, and (10) becomes the PI consensus
estimator of constants; its forward-Euler form, with the step absorbed in the gains, is::

    J~[k]   = J~[k-1] + k_phi (phi~[k] - J~[k-1]) - 2 k_I (L eta~)[k-1]
    b~[k]   = b~[k-1] + k_I (L J~)[k-1]
    eta~[k] = k_P b~[k] + k_I (L J~)[k-1]

(the signs of (10); (6), written with ``sum_j (J_j - J_i) = -(L J)_i``, is the same
system with ``b`` and ``eta`` negated). Back in plant coordinates, node ``i`` in round ``k`` with the
neighbours' values ``J_j, eta_j`` of round ``k-1`` computes::

    u_i = sum_j a_ij (J_i[k-1] - J_j[k-1]),   w_i = sum_j a_ij (eta_i[k-1] - eta_j[k-1])
    J_i[k]   = (1 - k_phi) J_i[k-1] Ahat^T + k_phi phi_i[k] - 2 k_I w_i Ahat^T
    b_i[k]   = (b_i[k-1] + k_I u_i) Ahat^T
    eta_i[k] = k_P b_i[k] + k_I u_i Ahat^T

and publishes ``(J_i[k], eta_i[k])`` stamped ``k``. ``k_phi`` plays the part of the
paper's input gain ``2 Ahat`` (in the rotating frame a scalar suffices; in continuous time
Assumption 6 is what makes ``2 Ahat`` stabilising).

Lost messages: if the newest value from ``j`` is stamped ``k-1-tau`` it is propagated by
the known dynamics, ``J_j Ahat^{tau T}``, i.e. in the rotating frame the last received
value is used as is. At an equilibrium the rotating-frame values are constant, so stale
values equal fresh ones and the fixed point -- exact tracking -- is unchanged by losses.
A neighbour never heard from is left out of the sums.

Disagreement dynamics and the gains. With ``L = sum_l lambda_l q_l q_l^T`` (undirected
graph) the rotating-frame error decouples, per Laplacian eigenvalue ``lambda``, into
``(J, b, eta)[k] = M(lambda) (J, b, eta)[k-1]`` (times ``I_m``; ``Ahat`` drops out)::

    M(lambda) = [[1 - k_phi,        0,   -2 k_I lambda],
                 [k_I lambda,        1,    0           ],
                 [k_I lambda (1+k_P), k_P,  0           ]]

The average of ``J`` is driven by ``lambda = 0`` and converges at rate ``|1 - k_phi|``;
the average of ``b`` has eigenvalue 1 but never reaches ``J`` (it is killed by ``L``).
The tracking error therefore decays as ``rho^k`` relative to the signal, with::

    rho = max(|1 - k_phi|, max_{lambda in spec(L), lambda > 0} rho(M(lambda)))

``det(zI - M) = z (z-1)(z-1+k_phi) + 2 c^2 ((1+k_P) z - 1)`` with ``c = k_I lambda``.
Near ``c = 0`` the root at 1 moves to ``1 - 2 c^2 k_P / k_phi``: small gains are stable
for every ``lambda > 0``, large ``c`` leaves the unit disc. So, unlike the continuous-time
Theorem 1 ("any gains above a threshold"), the stable ``k_I`` form a bounded window
``(0, c_max / lambda_max)``, and a stable design exists if and only if the graph is
connected (``lambda_2 > 0``): a disconnected graph admits none (a disagreement mode
with ``lambda = 0`` has eigenvalue 1). The achievable ``rho`` tends to 1 as
``lambda_2 / lambda_max`` shrinks (a long path); a caller can demand a rate with
``max_spectral_radius``. Gains are chosen to minimise ``rho`` by a grid search followed
by a Nelder-Mead refinement (deterministic).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from .errors import DesignError

__all__ = [
    "ConsensusGains",
    "mode_matrix",
    "disagreement_spectral_radius",
    "rotating_frame_matrix",
    "design_consensus_gains",
    "ConsensusNode",
]


@dataclass(frozen=True)
class ConsensusGains:
    """Gains of the discrete-time consensus and the resulting rate.

    Attributes
    ----------
    k_phi, k_I, k_P : float
        Input, integral and proportional gains (module docstring).
    spectral_radius : float
        ``rho`` of the disagreement dynamics (< 1).
    lambda_2, lambda_max : float
        Smallest non-zero and largest Laplacian eigenvalue.
    """

    k_phi: float
    k_I: float
    k_P: float
    spectral_radius: float
    lambda_2: float
    lambda_max: float


def mode_matrix(lam: float, *, k_phi: float, k_I: float, k_P: float) -> np.ndarray:
    """``M(lambda)``, the ``(3, 3)`` rotating-frame dynamics of one Laplacian mode."""
    c = k_I * lam
    return np.array([[1.0 - k_phi, 0.0, -2.0 * c], [c, 1.0, 0.0], [c * (1.0 + k_P), k_P, 0.0]])


def _mode_matrices(lambdas: np.ndarray, g, kI, kP) -> np.ndarray:
    """``M(lambda)`` for broadcast gains ``(G,)`` and eigenvalues ``(q,)``: shape ``(G, q, 3, 3)``."""
    g, kI, kP = (np.asarray(a, dtype=float)[:, None] for a in (g, kI, kP))
    c = kI * lambdas[None, :]
    M = np.zeros(c.shape + (3, 3))
    M[..., 0, 0] = 1.0 - g
    M[..., 0, 2] = -2.0 * c
    M[..., 1, 0] = c
    M[..., 1, 1] = 1.0
    M[..., 2, 0] = c * (1.0 + kP)
    M[..., 2, 1] = kP
    return M


def _rho_batch(lambdas: np.ndarray, g, kI, kP) -> np.ndarray:
    M = _mode_matrices(lambdas, np.atleast_1d(g), np.atleast_1d(kI), np.atleast_1d(kP))
    r = np.abs(np.linalg.eigvals(M)).max(axis=(-2, -1)) if lambdas.size else np.zeros(M.shape[0])
    return np.maximum(r, np.abs(1.0 - np.atleast_1d(g)))


def disagreement_spectral_radius(lambdas, *, k_phi: float, k_I: float, k_P: float) -> float:
    """``rho = max(|1 - k_phi|, max_{lambda > 0} rho(M(lambda)))`` over the given eigenvalues.

    Parameters
    ----------
    lambdas : (q,) array
        The non-zero Laplacian eigenvalues (disagreement modes).
    """
    lambdas = np.atleast_1d(np.asarray(lambdas, dtype=float))
    return float(_rho_batch(lambdas, k_phi, k_I, k_P)[0])


def rotating_frame_matrix(Adj, *, k_phi: float, k_I: float, k_P: float) -> np.ndarray:
    """The whole rotating-frame system ``(3p, 3p)`` on the state ``(J, b, eta)`` (scalar copy).

    Its eigenvalues are those of ``M(lambda)`` over ``spec(L)`` (used by the tests).
    """
    L = _laplacian(np.asarray(Adj, dtype=float))
    p = L.shape[0]
    I, Z = np.eye(p), np.zeros((p, p))
    return np.block(
        [
            [(1.0 - k_phi) * I, Z, -2.0 * k_I * L],
            [k_I * L, I, Z],
            [k_I * (1.0 + k_P) * L, k_P * I, Z],
        ]
    )


def _laplacian(Adj: np.ndarray) -> np.ndarray:
    return np.diag(Adj.sum(axis=1)) - Adj


def design_consensus_gains(Adj, *, max_spectral_radius: float = 1.0 - 1e-9) -> ConsensusGains:
    """Choose ``k_phi, k_I, k_P`` minimising the disagreement spectral radius.

    Parameters
    ----------
    Adj : (p, p) array
        Symmetric non-negative weighted adjacency, zero diagonal (Assumption 4).
    max_spectral_radius : float, keyword-only
        The design fails unless ``rho < max_spectral_radius`` (default: stable, with
        ``1e-9`` slack so a numerically marginal design is not called stable).

    Raises
    ------
    DesignError
        Naming the graph property: not undirected, not connected (no stable gains exist),
        or ``lambda_2 / lambda_max`` too small for the demanded rate.
    """
    from scipy.optimize import minimize

    Adj = np.asarray(Adj, dtype=float)
    if Adj.ndim != 2 or Adj.shape[0] != Adj.shape[1] or Adj.shape[0] < 2:
        raise DesignError(f"adjacency must be a square (p, p) matrix with p >= 2, got shape {Adj.shape}")
    if np.any(Adj < 0) or np.any(np.diag(Adj) != 0) or not np.all(np.isfinite(Adj)):
        raise DesignError("adjacency must be finite, non-negative, with a zero diagonal")
    if not np.allclose(Adj, Adj.T):
        raise DesignError("the consensus design needs an undirected graph (symmetric adjacency, Assumption 4)")
    if not 0.0 < max_spectral_radius <= 1.0:
        raise DesignError(f"max_spectral_radius must be in (0, 1], got {max_spectral_radius}")
    ev = np.sort(np.linalg.eigvalsh(_laplacian(Adj)))
    scale = max(ev[-1], 1e-300)
    n_zero = int(np.sum(ev <= 1e-9 * scale))
    if n_zero > 1:
        raise DesignError(
            f"the communication graph is not connected (its Laplacian has {n_zero} zero eigenvalues, "
            f"lambda_2 = 0): no gains make the discrete-time disagreement dynamics stable, a "
            f"disagreement mode keeps eigenvalue 1 for every k_I, k_P"
        )
    lam2, lammax = float(ev[1]), float(ev[-1])
    lambdas = np.unique(np.round(ev[1:] / scale, 12)) * scale

    def rho(params) -> float:
        g, kI, kP = params
        if kI <= 0 or kP <= 0 or not 0 < g < 2:
            return 10.0
        return disagreement_spectral_radius(lambdas, k_phi=g, k_I=kI, k_P=kP)

    grid = np.meshgrid(np.linspace(0.1, 1.0, 10), np.geomspace(0.01, 1.0, 15), np.geomspace(0.05, 5.0, 9))
    G, KI, KP = grid[0].ravel(), grid[1].ravel() / lammax, grid[2].ravel()
    order = np.argsort(_rho_batch(lambdas, G, KI, KP), kind="stable")
    starts = [np.array([G[t], KI[t], KP[t]]) for t in order[:4]]
    r_best, x = rho(starts[0]), starts[0]
    for x0 in starts:  # Nelder-Mead from the four best grid points
        res = minimize(rho, np.array(x0), method="Nelder-Mead", options={"xatol": 1e-10, "fatol": 1e-12, "maxfev": 500})
        if res.fun < r_best:
            r_best, x = float(res.fun), np.array(res.x)
    r = rho(x)
    if not r < max_spectral_radius:
        raise DesignError(
            f"no consensus gains reach spectral radius < {max_spectral_radius:g}: best found {r:.9f} "
            f"(k_phi={x[0]:.4g}, k_I={x[1]:.4g}, k_P={x[2]:.4g}); the graph is too poorly connected, "
            f"lambda_2 / lambda_max = {lam2 / lammax:.3g} (lambda_2 = {lam2:.3g}, lambda_max = {lammax:.3g})"
        )
    return ConsensusGains(float(x[0]), float(x[1]), float(x[2]), float(r), lam2, lammax)


class ConsensusNode:
    """One node's copy of the consensus (all ``v`` rows at once).

    Parameters
    ----------
    node : int
        This node's id (0-based).
    weights : mapping int -> float
        ``a_ij`` for every neighbour ``j`` (row ``i`` of the adjacency).
    Ahat : (m, m) array
        Companion matrix of the signals (eq. (5), discrete time).
    gains : ConsensusGains
    shape : (v, m)
        Shape of ``phi_i``, ``J_i``, ``eta_i``.

    Notes
    -----
    State: ``J``, ``b``, ``eta`` of the last round and, per neighbour, the newest
    ``(stamp, J_j, eta_j)`` received. The payload is ``concat(J.ravel(), eta.ravel())``.
    """

    def __init__(self, *, node: int, weights: Mapping[int, float], Ahat, gains: ConsensusGains, shape) -> None:
        self.node = int(node)
        self._w = {int(j): float(a) for j, a in weights.items() if a != 0 and int(j) != self.node}
        self._Ahat_T = np.array(Ahat, dtype=float).T
        self._powers = [np.eye(self._Ahat_T.shape[0])]
        self.gains = gains
        self.shape = (int(shape[0]), int(shape[1]))
        if self.shape[1] != self._Ahat_T.shape[0]:
            raise DesignError(f"signal shape {self.shape} does not match Ahat of order {self._Ahat_T.shape[0]}")
        self._J = np.zeros(self.shape)
        self._b = np.zeros(self.shape)
        self._eta = np.zeros(self.shape)
        self._last: dict[int, tuple[int, np.ndarray, np.ndarray]] = {}
        self._k: int | None = None
        self.rejected = 0

    @property
    def payload_size(self) -> int:
        return 2 * self.shape[0] * self.shape[1]

    @property
    def average(self) -> np.ndarray:
        """``J_i``, this node's estimate of ``(1/p) sum_j phi_j``; ``(v, m)`` copy."""
        return self._J.copy()

    def _power_T(self, tau: int) -> np.ndarray:
        while len(self._powers) <= tau:
            self._powers.append(self._powers[-1] @ self._Ahat_T)
        return self._powers[tau]

    def receive(self, sender: int, stamp: int, value: np.ndarray) -> None:
        """Keep ``value`` if it is from a neighbour, well formed and newer than what is held."""
        v = np.asarray(value, dtype=float)
        if sender not in self._w or v.shape != (self.payload_size,) or not np.all(np.isfinite(v)):
            self.rejected += 1
            return
        held = self._last.get(sender)
        if held is None or stamp > held[0]:
            half = self.payload_size // 2
            self._last[sender] = (int(stamp), v[:half].reshape(self.shape).copy(), v[half:].reshape(self.shape).copy())

    def step(self, k: int, phi: np.ndarray) -> np.ndarray:
        """Round ``k``: update from ``phi_i[k]`` and the held neighbour values; return the payload."""
        phi = np.asarray(phi, dtype=float)
        if phi.shape != self.shape:
            raise DesignError(f"phi must have shape {self.shape}, got {phi.shape}")
        if self._k is not None and k != self._k + 1:
            raise DesignError(f"rounds must be consecutive: got {k} after {self._k}")
        u, w = self.innovations(k)
        self._J, self._b, self._eta = consensus_update(self._J, self._b, u, w, phi, self._Ahat_T, self.gains)
        self._k = k
        return np.concatenate([self._J.ravel(), self._eta.ravel()])

    def innovations(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """``(u, w)`` of round ``k``: ``sum_j a_ij (J_i - J_j Ahat^tau)`` and the same for ``eta``
        over the held neighbour values (stamped ``k - 1 - tau``, none newer than ``k - 1``)."""
        u = np.zeros(self.shape)
        w = np.zeros(self.shape)
        for j, a in self._w.items():
            held = self._last.get(j)
            if held is None or held[0] > k - 1:
                continue
            P = self._power_T(k - 1 - held[0])
            u += a * (self._J - held[1] @ P)
            w += a * (self._eta - held[2] @ P)
        return u, w


def consensus_update(J: np.ndarray, b: np.ndarray, u: np.ndarray, w: np.ndarray, phi: np.ndarray, A_T: np.ndarray,
                     g: ConsensusGains) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One round of eqs. (6)-(10) given the innovations ``u``, ``w``: the new ``(J, b, eta)``.

    Arrays ``(..., v, m)`` (one node, or a stack of nodes); ``A_T`` is ``Ahat^T``."""
    J = ((1.0 - g.k_phi) * J - 2.0 * g.k_I * w) @ A_T + g.k_phi * phi
    b = (b + g.k_I * u) @ A_T
    eta = g.k_P * b + g.k_I * (u @ A_T)
    return J, b, eta
