"""Lur'e plants with slope-restricted nonlinearities and their fixed-step integration.

van der Horst, Chong, Kim, Sandberg, "Resilient nonlinear state estimation using the
median operation for a network of droop-controlled power inverters", eq. (7)::

    x' = A x + G phi(z),   phi(z) = (phi_1(z_1), ..., phi_N(z_N)),
    z_i = H_i x + w_i(t) + d_i,
    y_i = z_i + a_i,

with ``x`` of size ``n``, ``N`` scalar sensors, a known input ``w(t)``, an unknown bounded
disturbance ``d`` and sensor attacks ``a``. The paper adds ``phi(z)`` to ``A x`` directly,
which needs ``n = N``; the input matrix ``G`` (``(n, N)``, identity by default) is the
only generalisation. Assumption 3 (eq. (8)): every ``phi_i`` is slope-restricted,
``e_lo_i <= (phi_i(a) - phi_i(b)) / (a - b) <= e_hi_i``.

Integration (the paper is continuous-time and silent about it): classical fourth-order
Runge-Kutta with a fixed step. Over one step ``[t_k, t_k + dt)``

* the known input ``w(t)`` is *evaluated* at the RK4 stage times (it is a known function
  of time),
* the disturbance ``d`` is *held* at ``d[k]`` (a sampled signal; zero-order hold),
* ``dt`` may be split into ``substeps`` equal RK4 steps.

For a smooth ``phi`` the local error is O(dt^5); the saturation droop function is only
piecewise linear, so a step that crosses a kink is O(dt^2) locally. At the inverter
scenario's ``dt = 0.01 s`` one RK4 step per round agrees with 20 sub-steps to far below
the acceptance tolerances (tested).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

Vector = np.ndarray
KnownInput = Callable[[float], np.ndarray]
Nonlinearity = Callable[[np.ndarray], np.ndarray]


def rk4_step(f: Callable[[float, np.ndarray], np.ndarray], t: float, x: np.ndarray, dt: float) -> np.ndarray:
    """One classical Runge-Kutta step of ``x' = f(t, x)`` from ``t`` to ``t + dt``.

    Parameters
    ----------
    f : callable ``(t, x) -> (n,) array``
    t : float
    x : (n,) array
    dt : float

    Returns
    -------
    (n,) array, the new state (a new array; ``x`` is not modified).
    """
    k1 = f(t, x)
    k2 = f(t + 0.5 * dt, x + 0.5 * dt * k1)
    k3 = f(t + 0.5 * dt, x + 0.5 * dt * k2)
    k4 = f(t + dt, x + dt * k3)
    return x + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def integrate(
    f: Callable[[float, np.ndarray], np.ndarray], t: float, x: np.ndarray, dt: float, *, substeps: int = 1
) -> np.ndarray:
    """Advance ``x' = f(t, x)`` by ``dt`` with ``substeps`` equal RK4 steps."""
    if not isinstance(substeps, (int, np.integer)) or substeps < 1:
        raise ValueError(f"substeps must be a positive integer, got {substeps!r}")
    h = dt / substeps
    for s in range(substeps):
        x = rk4_step(f, t + s * h, x, h)
    return x


