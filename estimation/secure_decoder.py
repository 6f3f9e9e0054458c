"""Secure state reconstruction from compressed measurements, and the plain LS decoder.

Mao, Tabuada, "Decentralized resilient state-tracking", Sections III-D and VI (the paper
leaves the decoder unspecified: "any suitably modified RSR algorithm").

Model. Each sensor ``i`` has a window ``Y_i = O_i x + E_i`` (``O_i`` of shape ``(m, n)``,
``E_i`` non-zero for at most ``s`` sensors). Every node holds the compressed windows::

    Z = (D (x) I_m) Y,   i.e.  Z_r = sum_i d_ri Y_i,   r = 1..v,   Z of shape (v, m),

so ``vec Z = M x + (D_V (x) I_m) E_V`` with ``M = (D (x) I_m) O`` of shape ``(v m, n)``.

Secure decoder (exhaustive support search, the modification for compression). For each
candidate support ``V`` with ``|V| = s`` (supersets need not be tried separately: a
smaller true support is contained in some ``V`` of size ``s``), let ``N_V^T`` annihilate
``range(D_V)``, so ``Q_V = N_V^T (x) I_m`` removes every attack on ``V``. Solve
``min_x ||Q_V (vec Z - M x)||`` and keep the support with the smallest residual
relative to ``||Z||``. If ``(A, C)`` is ``2s``-sparse detectable w.r.t. ``D`` (Lemma 2)
any support with zero residual yields the true state (up to the stable unobservable
part): ``M(x - x') in range(D_{V u V'} (x) I_m)`` with ``|V u V'| <= 2s``.

Complexity: offline ``C(p, s)`` SVDs of ``(v m) x n`` matrices; per decode one product
of the stacked ``(C(p, s), q + n, v m)`` operators with ``vec Z``, i.e.
``O(C(p, s) v m (v m + n))`` flops -- exponential in ``s`` (the problem is NP-hard in
general), fine for the small ``p`` of the scenarios (``C(8, 2) = 28``).

The plain least-squares decoder ``x = M^+ vec Z`` is the non-resilient baseline.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np

from .errors import DesignError

__all__ = ["DecodeResult", "SecureDecoder", "least_squares_decode", "compressed_observability"]


@dataclass(frozen=True)
class DecodeResult:
    """Decoded state.

    Attributes
    ----------
    x : (n,) array
    support : tuple of int
        The support declared attacked (0-based sensors; empty for least squares).
    residual : float
        ``||Q_V (vec Z - M x)|| / ||Z||`` of the chosen support (0 when ``Z = 0``).
    """

    x: np.ndarray
    support: tuple[int, ...]
    residual: float


def _check(O_blocks, D) -> tuple[np.ndarray, np.ndarray]:
    O = np.asarray(O_blocks, dtype=float)
    D = np.asarray(D, dtype=float)
    if O.ndim != 3:
        raise DesignError(f"O_blocks must have shape (p, m, n), got {O.shape}")
    if D.ndim != 2 or D.shape[1] != O.shape[0]:
        raise DesignError(f"D must have shape (v, {O.shape[0]}), got {D.shape}")
    return O, D


def compressed_observability(O_blocks, D) -> np.ndarray:
    """``M = (D (x) I_m) O``, shape ``(v m, n)``, rows ordered as ``Z.ravel()`` (row-major)."""
    O, D = _check(O_blocks, D)
    return np.einsum("ri,imn->rmn", D, O).reshape(D.shape[0] * O.shape[1], O.shape[2])


def least_squares_decode(Z, O_blocks, D) -> DecodeResult:
    """Plain least squares ``x = M^+ vec Z`` (no support search; not resilient).

    Parameters
    ----------
    Z : (v, m) array
    O_blocks : (p, m, n) array
    D : (v, p) array
    """
    M = compressed_observability(O_blocks, D)
    z = np.asarray(Z, dtype=float).ravel()
    if z.shape[0] != M.shape[0]:
        raise DesignError(f"Z must have {M.shape[0]} entries, got {z.shape[0]}")
    x, *_ = np.linalg.lstsq(M, z, rcond=None)
    nz = np.linalg.norm(z)
    return DecodeResult(x, (), float(np.linalg.norm(z - M @ x) / nz) if nz > 0 else 0.0)


class SecureDecoder:
    """Exhaustive-search secure decoder for compressed windows (module docstring).

    Parameters
    ----------
    O_blocks : (p, m, n) array
        ``O_i`` per sensor.
    D : (v, p) array
        Compression matrix.
    s : int, keyword-only
        Number of sensors that may be attacked.
    rank_tol : float
        Relative tolerance for ranks of ``D_V`` and for the pseudo-inverses.
    """

    def __init__(self, O_blocks, D, *, s: int, rank_tol: float = 1e-10) -> None:
        O, D = _check(O_blocks, D)
        p, m, n = O.shape
        v = D.shape[0]
        if not isinstance(s, (int, np.integer)) or not 0 <= s < p:
            raise DesignError(f"s must be an integer in [0, {p - 1}], got {s!r}")
        self.s, self.p, self.n, self.v, self.m = int(s), p, n, v, m
        M = compressed_observability(O, D)
        self._supports = list(combinations(range(p), self.s))
        q = v * m
        self._X = np.zeros((len(self._supports), n, q))  # x_V = X_V vec Z
        self._R = np.zeros((len(self._supports), q, q))  # residual operator, zero-padded rows
        for t, V in enumerate(self._supports):
            DV = D[:, list(V)]
            U, sv, _ = np.linalg.svd(DV, full_matrices=True) if V else (np.eye(v), np.zeros(0), None)
            r = int(np.sum(sv > rank_tol * max(1.0, sv[0] if sv.size else 1.0)))
            Q = np.kron(U[:, r:].T, np.eye(m))  # annihilates range(D_V (x) I_m)
            B = Q @ M
            G = np.linalg.pinv(B, rcond=rank_tol)
            self._X[t] = G @ Q
            self._R[t, : Q.shape[0]] = Q - B @ (G @ Q)

    @property
    def n_supports(self) -> int:
        return len(self._supports)

    def decode(self, Z) -> DecodeResult:
        """Decode ``Z`` of shape ``(v, m)``; returns the state of the best-fitting support."""
        z = np.asarray(Z, dtype=float).ravel()
        if z.shape[0] != self.v * self.m:
            raise DesignError(f"Z must have shape ({self.v}, {self.m}), got {np.shape(Z)}")
        res = np.linalg.norm(self._R @ z, axis=1)
        t = int(np.argmin(res))
        nz = np.linalg.norm(z)
        return DecodeResult(self._X[t] @ z, self._supports[t], float(res[t] / nz) if nz > 0 else 0.0)
