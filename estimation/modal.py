"""Modal coordinates of a plant with real, distinct eigenvalues.

Mitra, Richards, Bagchi, Sundaram, "Resilient distributed state estimation with mobile
agents" (Autonomous Robots 2019), Section 3.1, eq. (4). Under Assumption 1 (``A`` has
real, distinct eigenvalues) a real similarity transformation diagonalises the plant::

    z[k] = W x[k],   x[k] = V z[k],   W A V = diag(lambda_1, ..., lambda_n).

Naming: the paper writes ``z = V x``; here ``V`` holds the eigenvectors as columns
(``x_hat = V @ z_hat``) and ``W = V^{-1}`` is the paper's ``V``.

Decoupled blocks. Plants made of decoupled sub-plants (the cells of Section 8) repeat the
same eigenvalues in every cell, so the global ``A`` violates Assumption 1 although each
cell satisfies it. The decomposition is therefore computed block by block: the blocks are
the connected components of the sparsity pattern of ``A`` (or given explicitly), and the
eigenvalues must be real and distinct *within* each block. The block-wise eigenbasis still
diagonalises ``A`` and every measurement column keeps its meaning per mode; whether modes
seen together by one sensing location are distinguishable is checked where it matters, in
the observer design (:mod:`estimation.switched_observer`).

Normalisation: the eigen-decomposition runs on every connected component of the
sparsity pattern (inside each given block); symmetric components use ``eigh``
(orthonormal eigenvectors), others ``eig`` with unit 2-norm columns. The largest-magnitude
entry of every eigenvector is made positive. Within a component the modes are ordered by
decreasing eigenvalue; components appear in the order of their smallest state index, so
a diagonal ``A`` keeps its state order (``V = I``).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .errors import DesignError

#: relative tolerance for "real" and "distinct" eigenvalues
EIG_TOL = 1e-9
#: largest condition number accepted for one block's eigenvector matrix
MAX_COND = 1e12


@dataclass(frozen=True, eq=False)
class ModalForm:
    """The modal decomposition of eq. (4), held per decoupled piece.

    ``V`` and ``W`` are block diagonal up to a permutation (one block per connected
    component of ``A``'s sparsity pattern), so only the pieces are stored: a team of
    1,024 agents on a 5,120-state diagonal plant holds 5,120 scalars, not two dense
    5,120 x 5,120 matrices. The dense ``V`` and ``W`` are built on first use (and kept).

    Attributes
    ----------
    lam : (n,) float array
        Eigenvalue of each mode (modal coordinate).
    block_of_mode : (n,) int array
        Index of the decoupled block each mode belongs to.
    blocks : tuple of (n_b,) int arrays
        State indices of each block.
    pieces : tuple of ``(states (s,) int array, first mode, vb (s, s), wb (s, s))``
        Each connected piece: ``V[states, first:first+s] = vb``, ``W[first:first+s, states] = wb``.
    V : (n, n) float array (property)
        Eigenvectors as columns: ``x = V z``.
    W : (n, n) float array (property)
        ``V^{-1}``: ``z = W x`` (the paper's ``V``).
    """

    lam: np.ndarray
    block_of_mode: np.ndarray
    blocks: tuple[np.ndarray, ...]
    pieces: tuple[tuple[np.ndarray, int, np.ndarray, np.ndarray], ...]

    @property
    def n(self) -> int:
        return int(self.lam.shape[0])

    def _dense(self, which: int) -> np.ndarray:
        n = self.n
        M = np.zeros((n, n))
        for idx, start, vb, wb in self.pieces:
            modes = np.arange(start, start + idx.size)
            if which == 0:
                M[np.ix_(idx, modes)] = vb
            else:
                M[np.ix_(modes, idx)] = wb
        M.setflags(write=False)
        return M

    @functools.cached_property
    def V(self) -> np.ndarray:
        """Dense ``(n, n)`` eigenvector matrix (built from the pieces on first use)."""
        return self._dense(0)

    @functools.cached_property
    def W(self) -> np.ndarray:
        """Dense ``(n, n)`` ``V^{-1}`` (built from the pieces on first use)."""
        return self._dense(1)

    @functools.cached_property
    def is_identity(self) -> bool:
        """Whether ``V`` is the identity (the state is already modal: ``x = z``); computed once."""
        return all(np.array_equal(idx, np.arange(start, start + idx.size)) and np.array_equal(vb, np.eye(idx.size))
                   for idx, start, vb, _ in self.pieces)

    @functools.cached_property
    def _where(self) -> tuple[np.ndarray, np.ndarray]:
        """Per state: its piece and its row inside the piece."""
        piece, local = np.zeros(self.n, dtype=int), np.zeros(self.n, dtype=int)
        for p, (idx, _, _, _) in enumerate(self.pieces):
            piece[idx], local[idx] = p, np.arange(idx.size)
        return piece, local

    def v_rows(self, states: np.ndarray) -> np.ndarray:
        """``V[states, :]`` ``(len(states), n)`` without the dense ``V``."""
        piece, local = self._where
        out = np.zeros((len(states), self.n))
        for r, st in enumerate(states):
            idx, start, vb, _ = self.pieces[piece[st]]
            out[r, start:start + idx.size] = vb[local[st]]
        return out

    @property
    def spectral_radius(self) -> float:
        """``rho(A)``, used by the MSS condition (23)."""
        return float(np.max(np.abs(self.lam))) if self.n else 0.0

    def to_modal(self, x: np.ndarray) -> np.ndarray:
        """``z = W x`` for ``x`` of shape ``(..., n)`` (leading batch axes allowed), piece by piece."""
        x = np.asarray(x, dtype=float)
        z = np.empty(x.shape)
        for idx, start, _, wb in self.pieces:
            z[..., start:start + idx.size] = x[..., idx] @ wb.T
        return z

    def to_state(self, z: np.ndarray) -> np.ndarray:
        """``x = V z`` for ``z`` of shape ``(..., n)``, piece by piece."""
        z = np.asarray(z, dtype=float)
        x = np.empty(z.shape)
        for idx, start, vb, _ in self.pieces:
            x[..., idx] = z[..., start:start + idx.size] @ vb.T
        return x

    def modal_rows(self, C: np.ndarray) -> np.ndarray:
        """``C~ = C V`` of eq. (4): measurement rows ``(r, n)`` in modal coordinates.

        Only the states a row reads enter the product (a sensing location reads a few
        states of a large plant: ``O(r s n)`` for ``s`` read states instead of ``O(r n^2)``)."""
        C = np.atleast_2d(np.asarray(C, dtype=float))
        if self.is_identity:
            return C.copy()
        cols = np.flatnonzero(np.any(C != 0, axis=0))
        return C[:, cols] @ self.v_rows(cols)


def decoupled_blocks(A: Any) -> tuple[np.ndarray, ...]:
    """Connected components of the sparsity pattern of ``A`` (exact zeros decouple).

    Returns the components as sorted state-index arrays, ordered by smallest index.
    """
    from scipy import sparse
    from scipy.sparse.csgraph import connected_components

    if sparse.issparse(A):
        pattern = sparse.csr_array(A != 0, dtype=np.int8)
        ncomp, labels = connected_components(pattern, directed=True, connection="weak")
    else:
        A = np.asarray(A)
        pattern = (A != 0) | (A.T != 0)
        ncomp, labels = connected_components(pattern.astype(np.int8), directed=False)
    comps = [np.flatnonzero(labels == c) for c in range(ncomp)]
    return tuple(sorted(comps, key=lambda c: int(c[0])))


def _block_eig(Ab: np.ndarray, where: str) -> tuple[np.ndarray, np.ndarray]:
    scale = max(1.0, float(np.max(np.abs(Ab)))) if Ab.size else 1.0
    if np.array_equal(Ab, Ab.T):
        lam, vec = np.linalg.eigh(Ab)
    else:
        lamc, vecc = np.linalg.eig(Ab)
        bad = np.flatnonzero(np.abs(lamc.imag) > EIG_TOL * scale)
        if bad.size:
            raise DesignError(
                f"{where}: A has complex eigenvalues {np.round(lamc[bad], 6).tolist()}; "
                "Assumption 1 of Mitra et al. needs real, distinct eigenvalues"
            )
        lam = lamc.real
        vec = np.real(vecc)
        vec = vec / np.linalg.norm(vec, axis=0, keepdims=True)
    order = np.argsort(-lam, kind="stable")
    lam, vec = lam[order], vec[:, order]
    if lam.size > 1:
        gaps = -np.diff(lam)
        j = int(np.argmin(gaps))
        if gaps[j] <= EIG_TOL * scale:
            raise DesignError(
                f"{where}: A has a repeated eigenvalue {lam[j]:.12g} (gap {gaps[j]:.3g}); "
                "Assumption 1 of Mitra et al. needs real, distinct eigenvalues within "
                "each decoupled block"
            )
    cond = np.linalg.cond(vec) if lam.size else 1.0
    if not np.isfinite(cond) or cond > MAX_COND:
        raise DesignError(f"{where}: eigenvector matrix is ill-conditioned (cond {cond:.3g})")
    idx = np.argmax(np.abs(vec), axis=0)
    sign = np.sign(vec[idx, np.arange(vec.shape[1])])
    sign[sign == 0] = 1.0
    return lam, vec * sign


def modal_form(A: Any, *, blocks: Sequence[Sequence[int] | np.ndarray] | None = None) -> ModalForm:
    """Modal coordinates of ``A`` (eq. (4)), computed per decoupled block.

    Parameters
    ----------
    A : (n, n) array or scipy.sparse array
        The discrete-time system matrix of eq. (1) (a sparse one is made dense block by
        block only).
    blocks : sequence of index sequences, optional
        A partition of ``0..n-1`` into decoupled blocks. ``A`` must have no entry
        coupling two blocks. Default: the connected components of the sparsity pattern.

    Returns
    -------
    ModalForm

    Raises
    ------
    DesignError
        ``A`` is not square/finite, ``blocks`` is not a decoupling partition, or a block
        has complex or repeated eigenvalues (Assumption 1) or near-defective eigenvectors.
    """
    from scipy import sparse

    entries: np.ndarray
    if sparse.issparse(A):  # a block-diagonal plant kept sparse: only its blocks are made dense
        A = sparse.csr_array(A, dtype=float)
        entries = A.data
    else:
        A = np.asarray(A, dtype=float)
        entries = A
    if A.ndim != 2 or A.shape[0] != A.shape[1]:
        raise DesignError(f"A must be square, got shape {A.shape}")
    if not np.all(np.isfinite(entries)):
        raise DesignError("A has non-finite entries")
    n = A.shape[0]
    if blocks is None:
        parts = decoupled_blocks(A)
    else:
        parts = tuple(np.asarray(sorted(int(i) for i in b), dtype=int) for b in blocks)
        flat = np.concatenate(parts) if parts else np.zeros(0, dtype=int)
        if flat.size != n or not np.array_equal(np.sort(flat), np.arange(n)):
            raise DesignError(f"blocks must partition the {n} states exactly once each")
        label = np.empty(n, dtype=int)
        for b, idx in enumerate(parts):
            label[idx] = b
        rows, cols = A.nonzero()
        cross = label[rows] != label[cols]
        if np.any(cross):
            r, c = int(rows[cross][0]), int(cols[cross][0])
            raise DesignError(f"blocks are not decoupled: A[{r}, {c}] = {A[r, c]:.6g} couples block {label[r]} and block {label[c]}")
    lam = np.zeros(n)
    block_of_mode = np.zeros(n, dtype=int)
    pieces = []
    start = 0
    for b, part in enumerate(parts):
        # a given block may itself split into decoupled pieces (e.g. a diagonal cell)
        Ap = A[part][:, part].toarray() if sparse.issparse(A) else A[np.ix_(part, part)]
        for sub in decoupled_blocks(Ap):
            idx = part[sub]
            lb, vb = _block_eig(Ap[np.ix_(sub, sub)], where=f"block {b} (states {part[0]}..{part[-1]})")
            modes = np.arange(start, start + idx.size)
            lam[modes] = lb
            wb = np.linalg.inv(vb)
            for arr in (idx, vb, wb):
                arr.setflags(write=False)
            pieces.append((idx, start, vb, wb))
            block_of_mode[modes] = b
            start += idx.size
    for arr in (lam, block_of_mode):
        arr.setflags(write=False)
    return ModalForm(lam=lam, block_of_mode=block_of_mode, blocks=parts, pieces=tuple(pieces))
