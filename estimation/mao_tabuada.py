"""Decentralized resilient state tracking by dynamic average consensus, discrete time.

Mao, Tabuada, "Decentralized resilient state-tracking"
(``papers/mao_tabuada_decentralized_resilient_state_tracking.md``). The paper is stated in
continuous time and notes that a discrete-time version is what can be implemented; this
is that version. Plant and sensors (eq. (1), Assumptions 1-5)::

    x[k+1] = A x[k],      y_i[k] = C_i x[k] + e_i[k],   i = 0..p-1 (scalar, e_i = 0 if honest)

Measurement window (eq. (2)-(3)): the discrete counterpart of ``[y, y', .., y^(n-1)]`` is
the last ``n`` samples, oldest first::

    Y_i[k] = (y_i[k-n+1], ..., y_i[k]) = O_i x[k-n+1] + E_i[k],   O_i = [C_i; C_i A; ..; C_i A^{n-1}]

and by Cayley-Hamilton (``det(zI - A) = z^n + alpha_{n-1} z^{n-1} + .. + alpha_0``) an
honest window obeys the companion dynamics of eq. (5)::

    Y_i[k+1] = Ahat Y_i[k],   Ahat = [[0, 1, 0, ..], .., [-alpha_0, -alpha_1, .., -alpha_{n-1}]]

Local sanity check (Section V): the discrete form of ``||Y_i' - Ahat Y_i|| <= eps`` is
``|r_i[k]| <= rtol * (|y_i[k]| + sum_j |alpha_j| |Y_i[k-1]_j|)`` with
``r_i[k] = y_i[k] + sum_j alpha_j Y_i[k-1]_j`` (the only entry of ``Y_i[k] - Ahat Y_i[k-1]``
that is not zero by construction); the tolerance is relative to the signal size because
the signals grow. A violation latches ``flagged``. A flagged node (it now knows it is
attacked) replaces its measurements from then on by the prediction of its last window
that passed the check, so its signal stays ``Ahat``-consistent (the paper is silent on
what a flagged node does; Assumption 1 keeps it running the algorithm).

Consensus (Sections V-VI): ``phi_i[k] = D[:, i] Y_i[k]^T``, shape ``(v, n)`` -- one copy
per row of ``D`` -- is averaged by :mod:`estimation.dynamic_consensus`; ``J_i`` tracks
``(1/p) (D (x) I_n) Y``. Before the window is full ``phi_i = 0``.

Decoding: ``Z = p J_i`` is decoded by :class:`estimation.secure_decoder.SecureDecoder`
(or plain least squares, ``decoder="least_squares"``, the non-resilient baseline) into
``x[k-n+1]``; the estimate is ``x_hat_i[k] = A^{n-1} x_hat_w``.

Long runs, numerical soundness: **limit** (not rescale). Every quantity of the estimator
(windows, ``J``, ``eta``, ``b``, estimate) is in plant units and within a constant factor
(``||D||``, ``p``, ``||O^+||``) of the measurements; the estimate must be reported in plant
units, and the plant's own state overflows in the same round, so a rescaling inside the
estimator buys nothing. Instead the signals must stay below ``SIGNAL_LIMIT = 1e150``
(so products of two signal-sized numbers remain finite); :func:`safe_horizon` gives the
last round for which that holds, the scenario's horizon must not exceed it, and
``step`` raises :class:`NumericalError` (naming the round) if a measurement or estimate
passes the limit. Relative accuracy does not degrade with the magnitude (no absolute
tolerances are used).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .base import Flags, Inbox
from .batching import Batch, Batchable
from .dynamic_consensus import ConsensusGains, ConsensusNode, design_consensus_gains
from .errors import DesignError, NumericalError
from .lti import float_horizon
from .secure_decoder import SecureDecoder, least_squares_decode
from .sparse_detectability import DetectabilityReport, design_compression, sparse_detectability

__all__ = [
    "SIGNAL_LIMIT",
    "companion",
    "window_observability",
    "safe_horizon",
    "MeasurementWindow",
    "MaoTabuadaDesign",
    "design_mao_tabuada",
    "check_report",
    "MaoTabuadaEstimator",
    "MaoTabuadaExample",
    "example",
]

SIGNAL_LIMIT = 1e150


def companion(A) -> tuple[np.ndarray, np.ndarray]:
    """``(Ahat, alpha)``: the companion matrix of eq. (5) and ``alpha = (alpha_0..alpha_{n-1})``."""
    A = np.asarray(A, dtype=float)
    if A.ndim != 2 or A.shape[0] != A.shape[1]:
        raise DesignError(f"A must be square, got shape {A.shape}")
    n = A.shape[0]
    alpha = np.real(np.poly(A))[1:][::-1].copy()
    Ahat = np.eye(n, k=1)
    Ahat[-1] = -alpha
    return Ahat, alpha


def window_observability(A, C) -> np.ndarray:
    """``O_i = [C_i; C_i A; ..; C_i A^{n-1}]`` for every sensor; shape ``(p, n, n)``."""
    A = np.asarray(A, dtype=float)
    C = np.atleast_2d(np.asarray(C, dtype=float))
    n = A.shape[0]
    rows, P = [], np.eye(n)
    for _ in range(n):
        rows.append(C @ P)
        P = A @ P
    return np.stack(rows, axis=1)


def safe_horizon(A, *, x0_norm: float, limit: float = SIGNAL_LIMIT, max_rounds: int = 10**6) -> int:
    """Last round ``k`` with ``||A^k||_2 x0_norm <= limit`` (capped at ``max_rounds``)."""
    if not x0_norm > 0:
        raise DesignError(f"x0_norm must be positive, got {x0_norm}")
    return float_horizon(np.asarray(A, dtype=float), x_norm=x0_norm, limit=limit, max_rounds=max_rounds, norm=2)


class MeasurementWindow:
    """The window ``Y_i[k]`` of one scalar sensor with its latched sanity check.

    Parameters
    ----------
    alpha : (n,) array
        Characteristic-polynomial coefficients ``alpha_0..alpha_{n-1}`` (see :func:`companion`).
    rtol : float, keyword-only
        Relative tolerance of the sanity check (the paper's ``epsilon``, made relative).
    """

    def __init__(self, alpha, *, rtol: float = 1e-9) -> None:
        self._alpha = np.array(alpha, dtype=float)
        self.n = self._alpha.shape[0]
        if not rtol > 0:
            raise DesignError(f"rtol must be positive, got {rtol}")
        self.rtol = float(rtol)
        self._Y = np.zeros(self.n)
        self._count = 0
        self.flagged = False
        self.flag_round: int | None = None
        self.last_residual = 0.0  # |r| / scale of the last checked sample

    @property
    def full(self) -> bool:
        return self._count >= self.n

    @property
    def values(self) -> np.ndarray:
        """``Y_i[k]``, oldest sample first; ``(n,)`` copy."""
        return self._Y.copy()

    def push(self, k: int, y: float | None) -> None:
        """Add the sample of round ``k`` (``None``: missing, predicted if the window is full)."""
        if self.full:
            pred = -float(self._alpha @ self._Y)
            if y is not None and not self.flagged:
                scale = abs(y) + float(np.abs(self._alpha) @ np.abs(self._Y))
                r = abs(y - pred)
                self.last_residual = r / scale if scale > 0 else 0.0
                if r > self.rtol * scale:
                    self.flagged, self.flag_round = True, int(k)
            if y is None or self.flagged:
                y = pred
        elif y is None:  # samples must be consecutive: start again
            self._count = 0
            return
        self._Y = np.roll(self._Y, -1)
        self._Y[-1] = y
        self._count += 1


def _frozen(a) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.flags.writeable = False
    return a


@dataclass(frozen=True)
class MaoTabuadaDesign:
    """Offline design shared by all nodes (read-only arrays).

    Attributes
    ----------
    A : (n, n), C : (p, n), Adj : (p, p), D : (v, p), Ahat : (n, n), alpha : (n,),
    O_blocks : (p, n, n), A_window : (n, n) ``= A^{n-1}``
    s : int
    gains : ConsensusGains
    detectability : DetectabilityReport
        ``2s``-sparse detectability w.r.t. ``D``.
    decoder : SecureDecoder
    rtol : float
        Sanity-check tolerance.
    """

    A: np.ndarray
    C: np.ndarray
    Adj: np.ndarray
    D: np.ndarray
    Ahat: np.ndarray
    alpha: np.ndarray
    O_blocks: np.ndarray
    A_window: np.ndarray
    s: int
    gains: ConsensusGains
    detectability: DetectabilityReport
    decoder: SecureDecoder
    rtol: float

    @property
    def p(self) -> int:
        return self.C.shape[0]

    @property
    def n(self) -> int:
        return self.A.shape[0]

    @property
    def v(self) -> int:
        return self.D.shape[0]


def design_mao_tabuada(
    A,
    C,
    Adj,
    *,
    s: int,
    D=None,
    rtol: float = 1e-9,
    max_spectral_radius: float = 1.0 - 1e-9,
    n_random: int = 20,
    seed: int = 0,
) -> MaoTabuadaDesign:
    """Build the offline design: compression ``D`` (Section IV), gains (Section VI), decoder.

    Parameters
    ----------
    A : (n, n) array
        Discrete-time state matrix (eigenvalues of modulus > 1 mirror Assumption 6).
    C : (p, n) array
        One scalar sensor per node.
    Adj : (p, p) array
        Symmetric adjacency of a connected graph (Assumption 4).
    s : int, keyword-only
        Attacked nodes to tolerate.
    D : (v, p) array, optional
        Given compression matrix (checked); searched by :func:`design_compression` if omitted.

    Raises
    ------
    DesignError
        ``(A, C)`` not ``2s``-sparse detectable (w.r.t. the given ``D``), or no stable
        consensus gains for the graph.
    """
    A = np.asarray(A, dtype=float)
    C = np.asarray(C, dtype=float)
    Adj = np.asarray(Adj, dtype=float)
    if C.ndim != 2 or A.ndim != 2 or C.shape[1] != A.shape[0] or A.shape[0] != A.shape[1]:
        raise DesignError(f"need A (n, n) and C (p, n); got A {A.shape}, C {C.shape}")
    if Adj.shape != (C.shape[0], C.shape[0]):
        raise DesignError(f"Adj must be ({C.shape[0]}, {C.shape[0]}) (one node per sensor), got {Adj.shape}")
    if D is None:
        rep = design_compression(A, C, s=s, n_random=n_random, seed=seed)
    else:
        rep = sparse_detectability(A, C, k=2 * s, D=D)
        if not rep.holds:
            raise DesignError(
                f"(A, C) is not {2 * s}-sparse detectable w.r.t. the given D (v = {rep.v}); "
                f"support {list(rep.worst_support)} fails (Lemma 2)"
            )
    gains = design_consensus_gains(Adj, max_spectral_radius=max_spectral_radius)
    Ahat, alpha = companion(A)
    O = window_observability(A, C)
    n = A.shape[0]
    return MaoTabuadaDesign(
        A=_frozen(A), C=_frozen(C), Adj=_frozen(Adj), D=_frozen(rep.D), Ahat=_frozen(Ahat),
        alpha=_frozen(alpha), O_blocks=_frozen(O), A_window=_frozen(np.linalg.matrix_power(A, n - 1)),
        s=int(s), gains=gains, detectability=rep, decoder=SecureDecoder(O, rep.D, s=s), rtol=float(rtol),
    )


def check_report(design: MaoTabuadaDesign, *, x0_norm: float | None = None) -> dict:
    """What ``rse check`` reports for this algorithm (plain JSON-able values)."""
    d, g = design.detectability, design.gains
    out: dict[str, Any] = {
        "p": design.p,
        "n": design.n,
        "s": design.s,
        "v": design.v,
        "sparse_detectability": {
            "k": 2 * design.s, "wrt": "D", "holds": d.holds, "margin": d.margin,
            "worst_support": list(d.worst_support), "cond_D": d.cond_D, "supports_checked": d.supports_checked,
        },
        "consensus": {
            "k_phi": g.k_phi, "k_I": g.k_I, "k_P": g.k_P, "spectral_radius": g.spectral_radius,
            "lambda_2": g.lambda_2, "lambda_max": g.lambda_max,
        },
        "decoder": {"kind": "exhaustive support search", "supports": design.decoder.n_supports},
        "numerics": {"strategy": "limit", "signal_limit": SIGNAL_LIMIT},
    }
    if x0_norm is not None:
        out["numerics"]["safe_horizon"] = safe_horizon(design.A, x0_norm=x0_norm)
    return out


class MaoTabuadaEstimator(Batchable, Flags):
    """Per-node estimator (interface of :mod:`estimation.base`).

    Parameters
    ----------
    design : MaoTabuadaDesign
    node : int, keyword-only
        0-based node id; the node reads sensor ``node``.
    decoder : {"secure", "least_squares"}
        The resilient decoder or the plain least-squares baseline.

    The outgoing payload of round ``k`` is ``(J_i[k].ravel(), eta_i[k].ravel())``,
    shape ``(2 v n,)``.
    """

    signal_limit = SIGNAL_LIMIT  #: what an estimate may reach (see the module docstring)

    def __init__(self, design: MaoTabuadaDesign, *, node: int, decoder: str = "secure") -> None:
        if not 0 <= int(node) < design.p:
            raise DesignError(f"node must be in 0..{design.p - 1}, got {node}")
        if decoder not in ("secure", "least_squares"):
            raise DesignError(f"decoder must be 'secure' or 'least_squares', got {decoder!r}")
        self.design, self.node, self.decoder = design, int(node), decoder
        row = design.Adj[self.node]
        self._window = MeasurementWindow(design.alpha, rtol=design.rtol)
        self._cons = ConsensusNode(
            node=self.node, weights={int(j): float(row[j]) for j in np.flatnonzero(row)},
            Ahat=design.Ahat, gains=design.gains, shape=(design.v, design.n),
        )
        self._x = np.zeros(design.n)
        self._k: int | None = None
        self.support: tuple[int, ...] = ()

    @property
    def estimate(self) -> np.ndarray:
        return self._x.copy()

    @property
    def flagged(self) -> bool:
        """Latched result of the local sanity check (this node's measurement is attacked)."""
        return self._window.flagged

    @property
    def flag_round(self) -> int | None:
        return self._window.flag_round

    @property
    def compressed(self) -> np.ndarray:
        """``p J_i``, this node's copy of ``(D (x) I_n) Y``; ``(v, n)``."""
        return self.design.p * self._cons.average

    def _measurement_value(self, k: int, measurement: np.ndarray | None) -> float | None:
        """The scalar reading of round ``k`` (None: none), checked against the signal limit."""
        if measurement is None:
            return None
        m = np.asarray(measurement, dtype=float).ravel()
        if m.shape != (1,):
            raise DesignError(f"node {self.node}: expected one scalar measurement, got shape {m.shape}")
        if not np.isfinite(m[0]) or abs(m[0]) > SIGNAL_LIMIT:
            raise NumericalError(
                f"node {self.node}, round {k}: measurement {m[0]:g} beyond the signal limit "
                f"{SIGNAL_LIMIT:g}; the horizon exceeds safe_horizon()"
            )
        return float(m[0])

    def batch_key(self) -> tuple:
        return (MaoTabuadaEstimator, id(self.design), self.decoder)

    @classmethod
    def batch(cls, members, **kw) -> Batch:
        """Every node's consensus and decoder stacked (:class:`estimation.mao_batch.MaoBatch`)."""
        from .mao_batch import MaoBatch

        return MaoBatch(members, **kw)

    def step(self, k: int, measurement: np.ndarray | None, inbox: Inbox) -> np.ndarray:
        y = self._measurement_value(k, measurement)
        if self._k is not None and k <= self._k:
            raise DesignError(f"node {self.node}: rounds must increase, got {k} after {self._k}")
        if self._k is not None:
            for missed in range(self._k + 1, k):  # no call in those rounds: predict
                self._window.push(missed, None)
                self._cons.step(missed, self._phi())
        self._window.push(k, y)
        for msg in inbox.values():
            self._cons.receive(int(msg.sender), int(msg.stamp), msg.value)
        payload = self._cons.step(k, self._phi())
        Z = self.compressed
        if self.decoder == "secure":
            res = self.design.decoder.decode(Z)
        else:
            res = least_squares_decode(Z, self.design.O_blocks, self.design.D)
        x = self.design.A_window @ res.x
        if not np.all(np.isfinite(x)) or np.max(np.abs(x), initial=0.0) > SIGNAL_LIMIT:
            raise NumericalError(f"node {self.node}, round {k}: estimate beyond the signal limit {SIGNAL_LIMIT:g}")
        self._x, self.support, self._k = x, res.support, k
        return payload

    def _phi(self) -> np.ndarray:
        if not self._window.full:
            return np.zeros((self.design.v, self.design.n))
        return np.outer(self.design.D[:, self.node], self._window.values)


@dataclass(frozen=True)
class MaoTabuadaExample:
    """Plain matrices of the example scenario (0-based node ids).

    Attributes
    ----------
    A : (4, 4), C : (8, 4), Adj : (8, 8)
    edges : tuple of (int, int)
        Undirected edges of the graph.
    s : int
        Attack budget.
    attacked : tuple of int
        The attacked nodes.
    x0, x0_attack : (4,) arrays
        True initial state, and the initial state whose outputs the attacked sensors
        report (a dynamics-consistent attack: it passes the sanity check).
    bias_node, bias_round, bias_value
        A bias added from ``bias_round`` on at ``bias_node`` (fails the sanity check).
    rounds : int
        Horizon (well inside :func:`safe_horizon`).
    D : (5, 8) array
        Compression matrix, ``v = 2s + 1 = 5 < p``.
    """

    A: np.ndarray
    C: np.ndarray
    Adj: np.ndarray
    edges: tuple[tuple[int, int], ...]
    s: int
    attacked: tuple[int, ...]
    x0: np.ndarray
    x0_attack: np.ndarray
    bias_node: int
    bias_round: int
    bias_value: float
    rounds: int
    D: np.ndarray


def example() -> MaoTabuadaExample:
    """The example for ``scenarios/mao_tabuada.toml`` (the paper has none). Choices:

    * plant ``n = 4``: a rotation-scaled pair ``1.02 +- 0.1j`` (modulus 1.0249), a real
      mode 1.04 and an alternating mode -1.03, coupled in a chain -- every eigenvalue has
      modulus > 1 (discrete counterpart of Assumption 6), distinct, so ``A`` is cyclic.
      Growth ``~1.04^k``: ``|x|`` is ~6e6 at round 400, the signal limit is reached after
      ~8800 rounds (:func:`safe_horizon`).
    * ``p = 8`` scalar sensors, rows of ``C`` with one decimal, picked so that any 4 of
      them observe the plant (``2s``-sparse detectable, ``s = 2``, normalised PBH margin 0.13).
    * graph: the circulant ``C_8(1, 2)`` (node ``i`` talks to ``i +- 1, i +- 2``), connected,
      undirected, ``lambda_2 = 2.59``, ``lambda_max = 6``.
    * attacked nodes 2 and 5 report the outputs of ``x0_attack``; a bias of 1.0 is switched
      on at node 5 in round 150.
    * ``D`` (``v = 2s + 1 = 5 < p``, the fewest rows possible) is the output of
      ``design_compression(A, C, s=2)`` (seed 0, orthonormal rows, ``cond(D) = 1``) rounded
      to 4 decimals, written out so that the scenario does not depend on a random
      generator; it is ``4``-sparse detectable w.r.t. ``D`` with margin 3.8e-3 (the
      identity has 0.13: compressing to 5 rows costs conditioning).
    """
    A = np.array([[1.02, 0.10, 0.0, 0.0], [-0.10, 1.02, 0.05, 0.0], [0.0, 0.0, 1.04, 0.10], [0.0, 0.0, 0.0, -1.03]])
    C = np.array(
        [
            [0.3, -0.9, 0.3, 0.4],
            [-0.9, 0.6, 0.0, 0.0],
            [-0.4, -0.9, -0.6, -0.6],
            [0.6, 0.2, 0.9, -0.6],
            [0.6, 0.4, -0.1, 0.4],
            [-0.7, 0.5, -0.5, 0.1],
            [0.3, -0.6, 0.9, -0.8],
            [0.8, 0.9, 0.6, -0.1],
        ]
    )
    p = 8
    edges = tuple(sorted({(min(i, (i + d) % p), max(i, (i + d) % p)) for i in range(p) for d in (1, 2)}))
    Adj = np.zeros((p, p))
    for i, j in edges:
        Adj[i, j] = Adj[j, i] = 1.0
    return MaoTabuadaExample(
        A=_frozen(A), C=_frozen(C), Adj=_frozen(Adj), edges=edges, s=2, attacked=(2, 5),
        x0=_frozen([1.0, -0.5, 0.8, 0.3]), x0_attack=_frozen([-2.0, 1.5, -1.0, 2.5]),
        bias_node=5, bias_round=150, bias_value=1.0, rounds=400,
        D=_frozen(
            [
                [-0.0675, 0.0709, -0.3438, -0.0563, 0.2876, -0.1941, -0.7001, -0.5085],
                [-0.2121, -0.4308, -0.1149, 0.0279, -0.8319, -0.0215, -0.2263, -0.1081],
                [0.2375, 0.0606, -0.1985, -0.5173, -0.1430, -0.6783, 0.3604, -0.1497],
                [0.6235, 0.1305, -0.1949, -0.4311, -0.1787, 0.4512, -0.2840, 0.2327],
                [-0.1970, 0.5347, -0.2575, 0.2115, -0.1882, -0.3285, -0.2411, 0.6024],
            ]
        ),
    )
