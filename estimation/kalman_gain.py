"""Partial-observer gains from the Riccati equation of the sampled system, for large plants.

Lee, Kim, Shim (IEEE TAC 2020) ask of the partial observer (5) only that
``W_i A V_i - L_i C_i V_i`` be Hurwitz; they choose ``L_i`` by pole placement. At a hundred
states seen through a few outputs (a power grid's swing modes, ``estimation.grid``) pole
placement is ill-conditioned: moving every mode, also those a bank sees only faintly, to one
real part takes gains of 1e5 and transients of 1e6. The steady-state Kalman gain of the sampled
partial system is well-conditioned at that size and moves each mode only as far as the bank
sees it; a faintly seen mode keeps about its own decay.

Sampled at the round step ``dt`` (the way the agent runs (5), ``estimation.lee_kim_shim``)::

    z[k+1] = Phi z[k] + W_i Bd u[k] + Ld (y[k] - C_o z[k]),   Phi = expm(A_o dt),  C_o = C_i V_i,

``Ld = Phi P C_o^T (C_o P C_o^T + I)^-1`` with ``P`` the stabilising solution of the discrete
algebraic Riccati equation of ``(Phi, C_o)`` with unit weights ``Q = I``, ``R = I`` (in the
common basis's coordinates). With ``Q > 0`` and ``(C_o, Phi)`` observable (the partial
observer's part is observable by construction), ``Phi - Ld C_o`` is Schur stable (Anderson,
Moore, Optimal Filtering, 1979, Sec. 4.4): the sampled error of (5) decays, which is (5)'s
condition at the samples. Its continuous-time equivalents ``log(eig) / dt`` are the poles
reported.
"""

from __future__ import annotations

import numpy as np

from .errors import DesignError


def sampled_kalman_gain(A_o: np.ndarray, C_o: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """``(Ld (o, m), poles (o,) complex)``: the steady-state Kalman gain of ``(expm(A_o dt), C_o)``
    with unit weights (module docstring) and the continuous-time equivalents of its error poles.

    Parameters
    ----------
    A_o : (o, o) array  ``W_i A V_i``
    C_o : (m, o) array  ``C_i V_i``
    dt : float > 0, the round step
    """
    from scipy.linalg import expm, solve_discrete_are

    if not dt > 0:
        raise DesignError(f"the Kalman gain needs a round step dt > 0, got {dt}")
    A_o, C_o = np.asarray(A_o, dtype=float), np.atleast_2d(np.asarray(C_o, dtype=float))
    o, m = A_o.shape[0], C_o.shape[0]
    Phi = expm(A_o * dt)
    try:
        P = solve_discrete_are(Phi.T, C_o.T, np.eye(o), np.eye(m))
    except (ValueError, np.linalg.LinAlgError) as exc:
        raise DesignError(f"the Riccati equation of the sampled partial system has no stabilising solution: {exc}") from None
    Ld = Phi @ P @ C_o.T @ np.linalg.inv(C_o @ P @ C_o.T + np.eye(m))
    eig = np.linalg.eigvals(Phi - Ld @ C_o)
    if not np.all(np.abs(eig) < 1.0):
        raise DesignError(f"the sampled Kalman gain leaves an error pole on or outside the unit circle ({np.abs(eig).max():.6g})")
    return Ld, np.log(eig.astype(complex)) / dt
