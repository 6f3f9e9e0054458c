"""Pole placement for one input column, without importing :mod:`scipy.signal`.

Importing :mod:`scipy.signal` costs about 0.45 s on a 2-core machine (it pulls in
``scipy.stats``, ``scipy.interpolate`` and the filter design code), which is a quarter of
``rse run scenarios/lee_kim_shim.toml``'s start-up. Every observer of the scenarios places
the poles of ``A.T`` with ``B = C.T`` of *one* row (a single output per observable part),
where the gain is unique. :func:`place_poles` computes it with the steps of
:func:`scipy.signal.place_poles` (Kautsky, Nichols and Van Dooren's method, version
1.17) for ``rank(B) == 1``: the same QR factorisations and solves, so the same numbers
(``tests/estimation/test_placement.py`` compares the two). Any other ``B`` is handed to
:func:`scipy.signal.place_poles` itself.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def _order_complex_poles(poles: np.ndarray) -> np.ndarray:
    """Real poles sorted, then each complex pair (negative imaginary part first), as
    scipy orders them; raises ValueError when a complex pole lacks its conjugate."""
    ordered = np.sort(poles[np.isreal(poles)])
    im_poles: list[complex] = []
    for p in np.sort(poles[np.imag(poles) < 0]):
        if np.conj(p) in poles:
            im_poles.extend((p, np.conj(p)))
    ordered = np.hstack((ordered, im_poles))
    if poles.shape[0] != len(ordered):
        raise ValueError("Complex poles must come with their conjugates")
    return ordered


def _single_input_gain(A: np.ndarray, B: np.ndarray, poles: np.ndarray) -> np.ndarray:
    """``K`` with ``eig(A - B K) = poles`` for a ``B`` of rank one (scipy's KNV steps)."""
    from scipy.linalg import qr

    n = A.shape[0]
    u, z = qr(B, mode="full")
    u0, u1, z = u[:, :1], u[:, 1:], z[:1, :]
    if n == 1:  # B square and of full rank: the one solution
        diag = np.diag(np.real(poles)).astype(float)
        return -np.real(np.linalg.lstsq(B, diag - A, rcond=-1)[0])
    columns = []
    skip = False
    for j in range(n):
        if skip:
            skip = False
            continue
        space = np.dot(u1.T, A - poles[j] * np.eye(n)).T
        Q, _ = qr(space, mode="full")
        vec = np.sum(Q[:, space.shape[1]:], axis=1)[:, np.newaxis]
        vec = vec / np.linalg.norm(vec)
        if ~np.isreal(poles[j]):
            vec = np.hstack([np.real(vec), np.imag(vec)])
            skip = True
        columns.append(vec)
    X = np.hstack(columns).astype(complex)
    idx = 0
    while idx < n - 1:
        if ~np.isreal(poles[idx]):
            re, im = X[:, idx].copy(), X[:, idx + 1]
            X[:, idx] = re - 1j * im
            X[:, idx + 1] = re + 1j * im
            idx += 1
        idx += 1
    try:
        m = np.linalg.solve(X.T, np.dot(np.diag(poles), X.T)).T
        gain = np.linalg.solve(z, np.dot(u0.T, m - A))
    except np.linalg.LinAlgError as exc:
        raise ValueError("The poles you've chosen can't be placed. Check the controllability matrix "
                         "and try another set of poles") from exc
    return np.real(-gain)


class Placement:
    """What :func:`place_poles` returns: ``gain_matrix`` and ``computed_poles``, as the
    fields of the same name of scipy's result."""

    def __init__(self, gain_matrix: np.ndarray, computed_poles: np.ndarray) -> None:
        self.gain_matrix = gain_matrix
        self.computed_poles = computed_poles


def place_poles(A: Any, B: Any, poles: Any) -> Any:
    """``K`` with ``eig(A - B K) = poles`` (``.gain_matrix``), as
    :func:`scipy.signal.place_poles` with its default method; a one-column ``B`` of rank
    one without importing :mod:`scipy.signal`. Raises ValueError as scipy does."""
    A = np.asarray(A)
    B = np.asarray(B)
    p = np.asarray(poles)
    single = (A.ndim == 2 and B.ndim == 2 and A.shape[0] == A.shape[1] == B.shape[0] and B.shape[1] == 1
              and p.ndim == 1 and len(p) == A.shape[0] and np.linalg.matrix_rank(B) == 1)
    if not single:
        from scipy.signal import place_poles as scipy_place_poles

        return scipy_place_poles(A, B, poles)
    p = _order_complex_poles(p)
    for q in p:
        if np.sum(q == p) > 1:
            raise ValueError("at least one of the requested pole is repeated more than rank(B) times")
    K = _single_input_gain(A, B, p)
    return Placement(K, _order_complex_poles(np.linalg.eig(A - np.dot(B, K))[0]))