def check_slope(
    phi: Nonlinearity, *, lower: np.ndarray, upper: np.ndarray, points: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Measure the secant slopes of a componentwise ``phi`` on a grid (Assumption 3, eq. (8)).

    Parameters
    ----------
    phi : callable ``(N,) -> (N,)``, componentwise
    lower, upper : (N,) arrays, the claimed slope bounds
    points : (m,) array of scalar arguments, applied to every component at once

    Returns
    -------
    (smin, smax) : two (N,) arrays, the smallest and largest secant slope between
        consecutive grid points. A caller compares them with ``lower`` / ``upper``.
    """
    pts = np.sort(np.asarray(points, dtype=float))
    if pts.ndim != 1 or pts.size < 2:
        raise ValueError("points must be a 1-D array of at least two values")
    n = np.asarray(lower).size
    vals = np.stack([phi(np.full(n, p)) for p in pts])  # (m, N)
    slopes = np.diff(vals, axis=0) / np.diff(pts)[:, None]
    return slopes.min(axis=0), slopes.max(axis=0)


@dataclass(frozen=True, eq=False)
class LurePlant:
    """A Lur'e plant (7) with known input ``w(t)``.

    Attributes
    ----------
    A : (n, n) array
    H : (N, n) array, rows ``H_i``
    G : (n, N) array, input matrix of ``phi`` (identity in the paper)
    phi : callable ``(N,) -> (N,)``, componentwise, slope-restricted
    slope_lower, slope_upper : (N,) arrays, the bounds ``e_lo``, ``e_hi`` of (8)
    w : callable ``t -> (N,) array``, the known input
    """

    A: np.ndarray
    H: np.ndarray
    G: np.ndarray
    phi: Nonlinearity
    slope_lower: np.ndarray
    slope_upper: np.ndarray
    w: KnownInput

    @classmethod
    def build(
        cls,
        *,
        A: np.ndarray,
        H: np.ndarray,
        phi: Nonlinearity,
        slope_upper: np.ndarray,
        w: KnownInput,
        slope_lower: np.ndarray | None = None,
        G: np.ndarray | None = None,
    ) -> "LurePlant":
        """Validate shapes and build a plant; arrays are copied and made read-only."""
        A = np.array(A, dtype=float)
        H = np.atleast_2d(np.array(H, dtype=float))
        if A.ndim != 2 or A.shape[0] != A.shape[1]:
            raise ValueError(f"A must be square (n, n), got shape {A.shape}")
        n = A.shape[0]
        if H.shape[1] != n:
            raise ValueError(f"H must be (N, {n}), got shape {H.shape}")
        N = H.shape[0]
        G = np.eye(n, N) if G is None else np.array(G, dtype=float)
        if G.shape != (n, N):
            raise ValueError(f"G must be ({n}, {N}), got shape {G.shape}")
        hi = np.broadcast_to(np.asarray(slope_upper, dtype=float), (N,)).copy()
        lo = np.zeros(N) if slope_lower is None else np.broadcast_to(np.asarray(slope_lower, dtype=float), (N,)).copy()
        if np.any(lo > hi) or not np.all(np.isfinite(hi)):
            raise ValueError(f"slope bounds must be finite with lower <= upper, got {lo} and {hi}")
        w0 = np.asarray(w(0.0), dtype=float)
        if w0.shape != (N,):
            raise ValueError(f"w(t) must return shape ({N},), got {w0.shape}")
        for arr in (A, H, G, lo, hi):
            arr.flags.writeable = False
        return cls(A=A, H=H, G=G, phi=phi, slope_lower=lo, slope_upper=hi, w=w)

    @property
    def n(self) -> int:
        """State dimension."""
        return self.A.shape[0]

    @property
    def N(self) -> int:
        """Number of scalar sensors."""
        return self.H.shape[0]

    def z(self, t: float, x: np.ndarray, d: np.ndarray | None = None) -> np.ndarray:
        """``z = H x + w(t) + d``, shape (N,) (eq. (7))."""
        z = self.H @ x + self.w(t)
        return z if d is None else z + d

    def rhs(self, t: float, x: np.ndarray, d: np.ndarray | None = None) -> np.ndarray:
        """``x' = A x + G phi(z)``, shape (n,) (eq. (7))."""
        return self.A @ x + self.G @ self.phi(self.z(t, x, d))

    def step(self, t: float, x: np.ndarray, dt: float, *, d: np.ndarray | None = None, substeps: int = 1) -> np.ndarray:
        """Advance the state from ``t`` to ``t + dt`` (RK4, ``w`` evaluated, ``d`` held).

        Parameters
        ----------
        t : float
        x : (n,) array
        dt : float, > 0
        d : (N,) array or None, the disturbance held over the step
        substeps : int, number of RK4 steps per ``dt``
        """
        if not dt > 0:
            raise ValueError(f"dt must be > 0, got {dt}")
        dd = None if d is None else np.asarray(d, dtype=float)
        return integrate(lambda s, xs: self.rhs(s, xs, dd), t, np.asarray(x, dtype=float), dt, substeps=substeps)

    def output(self, t: float, x: np.ndarray, *, d: np.ndarray | None = None, a: np.ndarray | None = None) -> np.ndarray:
        """Measured outputs ``y = z + a``, shape (N,) (eq. (7))."""
        z = self.z(t, x, d)
        return z if a is None else z + a
