"""A line of droop-controlled inverters as a Lur'e plant (van der Horst et al., Sections V-VI).

Topology (Fig. 2, Table I). The head node ``v'_0`` (substation) feeds a line; segment
``j = 0..N-1`` with impedance ``Z_j = R_j + jX_j`` joins ``v'_j`` to ``v'_{j+1}``. Customer
``i = 1..N`` hangs off ``v'_i`` through its service cable ``Z'_{i-1} = R'_{i-1} + jX'_{i-1}``
and sees the voltage ``v_i``. Column ``i`` of Table II gives ``R_{i-1}, X_{i-1}, R'_{i-1},
X'_{i-1}``. Customer ``i`` injects ``rho_i = rho_{g,i} - rho_{c,i}`` and
``q_i = q_{g,i} - q_{c,i}``.

Derivation of the linearised DistFlow terms (Baran and Wu, lossless). Across a branch that
carries ``(P, Q)`` away from the head, ``V_down^2 = V_up^2 - 2 (R P + X Q)``. Segment ``j``
carries ``P_j = -sum_{k>j} rho_k`` and ``Q_j = -sum_{k>j} q_k``; cable ``i`` carries
``-rho_i, -q_i``. Summing along the path ``v'_0 -> v'_i -> v_i``::

    v_i^2 = v'_0(t)^2 + 2 sum_k Rp[i,k] rho_k + 2 sum_k Xp[i,k] q_k,
    Rp[i,k] = sum_{j < min(i,k)} R_j + [i = k] R'_{i-1}     (resistance the paths share)
    Xp[i,k] = sum_{j < min(i,k)} X_j + [i = k] X'_{i-1}.

With ``x = q_g`` and ``z = v_bar^2 - v^2`` this is ``z = H x + w(t)`` (form (7)) with::

    H    = -2 Xp                                         (exactly the printed H)
    w(t) = v_bar^2 - v'_0(t)^2 - 2 Rp rho + 2 Xp q_c.

How the garbled parts of the text were resolved:

* **X' term of the known input.** The printed ``w_i`` adds ``2 beta'_j(rho_{j+1},
  q_{c,j+1})`` with ``beta'(r, s) = R' r + X' s`` summed over other customers' cables. Two
  corrections follow from the derivation: ``q = q_g - q_c`` enters through the same ``Xp``
  as ``q_g``, and ``H`` already carries ``-2 X'`` on its diagonal for ``q_g``, so ``q_c``
  must enter ``w`` as ``+2 X'_{i-1} q_{c,i}`` and ``rho`` as ``-2 R'_{i-1} rho_i`` (the same
  sign pattern as the printed line terms ``2 X_j sum q_c - 2 R_j sum rho``); and only
  customer ``i``'s own cable lies on the path to ``v_i``, so no other cable appears.
* **Sign of H_i in (14).** ``z = H x + w`` gives ``v_i^2 = v_bar^2 - H_i x - w_i``; the
  printed ``+ H_i x_hat`` has the sign flipped. We use
  ``v_hat_i^2 = v_bar^2 - H_i x_hat - w_i(t)``, so ``v_i^2 - v_hat_i^2 = -H_i (x - x_hat) - d_i``
  and ``|H_i (x - x_hat)|`` is the error of (36).
* **Squared-voltage attack.** The substation receives ``y_i = v_i + alpha_i`` (13) and forms
  ``y~_i = v_bar^2 - y_i^2 = z_i + a_i`` with ``a_i = -(2 v_i alpha_i + alpha_i^2)`` (the
  text prints ``2 v_i alpha_i alpha_i^2``; the sign follows from ``z = v_bar^2 - v^2``).
  ``alpha = +30 V`` at ``v ~ 230 V`` gives ``a ~ -14700 V^2``.
* **Slope bound.** The droop (12) has slopes ``Q_bar/(w_max - w_n)`` and
  ``Q_bar/(w_m - w_min)``; its slope bound is their maximum (the text prints ``min``, equal
  here because the design is symmetric). With ``w_max = -w_min = 17320.5 V^2`` the slopes
  are ``Q_bar_i / 17320.5 <= 3464.1 / 17320.5 = 0.2``, so ``e_bar = 0.2`` bounds every
  inverter; ``phi_i = Psi_i / tau_i`` has slopes in ``[0, e_bar / tau_i]`` (Assumption 3).

Disturbance (the paper says only "random, ``|d| <= 6 V``"): a voltage disturbance
``delta_i`` at each customer, independent and uniform in ``[-6, 6] V``, piecewise constant and
redrawn every ``hold = 0.1 s`` (seeded). It enters ``z_i`` as the squared-voltage change it
causes at the nominal voltage, ``d_i = v_bar^2 - (v_bar + delta_i)^2`` (``|d_i| <= 2796 V^2``),
so the droop controllers and the sensors both see it, as in (7).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from .lure import LurePlant


def _arr(values: Sequence[float]) -> np.ndarray:
    a = np.array(values, dtype=float)
    a.flags.writeable = False
    return a


@dataclass(frozen=True)
class InverterParams:
    """Parameters of Section VI (Table II; index ``i - 1`` is customer ``i``).

    Units: ohm, s, W, VAr, V, V^2. ``e_bar`` is the common slope bound of ``Psi_i`` in
    VAr/V^2 (the paper writes A/V).
    """

    R: np.ndarray = field(default_factory=lambda: _arr([0.00343, 0.00172, 0.00343, 0.00515, 0.00172]))
    X: np.ndarray = field(default_factory=lambda: _arr([0.04711, 0.02356, 0.04711, 0.07067, 0.02356]))
    R_cable: np.ndarray = field(default_factory=lambda: _arr([0.00147, 0.00662, 0.00147, 0.00147, 0.00147]))
    X_cable: np.ndarray = field(default_factory=lambda: _arr([0.02157, 0.09707, 0.02157, 0.02157, 0.02157]))
    tau: np.ndarray = field(default_factory=lambda: _arr([1.0, 1.0, 1.0, 1.0, 1.0]))
    rho_g: np.ndarray = field(default_factory=lambda: _arr([3500.0, 5500.0, 4000.0, 4500.0, 3000.0]))
    rho_c: np.ndarray = field(default_factory=lambda: _arr([2295.0, 5440.0, 5440.0, 2295.0, 2720.0]))
    q_c: np.ndarray = field(default_factory=lambda: _arr([300.0, 960.0, 480.0, 600.0, 400.0]))
    Q_bar: np.ndarray = field(default_factory=lambda: _arr([2321.6, 3464.1, 2467.8, 2800.0, 1999.0]))
    v_bar: float = 230.0
    v0_offset: float = 230.0
    v0_amplitude: float = 5.0
    v0_omega: float = 1.0
    e_bar: float = 0.2
    w_min: float = -17320.5
    w_m: float = 0.0
    w_n: float = 0.0
    w_max: float = 17320.5

    def __post_init__(self) -> None:
        n = self.R.size
        for name in ("X", "R_cable", "X_cable", "tau", "rho_g", "rho_c", "q_c", "Q_bar"):
            if getattr(self, name).shape != (n,):
                raise ValueError(f"InverterParams.{name} must have shape ({n},), got {getattr(self, name).shape}")
        if np.any(self.tau <= 0):
            raise ValueError(f"InverterParams.tau must be > 0, got {self.tau}")
        if not self.w_min < self.w_m <= 0.0 <= self.w_n < self.w_max:
            raise ValueError("droop breakpoints must satisfy w_min < w_m <= 0 <= w_n < w_max, got "
                             f"{self.w_min}, {self.w_m}, {self.w_n}, {self.w_max}")
        slope = droop_slope_bound(Q_bar=self.Q_bar, w_min=self.w_min, w_m=self.w_m, w_n=self.w_n, w_max=self.w_max)
        if np.any(slope > self.e_bar * (1 + 1e-6)):
            raise ValueError(f"e_bar = {self.e_bar} is below the droop slopes {slope}")


def droop(w: np.ndarray, *, Q_bar: np.ndarray, w_min: float, w_m: float, w_n: float, w_max: float) -> np.ndarray:
    """Saturation droop function ``Psi(w)`` of eq. (12), componentwise.

    Parameters
    ----------
    w : array, squared-voltage deviations ``v_bar^2 - v^2`` in V^2
    Q_bar : array broadcastable with ``w``, saturation limits in VAr
    w_min < w_m <= 0 <= w_n < w_max : breakpoints in V^2

    Returns
    -------
    array of the broadcast shape: ``-Q_bar`` below ``w_min``, linear to 0 at ``w_m``, 0 on
    ``[w_m, w_n]``, linear to ``Q_bar`` at ``w_max``, ``Q_bar`` above.
    """
    w = np.asarray(w, dtype=float)
    # clip to [0, 1] by the two ufuncs (np.clip's wrappers cost more than the maths here)
    lo = -np.minimum(np.maximum((w_m - w) / (w_m - w_min), 0.0), 1.0)
    hi = np.minimum(np.maximum((w - w_n) / (w_max - w_n), 0.0), 1.0)
    return (lo + hi) * Q_bar


def droop_slope_bound(*, Q_bar: np.ndarray, w_min: float, w_m: float, w_n: float, w_max: float) -> np.ndarray:
    """Largest slope of (12): ``max(Q_bar/(w_max - w_n), Q_bar/(w_m - w_min))``; the least is 0."""
    Q = np.asarray(Q_bar, dtype=float)
    return np.maximum(Q / (w_max - w_n), Q / (w_m - w_min))


def distflow_paths(*, R: np.ndarray, X: np.ndarray, R_cable: np.ndarray, X_cable: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shared-path resistance and reactance ``(Rp, Xp)``, each ``(N, N)`` (module docstring).

    ``Rp[i, k] = sum_{j < min(i, k) + 1} R_j + [i = k] R_cable_i`` with 0-based ``i, k``.
    """
    R, X, Rc, Xc = (np.asarray(a, dtype=float) for a in (R, X, R_cable, X_cable))
    idx = np.arange(R.size)
    shared = np.minimum.outer(idx, idx)  # number of line segments shared, minus one
    Rp = np.cumsum(R)[shared] + np.diag(Rc)
    Xp = np.cumsum(X)[shared] + np.diag(Xc)
    return Rp, Xp


