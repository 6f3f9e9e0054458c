"""Small, numerically careful subspace helpers (orthonormal bases as matrices).

A subspace of R^n is represented by an ``(n, d)`` matrix with orthonormal columns
(``d = 0`` allowed). Ranks are decided with a tolerance relative to the data.
"""

from __future__ import annotations

import numpy as np

#: Relative tolerance used to decide ranks and memberships.
RTOL = 1e-9


def basis(M: np.ndarray, *, rtol: float = RTOL) -> np.ndarray:
    """Orthonormal basis ``(n, r)`` of the column space of ``M`` (``(n, m)``)."""
    from scipy.linalg import orth

    M = np.asarray(M, dtype=float)
    if M.size == 0 or M.shape[1] == 0:
        return np.zeros((M.shape[0], 0))
    return orth(M, rcond=rtol)


def kernel(M: np.ndarray, *, rtol: float = RTOL) -> np.ndarray:
    """Orthonormal basis ``(m, r)`` of the null space of ``M`` (``(p, m)``)."""
    from scipy.linalg import null_space

    M = np.asarray(M, dtype=float)
    if M.shape[0] == 0:
        return np.eye(M.shape[1])
    return null_space(M, rcond=rtol)


def intersect(Q1: np.ndarray, Q2: np.ndarray, *, rtol: float = RTOL) -> np.ndarray:
    """Orthonormal basis of ``span(Q1) & span(Q2)`` for orthonormal ``Q1``, ``Q2``."""
    n = Q1.shape[0]
    if Q1.shape[1] == 0 or Q2.shape[1] == 0:
        return np.zeros((n, 0))
    N = kernel(np.hstack([Q1, -Q2]), rtol=rtol)
    if N.shape[1] == 0:
        return np.zeros((n, 0))
    return basis(Q1 @ N[: Q1.shape[1]], rtol=rtol)


def add(*Qs: np.ndarray, n: int, rtol: float = RTOL) -> np.ndarray:
    """Orthonormal basis of the sum of the given subspaces of R^n."""
    cols = [Q for Q in Qs if Q.shape[1] > 0]
    if not cols:
        return np.zeros((n, 0))
    return basis(np.hstack(cols), rtol=rtol)


def contains(Q: np.ndarray, v: np.ndarray, *, tol: float = 1e-7) -> bool:
    """Whether the vector(s) ``v`` (``(n,)`` or ``(n, k)``) lie in ``span(Q)``."""
    v = np.asarray(v, dtype=float).reshape(Q.shape[0], -1)
    scale = max(float(np.linalg.norm(v)), 1e-300)
    if Q.shape[1] == 0:
        return bool(np.linalg.norm(v) <= tol * scale)
    residual = v - Q @ (Q.T @ v)
    return bool(np.linalg.norm(residual) <= tol * scale)


def same(Q1: np.ndarray, Q2: np.ndarray) -> bool:
    """Whether two orthonormal bases span the same subspace."""
    return Q1.shape[1] == Q2.shape[1] and contains(Q1, Q2)


def complement_in(E: np.ndarray, F: np.ndarray, *, rtol: float = RTOL) -> np.ndarray:
    """Orthonormal basis of ``E & F^perp`` (the orthogonal complement of F inside E).

    ``F`` must be a subspace of ``E``; then ``E = F (+) result``.
    """
    if E.shape[1] == 0:
        return E
    if F.shape[1] == 0:
        return E
    N = kernel(F.T @ E, rtol=rtol)
    return E @ N
