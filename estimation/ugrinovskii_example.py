"""The illustrative example of Section IV of Ugrinovskii, "Distributed H-infinity estimation
resilient to biasing attacks", as plain matrices.

Six-state unstable plant with ``B = 0.1 I``; sensor ``i`` measures coordinates ``i`` and
``i + 1`` (sensor 6 measures 6 and 1), ``D_i = 0.01 I``; the nodes broadcast their full
estimates, ``W = I``, over noisy channels ``H_ij = H_c,ij = (0.1 / sqrt 2) [1 ... 1]'``;
scalar attacks ``F_i = [1 ... 1]'``; detector attack matrix ``0`` (``F_c,i = 0``) unless
``detector_attack=True``; ``G_i(s) = 410 / (s + 40)``; ``Z_ij = Zbar_ij = 0.01 I``.

Where the paper is silent:

* the graph: the text does not give it. A directed ring, node ``i`` receiving from node
  ``i - 1`` (0-based here: node ``i`` receives from ``(i - 1) mod 6``), together with
  ``U = Hhat Hhat' + Z`` in both LMIs (``observer_channel="H_hat"``) reproduces the paper's
  ``gamma^2 = 6.9113e-3`` and ``gamma_bar^2 = 3.4511e-2`` to within 0.1 %;
* ``P = (L + L_T) (x) I`` with ``L``, ``L_T`` the Laplacians of the ring and of its transpose
  (the consensus weight of [22] that the example keeps);
* the realisation of ``-G(s)/s`` is the scaled one of :func:`estimation.ugrinovskii.first_order_attack_model`;
* with ``detector_attack=True`` (the paper's general scenario, Section II-B) the detector
  attack matrix is ``F_c,i = [F_i; 0]``: the attacker adds the same scalar to every
  component of the detector's error estimate ``e_hat_i``.

The paper's node ``k`` (1-based) is index ``k - 1`` here; its attacked "node 2" is index 1.
"""

from __future__ import annotations

import numpy as np

from .hinf_lmi import ResilientProblem
from .ugrinovskii import first_order_attack_model

__all__ = ["PAPER_GAMMA2", "PAPER_GAMMA2_BAR", "plant_matrix", "example_problem"]

#: The values the paper reports for the example (Section IV).
PAPER_GAMMA2 = 6.9113e-3
PAPER_GAMMA2_BAR = 3.4511e-2


def plant_matrix() -> np.ndarray:
    """The 6 x 6 matrix ``A`` of Section IV (from [22])."""
    return np.array(
        [
            [0.3775, 0, 0, 0, 0, 0],
            [0.2959, 0.3510, 0, 0, 0, 0],
            [1.4751, 0.6232, 1.0078, 0, 0, 0],
            [0.2340, 0, 0, 0.5596, 0, 0],
            [0, 0, 0, 0.4437, 1.1878, -0.0215],
            [0, 0, 0, 0, 2.2023, 1.0039],
        ]
    )


def example_problem(*, detector_attack: bool = False) -> ResilientProblem:
    """The Section IV example as a :class:`~estimation.hinf_lmi.ResilientProblem`.

    Parameters
    ----------
    detector_attack : bool, keyword-only
        ``False`` (the paper's example): ``F_c,i = 0``. ``True``: ``F_c,i = [F_i; 0]`` so
        that the design accounts for attacks on the detectors as well.

    Returns
    -------
    ResilientProblem with ``n = 6``, ``N = 6``, directed ring.
    """
    n = N = 6
    A = plant_matrix()
    eye = np.eye(n)
    C = tuple(eye[[i, (i + 1) % n]] for i in range(N))
    D = tuple(0.01 * np.eye(2) for _ in range(N))
    neighbours = tuple(((i - 1) % N,) for i in range(N))
    edges = [(i, j) for i in range(N) for j in neighbours[i]]
    h = (0.1 / np.sqrt(2.0)) * np.ones((n, 1))
    Omega, Gamma, Upsilon = first_order_attack_model(gain=410.0, pole=40.0)
    F = np.ones((n, 1))
    ne = Omega.shape[0]
    Fc = np.vstack([F, np.zeros((ne, 1))]) if detector_attack else np.zeros((n + ne, 1))
    Adj = np.zeros((N, N))
    for i, j in edges:
        Adj[i, j] = 1.0
    Lap = np.diag(Adj.sum(axis=1)) - Adj
    LapT = np.diag(Adj.T.sum(axis=1)) - Adj.T
    return ResilientProblem(
        A=A,
        B=0.1 * eye,
        C=C,
        D=D,
        neighbours=neighbours,
        W={e: eye.copy() for e in edges},
        H={e: h.copy() for e in edges},
        Hc={e: h.copy() for e in edges},
        Z={e: 0.01 * eye for e in edges},
        Zbar={e: 0.01 * eye for e in edges},
        F=tuple(F.copy() for _ in range(N)),
        Fc=tuple(Fc.copy() for _ in range(N)),
        Omega=tuple(Omega.copy() for _ in range(N)),
        Gamma=tuple(Gamma.copy() for _ in range(N)),
        Upsilon=tuple(Upsilon.copy() for _ in range(N)),
        P=np.kron(Lap + LapT, eye),
    )
