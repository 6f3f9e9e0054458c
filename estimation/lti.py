"""Continuous-time LTI plants and their exact discretisation.

``x' = A x + B u``, ``y_i = C_i x + a_i`` (Lee, Kim, Shim, eq. (1)).

Discretisation: zero-order hold. Over one step ``[t_k, t_k + dt)`` the input is held at
``u(t_k)`` and the linear part is integrated exactly::

    x[k+1] = Ad x[k] + Bd u[k],   Ad = expm(A dt),   Bd = (int_0^dt expm(A s) ds) B,

computed from one matrix exponential of the augmented matrix ``[[A, B], [0, 0]] dt``
(Van Loan). With a piecewise-constant input this is exact; for a smooth input the error is
O(dt) in the input only (tests compare with a 10x finer step).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from .errors import DesignError


def zoh(A: np.ndarray, B: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact zero-order-hold discretisation ``(Ad, Bd)`` of ``x' = A x + B u`` at step ``dt``.

    Parameters
    ----------
    A : (n, n) array
    B : (n, p) array (``p`` may be 0)
    dt : float, > 0
    """
    from scipy.linalg import expm

    A = np.asarray(A, dtype=float)
    B = np.asarray(B, dtype=float).reshape(A.shape[0], -1)
    n, p = B.shape
    M = np.zeros((n + p, n + p))
    M[:n, :n] = A * dt
    M[:n, n:] = B * dt
    E = expm(M)
    return E[:n, :n], E[:n, n:]