class DroopNonlinearity:
    """``phi_i(z_i) = Psi_i(z_i) / tau_i`` of (7), componentwise (a picklable callable)."""

    def __init__(self, params: InverterParams) -> None:
        self.params = params

    def __call__(self, z: np.ndarray) -> np.ndarray:
        p = self.params
        return (1.0 / p.tau) * droop(z, Q_bar=p.Q_bar, w_min=p.w_min, w_m=p.w_m, w_n=p.w_n, w_max=p.w_max)


class InverterNetwork:
    """The line of ``N`` inverters in the coordinates of (7): ``x = q_g``, ``z = v_bar^2 - v^2``.

    Parameters
    ----------
    params : InverterParams, Table II and Section VI by default

    Attributes
    ----------
    params : InverterParams
    Rp, Xp : (N, N) arrays, shared-path resistance / reactance
    plant : LurePlant with ``A = diag(-1/tau)``, ``H = -2 Xp``, ``phi_i = Psi_i / tau_i``,
        slope bounds ``[0, e_bar / tau_i]`` and the known input ``w(t)``

    The network, its plant and its bound methods pickle (no closures), so estimators built
    on them can be shipped to other processes.
    """

    def __init__(self, params: InverterParams | None = None) -> None:
        self.params = p = InverterParams() if params is None else params
        self.Rp, self.Xp = distflow_paths(R=p.R, X=p.X, R_cable=p.R_cable, X_cable=p.X_cable)
        rho = p.rho_g - p.rho_c
        # constant part of w(t) = v_bar^2 - v0(t)^2 - 2 Rp rho + 2 Xp q_c
        self._w_loads = -2.0 * self.Rp @ rho + 2.0 * self.Xp @ p.q_c
        inv_tau = 1.0 / p.tau
        self.plant = LurePlant.build(A=np.diag(-inv_tau), H=-2.0 * self.Xp, phi=DroopNonlinearity(p),
                                     slope_upper=p.e_bar * inv_tau, w=self.w)

    @property
    def N(self) -> int:
        """Number of customers (= sensors = states)."""
        return self.params.R.size

    def head_voltage(self, t: float) -> float:
        """``v'_0(t) = 230 + 5 sin t`` V (Section VI)."""
        p = self.params
        return p.v0_offset + p.v0_amplitude * np.sin(p.v0_omega * t)

    def w(self, t: float) -> np.ndarray:
        """Known input ``w(t) = v_bar^2 - v'_0(t)^2 - 2 Rp rho + 2 Xp q_c``, shape (N,)."""
        return self.params.v_bar**2 - self.head_voltage(t) ** 2 + self._w_loads

    def voltages(self, t: float, x: np.ndarray, *, d: np.ndarray | None = None) -> np.ndarray:
        """True customer voltages ``v = sqrt(v_bar^2 - z)`` in V, shape (N,)."""
        return np.sqrt(self.params.v_bar**2 - self.plant.z(t, x, d))

    def squared_voltage_estimate(self, t: float, x_hat: np.ndarray) -> np.ndarray:
        """Voltage estimate (14), sign corrected: ``v_hat^2 = v_bar^2 - H x_hat - w(t)``, (N,)."""
        return self.params.v_bar**2 - self.plant.H @ x_hat - self.w(t)

    def lure_output(self, y_volts: np.ndarray) -> np.ndarray:
        """Measured voltages (13) to the output of (7): ``y~ = v_bar^2 - y^2`` in V^2."""
        return self.params.v_bar**2 - np.asarray(y_volts, dtype=float) ** 2

    def squared_attack(self, z: np.ndarray, alpha: np.ndarray) -> np.ndarray:
        """Attack in the coordinates of (7), ``a = -(2 v alpha + alpha^2)``, ``v = sqrt(v_bar^2 - z)``."""
        v = np.sqrt(self.params.v_bar**2 - np.asarray(z, dtype=float))
        alpha = np.asarray(alpha, dtype=float)
        return -(2.0 * v * alpha + alpha**2)

    def squared_disturbance(self, delta: np.ndarray) -> np.ndarray:
        """Voltage disturbance ``delta`` (V) to ``d = v_bar^2 - (v_bar + delta)^2`` (V^2)."""
        vb = self.params.v_bar
        return vb**2 - (vb + np.asarray(delta, dtype=float)) ** 2


