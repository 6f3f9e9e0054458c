"""Mean-square stability of LFRE over Bernoulli erasure channels (Theorem 2).

Mitra et al. 2019, Section 7.1. With a baseline graph strongly ``(m f + 1)``-robust with
respect to every source set (``m >= 3``) and i.i.d. erasures of probability ``p`` on every
link, the LFRE rule (21)-(22) is mean-square stable if (eq. (23))::

    rho^2 pbar < 1,

    pbar = 1 - sum_{l = 2f+1}^{(m-1)f+1} binom((m-1)f+1, l) (1-p)^l p^{(m-1)f+1-l}   (24)

i.e. one minus the probability that at least ``2f + 1`` of ``(m-1)f + 1`` regular
neighbours get through. For ``m <= 2`` the sum is empty and ``pbar = 1``: nothing can be
certified (Remark 13). For ``f = 0``, ``pbar = p`` (Remark 12).

``pbar`` increases monotonically from 0 (``p = 0``, when ``m >= 3``) to 1 (``p = 1``),
so the largest tolerable erasure probability solves ``rho^2 pbar(p) = 1`` (bisection,
:func:`scipy.optimize.brentq`). For the paper's setup (``rho = 1.2, m = 3, f = 1``)
``pbar = 1 - (1-p)^3`` and ``p* = 1 - (1 - 1/1.44)^(1/3) = 0.32647...``; the paper
quotes 0.32.
"""

from __future__ import annotations

import math

import numpy as np

from .errors import DesignError


def _check(m: int, f: int) -> tuple[int, int]:
    for name, v, lo in (("m", m, 1), ("f", f, 0)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
            raise DesignError(f"{name} must be an integer >= {lo}, got {v!r}")
    return int(m), int(f)


def effective_erasure_probability(p: float | np.ndarray, *, m: int, f: int) -> float | np.ndarray:
    """``pbar`` of eq. (24).

    Parameters
    ----------
    p : float or array in [0, 1]
        Per-link erasure probability (vectorised).
    m : int >= 1
        Robustness multiplier: the graph is strongly ``(m f + 1)``-robust.
    f : int >= 0
        Attack budget (f-local adversaries).
    """
    from scipy.special import comb

    m, f = _check(m, f)
    pa = np.asarray(p, dtype=float)
    if np.any((pa < 0) | (pa > 1)) or not np.all(np.isfinite(pa)):
        raise DesignError(f"erasure probability must be in [0, 1], got {p!r}")
    nreg = (m - 1) * f + 1
    q = 1.0 - pa
    ok = np.zeros_like(pa)
    for l in range(2 * f + 1, nreg + 1):
        ok = ok + comb(nreg, l, exact=True) * q**l * pa ** (nreg - l)
    out = 1.0 - ok
    return float(out) if out.ndim == 0 else out


def mss_margin(p: float | np.ndarray, *, rho: float, m: int, f: int) -> float | np.ndarray:
    """``rho^2 pbar`` of eq. (23); mean-square stability is certified when it is < 1."""
    if not (rho >= 0 and math.isfinite(rho)):
        raise DesignError(f"spectral radius rho must be finite and >= 0, got {rho!r}")
    return rho**2 * effective_erasure_probability(p, m=m, f=f)


def is_mean_square_stable(p: float, *, rho: float, m: int, f: int) -> bool:
    """Theorem 2's condition ``rho^2 pbar < 1``."""
    return bool(mss_margin(p, rho=rho, m=m, f=f) < 1.0)


def max_erasure_probability(*, rho: float, m: int, f: int, xtol: float = 1e-14) -> float:
    """Largest ``p`` with ``rho^2 pbar(p) <= 1`` (the supremum of the tolerable ones).

    Returns 1.0 when ``rho <= 1`` (every ``p < 1`` is tolerated: marginally stable or
    stable plants, Section 8.2) and 0.0 when nothing is certified (``pbar = 1``, i.e.
    ``m <= 2`` with ``rho > 1``).
    """
    from scipy.optimize import brentq

    m, f = _check(m, f)
    if not (rho >= 0 and math.isfinite(rho)):
        raise DesignError(f"spectral radius rho must be finite and >= 0, got {rho!r}")
    if rho <= 1.0:
        return 1.0
    g = lambda p: rho**2 * effective_erasure_probability(p, m=m, f=f) - 1.0
    if g(0.0) >= 0.0:
        return 0.0
    return float(brentq(g, 0.0, 1.0, xtol=xtol))


def robustness_multiplier(r: int | float, *, f: int) -> int | float:
    """Largest ``m`` with ``m f + 1 <= r`` for a strongly ``r``-robust graph.

    ``r`` may be ``inf`` (no non-source agent); ``f = 0`` gives ``inf`` for any ``r >= 1``.
    """
    if f < 0:
        raise DesignError(f"f must be >= 0, got {f}")
    if r < 1:
        return 0
    if f == 0 or math.isinf(r):
        return math.inf
    return (int(r) - 1) // f
