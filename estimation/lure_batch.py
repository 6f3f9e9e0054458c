"""Many Lur'e observers and sign-median agents as one stacked state (the batched round).

The per-agent definitions are :class:`estimation.median_bank.LureObserver` (observer (9)
of van der Horst et al., RK4 with the innovation held) and
:func:`estimation.distributed_median.sign_median_update` (the sign-based distributed
median, Lie splitting: consensus, drift, implicit sgn). Here ``m`` observers with one
sensor each are one ``(m, n)`` state: one RK4 step of

    X' = X A^T + phi(X H^T + w(t) + R K^T) G^T + R L^T            (9), row by row

and ``m`` median agents are one ``(m, n)`` update. The stacked products sum in another
order than the per-row ones, so the estimates equal the per-agent path's within 1e-12
relative, not bit for bit.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from .lure import LurePlant, integrate


class StackedLureObservers:
    """``m`` observers (9), each on one sensor, stepped as one ``(m, n)`` state.

    Parameters
    ----------
    observers : :class:`~estimation.median_bank.LureObserver` objects on one plant, one
        sensor each, one ``dt``, ``substeps`` and measurement map (their state is taken
        over; :meth:`sync` writes it back)
    """

    def __init__(self, observers: Sequence[Any]) -> None:
        obs = list(observers)
        first = obs[0]
        if any(len(o._S) != 1 for o in obs):
            raise ValueError("stacked observers read one sensor each")
        self._obs = obs
        self._pl: LurePlant = first._plant
        self._dt, self._sub, self._map = first._dt, first._substeps, first._map
        self._S = np.array([o._S[0] for o in obs])
        self._L = np.stack([o._L[:, 0] for o in obs])  # (m, n)
        self._K = np.stack([o._K[:, 0] for o in obs])  # (m, N)
        self._HS = self._pl.H[self._S]  # (m, n)
        self.X = np.stack([o._x for o in obs])
        self._r = np.array([o._r[0] for o in obs])
        ks = {o._k for o in obs}
        if len(ks) != 1:
            raise ValueError("stacked observers must be at one round")
        self._k = ks.pop()
        pl = self._pl
        self._AT, self._HT, self._GT = pl.A.T, pl.H.T, pl.G.T

    def _rhs(self, t: float, X: np.ndarray) -> np.ndarray:
        pl = self._pl
        Xi = X @ self._HT + pl.w(t) + self._KR  # (9), second line, every observer
        return X @ self._AT + pl.phi(Xi) @ self._GT + self._LR  # (9), first line

    def step(self, k: int, y: np.ndarray | None) -> np.ndarray:
        """Round ``k``; ``y`` ``(m,)`` what each observer's sensor published (None or NaN:
        no measurement, zero innovation). Returns the ``(m, n)`` estimates (the state itself)."""
        if self._k is not None:
            for j in range(self._k, k):
                self._KR = self._K * self._r[:, None]
                self._LR = self._L * self._r[:, None]
                self.X = integrate(self._rhs, j * self._dt, self.X, self._dt, substeps=self._sub)
                self._r = np.zeros_like(self._r)
        self._k = k
        if y is not None:
            y = np.asarray(y, dtype=float)
            if self._map is not None:
                y = np.asarray(self._map(y), dtype=float)
            t = k * self._dt
            r = y - np.einsum("ij,ij->i", self._HS, self.X) - self._pl.w(t)[self._S]
            self._r = np.where(np.isnan(r), 0.0, r)
        return self.X

    def sync(self) -> None:
        for o, x, r in zip(self._obs, self.X, self._r):
            o._x, o._r, o._k = x.copy(), np.array([r]), self._k


def sign_median_stacked(XI: np.ndarray, mean: np.ndarray, d: np.ndarray, target: np.ndarray, *, kappa: float,
                        gamma: float, dt: float, t: float, drift: Callable | None, substeps: int, sign: str,
                        shift: np.ndarray | None) -> np.ndarray:
    """:func:`~estimation.distributed_median.sign_median_update` of ``m`` agents at once.

    ``XI`` ``(m, n)`` the agents' ``xi[k-1]``; ``mean`` ``(m, n)`` the mean of the neighbour
    values each used (any value where ``d = 0``); ``d`` ``(m,)`` how many; ``target`` ``(m, n)``
    each agent's own ``z_i[k]``. The drift must take a stack of states.
    """
    c = (kappa * gamma) * d.astype(float)[:, None]
    heard = c > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        stay = np.exp(-c * dt)
        xc = np.where(heard, stay * XI + (1.0 - stay) * mean, XI)
        g = np.where(heard, -kappa * np.expm1(-c * dt) / np.where(heard, c, 1.0), kappa * dt)
    xf = xc if drift is None else integrate(drift, t, xc, dt, substeps=substeps)
    if shift is not None:
        xf = xf + shift
    s = np.clip((target - xf) / g, -1.0, 1.0) if sign == "implicit" else np.sign(target - XI)
    return xf + g * s
