"""W-MSR resilient consensus with local observers, on the modes of a discrete-time plant.

The plant ``x[k+1] = A x[k]``, ``y_i[k] = C_i x[k]`` is written in modal coordinates
``z = W x`` (``A = V diag(lam) W``, ``W = V^-1``; ``A`` must have real eigenvalues and be
diagonalisable). Agent ``i`` observes mode ``j`` when ``C_i v_j != 0``. For each agent:

* the modes it observes are estimated by a local Luenberger observer (predictor form)
  ``z_o[k] = lam_o z_o[k-1] + L_i (y_i[k-1] - C_o z_o[k-1])``, with the poles of
  ``diag(lam_o) - L_i C_o`` placed at ``pole * (1, 0.9, 0.8, ...)``;
* every other mode ``j`` follows its neighbours: ``z_j[k] = lam_j * W-MSR_F(z_ij[k-1];
  the values z_lj[k-1] of the in-neighbours' estimates stamped k - 1)``.

W-MSR (LeBlanc, Zhang, Koutsoukos, Sundaram, "Resilient asymptotic consensus in robust
networks", IEEE JSAC 31(4), 2013, Section III-B), per component: a node removes the ``F``
largest values strictly above its own (all of them if there are fewer than ``F``) and the
``F`` smallest strictly below its own (likewise), and takes the average of the rest and its
own value (equal weights, so every weight is at least ``1 / (d_i + 1)``).

What is claimed (see the package README): with at most ``F`` Byzantine in-neighbours per
agent (F-local), ``|lam_j| <= 1`` for every mode some regular agent does not observe, and
a graph strongly ``(2F+1)``-robust with respect to the observers of each such mode, every
regular agent's error converges to 0. The W-MSR value of a regular agent lies between the
smallest and the largest value of its regular in-neighbours and itself (at most ``F``
values are Byzantine and ``F`` are removed on each side), so the largest error of the
regular agents on such a mode never grows (``|lam_j| <= 1``), and the robustness lets
the observers' vanishing errors reach every agent (the argument of LeBlanc et al.'s
Theorem 2, with the observers in the role of Mitra et al.'s source set). An unstable
unobserved mode is not claimed (``rse check`` says so).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from scipy.signal import place_poles

from estimation.base import EstimatePayload, Received
from estimation.errors import DesignError


def wmsr(own: np.ndarray, values: np.ndarray, f: int) -> np.ndarray:
    """One W-MSR update, per component (LeBlanc et al. 2013, Section III-B, equal weights).

    Parameters
    ----------
    own : (m,) the node's own values
    values : (d, m) the in-neighbours' values (d may be 0)
    f : the number of values removed on each side (``F``)

    Returns
    -------
    (m,) the average of ``own`` and the values kept.
    """
    own = np.asarray(own, dtype=float)
    values = np.asarray(values, dtype=float).reshape(-1, own.shape[0])
    d = values.shape[0]
    if d == 0:
        return own.copy()
    ordered = np.sort(values, axis=0)
    above = np.minimum((values > own).sum(axis=0), f)  # removed from the top
    below = np.minimum((values < own).sum(axis=0), f)  # removed from the bottom
    rank = np.arange(d)[:, None]
    keep = (rank >= below) & (rank < d - above)
    return (own + np.where(keep, ordered, 0.0).sum(axis=0)) / (1 + keep.sum(axis=0))


def average(own: np.ndarray, values: np.ndarray) -> np.ndarray:
    """The non-resilient comparison: the plain average of ``own`` and every value."""
    values = np.asarray(values, dtype=float).reshape(-1, np.shape(own)[0])
    return (own + values.sum(axis=0)) / (1 + values.shape[0])


@dataclass(frozen=True)
class LocalObserver:
    """Agent ``i``'s observer of the modes it sees."""

    observed: np.ndarray  # (m_o,) mode indices
    C: np.ndarray  # (p_i, m_o) C_i V restricted to the observed modes
    L: np.ndarray  # (m_o, p_i)


@dataclass(frozen=True)
class WmsrDesign:
    lam: np.ndarray  # (n,) real eigenvalues, in decreasing order
    V: np.ndarray  # (n, n) unit eigenvectors (columns)
    W: np.ndarray  # (n, n) V^-1
    observers: tuple[LocalObserver, ...]

    def observers_of(self, j: int) -> list[int]:
        """Agent indices that observe mode ``j``."""
        return [i for i, ob in enumerate(self.observers) if j in ob.observed]