def voltage_attack(*, N: int, sensors: Sequence[int], magnitude: float, start: float) -> Callable[[float], np.ndarray]:
    """Constant additive voltage attack ``alpha(t)`` of (13), shape (N,), 0-based sensor ids.

    ``alpha_i(t) = magnitude`` for ``i`` in ``sensors`` and ``t >= start`` (compared with a
    1e-9 s tolerance so that a grid time ``k dt`` equal to ``start`` counts), else 0.
    """
    ids = np.array(sorted(set(int(s) for s in sensors)), dtype=int)
    if ids.size and (ids.min() < 0 or ids.max() >= N):
        raise ValueError(f"attacked sensors must be in 0..{N - 1}, got {list(sensors)}")
    on = np.zeros(N)
    on[ids] = magnitude

    def alpha(t: float) -> np.ndarray:
        return on.copy() if t >= start - 1e-9 else np.zeros(N)

    return alpha


def random_voltage_disturbance(*, N: int, seed: int, bound: float = 6.0, hold: float = 0.1) -> Callable[[float], np.ndarray]:
    """Seeded piecewise-constant voltage disturbance ``delta(t)`` in V, shape (N,).

    On ``[m hold, (m+1) hold)`` every component is an independent uniform draw in
    ``[-bound, bound]`` from a generator seeded with ``(seed, m)`` (random access, so any
    caller gets the same value for the same ``t``). Grid times within 1e-9 s of a
    boundary belong to the later interval.
    """
    if not bound >= 0 or not hold > 0:
        raise ValueError(f"need bound >= 0 and hold > 0, got bound={bound}, hold={hold}")

    def delta(t: float) -> np.ndarray:
        if t < 0:
            raise ValueError(f"the disturbance is defined for t >= 0, got t={t}")
        m = int(np.floor(t / hold + 1e-9))
        return np.random.default_rng([int(seed), m]).uniform(-bound, bound, size=N)

    return delta


