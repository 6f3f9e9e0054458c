"""Distributed median of a bank of time-varying estimates: one agent's step (pure numpy).

Each agent ``i`` of a team holds a local, time-varying estimate ``z_i(t)`` in ``R^n`` (for
the inverter line: the state estimate of its own observer (9), van der Horst et al.). The
team agrees on the componentwise median ``med_j z_j(t)`` without a centre, by the
sign-based distributed median solver of Lee, Kim, Shim (IEEE TAC 2020), eq. (4), scaled
by ``kappa`` and with an optional known drift ``f`` (the role of ``A x + B u`` in their
eq. (6))::

    xi_i' = f(t, xi_i) + kappa sgn(z_i - xi_i) + kappa gamma sum_{j in N_i} (xi_j - xi_i),

componentwise. ``kappa`` has the units of the state per second, ``gamma`` those of one
over the state (``kappa gamma`` is a rate). Without drift this is eq. (4) with
``s_i = 1``, run ``kappa`` times faster: on a connected undirected graph and for constant
``z`` every ``xi_i`` ends within ``2 sqrt(N) / (gamma lambda_2)`` of the median set
(their Theorem 1), whatever ``kappa``. The drift lets ``xi`` move with the common
motion of the ``z_j`` (their model), so that ``kappa`` only has to exceed the rate at
which the median departs from it; without drift ``kappa`` must exceed the rate of the
median itself.

Two kinds of drift: ``drift = f(t, xi)``, a model evaluated at the agent's own ``xi`` (as
``A x_i + B u`` in LKS eq. (6); for a contracting ``f`` this also pulls ``xi`` towards the
model's own solution), or ``reference = r(k)``, a trajectory every agent computes alike
(e.g. the model run open loop from a common initial state): ``xi`` then moves by
``r(k) - r(k-1)`` per step whatever its value, which is eq. (4) in the coordinates
``xi - r`` (the median commutes with the shift), so ``xi`` tracks the median itself.

The discretised solver has a rate limit: one sign step moves ``xi`` by at most
``g <= min(kappa dt, 1 / (gamma d_i))`` (below), so it follows a median that moves
faster than ``min(kappa, 1 / (gamma d_i dt))`` only with a lag, while its disagreement
shrinks only as ``1 / gamma``. Tracking a fast median needs a good drift, not a large gain.

Discretisation at the round step ``dt`` (round ``k`` <-> ``t_k = k dt``). Agent ``i``
computes ``xi_i[k]`` from ``xi_i[k-1]``, the neighbours' ``xi_j[k-1]`` (the messages
stamped ``k - 1``, the freshest it can have) and its own ``z_i[k]``, by Lie splitting:

1. consensus, at ``t_{k-1}``: the self-coupling ``-kappa gamma d_i xi_i`` integrated
   exactly with the neighbours' values held (as in :mod:`estimation.median_solver`)::

       xi_c = e^{-c dt} xi_i[k-1] + (1 - e^{-c dt}) mean_j xi_j[k-1],   c = kappa gamma d_i,

   a convex combination, stable for every ``c dt``; with ``c dt >> 1`` it becomes a
   Jacobi step that oscillates on bipartite graphs (a line), so keep ``c dt`` of order 1;
2. drift: ``xi_f`` = ``substeps`` RK4 steps of ``xi' = f(t, xi)`` from ``t_{k-1}`` to
   ``t_k`` (skipped without drift);
3. sign term, implicit (the default, as ``sign = "implicit"`` in
   :class:`estimation.lee_kim_shim.LeeKimShim`): the sgn is evaluated at the end of the
   step, which is the exact solution of ``xi+ = xi_f + g s, s in Sgn(z_i[k] - xi+)``::

       xi_i[k] = xi_f + g clip((z_i[k] - xi_f) / g, -1, 1),
       g = kappa (1 - e^{-c dt}) / c   (kappa dt when d_i = 0),

   ``g`` being what one step of ``kappa sgn`` moves ``xi`` through the consensus decay.
   An agent within ``g`` of its own value lands on it; otherwise it moves by ``g``
   towards it. ``sign = "held"`` uses ``sgn(z_i[k] - xi_i[k-1])`` instead, held from the
   start of the step (explicit; it chatters with amplitude ``g``).

With ``f = 0``, ``kappa = 1``, ``sign = "held"`` and constant values, one step is exactly
the step of :func:`estimation.median_solver.run_scalar_median_solver` (tested).

:class:`FloodingMedian` is the exact reference: every agent floods the newest estimate of
every agent it knows (a table of ``N`` stamped rows), and takes the componentwise median
of its table. After ``diameter`` rounds every row is known, each ``h`` rounds old for an
agent ``h`` hops away; with ``predict``, the agent moves every stale row forward to the
current round with the drift ``f`` (open loop), which removes most of the staleness.
Messages are ``N (n + 1)`` floats, against ``n`` for the sign-based solver.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from typing import Any

import numpy as np

from .base import Inbox
from .lure import integrate

Drift = Callable[[float, np.ndarray], np.ndarray]
SIGNS = ("implicit", "held")


def consensus_step(c: float, dt: float) -> tuple[float, float]:
    """``(stay, move) = (e^{-c dt}, (1 - e^{-c dt}) / c)`` (``move = dt`` at ``c = 0``)."""
    if c < 0 or dt <= 0:
        raise ValueError(f"need c >= 0 and dt > 0, got c={c}, dt={dt}")
    stay = float(np.exp(-c * dt))
    move = float(-np.expm1(-c * dt) / c) if c > 0 else float(dt)
    return stay, move


def sign_median_update(
    xi: np.ndarray,
    neighbours: Iterable[np.ndarray],
    target: np.ndarray,
    *,
    kappa: float | np.ndarray,
    gamma: float,
    dt: float,
    t: float = 0.0,
    drift: Drift | None = None,
    substeps: int = 1,
    sign: str = "implicit",
    shift: np.ndarray | None = None,
) -> np.ndarray:
    """One step of the sign-based distributed median (module docstring, steps 1-3).

    Parameters
    ----------
    xi : (n,) array, ``xi_i[k-1]``
    neighbours : iterable of (n,) arrays, ``xi_j[k-1]`` of the neighbours heard from
    target : (n,) array, the agent's own value ``z_i[k]``
    kappa : float > 0 or (n,) array, the sign gain (state units per second)
    gamma : float > 0, the coupling (``kappa gamma`` is a rate)
    dt : float > 0
    t : float, ``t_{k-1}`` (the drift's start time)
    drift : callable ``(t, xi) -> xi'``, optional
    substeps : int, RK4 steps of the drift per ``dt``
    sign : "implicit" or "held"
    shift : (n,) array, optional, a common motion over the step (``r(k) - r(k-1)`` of a
        reference), added in step 2 instead of (or after) the drift

    Returns
    -------
    (n,) array, ``xi_i[k]`` (a new array).
    """
    if sign not in SIGNS:
        raise ValueError(f"sign must be one of {SIGNS}, got {sign!r}")
    xi = np.asarray(xi, dtype=float)
    nb = [np.asarray(v, dtype=float) for v in neighbours]
    d = len(nb)
    kap = np.asarray(kappa, dtype=float)
    if np.any(kap <= 0) or not gamma > 0:
        raise ValueError(f"kappa and gamma must be > 0, got {kappa}, {gamma}")
    # 1. consensus with the neighbours' values held, self-coupling exact
    c = kap * gamma * d
    if d:
        stay = np.exp(-c * dt)
        mean = np.sum(nb, axis=0) / d
        xc = stay * xi + (1.0 - stay) * mean
        g = -kap * np.expm1(-c * dt) / c
    else:
        xc = xi.copy()
        g = kap * dt
    # 2. drift / common motion
    xf = xc if drift is None else integrate(drift, t, xc, dt, substeps=substeps)
    if shift is not None:
        xf = xf + np.asarray(shift, dtype=float)
    # 3. sign term towards the own value
    target = np.asarray(target, dtype=float)
    s = np.clip((target - xf) / g, -1.0, 1.0) if sign == "implicit" else np.sign(target - xi)
    return xf + g * s


class SignMedianAgent:
    """One agent's sign-based distributed median of time-varying local values.

    Parameters
    ----------
    n : int, dimension of the values
    kappa, gamma, dt, drift, substeps, sign : see :func:`sign_median_update`
    reference : callable ``k -> (n,)``, optional, a common reference trajectory (module
        docstring); each step adds ``reference(k) - reference(k - 1)``
    x0 : (n,) array, optional, ``xi_i[0]``; by default the agent's own value in round 0
    max_age : int, neighbour values stamped older than ``k - 1 - max_age`` are not used

    ``step(k, target, inbox)`` returns ``xi_i[k]`` (read-only, never modified later);
    ``inbox`` maps a neighbour to an object with ``stamp`` and ``value`` (an
    :class:`estimation.base.Received`). A skipped round repeats the step with the same
    neighbour values and the newest own value.
    """

    def __init__(self, *, n: int, kappa: float | np.ndarray, gamma: float, dt: float, drift: Drift | None = None,
                 substeps: int = 1, sign: str = "implicit", x0: np.ndarray | None = None, max_age: int = 3,
                 reference: Callable[[int], np.ndarray] | None = None) -> None:
        if not dt > 0:
            raise ValueError(f"dt must be > 0, got {dt}")
        if np.any(np.asarray(kappa) <= 0) or not gamma > 0:
            raise ValueError(f"kappa and gamma must be > 0, got {kappa}, {gamma}")
        if sign not in SIGNS:
            raise ValueError(f"sign must be one of {SIGNS}, got {sign!r}")
        self.n, self.dt = int(n), float(dt)
        self._kw: dict[str, Any] = dict(kappa=kappa, gamma=float(gamma), dt=self.dt, drift=drift, substeps=int(substeps), sign=sign)
        self.max_age = int(max_age)
        self._ref = reference
        self._xi: np.ndarray | None = None if x0 is None else np.array(x0, dtype=float).reshape(self.n)
        self._k: int | None = None

    @property
    def estimate(self) -> np.ndarray:
        """``xi_i`` of the last round (a copy)."""
        if self._xi is None:
            raise RuntimeError("no round has run yet")
        return self._xi.copy()

    def step(self, k: int, target: np.ndarray, inbox: Mapping | None = None) -> np.ndarray:
        target = np.asarray(target, dtype=float).reshape(self.n)
        if self._k is None:
            xi = target.copy() if self._xi is None else self._xi
        else:
            if k <= self._k:
                raise ValueError(f"rounds must increase, got k={k} after k={self._k}")
            oldest = k - 1 - self.max_age
            nb = [r.value for r in (inbox or {}).values() if r.stamp >= oldest]
            assert self._xi is not None  # set with self._k
            xi = self._xi
            for kk in range(self._k, k):
                shift = None if self._ref is None else np.asarray(self._ref(kk + 1), dtype=float) - self._ref(kk)
                xi = sign_median_update(xi, nb, target, t=kk * self.dt, shift=shift, **self._kw)
        xi = np.array(xi, dtype=float)
        xi.flags.writeable = False
        self._xi, self._k = xi, k
        return xi


class FloodingMedian:
    """Exact componentwise median by flooding (the reference for :class:`SignMedianAgent`).

    Parameters
    ----------
    agent : int, this agent's index ``0..N-1``
    N, n : int, team size and dimension
    dt : float; drift, substeps : see :func:`sign_median_update` (used with ``predict``; the
        drift must accept a stack of rows, ``(m, n) -> (m, n)``)
    predict : bool, move stale rows to the current round with the drift (open loop)

    ``step(k, value, inbox)`` stores ``(k, value)`` as this agent's row, merges the tables
    in the inbox (newest stamp per row wins) and returns the payload, the flattened table
    ``(N, n + 1)``: column 0 the stamp (-1: unknown), then the row. ``estimate`` is the
    componentwise median of the known rows (predicted to ``k`` with ``predict``).
    """

    def __init__(self, *, agent: int, N: int, n: int, dt: float, drift: Drift | None = None, substeps: int = 1,
                 predict: bool = False) -> None:
        if not 0 <= agent < N:
            raise ValueError(f"agent must be in 0..{N - 1}, got {agent}")
        if predict and drift is None:
            raise ValueError("predict needs a drift")
        self.agent, self.N, self.n, self.dt = int(agent), int(N), int(n), float(dt)
        self._drift, self._substeps, self._predict = drift, int(substeps), bool(predict)
        self._stamp = np.full(self.N, -1, dtype=np.int64)
        self._rows = np.zeros((self.N, self.n))
        self._pred = np.zeros((self.N, self.n))  # rows moved to the current round
        self._pred_at = np.full(self.N, -1, dtype=np.int64)  # round the predicted row is at
        self._pred_src = np.full(self.N, -1, dtype=np.int64)  # stamp of the row it started from
        self._est = np.zeros(self.n)
        self._k: int | None = None

    @property
    def estimate(self) -> np.ndarray:
        return self._est.copy()

    @property
    def stamps(self) -> np.ndarray:
        """Stamp of every row (-1: not heard of yet), a copy."""
        return self._stamp.copy()

    def pack(self) -> np.ndarray:
        """The payload: ``(N, n + 1)`` flattened, finite (unknown rows are zeros)."""
        return np.concatenate([self._stamp[:, None].astype(float), self._rows], axis=1).ravel()

    def unpack(self, payload: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(stamps (N,), rows (N, n))`` of a payload; ValueError if it is not a valid table
        (wrong size, non-finite entries, stamps that are not integers >= -1)."""
        a = np.asarray(payload, dtype=float)
        if a.size != self.N * (self.n + 1):
            raise ValueError(f"a flooding table has {self.N * (self.n + 1)} numbers, got {a.size}")
        if not np.all(np.isfinite(a)):
            raise ValueError("a flooding table must be finite")
        a = a.reshape(self.N, self.n + 1)
        if np.any(a[:, 0] < -1) or np.any(a[:, 0] != np.round(a[:, 0])):
            raise ValueError("flooding stamps must be integers >= -1")
        return a[:, 0].astype(np.int64), a[:, 1:]

    def step(self, k: int, value: np.ndarray, inbox: Inbox | None = None) -> np.ndarray:
        if self._k is not None and k <= self._k:
            raise ValueError(f"rounds must increase, got k={k} after k={self._k}")
        for r in (inbox or {}).values():
            try:
                stamps, rows = self.unpack(r.value)
            except ValueError:
                continue  # not a flooding table: ignored
            newer = (stamps > self._stamp) & (stamps <= k)
            self._stamp[newer] = stamps[newer]
            self._rows[newer] = rows[newer]
        self._stamp[self.agent] = k
        self._rows[self.agent] = np.asarray(value, dtype=float).reshape(self.n)
        known = self._stamp >= 0
        if self._predict:
            assert self._drift is not None  # prediction needs the drift (checked at construction)
            fresh = known & (self._stamp != self._pred_src)
            self._pred[fresh] = self._rows[fresh]
            self._pred_at[fresh] = self._pred_src[fresh] = self._stamp[fresh]
            for kk in range(int(self._pred_at[known].min()), k):  # all rows at kk move to kk + 1 together
                sel = known & (self._pred_at == kk)
                self._pred[sel] = integrate(self._drift, kk * self.dt, self._pred[sel], self.dt, substeps=self._substeps)
                self._pred_at[sel] = kk + 1
            vals = self._pred[known]
        else:
            vals = self._rows[known]
        self._est = np.median(vals, axis=0)
        self._k = k
        return self.pack()