def zoh_integral(A: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """``(expm(A dt), int_0^dt expm(A s) ds)``: the state and held-input matrices of ``x' = A x + w``."""
    A = np.asarray(A, dtype=float)
    return zoh(A, np.eye(A.shape[0]), dt)


@dataclass(frozen=True)
class ContinuousLTI:
    """A continuous-time LTI plant with sensor banks.

    Attributes
    ----------
    A : (n, n) array
    B : (n, p) array
    banks : tuple of (m_i, n) arrays
        ``C_i``, one per sensor bank (Lee, Kim, Shim eq. (1b)).
    state_names : tuple of str
    """

    A: np.ndarray
    B: np.ndarray
    banks: tuple[np.ndarray, ...]
    state_names: tuple[str, ...]

    def __post_init__(self) -> None:
        n = self.A.shape[0]
        if self.A.shape != (n, n):
            raise DesignError(f"A must be square, got shape {self.A.shape}")
        if self.B.shape[0] != n:
            raise DesignError(f"B must have {n} rows, got shape {self.B.shape}")
        for i, C in enumerate(self.banks):
            if C.ndim != 2 or C.shape[1] != n:
                raise DesignError(f"sensor bank {i + 1}: C must have {n} columns, got shape {C.shape}")

    @property
    def n(self) -> int:
        return self.A.shape[0]

    @property
    def C(self) -> np.ndarray:
        """All banks stacked, ``(m, n)`` (the array itself when the banks are consecutive row
        views of one array, :func:`stacked_banks`; read-only then)."""
        base = self.banks[0].base if self.banks else None
        if base is not None and base.ndim == 2 and base.shape[0] == sum(b.shape[0] for b in self.banks):
            row = 0
            for b in self.banks:
                if (b.base is not base or b.shape[1] != base.shape[1] or b.strides != base.strides
                        or b.__array_interface__["data"][0] != base[row:].__array_interface__["data"][0]):
                    break
                row += b.shape[0]
            else:
                return base
        return np.vstack(self.banks)


def stacked_banks(banks: "list[np.ndarray]") -> tuple[np.ndarray, ...]:
    """``banks`` as consecutive row views of one read-only stacked array (one copy of the
    rows instead of two when :attr:`ContinuousLTI.C` is read: a large plant's many banks)."""
    C = np.vstack(banks) if banks else np.zeros((0, 0))
    C.setflags(write=False)
    out, row = [], 0
    for b in banks:
        out.append(C[row:row + b.shape[0]])
        row += b.shape[0]
    return tuple(out)


def three_inertia(*, J: float = 0.01, b: float = 0.007, k: float = 1.37) -> ContinuousLTI:
    """The three-inertia system of Lee, Kim, Shim, Section IV.

    State ``x = [theta1, dtheta1, theta2, dtheta2, theta3, dtheta3]``, input a torque on
    inertia 1, five single-sensor banks measuring ``theta1, theta2, theta3,
    theta1 - theta2, theta2 - theta3``. Defaults are the paper's
    ``J1 = J2 = J3 = 0.01``, ``b1 = b2 = b3 = 0.007``, ``k1 = k2 = 1.37``.
    """
    J1 = J2 = J3 = J
    b1 = b2 = b3 = b
    k1 = k2 = k
    A = np.array(
        [
            [0, 1, 0, 0, 0, 0],
            [-k1 / J1, -b1 / J1, k1 / J1, 0, 0, 0],
            [0, 0, 0, 1, 0, 0],
            [k1 / J2, 0, -(k1 + k2) / J2, -b2 / J2, k2 / J2, 0],
            [0, 0, 0, 0, 0, 1],
            [0, 0, k2 / J3, 0, -k2 / J3, -b3 / J3],
        ],
        dtype=float,
    )
    B = np.array([[0.0], [1 / J1], [0], [0], [0], [0]])
    C = np.array(
        [
            [1, 0, 0, 0, 0, 0],
            [0, 0, 1, 0, 0, 0],
            [0, 0, 0, 0, 1, 0],
            [1, 0, -1, 0, 0, 0],
            [0, 0, 1, 0, -1, 0],
        ],
        dtype=float,
    )
    return ContinuousLTI(
        A=A,
        B=B,
        banks=tuple(C[i : i + 1] for i in range(5)),
        state_names=("theta1", "dtheta1", "theta2", "dtheta2", "theta3", "dtheta3"),
    )


#: the largest signal a run may reach: products of two signals (squared norms, the
#: monitor's ``|e|_2``) stay finite in float64 (max ~1.8e308)
FLOAT_SIGNAL_LIMIT = 1e150


def float_horizon(Ad: np.ndarray, *, x_norm: float, limit: float = FLOAT_SIGNAL_LIMIT, max_rounds: int,
                  norm: Literal["fro"] | int = "fro") -> int:
    """The last round ``k <= max_rounds`` up to which ``||Ad^j|| x_norm <= limit`` for every
    ``j <= k``: how long an unstable plant's state stays representable (``max_rounds``
    when it does for the whole horizon).

    ``||Ad^j||`` is accumulated in log scale (the running product is renormalised each
    step), measured by default in the Frobenius norm, an upper bound of the 2-norm
    (conservative; ``norm=2`` for the 2-norm itself). Once ``||Ad^j|| < 1`` the powers can never again exceed the largest one seen before
    (``||Ad^(q j + r)|| <= ||Ad^r||``), so a stable plant returns after a few steps.

    A sparse ``Ad`` that splits into decoupled blocks (a diagonal or block-diagonal plant,
    :func:`decoupled_groups`) is raised to its powers block by block, blocks of one size
    stacked: ``||Ad^j||_F^2`` is the sum of the blocks' squares (``||Ad^j||_2`` the largest
    block's), and no dense ``(n, n)``
    power is formed (a 1,024-agent cell team's ``n = 5120`` needs 20 kB, not 400 MB).

    Parameters
    ----------
    Ad : (n, n) array, the one-round transition matrix
    x_norm : float, > 0, a bound of the state's norm at round 0 (input effects included)
    """
    from scipy import sparse

    A = sparse.csr_array(Ad, dtype=float) if sparse.issparse(Ad) else np.asarray(Ad, dtype=float)
    if not x_norm > 0:
        return max_rounds
    budget = np.log(limit / x_norm)
    if budget < 0:
        return 0
    groups = decoupled_groups(A)
    if len(groups) == 1 and groups[0].shape[0] == 1:  # one coupled block: the dense product
        As = [dense(A)]
        Ps = [np.eye(A.shape[0])]
    else:
        As = [_gather_blocks(A, idx) for idx in groups]  # (blocks, s, s) per size s
        Ps = [np.broadcast_to(np.eye(idx.shape[1]), Ab.shape).copy() for idx, Ab in zip(groups, As)]
    log_scale = 0.0
    for k in range(1, max_rounds + 1):
        Ps = [Ab @ P for Ab, P in zip(As, Ps)]
        if len(Ps) == 1 and Ps[0].ndim == 2:
            nP = float(np.linalg.norm(Ps[0], norm))
        elif norm == "fro":  # the blocks' squares add up
            nP = float(np.sqrt(sum(float(np.vdot(P, P)) for P in Ps)))
        else:  # an induced norm of a block-diagonal matrix: the largest block's
            nP = max(float(np.max(np.linalg.norm(P, norm, axis=(1, 2)))) for P in Ps)
        if nP == 0.0:
            return max_rounds
        log_scale += np.log(nP)
        for P in Ps:
            P /= nP
        if log_scale > budget:
            return k - 1
        if log_scale < 0.0:
            return max_rounds
    return max_rounds


def dense(A: Any) -> np.ndarray:
    """``A`` as a dense float array: a ``scipy.sparse`` plant matrix (the block-diagonal
    ``A`` of a cell plant, :mod:`estimation.cells`) made dense, for the analyses of
    small plants that need it (eigenvalues, matrix powers). scipy is not imported: a process
    without it (the monitor's image) calls this on a dense ``A``."""
    return np.asarray(A.toarray() if hasattr(A, "toarray") else A, dtype=float)


def _gather_blocks(A: Any, idx: np.ndarray) -> np.ndarray:
    """The decoupled blocks ``A[idx[b]][:, idx[b]]`` stacked, ``(blocks, s, s)``; a sparse
    ``A`` gives its non-zeros only (no dense ``(n, n)`` array)."""
    from scipy import sparse

    if not sparse.issparse(A):
        return np.asarray(A[idx[:, :, None], idx[:, None, :]])
    nb, s = idx.shape
    flat = idx.reshape(-1)
    sub = sparse.coo_array(A[flat][:, flat])  # block-diagonal in this order: block b at rows b s .. b s + s - 1
    out = np.zeros((nb, s, s))
    out[sub.row // s, sub.row % s, sub.col % s] = sub.data
    return out


def decoupled_groups(A: Any) -> list[np.ndarray]:
    """The decoupled blocks of a square ``A`` (connected components of its sparsity
    pattern), grouped by size: one ``(blocks, size)`` int array of state indices per size.

    ``A`` is a numpy or a ``scipy.sparse`` array. Only a sparse ``A`` is split (at most ``n^2 / 16`` non-zeros: the index arrays then stay
    below an eighth of ``A``'s memory); a denser one is one block, ``[arange(n)[None]]``.
    """
    from scipy.sparse import coo_matrix, issparse
    from scipy.sparse.csgraph import connected_components

    n = A.shape[0]
    whole = [np.arange(n)[None, :]]
    if n < 2 or (A.count_nonzero() if issparse(A) else np.count_nonzero(A)) > n * n // 16:
        return whole
    rows, cols = A.nonzero()
    ncomp, labels = connected_components(coo_matrix((np.ones(rows.size), (rows, cols)), shape=(n, n)),
                                         directed=True, connection="weak")
    if ncomp == 1:
        return whole
    order = np.argsort(labels, kind="stable")
    sizes = np.bincount(labels, minlength=ncomp)
    members = np.split(order, np.cumsum(sizes)[:-1])
    by_size: dict[int, list[np.ndarray]] = {}
    for m in members:
        by_size.setdefault(m.size, []).append(m)
    return [np.stack(ms) for _, ms in sorted(by_size.items())]
