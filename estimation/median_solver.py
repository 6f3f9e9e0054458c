"""The distributed median solver of Lee, Kim, Shim, Section II, and its sgn term.

Scalar solver, eq. (4)::

    x_i' = s_i sgn(z_i - x_i) + gamma * sum_{j in N_i} (x_j - x_i)

Theorem 1: on a connected undirected graph, ``limsup |x_i|_M <= 2 sqrt(N) / (gamma
lambda_2)`` where ``M`` is the median set of the indicated ``z_i``.

Discretisation (used by :func:`run_scalar_median_solver` and by the state estimator):
over one step ``dt`` the sgn term and the neighbours' values are held, and the
self-coupling ``-gamma d_i x_i`` is integrated exactly::

    x_i+ = e^{-c dt} x_i + (1 - e^{-c dt}) / c * (s_i sgn(z_i - x_i) + gamma sum_j x_j),
    c = gamma d_i.

The update is a convex combination of ``x_i`` and the neighbours' mean plus a bounded
push, so it is stable for every ``dt``; the held sgn chatters with amplitude O(dt).
"""

from __future__ import annotations

import numpy as np

from .graphs import algebraic_connectivity, in_neighbours


def sgn(x: np.ndarray) -> np.ndarray:
    """The signum of the paper's notation (``sgn(0) = 0``)."""
    return np.sign(x)


def sgn_median_term(z: np.ndarray, x: np.ndarray, s: np.ndarray) -> np.ndarray:
    """``s * sgn(z - x)``, the local median-seeking term of eqs. (4) and (6).

    Parameters
    ----------
    z : (o,) array  local (partial) estimates ``w_l^T V_i z_i``
    x : (o,) array  the current estimate projected the same way ``w_l^T x_hat_i``
    s : (o,) array of {0, 1}  indicators ``s_i^l``
    """
    return s * np.sign(z - x)


def theorem1_bound(Adj: np.ndarray, gamma: float) -> float:
    """``2 sqrt(N) / (gamma lambda_2(L))`` of Theorem 1."""
    N = Adj.shape[0]
    return 2.0 * np.sqrt(N) / (gamma * algebraic_connectivity(Adj))


def run_scalar_median_solver(
    z: np.ndarray,
    s: np.ndarray,
    Adj: np.ndarray,
    *,
    gamma: float,
    dt: float,
    steps: int,
    x0: np.ndarray,
) -> np.ndarray:
    """Integrate eq. (4) for ``steps`` steps; returns the trajectory ``(steps + 1, N)``."""
    z = np.asarray(z, dtype=float)
    s = np.asarray(s, dtype=float)
    N = len(z)
    nbrs = [in_neighbours(Adj, i) for i in range(N)]
    c = gamma * np.array([len(nb) for nb in nbrs], dtype=float)
    decay = np.exp(-c * dt)
    gain = np.where(c > 0, (1 - decay) / np.where(c > 0, c, 1.0), dt)
    x = np.array(x0, dtype=float)
    out = np.empty((steps + 1, N))
    out[0] = x
    Adjf = np.asarray(Adj, dtype=float)
    for k in range(steps):
        push = sgn_median_term(z, x, s) + gamma * (Adjf @ x)
        x = decay * x + gain * push
        out[k + 1] = x
    return out


def median_set(z: np.ndarray, s: np.ndarray) -> tuple[float, float]:
    """The median interval ``[lo, hi]`` of the indicated values (Section II)."""
    vals = np.sort(np.asarray(z, dtype=float)[np.asarray(s) == 1])
    S = len(vals)
    if S == 0:
        raise ValueError("no indicated value")
    if S % 2:
        return float(vals[S // 2]), float(vals[S // 2])
    return float(vals[S // 2 - 1]), float(vals[S // 2])
