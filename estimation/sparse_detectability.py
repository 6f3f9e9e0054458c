"""Sparse detectability with respect to a compression matrix, and the search for ``D``.

Mao, Tabuada, "Decentralized resilient state-tracking", Section IV
(``papers/mao_tabuada_decentralized_resilient_state_tracking.md``).

Discrete-time plant ``x[k+1] = A x[k]``, scalar sensors ``y_i[k] = C_i x[k] + e_i[k]``,
``C`` of shape ``(p, n)``, compression ``D`` of shape ``(v, p)``.

Definition 3: for a support ``V`` (a set of at most ``k`` sensors) let ``L_V`` be any
matrix with ``ker L_V = D span{e_i : i in V} = range(D_V)``. ``(A, C)`` is
``k``-sparse detectable w.r.t. ``D`` when ``(A, L_V D C)`` is detectable for every
``|V| <= k``. Here ``L_V = N_V^T`` with ``N_V`` an orthonormal basis of
``range(D_V)^perp``, and detectability is the discrete-time PBH test: every eigenvalue
``mu`` of ``A`` with ``|mu| >= 1`` must satisfy ``rank [mu I - A; L_V D C] = n``.
A larger support only enlarges ``ker L_V``, so checking ``|V| = min(k, p)`` suffices:
``C(p, k)`` supports, each an SVD of a ``(n + v) x n`` matrix per unstable eigenvalue.

Margin (what "how well conditioned" means here, the paper is silent): the smallest
singular value of ``[(mu I - A) / ||A||; L_V D C / ||C||]`` over all supports and all
``|mu| >= 1``. It is 0 exactly when the property fails; the property is declared to hold
when the margin exceeds ``tol`` (default ``1e-9``). The report also gives ``cond(D)``.

Facts used by :func:`design_compression`:

* Lemma 1 / Corollary 1: if ``(A, C)`` is not ``2s``-sparse detectable (w.r.t. the
  identity) no ``D`` works -- :class:`DesignError`.
* ``v >= 2s + 1`` is necessary when ``A`` is not Schur: with ``v <= 2s`` a support made
  of a column basis of ``D`` gives ``range(D_V) = range(D)``, hence ``L_V D = 0``.
* ``D = I_p`` works whenever ``(A, C)`` is ``2s``-sparse detectable (Corollary 1).

The search (the paper gives none): for ``v = 2s+1, ..., p-1`` try, in this order, the
first ``v`` rows of the orthonormal DCT-II matrix of order ``p`` (deterministic, rows
orthonormal so ``cond(D) = 1``) and ``n_random`` random matrices with orthonormal rows
drawn from a seeded generator; the first ``v`` for which some candidate passes is kept
and, among its passing candidates, the one with the largest margin. If no ``v < p``
works, ``D = I_p``.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations
from math import comb

import numpy as np

from .errors import DesignError

__all__ = [
    "DetectabilityReport",
    "sparse_detectability",
    "sparse_detectability_index",
    "design_compression",
]


@dataclass(frozen=True)
class DetectabilityReport:
    """Outcome of a ``k``-sparse detectability test w.r.t. ``D``.

    Attributes
    ----------
    k : int
        Number of sensors removed (the ``2s`` of Lemma 2).
    holds : bool
        Whether ``(A, L_V D C)`` is detectable for every ``|V| <= k``.
    margin : float
        Smallest normalised PBH singular value (0 when it fails); see the module docstring.
    worst_support : tuple of int
        A support attaining the margin (0-based sensor ids).
    v : int
        Rows of ``D``.
    cond_D : float
        ``sigma_max(D) / sigma_min(D)`` (inf when ``D`` is row-rank deficient).
    supports_checked : int
        ``C(p, min(k, p))``.
    """

    k: int
    holds: bool
    margin: float
    worst_support: tuple[int, ...]
    v: int
    cond_D: float
    supports_checked: int
    D: np.ndarray

    def __repr__(self) -> str:  # the matrix is long; keep the repr readable
        return (
            f"DetectabilityReport(k={self.k}, holds={self.holds}, margin={self.margin:.3g}, "
            f"worst_support={self.worst_support}, v={self.v}, cond_D={self.cond_D:.3g})"
        )


def _check_AC(A, C) -> tuple[np.ndarray, np.ndarray]:
    A = np.asarray(A, dtype=float)
    C = np.asarray(C, dtype=float)
    if A.ndim != 2 or A.shape[0] != A.shape[1]:
        raise DesignError(f"A must be a square matrix, got shape {A.shape}")
    if C.ndim != 2 or C.shape[1] != A.shape[0]:
        raise DesignError(f"C must have shape (p, {A.shape[0]}) (one row per scalar sensor), got {C.shape}")
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(C))):
        raise DesignError("A and C must be finite")
    return A, C


def _check_D(D, p: int) -> np.ndarray:
    D = np.asarray(D, dtype=float)
    if D.ndim != 2 or D.shape[1] != p or D.shape[0] < 1:
        raise DesignError(f"D must have shape (v, {p}) with v >= 1, got {D.shape}")
    if not np.all(np.isfinite(D)):
        raise DesignError("D must be finite")
    return D


def _unstable_eigenvalues(A: np.ndarray) -> np.ndarray:
    """Eigenvalues with ``|mu| >= 1`` (discrete-time instability), one per conjugate pair."""
    ev = np.linalg.eigvals(A)
    ev = ev[np.abs(ev) >= 1.0 - 1e-12]
    return ev[ev.imag >= -1e-12 * np.maximum(1.0, np.abs(ev))]


def _annihilator(DV: np.ndarray, *, tol: float = 1e-10) -> np.ndarray:
    """``N^T`` with ``N`` an orthonormal basis of ``range(DV)^perp``; shape ``(v - r, v)``."""
    v = DV.shape[0]
    if DV.shape[1] == 0:
        return np.eye(v)
    U, sv, _ = np.linalg.svd(DV, full_matrices=True)
    r = int(np.sum(sv > tol * max(1.0, sv[0] if sv.size else 1.0)))
    return U[:, r:].T


def sparse_detectability(A, C, *, k: int, D=None, tol: float = 1e-9) -> DetectabilityReport:
    """Test whether ``(A, C)`` is ``k``-sparse detectable w.r.t. ``D`` (Definition 3).

    Parameters
    ----------
    A : (n, n) array
        Discrete-time state matrix.
    C : (p, n) array
        One row per scalar sensor.
    k : int, keyword-only
        Number of sensors that may be removed (``2s`` for Lemma 2).
    D : (v, p) array, optional
        Compression matrix; the identity when omitted.
    tol : float
        Margin below which a PBH matrix is declared rank deficient.

    Returns
    -------
    DetectabilityReport
    """
    A, C = _check_AC(A, C)
    p, n = C.shape
    D = np.eye(p) if D is None else _check_D(D, p)
    if not isinstance(k, (int, np.integer)) or k < 0:
        raise DesignError(f"k must be a non-negative integer, got {k!r}")
    k = int(min(k, p))
    sv = np.linalg.svd(D, compute_uv=False)
    cond_D = float(sv[0] / sv[-1]) if sv[-1] > 1e-14 * sv[0] and D.shape[0] <= p else float("inf")
    nA = max(np.linalg.norm(A, 2), 1e-300)
    nC = max(np.linalg.norm(C, 2), 1e-300)
    mus = _unstable_eigenvalues(A)
    DC = D @ C / nC
    worst = np.inf
    worst_V: tuple[int, ...] = ()
    for V in combinations(range(p), k):
        N = _annihilator(D[:, list(V)])
        LDC = N @ DC
        for mu in mus:
            pbh = np.vstack([(mu * np.eye(n) - A) / nA, LDC.astype(complex)])
            m = float(np.linalg.svd(pbh, compute_uv=False)[-1]) if pbh.shape[0] >= n else 0.0
            if m < worst:
                worst, worst_V = m, tuple(V)
    if mus.size == 0:  # A Schur: every pair is detectable
        worst = np.inf
    return DetectabilityReport(
        k=k,
        holds=bool(worst > tol),
        margin=float(worst),
        worst_support=worst_V,
        v=D.shape[0],
        cond_D=cond_D,
        supports_checked=comb(p, k),
        D=D.copy(),
    )


def sparse_detectability_index(A, C, *, D=None, tol: float = 1e-9) -> int:
    """The sparse detectability index w.r.t. ``D``: the largest ``k`` that holds (Definition 3).

    Returns ``p`` when even removing every sensor leaves a detectable pair (``A`` Schur),
    and ``-1`` when ``(A, D C)`` itself is not detectable.
    """
    A, C = _check_AC(A, C)
    p = C.shape[0]
    best = -1
    for k in range(p + 1):
        if not sparse_detectability(A, C, k=k, D=D, tol=tol).holds:
            break
        best = k
    return best


def _orthonormal_rows(M: np.ndarray) -> np.ndarray:
    Q, _ = np.linalg.qr(M.T)
    return Q.T


def design_compression(
    A, C, *, s: int, n_random: int = 20, seed: int = 0, tol: float = 1e-9, min_margin: float = 0.0
) -> DetectabilityReport:
    """Find a compression ``D`` with as few rows as possible such that ``(A, C)`` is
    ``2s``-sparse detectable w.r.t. ``D`` (Section IV; the search is the module docstring's).

    Parameters
    ----------
    A : (n, n) array
    C : (p, n) array
    s : int, keyword-only
        Number of attacked sensors to tolerate.
    n_random : int
        Random candidates per ``v`` besides the DCT rows.
    seed : int
        Seed of the candidate generator (the result is deterministic).
    tol : float
        Rank tolerance of the PBH test.
    min_margin : float
        A candidate must also have margin ``>= min_margin`` (a conditioning requirement).

    Returns
    -------
    DetectabilityReport
        Its ``D`` is the chosen matrix, shape ``(v, p)``.

    Raises
    ------
    DesignError
        If ``(A, C)`` is not ``2s``-sparse detectable (then no ``D`` exists, Corollary 1).
    """
    from scipy.fft import dct

    A, C = _check_AC(A, C)
    p = C.shape[0]
    if not isinstance(s, (int, np.integer)) or s < 0:
        raise DesignError(f"s must be a non-negative integer, got {s!r}")
    ident = sparse_detectability(A, C, k=2 * s, tol=tol)
    if not ident.holds:
        raise DesignError(
            f"(A, C) is not {2 * s}-sparse detectable (removing sensors {list(ident.worst_support)} "
            f"leaves an unstable mode unobservable), so no compression matrix D exists "
            f"(Lemma 1, Corollary 1); s = {s} attacked sensors cannot be tolerated with p = {p}"
        )
    rng = np.random.default_rng(seed)
    full_dct = dct(np.eye(p), type=2, norm="ortho", axis=0)
    for v in range(2 * s + 1, p):
        cands = [full_dct[:v]] + [_orthonormal_rows(rng.standard_normal((v, p))) for _ in range(n_random)]
        good = []
        for Dc in cands:
            rep = sparse_detectability(A, C, k=2 * s, D=Dc, tol=tol)
            if rep.holds and rep.margin >= min_margin:
                good.append(rep)
        if good:
            return max(good, key=lambda r: r.margin)
    return ident
