"""Fully distributed resilient state estimation by a distributed median solver.

Lee, Kim, Shim, IEEE TAC 2020 (``papers/lee_kim_shim_2020_distributed_median_solver.md``).

Per agent ``i`` (reading sensor bank ``y_i = C_i x + a_i``):

* partial observer, eq. (5)::

      z_i' = W_i (A V_i z_i + B u) + L_i (y_i - C_i V_i z_i)            (o_i states)

* median-solver coupling, eq. (6)::

      x_i' = A x_i + B u + kappa sum_l s_i^l sgn(w_l^T V_i z_i - w_l^T x_i) v_l
             + kappa gamma sum_{j in N_i} (x_j - x_i)

* the Lyapunov-stable variant, eq. (11), with ``P_bar = V^T P V``::

      x_i' = A x_i + B u + kappa V sqrt(P_bar)^{-1} W sum_l s_i^l sgn(wb_l^T (V_i z_i - x_i)) v_l
             + kappa gamma sum_j (x_j - x_i),     wb_l^T = row l of sqrt(P_bar) W

* a non-resilient baseline: the sgn replaced by the linear innovation
  ``kappa sum_l s_i^l (w_l^T V_i z_i - w_l^T x_i) v_l``, same coupling.

Discretisation at the round step ``dt`` (round ``k`` <-> ``t_k = k dt``): over
``[t_{k-1}, t_k)`` the input ``u(t_{k-1})``, the measurement ``y_i[k-1]``, the sgn term
evaluated at ``t_{k-1}`` and the neighbours' estimates stamped ``k-1`` are held; the
linear part (``A`` and the self-coupling ``-kappa gamma d_i I``, ``d_i`` = number of
neighbour messages used this round) is integrated exactly (matrix exponential, zero-order
hold). Plain forward Euler is unstable at ``dt = 1e-2`` for the three-inertia plant
(its 20 rad/s mode); this scheme is stable there. Rounds skipped between two calls
(a realtime agent that fell behind, or was cut off, runs only the newest measurement) are
integrated the same way, with ``y_i`` only over the first step: a skipped round carries no
measurement, so the partial observer predicts open loop over the rest of the gap rather
than hold a stale ``y_i`` there. Each step of a gap uses the neighbours' estimates stamped
within ``max_age`` rounds of that step (:func:`estimation.base.held`), never one stamped
later: an estimate of ``x`` at the end of a 3 s gap, coupled in over the whole gap, pulled
``x_i`` as far off as holding ``y_i`` did (an agent cut off for 3 s came back 0.3 to 0.6
off, against 0.05), while a gap of a few rounds without coupling drifted the attacked
agent off its bound.

Gains ``L_i`` are placed by :func:`shifted_poles`: every complex pair of
``W_i A V_i`` keeps its frequency and gets real part ``real_part``; real eigenvalues are
sent to distinct real poles ``real_part * (1, 1.25, 1.5, ...)``. (The paper's literal
"eigenvalues near -1" with distinct real poles gives gains ~1e3 and huge peaking.)
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from .base import EstimatePayload, Inbox, held
from .batching import Batch, Batchable
from .errors import DesignError
from .graphs import algebraic_connectivity
from .lti import zoh, zoh_integral
from .observability import CommonBasis, common_basis

VARIANTS = ("median", "lyapunov", "linear")
#: largest state dimension whose agents the simulator steps as one stacked batch
BATCH_MAX_N = 64


def shifted_poles(A_o: np.ndarray, *, real_part: float = -1.0) -> np.ndarray:
    """Pole targets for the partial observer: modal frequencies kept, real parts moved.

    Parameters
    ----------
    A_o : (o, o) array  ``W_i A V_i``
    real_part : float < 0
    """
    if real_part >= 0:
        raise DesignError(f"observer pole real part must be negative, got {real_part}")
    lam = np.linalg.eigvals(A_o)
    scale = max(1.0, float(np.max(np.abs(lam)))) if len(lam) else 1.0
    poles: list[complex] = []
    n_real = 0
    for l in sorted(lam, key=lambda c: (c.imag, c.real)):
        if abs(l.imag) <= 1e-9 * scale:
            poles.append(real_part * (1.0 + 0.25 * n_real))
            n_real += 1
        else:
            poles.append(complex(real_part, l.imag))
    return np.array(poles)


@dataclass(frozen=True)
class PartialObserverDesign:
    """Decomposition and gain of one agent's partial observer (eq. (5)).

    Attributes
    ----------
    C : (m_i, n) array  the agent's stacked sensor rows
    observable : (o_i,) int array  indices ``l`` with ``s_i^l = 1``
    V_i : (n, o_i) array;  W_i : (o_i, n) array
    L : (o_i, m_i) array  observer gain (for ``gains = "kalman"``: ``Ld / dt``)
    poles : (o_i,) complex array  eigenvalues of ``W_i A V_i - L C V_i`` (for ``gains =
        "kalman"``: the continuous-time equivalents ``log(eig(Phi - Ld C V_i)) / dt``)
    Ld : (o_i, m_i) array or None  the sampled gain at step ``dt`` when designed as such
        (:mod:`estimation.kalman_gain`); None: the agent places ``exp(poles dt)``
    dt : float or None  the round step ``Ld`` was designed for
    """

    C: np.ndarray
    observable: np.ndarray
    V_i: np.ndarray
    W_i: np.ndarray
    L: np.ndarray
    poles: np.ndarray
    Ld: np.ndarray | None = None
    dt: float | None = None


@dataclass(frozen=True)
class LKSDesign:
    """Offline design shared by every agent (computed once per scenario)."""

    A: np.ndarray
    B: np.ndarray
    basis: CommonBasis
    observers: tuple[PartialObserverDesign, ...]
    #: ``sqrt(P_bar)`` of eq. (11), or None when the plant is not shown Lyapunov stable
    sqrt_Pbar: np.ndarray | None = field(default=None)

    @property
    def n(self) -> int:
        return self.A.shape[0]


def lyapunov_certificate(A: np.ndarray, basis: CommonBasis) -> np.ndarray | None:
    """``sqrt(P_bar)`` for eq. (11) with ``P A + A^T P <= 0``, or None.

    With a real modal basis of a diagonalizable ``A`` whose eigenvalues have non-positive
    real parts, ``W A V`` is block diagonal with blocks ``lambda`` or
    ``[[a, b], [-b, a]]``, so ``P_bar = I`` (``P = W^T W``) certifies Lyapunov stability.
    Otherwise, for Hurwitz ``A``, ``P`` solves ``A^T P + P A = -I``.
    """
    from scipy.linalg import sqrtm

    lam = np.linalg.eigvals(A)
    scale = max(1.0, float(np.max(np.abs(lam))))
    if np.any(lam.real > 1e-9 * scale):
        return None
    if basis.method == "modal":
        Abar = basis.W @ A @ basis.V
        if np.max(np.linalg.eigvalsh(Abar + Abar.T)) <= 1e-9 * scale:
            return np.eye(A.shape[0])
    if np.all(lam.real < -1e-9 * scale):
        from scipy.linalg import solve_continuous_lyapunov

        P = solve_continuous_lyapunov(A.T, -np.eye(A.shape[0]))
        Pbar = basis.V.T @ P @ basis.V
        Pbar = 0.5 * (Pbar + Pbar.T)
        return np.real(sqrtm(Pbar))
    return None


def design(
    A: np.ndarray,
    B: np.ndarray,
    agent_C: Sequence[np.ndarray],
    *,
    real_part: float = -1.0,
    poles: Sequence[Sequence[complex]] | None = None,
    gains: str = "place",
    dt: float | None = None,
) -> LKSDesign:
    """Common basis, decompositions and observer gains for every agent.

    Parameters
    ----------
    A : (n, n) array;  B : (n, p) array
    agent_C : sequence of (m_i, n) arrays, the stacked sensor rows each agent reads
    real_part : float, the real part the observer poles are moved to
    poles : optional explicit poles per agent (each of length ``o_i``)
    gains : ``"place"`` (pole placement, :func:`shifted_poles`) or ``"kalman"`` (the sampled
        system's steady-state Kalman gain at step ``dt``, :mod:`estimation.kalman_gain`)
    """
    if gains not in ("place", "kalman"):
        raise DesignError(f"unknown observer gain design {gains!r}; expected 'place' or 'kalman'")
    A = np.asarray(A, dtype=float)
    B = np.asarray(B, dtype=float).reshape(A.shape[0], -1)
    basis = common_basis(A, agent_C)
    observers = []
    for i, C in enumerate(agent_C):
        C = np.atleast_2d(np.asarray(C, dtype=float))
        obs = np.flatnonzero(basis.S[i])
        V_i = basis.V[:, obs]
        W_i = basis.W[obs, :]
        if len(obs) == 0:
            observers.append(PartialObserverDesign(C, obs, V_i, W_i, np.zeros((0, C.shape[0])), np.zeros(0)))
            continue
        A_o = W_i @ A @ V_i
        C_o = C @ V_i
        if gains == "kalman":
            from .kalman_gain import sampled_kalman_gain

            try:
                Ld, achieved_c = sampled_kalman_gain(A_o, C_o, float(dt or 0.0))
            except DesignError as exc:
                raise DesignError(f"agent {i + 1}: {exc}") from None
            observers.append(PartialObserverDesign(C, obs, V_i, W_i, Ld / float(dt or 1.0), achieved_c, Ld=Ld, dt=dt))
            continue
        target = np.asarray(poles[i], dtype=complex) if poles is not None else shifted_poles(A_o, real_part=real_part)
        if len(target) != len(obs):
            raise DesignError(f"agent {i + 1}: {len(target)} observer poles given, the observable part has {len(obs)} states")
        try:
            res = _place_poles(A_o.T, C_o.T, target)
        except ValueError as exc:
            raise DesignError(f"agent {i + 1}: observer pole placement failed: {exc}") from exc
        L = np.real(res.gain_matrix.T)
        achieved = np.linalg.eigvals(A_o - L @ C_o)
        observers.append(PartialObserverDesign(C, obs, V_i, W_i, L, achieved))
    return LKSDesign(A=A, B=B, basis=basis, observers=tuple(observers), sqrt_Pbar=lyapunov_certificate(A, basis))


def _place_poles(A: np.ndarray, B: np.ndarray, poles: np.ndarray):
    # scipy.signal's place_poles, without importing scipy.signal for a single output
    # (about 0.45 s of start-up; see estimation.placement)
    from .placement import place_poles

    return place_poles(A, B, poles)


def discrete_gain(Phi: np.ndarray, C: np.ndarray, poles: np.ndarray, *, agent: int = 0) -> np.ndarray:
    """Gain ``L_d`` with ``eig(Phi - L_d C) = poles`` (discrete-time observer placement)."""
    try:
        res = _place_poles(Phi.T, C.T, poles)
    except ValueError as exc:
        raise DesignError(f"agent {agent + 1}: discrete observer pole placement failed: {exc}") from exc
    return np.real(res.gain_matrix.T)


def theorem3_bound(des: LKSDesign, Adj: np.ndarray, gamma: float) -> float | None:
    """Steady-state bound of Theorem 3 (Lyapunov-stable plants), or None if not applicable."""
    if des.sqrt_Pbar is None:
        return None
    N, n = Adj.shape[0], des.n
    lam2 = algebraic_connectivity(Adj)
    if lam2 <= 0:
        return None
    M = des.basis.V @ np.linalg.inv(des.sqrt_Pbar)
    return float((N * n**2 + np.sqrt(n)) * np.sqrt(N) / (gamma * lam2) * np.linalg.norm(M, 2))


class LeeKimShim(Batchable, EstimatePayload):
    """One agent's estimator: partial observer (5) + median coupling (6) / (11) / linear.

    Parameters
    ----------
    des : LKSDesign
    agent : int, 0-based index into ``des.observers``
    kappa, gamma : float > 0, the gains of eq. (6)
    dt : float > 0, the round step
    variant : {"median", "lyapunov", "linear"}
    input_fn : callable ``t -> (p,) array``, the known input
    x0 : (n,) array, initial estimate;  z0 : (o_i,) array, initial partial estimate (0)
    max_age : int, neighbour messages stamped older than ``k - 1 - max_age`` are ignored
        in round ``k`` (a silent neighbour drops out of the coupling, which is what lets
        agents leave and join, Section III-C)
    max_degree : int, the largest number of neighbours whose messages can be used
    """

    def __init__(
        self,
        des: LKSDesign,
        *,
        agent: int,
        kappa: float,
        gamma: float,
        dt: float,
        variant: str = "median",
        input_fn: Callable[[float], np.ndarray],
        x0: np.ndarray,
        z0: np.ndarray | None = None,
        max_age: int = 3,
        max_degree: int,
        sign: str = "implicit",
    ) -> None:
        if variant not in VARIANTS:
            raise DesignError(f"unknown variant {variant!r}; expected one of {', '.join(VARIANTS)}")
        if kappa <= 0 or gamma <= 0 or dt <= 0:
            raise DesignError(f"kappa, gamma and dt must be > 0, got {kappa}, {gamma}, {dt}")
        ob = des.observers[agent]
        n, o = des.n, len(ob.observable)
        self.n, self.dt, self.max_age = n, dt, max_age
        self._u = input_fn
        self._xh = np.array(x0, dtype=float).reshape(n)
        self._z = np.zeros(o) if z0 is None else np.array(z0, dtype=float).reshape(o)
        self._y: np.ndarray | None = None
        self._k: int | None = None
        A, B = des.A, des.B
        # correction term G phi(E z - F x), eqs. (6), (11), linear baseline
        if variant == "lyapunov":
            if des.sqrt_Pbar is None:
                raise DesignError("variant 'lyapunov' (eq. 11) needs a Lyapunov-stable plant")
            Wb = des.sqrt_Pbar @ des.basis.W
            Wb_i = Wb[ob.observable]
            G = des.basis.V @ np.linalg.inv(des.sqrt_Pbar) @ des.basis.W @ ob.V_i
            self._E, self._F = Wb_i @ ob.V_i, Wb_i
        else:
            G = ob.V_i
            self._E, self._F = None, ob.W_i
        self._linear = variant == "linear"
        if sign not in ("implicit", "held"):
            raise DesignError(f"unknown sign discretisation {sign!r}; expected 'implicit' or 'held'")
        self._implicit = sign == "implicit"
        # eq. (6) per neighbour count d (see "Discretisation" in the module docstring)
        kg = kappa * gamma
        self._Ad, Bd = zoh(A, B, dt)
        self._Bd = Bd
        self._Gs, self._alpha, self._stay = [], [], []
        for d in range(max_degree + 1):
            c = kg * d
            _, Gam = zoh_integral(A - c * np.eye(n), dt)
            self._Gs.append(kappa * Gam @ G)
            alpha = (1.0 - np.exp(-c * dt)) / d if d else 0.0
            self._alpha.append(alpha)
            self._stay.append(np.exp(-c * dt))
        # implicit sgn: how far one step of the sgn term moves each sliding variable
        self._band = [np.maximum(np.abs(np.diag(self._F @ Gs)), 1e-300) if len(self._F) else np.ones(0) for Gs in self._Gs]
        # eq. (5), exactly discretised: the sampled observable part is
        # z+ = Phi_o z + W_i Bd u + L_d (y - C V_i z) with Phi_o = expm(W_i A V_i dt) and
        # L_d placing the eigenvalues of Phi_o - L_d C V_i at exp(p dt) for the
        # continuous design's poles p, so the error dynamics match (5)'s at the samples.
        p = B.shape[1]
        m = ob.C.shape[0]
        if o:
            A_o = ob.W_i @ A @ ob.V_i
            C_o = ob.C @ ob.V_i
            Phi_o, _ = zoh_integral(A_o, dt)
            Gou = ob.W_i @ Bd
            if ob.Ld is None:
                Ld = discrete_gain(Phi_o, C_o, np.exp(ob.poles * dt), agent=agent)
            elif ob.dt != dt:
                raise DesignError(f"agent {agent + 1}: the observer gain was designed for dt = {ob.dt}, the agent steps {dt}")
            else:
                Ld = ob.Ld
            Phi_z = Phi_o - Ld @ C_o
        else:
            Phi_o = Phi_z = np.zeros((0, 0))
            Gou, Ld = np.zeros((0, p)), np.zeros((0, m))
        self._o = o
        # One matrix per neighbour count d, acting on v = [x; z; sum_j x_j; u; y]:
        #   [x+; z+]_free = M_d v      (free motion: model, consensus, partial observer)
        # and, without a measurement, on v = [x; z; sum_j x_j; u] (observer runs open loop).
        self._M, self._M_open = [], []
        for d in range(max_degree + 1):
            M = np.zeros((n + o, 2 * n + o + p + m))
            M[:n, :n] = self._stay[d] * self._Ad
            M[:n, n + o : 2 * n + o] = self._alpha[d] * self._Ad
            M[:n, 2 * n + o : 2 * n + o + p] = Bd
            M[n:, n : n + o] = Phi_z
            M[n:, 2 * n + o : 2 * n + o + p] = Gou
            M[n:, 2 * n + o + p :] = Ld
            Mo = M[:, : 2 * n + o + p].copy()
            Mo[n:, n : n + o] = Phi_o
            self._M.append(M)
            self._M_open.append(Mo)
        # the sliding variables inner = E z - F x as one matrix on [x; z]
        E = np.eye(o) if self._E is None else self._E
        self._H = np.hstack([-self._F, E]) if o else np.zeros((0, n))
        self._inv_band = [1.0 / b for b in self._band]
        self._s = np.concatenate([self._xh, self._z])
        self._zero_n = np.zeros(n)
        del self._xh, self._z

    @property
    def estimate(self) -> np.ndarray:
        """Current ``x_hat_i`` (copy), shape ``(n,)``."""
        return self._s[: self.n].copy()

    def batch_key(self) -> tuple | None:
        """None above :data:`BATCH_MAX_N` states: the stacked product is block diagonal, so it
        costs as many times the per-agent products as there are members (case118's 108 states,
        six agents: slower than stepping each), and the per-agent step is the definition
        itself (``rse run`` equals ``rse simulate`` bit for bit)."""
        if self.n > BATCH_MAX_N:
            return None
        return (LeeKimShim, self.n, self.dt, self.max_age, self._linear, self._implicit, id(self._u))

    @classmethod
    def batch(cls, members, **kw) -> Batch:
        """Every member in one stacked step (:class:`estimation.lks_batch.LKSBatch`)."""
        from .lks_batch import LKSBatch

        return LKSBatch(members, **kw)

    @property
    def partial_estimate(self) -> np.ndarray:
        """Current ``z_i`` (copy), shape ``(o_i,)``."""
        return self._s[self.n :].copy()

    def step(self, k: int, measurement: np.ndarray | None, inbox: Inbox) -> np.ndarray:
        """Advance to round ``k`` and return ``x_hat_i[k]`` (see the module docstring).

        The returned array is read-only and never modified afterwards.
        """
        if self._k is not None:
            for kk in range(self._k, k):
                self._advance(kk, held(inbox, kk, self.max_age))
                self._y = None  # a skipped round carries no measurement: the rest of a gap predicts
        self._k = k
        self._y = None if measurement is None else np.asarray(measurement, dtype=float)
        out = self._s[: self.n]
        return out

    def _advance(self, kk: int, nb: list[np.ndarray]) -> None:
        u = self._u(kk * self.dt)
        d = len(nb)
        if d == 0:
            total = self._zero_n
        else:
            total = nb[0]
            for v in nb[1:]:
                total = total + v
        s = self._s
        if self._y is not None:
            sn = self._M[d] @ np.concatenate((s, total, u, self._y))
        else:
            sn = self._M_open[d] @ np.concatenate((s, total, u))
        if self._o:
            if self._linear:
                phi = self._H @ s
            elif self._implicit:  # sgn evaluated implicitly at the end of the step
                phi = self._H @ sn
                phi *= self._inv_band[d]
                np.clip(phi, -1.0, 1.0, out=phi)
            else:
                phi = np.sign(self._H @ s)
            sn[: self.n] += self._Gs[d] @ phi
        sn.flags.writeable = False
        self._s = sn