def reference_signals(
    net: InverterNetwork, *, attacked: Sequence[int] = (0, 3), magnitude: float = 30.0, start: float = 10.5,
    disturbance_seed: int | None = None, bound: float = 6.0, hold: float = 0.1,
) -> tuple[Callable[[float, np.ndarray], np.ndarray], Callable[[float], np.ndarray] | None]:
    """Attack and disturbance of Section VI-C in the coordinates of (7).

    Returns
    -------
    attack : callable ``(t, z) -> a`` (N,), ``a = -(2 v alpha + alpha^2)`` for the constant
        voltage attack ``alpha`` (sensors 1 and 4, i.e. ids 0 and 3, +30 V from 10.5 s)
    disturbance : callable ``t -> d`` (N,) from :func:`random_voltage_disturbance` with the
        given seed, or ``None`` when ``disturbance_seed`` is ``None``
    """
    alpha = voltage_attack(N=net.N, sensors=attacked, magnitude=magnitude, start=start)

    def attack(t: float, z: np.ndarray) -> np.ndarray:
        return net.squared_attack(z, alpha(t))

    if disturbance_seed is None:
        return attack, None
    delta = random_voltage_disturbance(N=net.N, seed=disturbance_seed, bound=bound, hold=hold)

    def disturbance(t: float) -> np.ndarray:
        return net.squared_disturbance(delta(t))

    return attack, disturbance
