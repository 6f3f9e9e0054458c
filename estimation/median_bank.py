"""Median of a bank of observers for Lur'e plants (van der Horst, Chong, Kim, Sandberg).

* :func:`design_bank` -- one observer (9) per sensor, gains from the LMI (10) of
  Proposition 1 (cvxpy, Clarabel).
* :class:`LureObserver` -- observer (9) on a subset ``S`` of the sensors: ``S = {i}`` for
  the bank, all sensors for the conventional observer (16).
* :func:`median_fuse` -- componentwise median (5); :class:`MedianBank` the central estimator.
* :func:`design_conventional` -- (16) with all sensors; :func:`static_inversion`.
* :func:`run_central` -- the reference loop: plant, bank, median, conventional and static
  inversion in lockstep at the scenario's ``dt``.

LMI (10) for sensors ``S`` (``p = |S|``), linear in ``P, Y = P L, U = diag(u), W = K^T U``::

    [ P A + A'P - Y H_S - H_S'Y' + nu I   P G + H'U - H_S'W   P      -P    ]
    [ (P G + H'U - H_S'W)'                -2 U diag(1/e_hi)   0      0     ]  <= 0
    [ P                                   0                   -mu_d I 0    ]
    [ -P                                  0                   0   -mu_a I  ]

As printed, (10) is homogeneous in all variables, so minimising ``mu_d`` runs to the
solver's margin with ``nu = 0``. Normalisation: ``nu = 1`` and ``mu_a = mu_d``; then
``mu_d`` has an attained optimum ``mu_d*`` (2.049, 2.056, 2.020, 2.008, 2.011 for the
five inverter sensors).

Gain rule (the paper is silent; the optimum leaves ``L`` free over a wide range): second
stage, keep ``mu_d <= (1 + slack) mu_d*`` and minimise ``||Y||_F + ||W||_F``, the
smallest output-injection gains that keep ``mu_d`` within ``slack`` of its optimum. Small
``|L|`` and ``|K|`` are what the disturbance and attack gains ``delta_i, alpha_i`` of (30)
grow with, so this picks the certified design least sensitive to the sensor's disturbance.
The default ``slack = 1e-3`` is a numerical tolerance (the gains are, in effect, the
minimum-norm gains on the optimal set), not a tuning knob. For the inverter line it gives
``|L_i|`` of 0.2-0.6 and ``K_i`` ~ 0, against ``|L_i|`` of 110-350 at the solver's interior
point of the first stage, which tracks the disturbed sensor far too closely (the median's
error with the +-6 V disturbance was ~10x larger with those gains).

Discretisation of the observers (continuous in the paper): per round, RK4 over
``[t_k, t_{k+1})`` with ``w(t)`` evaluated at the stage times and the *innovation*
``r_k = y_S[k] - H_S x_hat[k] - w_S(t_k)`` held (sample and hold of the output injection).
An observer that starts on the true state of an undisturbed plant therefore reproduces
the plant's own RK4 step exactly. Output injection is explicit in ``r``, so a gain needs
``dt * |eig(L H_S)| < 2``; the conventional design bounds it (:func:`design_conventional`).

Reference settings of the inverter tests: ``dt = 0.01 s``, one RK4 step per round for the
plant and every observer, plant from ``q_g = 0``, every observer from ``Q_bar / 4``,
conventional ``max_rate = 0.2 / dt``.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from .base import Inbox
from .errors import InfeasibleError
from .lure import LurePlant, integrate

_EPS = 1e-6  # strictness margin for P > 0 and U > 0


def _lmi(plant: LurePlant, sensors: Sequence[int], cp):
    """cvxpy variables and constraints of (10) for the sensor subset ``sensors``."""
    n, N = plant.n, plant.N
    HS = plant.H[list(sensors)]
    p = HS.shape[0]
    P = cp.Variable((n, n), symmetric=True)
    Y = cp.Variable((n, p))
    u = cp.Variable(N)
    W = cp.Variable((p, N))
    mu = cp.Variable()
    U = cp.diag(u)
    A, G, H = plant.A, plant.G, plant.H
    top = P @ A + A.T @ P - Y @ HS - HS.T @ Y.T + np.eye(n)  # nu = 1
    B = P @ G + H.T @ U - HS.T @ W
    D = -2.0 * cp.diag(cp.multiply(u, 1.0 / plant.slope_upper))
    Znn, ZNn = np.zeros((n, n)), np.zeros((N, n))
    M = cp.bmat([[top, B, P, -P],
                 [B.T, D, ZNn, ZNn],
                 [P, ZNn.T, -mu * np.eye(n), Znn],
                 [-P, ZNn.T, Znn, -mu * np.eye(n)]])  # mu_a = mu_d = mu
    cons = [0.5 * (M + M.T) << 0, P >> _EPS * np.eye(n), u >= _EPS]
    return dict(P=P, Y=Y, u=u, W=W, mu=mu, HS=HS), cons


def lmi_matrix(plant: LurePlant, *, sensors: Sequence[int], P, L, K, U, mu: float) -> np.ndarray:
    """The left-hand side of (10) (``nu = 1``, ``mu_a = mu_d = mu``) at given values, for checks."""
    n, N = plant.n, plant.N
    HS = plant.H[list(sensors)]
    Acl = plant.A - L @ HS
    top = P @ Acl + Acl.T @ P + np.eye(n)
    B = P @ plant.G + (plant.H - K @ HS).T @ U
    D = -2.0 * U @ np.diag(1.0 / plant.slope_upper)
    Z = np.zeros
    return np.block([[top, B, P, -P],
                     [B.T, D, Z((N, n)), Z((N, n))],
                     [P, Z((n, N)), -mu * np.eye(n), Z((n, n))],
                     [-P, Z((n, N)), Z((n, n)), -mu * np.eye(n)]])


def _solve(prob, what: str) -> None:
    try:
        with warnings.catch_warnings():  # "inaccurate" points are checked by _extract instead
            warnings.simplefilter("ignore", UserWarning)
            prob.solve(solver="CLARABEL")
    except Exception as exc:  # cvxpy raises SolverError and others
        raise InfeasibleError(f"{what}: solver failed ({exc})") from exc
    if prob.status not in ("optimal", "optimal_inaccurate"):
        raise InfeasibleError(f"{what}: LMI (10) is {prob.status}")


def _extract(v: dict, plant: LurePlant, sensors, what: str) -> dict:
    P, u = v["P"].value, v["u"].value
    L = np.linalg.solve(P, v["Y"].value)
    K = (v["W"].value / u).T  # W = K^T U
    U = np.diag(u)
    mu = float(v["mu"].value)
    M = lmi_matrix(plant, sensors=sensors, P=P, L=L, K=K, U=U, mu=mu)
    worst = float(np.max(np.linalg.eigvalsh(0.5 * (M + M.T))))
    if worst > 1e-6 * max(1.0, float(np.max(np.abs(M)))):
        raise InfeasibleError(f"{what}: solver returned a point that violates (10) by {worst:.3g}")
    return dict(P=P, L=L, K=K, U=U, mu=mu, lmi_max_eig=worst)


def design_observer(plant: LurePlant, *, sensors: Sequence[int], slack: float = 1e-3) -> dict:
    """Gains of observer (9) on ``sensors`` by LMI (10), normalised and with the gain rule.

    Parameters
    ----------
    plant : LurePlant
    sensors : sequence of int, 0-based sensor ids ``S`` used by the observer
    slack : float >= 0, the second stage keeps ``mu_d <= (1 + slack) mu_d*``

    Returns
    -------
    dict of plain arrays/floats: ``sensors`` (p,) int, ``L`` (n, p), ``K`` (N, p), ``P``
    (n, n), ``U`` (N, N), ``mu_d`` and ``mu_a`` (value at the chosen gains), ``mu_d_opt``
    (the optimum ``mu_d*``), ``nu`` (= 1), ``lmi_max_eig`` (largest eigenvalue of (10) at
    the returned point, <= 0 up to round-off).

    Raises
    ------
    InfeasibleError
        If (10) is infeasible or the solver fails.
    """
    import cvxpy as cp

    sensors = [int(s) for s in sensors]
    if not sensors or min(sensors) < 0 or max(sensors) >= plant.N:
        raise ValueError(f"sensors must be a non-empty subset of 0..{plant.N - 1}, got {sensors}")
    if not slack >= 0:
        raise ValueError(f"slack must be >= 0, got {slack}")
    what = f"observer on sensors {sensors}"
    v, cons = _lmi(plant, sensors, cp)
    _solve(cp.Problem(cp.Minimize(v["mu"]), cons), what)
    mu_opt = float(v["mu"].value)
    v, cons = _lmi(plant, sensors, cp)
    cons.append(v["mu"] <= (1.0 + slack) * mu_opt)
    _solve(cp.Problem(cp.Minimize(cp.norm(v["Y"], "fro") + cp.norm(v["W"], "fro")), cons), what)
    r = _extract(v, plant, sensors, what)
    return dict(sensors=np.array(sensors), L=r["L"], K=r["K"], P=r["P"], U=r["U"], mu_d=r["mu"],
                mu_a=r["mu"], mu_d_opt=mu_opt, nu=1.0, lmi_max_eig=r["lmi_max_eig"])


def design_bank(plant: LurePlant, *, slack: float = 1e-3) -> dict:
    """One observer per sensor (Proposition 1 for every ``i``); a plain, cacheable result.

    Returns
    -------
    dict of arrays stacked over sensors ``i = 0..N-1``: ``L`` (N, n, 1), ``K`` (N, N, 1),
    ``P`` (N, n, n), ``U`` (N, N, N), ``mu_d``, ``mu_a``, ``mu_d_opt``, ``nu``,
    ``lmi_max_eig`` (N,), and ``slack`` (float). ``np.savez(**bank)`` stores it.
    """
    ds = [design_observer(plant, sensors=[i], slack=slack) for i in range(plant.N)]
    out: dict[str, Any] = {k: np.stack([d[k] for d in ds]) for k in ("L", "K", "P", "U")}
    for k in ("mu_d", "mu_a", "mu_d_opt", "nu", "lmi_max_eig"):
        out[k] = np.array([d[k] for d in ds], dtype=float)
    out["slack"] = float(slack)
    return out


def design_conventional(plant: LurePlant, *, max_rate: float, slack: float = 1e-3) -> dict:
    """Gains of the conventional observer (16) on all sensors.

    With all sensors (10) has no attained optimum (``mu_d -> 0`` as ``|L| -> inf``, too fast
    for any fixed step). The stated design adds the pole-region LMI
    ``P (A - L H) + (A - L H)' P + 2 max_rate P >= 0`` (with the same ``P``), which keeps the
    eigenvalues of ``A - L H`` in ``Re s >= -max_rate``, minimises ``mu_d`` (now attained)
    and then applies the same gain rule as the bank (minimum ``||Y||_F + ||W||_F`` with
    ``mu_d <= (1 + slack) mu_d*``). Choose ``max_rate * dt`` well below 2 (the reference
    uses ``0.2 / dt``); the result sits on the region's edge, near static inversion.

    Returns
    -------
    dict as :func:`design_observer` with ``sensors = 0..N-1`` and ``max_rate``.
    """
    import cvxpy as cp

    if not max_rate > 0:
        raise ValueError(f"max_rate must be > 0, got {max_rate}")
    sensors = list(range(plant.N))
    what = f"conventional observer (max_rate {max_rate})"
    v, cons = _lmi(plant, sensors, cp)
    P, Y, HS, A = v["P"], v["Y"], v["HS"], plant.A
    region = P @ A + A.T @ P - Y @ HS - HS.T @ Y.T + 2.0 * max_rate * P
    cons.append(0.5 * (region + region.T) >> 0)
    _solve(cp.Problem(cp.Minimize(v["mu"]), cons), what)
    mu_opt = float(v["mu"].value)
    cons.append(v["mu"] <= (1.0 + slack) * mu_opt)
    _solve(cp.Problem(cp.Minimize(cp.norm(v["Y"], "fro") + cp.norm(v["W"], "fro")), cons), what)
    r = _extract(v, plant, sensors, what)
    return dict(sensors=np.array(sensors), L=r["L"], K=r["K"], P=r["P"], U=r["U"], mu_d=r["mu"],
                mu_a=r["mu"], mu_d_opt=mu_opt, nu=1.0, lmi_max_eig=r["lmi_max_eig"], max_rate=float(max_rate))


def check_report(bank: dict, *, n_attacked: int) -> dict:
    """What ``rse check`` prints: LMI feasibility, ``mu_d`` per observer and ``N > 2M``.

    Parameters
    ----------
    bank : dict from :func:`design_bank` (possibly loaded from a cache)
    n_attacked : int, the attack budget ``M``

    Returns
    -------
    dict with ``feasible`` (bool), ``mu_d`` (list of float), ``mu_d_opt`` (list),
    ``N``, ``M`` (int) and ``N_gt_2M`` (bool).
    """
    mu = np.asarray(bank["mu_d"], dtype=float)
    N = mu.size
    if not 0 <= n_attacked:
        raise ValueError(f"n_attacked must be >= 0, got {n_attacked}")
    feasible = bool(np.all(np.isfinite(mu)) and np.all(np.asarray(bank["lmi_max_eig"]) <= 1e-6 * np.maximum(1, mu)))
    return dict(feasible=feasible, mu_d=mu.tolist(), mu_d_opt=np.asarray(bank["mu_d_opt"]).tolist(),
                N=int(N), M=int(n_attacked), N_gt_2M=bool(N > 2 * n_attacked))


def median_fuse(estimates: np.ndarray, *, n_attacked: int | None = None) -> np.ndarray:
    """Componentwise median (5) of the bank's estimates.

    Parameters
    ----------
    estimates : (N, n) array, row ``i`` is observer ``i``'s estimate
    n_attacked : int, optional, the budget ``M``; if given, ``N > 2M`` is required

    Returns
    -------
    (n,) array. With ``N > 2M`` every component lies within the range of the unattacked
    rows (the mechanism of Theorem 1). For even ``N`` the two middle values are averaged.
    """
    X = np.asarray(estimates, dtype=float)
    if X.ndim != 2 or X.shape[0] == 0:
        raise ValueError(f"estimates must be a non-empty (N, n) array, got shape {X.shape}")
    if n_attacked is not None and not X.shape[0] > 2 * n_attacked:
        raise ValueError(f"the median needs N > 2M, got N={X.shape[0]}, M={n_attacked}")
    return np.median(X, axis=0)


class LureObserver:
    """Observer (9) (or (16) when ``sensors`` is all of them) at a fixed step ``dt``.

    Parameters
    ----------
    plant : LurePlant
    sensors : sequence of int, the sensors ``S`` it reads (0-based)
    L : (n, p) array; K : (N, p) array, gains for ``p = |S|``
    dt : float, round length; round ``k`` is ``t_k = k dt``
    x0 : (n,) array, the estimate it reports in its first round
    substeps : int, RK4 steps per round
    measurement_map : callable ``(p,) -> (p,)``, optional, maps what the sensor publishes to
        the output ``y_S`` of (7) (e.g. :meth:`InverterNetwork.lure_output` for volts)

    ``step(k, measurement, inbox)`` advances the estimate to round ``k`` (RK4 with the
    innovation of the previous round held, module docstring), then stores the innovation
    of round ``k`` and returns ``x_hat[k]``. ``measurement=None`` gives zero innovation
    (open-loop prediction). ``inbox`` is ignored (central use).
    """

    def __init__(self, plant: LurePlant, *, sensors: Sequence[int], L: np.ndarray, K: np.ndarray, dt: float,
                 x0: np.ndarray, substeps: int = 1, measurement_map: Callable | None = None) -> None:
        self._plant = plant
        self._S = [int(s) for s in sensors]
        p = len(self._S)
        self._L = np.array(L, dtype=float).reshape(plant.n, p)
        self._K = np.array(K, dtype=float).reshape(plant.N, p)
        if not dt > 0:
            raise ValueError(f"dt must be > 0, got {dt}")
        self._dt, self._substeps, self._map = float(dt), int(substeps), measurement_map
        self._x = np.array(x0, dtype=float).reshape(plant.n)
        self._r = np.zeros(p)
        self._k: int | None = None

    @property
    def estimate(self) -> np.ndarray:
        """Current estimate ``x_hat[k]``, shape (n,) (a copy)."""
        return self._x.copy()

    def _rhs(self, t: float, x: np.ndarray) -> np.ndarray:
        pl = self._plant
        xi = pl.H @ x + pl.w(t) + self._K @ self._r  # (9), second line
        return pl.A @ x + pl.G @ pl.phi(xi) + self._L @ self._r  # (9), first line

    def step(self, k: int, measurement: np.ndarray | None, inbox: Inbox | None = None) -> np.ndarray:
        if self._k is not None:
            if k <= self._k:
                raise ValueError(f"rounds must increase, got k={k} after k={self._k}")
            for j in range(self._k, k):
                self._x = integrate(self._rhs, j * self._dt, self._x, self._dt, substeps=self._substeps)
                self._r = np.zeros_like(self._r)  # a skipped round carries no measurement
        self._k = k
        if measurement is not None:
            y = np.asarray(measurement, dtype=float).reshape(len(self._S))
            y = y if self._map is None else np.asarray(self._map(y), dtype=float).reshape(len(self._S))
            t = k * self._dt
            self._r = y - self._plant.H[self._S] @ self._x - self._plant.w(t)[self._S]
        return self._x.copy()


class MedianBank:
    """Central resilient estimator: observers (9), one per sensor, fused by the median (5).

    Parameters
    ----------
    plant : LurePlant
    bank : dict from :func:`design_bank`
    dt : float
    x0 : (n,) array or (N, n) array, initial estimate(s)
    n_attacked : int, optional, the budget ``M`` (checked ``N > 2M``)
    substeps, measurement_map : passed to every :class:`LureObserver` (the map must act
        componentwise, e.g. :meth:`InverterNetwork.lure_output`)

    ``step(k, measurement, inbox)`` takes all ``N`` outputs ``y[k]`` (``(N,)``, ``None``
    for none) and returns the median estimate; ``estimates`` is the bank's ``(N, n)``.
    """

    def __init__(self, plant: LurePlant, *, bank: dict, dt: float, x0: np.ndarray, n_attacked: int | None = None,
                 substeps: int = 1, measurement_map: Callable | None = None) -> None:
        x0 = np.broadcast_to(np.asarray(x0, dtype=float), (plant.N, plant.n))
        self._M = n_attacked
        self._obs = [LureObserver(plant, sensors=[i], L=bank["L"][i], K=bank["K"][i], dt=dt, x0=x0[i],
                                  substeps=substeps, measurement_map=measurement_map) for i in range(plant.N)]
        self._x = median_fuse(x0, n_attacked=n_attacked)

    @property
    def estimate(self) -> np.ndarray:
        return self._x.copy()

    @property
    def estimates(self) -> np.ndarray:
        """The bank's estimates, shape (N, n)."""
        return np.stack([o.estimate for o in self._obs])

    def step(self, k: int, measurement: np.ndarray | None, inbox: Inbox | None = None) -> np.ndarray:
        y = None if measurement is None else np.asarray(measurement, dtype=float).reshape(len(self._obs))
        rows = [o.step(k, None if y is None else y[i:i + 1]) for i, o in enumerate(self._obs)]
        self._x = median_fuse(np.stack(rows), n_attacked=self._M)
        return self._x.copy()