def design(A: np.ndarray, agent_C: list[np.ndarray], *, pole: float) -> WmsrDesign:
    """The modal decomposition and every agent's local observer gain.

    Raises :class:`DesignError` when ``A`` has complex eigenvalues or is not
    diagonalisable, when a mode is observed by no agent, or when an agent's observed modes
    are not jointly observable from its sensors (repeated eigenvalues seen through too
    few outputs).
    """
    A = np.asarray(A, dtype=float)
    lam, V = np.linalg.eig(A)
    if np.max(np.abs(lam.imag), initial=0.0) > 1e-10:
        raise DesignError("plant.A has complex eigenvalues; W-MSR on modal coordinates needs real ones")
    lam, V = lam.real, V.real
    order = np.argsort(-lam, kind="stable")
    lam, V = lam[order], V[:, order]
    V = V / np.linalg.norm(V, axis=0)
    V = V * np.sign(V[np.argmax(np.abs(V), axis=0), np.arange(V.shape[1])])
    if np.linalg.cond(V) > 1e10:
        raise DesignError("plant.A is not diagonalisable")
    W = np.linalg.inv(V)
    observers = []
    for i, C in enumerate(agent_C):
        CV = np.atleast_2d(C) @ V
        seen = np.flatnonzero(np.linalg.norm(CV, axis=0) > 1e-9 * max(1.0, np.linalg.norm(C)))
        Co = CV[:, seen]
        m = seen.size
        if m == 0:
            observers.append(LocalObserver(seen, Co, np.zeros((0, Co.shape[0]))))
            continue
        Lo = np.diag(lam[seen])
        O = np.vstack([Co @ np.linalg.matrix_power(Lo, r) for r in range(m)])
        if np.linalg.matrix_rank(O) < m:
            raise DesignError(f"agent index {i}: its sensors see modes {seen.tolist()} but cannot tell them apart "
                              "(repeated eigenvalues through too few outputs)")
        poles = pole * (1.0 - 0.1 * np.arange(m))
        if m == 1 and Co.shape[0] == 1:
            L = np.array([[(lam[seen[0]] - poles[0]) / Co[0, 0]]])
        else:
            L = place_poles(Lo.T, Co.T, poles).gain_matrix.T
        observers.append(LocalObserver(seen, Co, L))
    for j in range(lam.size):
        if not any(j in ob.observed for ob in observers):
            raise DesignError(f"mode {j + 1} (eigenvalue {lam[j]:.6g}) is observed by no agent")
    return WmsrDesign(lam=lam, V=V, W=W, observers=tuple(observers))


class WmsrObserver(EstimatePayload):
    """Agent ``agent``'s estimator: local observer on the modes it sees, W-MSR (or the
    plain average) with its in-neighbours on the others. The payload is the estimate
    (declared by :class:`estimation.base.EstimatePayload`).

    ``step(k, y, inbox)``: ``y`` is ``y_i[k]`` or None; ``inbox`` maps an in-neighbour index to
    its newest message; only values stamped ``k - 1`` are used (older ones are stale).
    """

    def __init__(self, design: WmsrDesign, *, agent: int, x0: np.ndarray, f: int, fusion: str = "wmsr") -> None:
        if fusion not in ("wmsr", "average"):
            raise ValueError(f"fusion must be 'wmsr' or 'average', got {fusion!r}")
        self.design = design
        self.agent = agent
        self.f = f
        self.fusion = fusion
        ob = design.observers[agent]
        self._obs = ob.observed
        self._others = np.setdiff1d(np.arange(design.lam.size), ob.observed)
        self._ob = ob
        self._z = design.W @ np.asarray(x0, dtype=float)
        self._y_prev: np.ndarray | None = None

    @property
    def estimate(self) -> np.ndarray:
        return self.design.V @ self._z

    def step(self, k: int, measurement: np.ndarray | None, inbox: Mapping[int, Received]) -> np.ndarray:
        d, z = self.design, self._z
        if k > 0:
            new = np.empty_like(z)
            o, u = self._obs, self._others
            if o.size:
                zo = z[o]
                new[o] = d.lam[o] * zo
                if self._y_prev is not None:
                    new[o] += self._ob.L @ (self._y_prev - self._ob.C @ zo)
            if u.size:
                fresh = [inbox[j].value for j in sorted(inbox) if inbox[j].stamp == k - 1]
                vals = (np.asarray(fresh, dtype=float) @ d.W.T)[:, u] if fresh else np.zeros((0, u.size))
                fused = wmsr(z[u], vals, self.f) if self.fusion == "wmsr" else average(z[u], vals)
                new[u] = d.lam[u] * fused
            z = self._z = new
        self._y_prev = None if measurement is None else np.array(measurement, dtype=float)
        return d.V @ z