def static_inversion(plant: LurePlant, t: float, y: np.ndarray) -> np.ndarray:
    """``x_hat = H^-1 (y - w(t))`` (least squares if ``H`` is not square), shape (n,).

    The design-independent limit of the conventional observer as its gains grow.
    """
    y = np.asarray(y, dtype=float).reshape(plant.N)
    return np.linalg.lstsq(plant.H, y - plant.w(t), rcond=None)[0]


def output_error(H: np.ndarray, x: np.ndarray, x_hat: np.ndarray) -> np.ndarray:
    """``max_k |H_k (x - x_hat)|`` per time step: (T, n), (T, n) -> (T,) (V^2 for inverters, (36))."""
    return np.max(np.abs((np.asarray(x) - np.asarray(x_hat)) @ np.asarray(H).T), axis=-1)


def window_error(run: dict, key: str, H: np.ndarray, *, t0: float, t1: float) -> float:
    """Largest :func:`output_error` of estimate ``run[key]`` over ``t0 <= t <= t1`` (a run of :func:`run_central`)."""
    m = (run["t"] >= t0 - 1e-9) & (run["t"] <= t1 + 1e-9)
    if not np.any(m):
        raise ValueError(f"no samples in [{t0}, {t1}]")
    return float(np.max(output_error(H, run["x"][m], run[key][m])))


def run_central(plant: LurePlant, *, bank: dict, conventional: dict, dt: float, t_end: float, x0: np.ndarray,
                xhat0: np.ndarray, attack: Callable[[float, np.ndarray], np.ndarray] | None = None,
                disturbance: Callable[[float], np.ndarray] | None = None, n_attacked: int | None = None,
                plant_substeps: int = 1) -> dict:
    """Reference loop of the central scheme: plant, bank + median, conventional, static inversion.

    Round ``k`` (``t_k = k dt``, ``k = 0..round(t_end/dt)``): ``d[k] = disturbance(t_k)``,
    ``z[k] = H x[k] + w(t_k) + d[k]``, ``y[k] = z[k] + attack(t_k, z[k])``; every estimator
    steps with ``y[k]``; then the plant advances with ``d[k]`` held.

    Parameters
    ----------
    attack : callable ``(t, z) -> (N,)`` in the coordinates of (7), optional
    disturbance : callable ``t -> (N,)`` in the coordinates of (7), optional

    Returns
    -------
    dict of arrays: ``t`` (T,), ``x`` (T, n), ``y`` (T, N), ``bank`` (T, N, n), ``median``,
    ``conventional``, ``static`` (T, n each).
    """
    steps = int(round(t_end / dt))
    bank_est = MedianBank(plant, bank=bank, dt=dt, x0=xhat0, n_attacked=n_attacked)
    conv = LureObserver(plant, sensors=range(plant.N), L=conventional["L"], K=conventional["K"], dt=dt,
                        x0=np.broadcast_to(np.asarray(xhat0, dtype=float), (plant.N, plant.n))[0])
    x = np.array(x0, dtype=float).reshape(plant.n)
    T = steps + 1
    out: dict[str, np.ndarray] = {k: np.zeros((T, plant.n)) for k in ("x", "median", "conventional", "static")}
    out["bank"] = np.zeros((T, plant.N, plant.n))
    out["y"] = np.zeros((T, plant.N))
    out["t"] = dt * np.arange(T)
    for k in range(T):
        t = k * dt
        d = np.zeros(plant.N) if disturbance is None else np.asarray(disturbance(t), dtype=float)
        z = plant.z(t, x, d)
        y = z if attack is None else z + attack(t, z)
        out["x"][k], out["y"][k] = x, y
        out["median"][k] = bank_est.step(k, y)
        out["bank"][k] = bank_est.estimates
        out["conventional"][k] = conv.step(k, y)
        out["static"][k] = static_inversion(plant, t, y)
        if k < steps:
            x = plant.step(t, x, dt, d=d, substeps=plant_substeps)
    return out
