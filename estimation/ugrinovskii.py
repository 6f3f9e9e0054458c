"""Ugrinovskii's controlled distributed H-infinity observer, resilient to biasing attacks.

Ugrinovskii, "Distributed H-infinity estimation resilient to biasing attacks". Node ``i``
runs (paper's equation numbers)::

    x_hat'   = A x_hat + L (y - C x_hat) + sum_j K_j (c_j - W_j x_hat) - F u + F f     (8)
    e_hat'   = (A - L C - sum K_j W_j) e_hat + sum_j K_j eta_j + Lbar zeta
               + sum_j Kbar_j (zeta_j - W_j e_hat + eta_j) + Fbar (f_c - u)          (17)
    eps_hat' = Omega eps_hat + Lcheck zeta + sum_j Kcheck_j (zeta_j - W_j e_hat + eta_j)
               + Gammabar (f_c - u)                                                   (17)
    u = Ups eps_hat                                                                   (19)

with ``zeta = y - C x_hat``, ``zeta_j = c_j - W_j x_hat`` (10), ``c_j = W_j x_hat_j`` (3) and
``eta_j = W_j e_hat_j`` (18) built by the receiver from the neighbour's payload
``[x_hat_j; e_hat_j]``, and ``[Fbar; Gammabar] = F_c,i``. Gains: ``L``, ``K_j`` from the
observer Riccati equation (41) via (42); ``[L_hat; Lcheck]``, ``[K_hat_j; Kcheck_j]`` from the
detector Riccati equation (35) via (36); ``Lbar = L_hat - L``, ``Kbar_j = K_hat_j - K_j``
(44). ``u`` is the attack indicator. :class:`UgrinovskiiBaseline` is (8) without the
controller (``u = 0``), with the same ``L``, ``K_j``.

Discretisation at the round step ``dt`` (round ``k`` is ``t_k = k dt``; ``step(k, ...)``
advances from ``t_{k-1}`` to ``t_k``):

* Riccati equations: exact flow map, :class:`estimation.hinf_riccati.RiccatiFlow`.
* Node dynamics (stiff: eigenvalues of the local 14 x 14 matrix down to about ``-2400``
  at ``t = 0`` for the example's 5 %-backed-off design, far lower at the unbacked
  optimum; an explicit scheme would need ``dt < 1e-3``): exponential
  integrator with zero-order hold. Over ``[t_{k-1}, t_k)`` the gains are frozen at their
  value at ``t_{k-1}``, and the inputs -- measurement ``y_i[k]``, the newest neighbour
  payloads (stamped ``k - 1`` when fresh), attack ``f(t_{k-1})`` -- are held; the linear
  local dynamics are then integrated exactly by one matrix exponential of
  ``[[M, G], [0, 0]] dt`` (Van Loan), which is stable at any ``dt``. The exponential is
  recomputed only when a Riccati solution has moved by more than ``gain_rtol`` (relative,
  Frobenius) since the last recomputation (default ``1e-3``), so the gains used lag the
  exact ones by at most that relative amount. Neighbour coupling is explicit (one round
  old), so the scheme is first order in ``dt``: for the example, ``dt = 5e-3`` against
  ``dt = 1.25e-3`` changes the peak attack-induced error by < 2 % and ``u`` by < 1e-3 of
  the attack amplitude (tests/estimation/test_ugrinovskii_observer.py).
* Missing data: no measurement (``None``) replaces ``y`` by the prediction ``C x_hat``
  (zero innovation at the start of the step); a neighbour absent from the inbox keeps its
  newest earlier payload; one never heard from contributes zero innovation
  (``c_j = W_j x_hat``, ``eta_j = W_j e_hat``). A payload of the wrong shape or with
  non-finite values is ignored and counted in ``rejected``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np

from .base import Inbox, Received
from .batching import Batch, Batchable
from .errors import DesignError, NumericalError
from .hinf_lmi import ResilientProblem, node_riccati_data
from .hinf_riccati import RiccatiFlow
from .ugrinovskii_system import Template, system, template

__all__ = ["first_order_attack_model", "UgrinovskiiNode", "UgrinovskiiBaseline", "run_network"]

Attack = Callable[[float], "np.ndarray | float"]


def first_order_attack_model(*, gain: float, pole: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Minimal realisation (13) of ``-G(s)/s`` for ``G(s) = gain / (s + pole)`` (scalar).

    ``Omega = [[0, 1], [0, -pole]]``, ``Gamma = [0; gain]``, ``Ups = [-1, 0]``: then
    ``Ups (sI - Omega)^-1 Gamma = -gain / (s (s + pole))``. The gain sits in ``Gamma``, not in
    ``Ups``: with ``Ups = [-gain, 0]`` the LMI solver returns an inaccurate optimum for the
    example (``gain = 410``) because ``Rcheck > Ups' Ups`` is then badly scaled.
    Lemma 1 needs ``(s + G)^-1 G = gain / (s^2 + pole s + gain)`` stable: ``gain, pole > 0``.

    Returns
    -------
    Omega (2, 2), Gamma (2, 1), Upsilon (1, 2) arrays.
    """
    if not (gain > 0 and pole > 0):
        raise DesignError(f"G(s) = gain/(s + pole) needs gain > 0 and pole > 0 (Lemma 1), got {gain}, {pole}")
    return (
        np.array([[0.0, 1.0], [0.0, -float(pole)]]),
        np.array([[0.0], [float(gain)]]),
        np.array([[-1.0, 0.0]]),
    )


class _NodeBase(Batchable):
    """Shared state and round logic of the controlled node and the baseline.

    Batchable: the nodes of a team step together in :class:`estimation.ugrinovskii_batch.UgrinovskiiBatch`."""

    _controlled = True

    def __init__(
        self,
        problem: ResilientProblem,
        design: Mapping[str, np.ndarray],
        *,
        node: int,
        dt: float,
        xi0: np.ndarray | None = None,
        observer_attack: Attack | None = None,
        detector_attack: Attack | None = None,
        gain_rtol: float = 1e-3,
    ) -> None:
        if not 0 <= node < problem.N:
            raise DesignError(f"node must be in 0..{problem.N - 1}, got {node}")
        if not dt > 0:
            raise DesignError(f"dt must be > 0, got {dt}")
        if not gain_rtol >= 0:
            raise DesignError(f"gain_rtol must be >= 0, got {gain_rtol}")
        i, n = node, problem.n
        self.node, self.dt, self.gain_rtol = i, float(dt), float(gain_rtol)
        self._pb = problem
        self._nb = problem.neighbours[i]
        self._ne = problem.ne(i) if self._controlled else 0
        self._nf = problem.F[i].shape[1]
        self._p = problem.C[i].shape[0]
        self._pj = [problem.W[(i, j)].shape[0] for j in self._nb]
        self._Ub = [np.asarray(design[f"Ubar_{i}_{j}"], float) for j in self._nb]
        self._U = [np.asarray(design[f"U_{i}_{j}"], float) for j in self._nb]
        gb = float(design["gamma2_bar"])
        A_, B1, Sb = node_riccati_data(problem, "obs", {(i, j): u for j, u in zip(self._nb, self._Ub)}, i)
        Qb = np.asarray(design[f"Qbar_{i}"], float)
        self._obs = RiccatiFlow(A=A_, B=B1, S=Sb, R=np.asarray(design[f"Rbar_{i}"], float), gamma2=gb,
                                Y0=gb * np.linalg.inv(Qb), dt=dt, name=f"observer Riccati (41) of node {i}")
        if self._controlled:
            g = float(design["gamma2"])
            Ab, Bb, S = node_riccati_data(problem, "det", {(i, j): u for j, u in zip(self._nb, self._U)}, i)
            Q = np.asarray(design[f"Q_{i}"], float)
            self._det = RiccatiFlow(A=Ab, B=Bb, S=S, R=np.asarray(design[f"R_{i}"], float), gamma2=g,
                                    Y0=g * np.linalg.inv(Q), dt=dt, name=f"detector Riccati (35) of node {i}")
        x0 = np.zeros(n) if xi0 is None else np.asarray(xi0, dtype=float).reshape(-1)
        if x0.shape != (n,) or not np.all(np.isfinite(x0)):
            raise DesignError(f"xi0 must be a finite vector of length {n}")
        self._s = np.concatenate([x0, np.zeros(self._state_dim - n)])
        self._fa, self._fd = observer_attack, detector_attack
        self._last: dict[int, np.ndarray] = {}
        self._k: int | None = None
        self._disc: tuple[np.ndarray, np.ndarray] | None = None
        self._tpl: Template | None = None  # the constant part of (M, G), built at the first refresh
        self._ref: tuple = ()
        self.rejected = 0
        self.refreshes = 0

    def batch_key(self) -> tuple:
        return (type(self), id(self._pb), self.dt, self._controlled)

    @classmethod
    def batch(cls, members, **kw) -> Batch:
        from .ugrinovskii_batch import UgrinovskiiBatch

        return UgrinovskiiBatch(members, **kw)

    # -- sizes and read-only views ------------------------------------------------------
    @property
    def _state_dim(self) -> int:
        n = self._pb.n
        return 2 * n + self._ne if self._controlled else n

    @property
    def _payload_dim(self) -> int:
        return 2 * self._pb.n if self._controlled else self._pb.n

    @property
    def estimate(self) -> np.ndarray:
        """``x_hat_i``, (n,) copy."""
        return self._s[: self._pb.n].copy()

    @property
    def t(self) -> float:
        return 0.0 if self._k is None else self._k * self.dt

    @property
    def Ybar(self) -> np.ndarray:
        """Observer Riccati solution (41), (n, n) copy."""
        return self._obs.Y

    # -- the local linear system s' = M s + G v ---------------------------------------
    def _input_dim(self) -> int:
        return self._p + 2 * sum(self._pj) + 2 * self._nf

    def _system(self) -> tuple[np.ndarray, np.ndarray]:
        """``(M, G)`` at the current Riccati solutions: the gains (42), (36), (31), (44) in
        (8), (17) (:func:`estimation.ugrinovskii_system.system`)."""
        if self._tpl is None:
            self._tpl = template(self)
        return system(self._tpl, self._obs.Y, self._det.Y if self._controlled else None)

    def _flows(self) -> tuple[RiccatiFlow, ...]:
        return (self._obs, self._det) if self._controlled else (self._obs,)

    def _stale(self) -> bool:
        """Whether the discretisation must be recomputed (none yet, or a Riccati solution
        moved by more than ``gain_rtol`` since the last one)."""
        return self._disc is None or any(
            np.linalg.norm(fl.deviation - D0) > tol for fl, (D0, tol) in zip(self._flows(), self._ref)
        )

    def _discretisation(self, stale: bool | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(Phi, Gd)`` of the step; ``stale``: :meth:`_stale` when already known (a batch
        tests every node's flows at once)."""
        if stale is None:
            stale = self._stale()
        if stale or self._disc is None:
            self._refresh(*self._system())
        assert self._disc is not None
        return self._disc

    def _refresh(self, M: np.ndarray, G: np.ndarray) -> None:
        """The discretisation of ``s' = M s + G v`` over ``dt`` (the current Riccati
        solutions' ``(M, G)``) and the solutions it was computed at."""
        from scipy.linalg import expm  # not at import (see hinf_riccati)

        bal, sc = self._balanced(M, G)
        self._refreshed(expm(bal), sc)

    def _balanced(self, M: np.ndarray, G: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``T^-1 [[M, G], [0, 0]] dt T`` and the diagonal of ``T``: exact diagonal (powers of
        2) balancing, ``expm(aug) = T expm(T^-1 aug T) T^-1``, by LAPACK's gebal without
        permutation (what ``scipy.linalg.matrix_balance(permute=False)`` calls)."""
        from scipy.linalg.lapack import dgebal  # not at import (see hinf_riccati)

        d, m = M.shape[0], G.shape[1]
        aug = np.zeros((d + m, d + m))
        aug[:d, :d], aug[:d, d:] = M * self.dt, G * self.dt
        if not np.isfinite(aug).all():
            raise NumericalError(f"node {self.node}: the gains are not finite")
        bal, _, _, sc, info = dgebal(aug, scale=1, permute=0, overwrite_a=1)
        if info != 0:
            raise NumericalError(f"node {self.node}: balancing failed (gebal info {info})")
        return bal, sc

    def _refreshed(self, expbal: np.ndarray, sc: np.ndarray) -> None:
        """Keep ``(Phi, Gd)`` from ``expm`` of :meth:`_balanced`'s matrix and the solutions now."""
        d = self._state_dim
        E = sc[:, None] * expbal / sc[None, :]
        self._disc = (E[:d, :d].copy(), E[:d, d:].copy())
        self._ref = tuple((fl.deviation.copy(), self.gain_rtol * np.linalg.norm(fl.Y)) for fl in self._flows())
        self.refreshes += 1

    # -- one round ------------------------------------------------------------------------
    def _inputs(self, measurement: np.ndarray | None, inbox: Inbox) -> np.ndarray:
        pb, i, n = self._pb, self.node, self._pb.n
        xh = self._s[:n]
        eh = self._s[n: 2 * n] if self._controlled else np.zeros(n)
        if measurement is None:
            y = pb.C[i] @ xh
        else:
            y = np.asarray(measurement, dtype=float).reshape(-1)
            if y.shape != (self._p,):
                raise DesignError(f"node {i}: measurement must have length {self._p}, got {y.shape}")
        for j, msg in inbox.items():
            if j not in self._nb:
                continue
            v = np.asarray(msg.value, dtype=float).reshape(-1)
            if v.shape != (self._payload_dim,) or not np.all(np.isfinite(v)):
                self.rejected += 1
                continue
            self._last[j] = v
        c, eta = [], []
        for j in self._nb:
            W = pb.W[(i, j)]
            heard = self._last.get(j)
            xj = xh if heard is None else heard[:n]
            ej = eh if (heard is None or not self._controlled) else heard[n:]
            c.append(W @ xj)
            eta.append(W @ ej)
        t0 = self.t
        f = np.zeros(self._nf) if self._fa is None else np.asarray(self._fa(t0), float).reshape(self._nf)
        fc = np.zeros(self._nf) if self._fd is None else np.asarray(self._fd(t0), float).reshape(self._nf)
        return np.concatenate([y, *c, *eta, f, fc])

    def _payload(self) -> np.ndarray:
        return self._s[: self._payload_dim].copy()

    def step(self, k: int, measurement: np.ndarray | None, inbox: Inbox) -> np.ndarray:
        """Advance to round ``k`` and return the payload stamped ``k``.

        Round 0 (the first call) sets up and returns the initial payload without moving.
        The payload is ``[x_hat_i; e_hat_i]`` ((2n,)) for the controlled node, ``x_hat_i``
        ((n,)) for the baseline.

        Raises
        ------
        DesignError
            ``k`` does not increase, or the measurement has the wrong length.
        NumericalError
            A Riccati solution stopped being positive definite or bounded.
        """
        k = int(k)
        if self._k is None:
            self._k = k
            self._inputs(measurement, inbox)  # record first messages
            self._after_step()
            return self._payload()
        if k <= self._k:
            raise DesignError(f"node {self.node}: round {k} after round {self._k}; rounds must increase")
        v = self._inputs(measurement, inbox)
        while self._k < k:  # a skipped round holds the inputs
            Phi, Gd = self._discretisation()
            self._s = Phi @ self._s + Gd @ v
            self._obs.step()
            if self._controlled:
                self._det.step()
            self._k += 1
        self._after_step()
        return self._payload()

    def _after_step(self) -> None:
        """Called at the end of every :meth:`step` (the runtime updates its attack flag)."""

    # -- what a batch (estimation.ugrinovskii_batch) may do for all members at once ------------
    def _plain_inputs(self) -> bool:
        """Whether :meth:`_inputs` is this module's (a batch may then build every member's
        inputs from the stacked states; a runtime that adds to them says False)."""
        return True

    @classmethod
    def _after_steps(cls, members: "list[_NodeBase]", indicators: np.ndarray) -> None:
        """:meth:`_after_step` of every member of a batch after a stacked step;
        ``indicators``: their :attr:`attack_indicator` ``u`` (19) as rows ``(M, nf)``."""
        for m in members:
            m._after_step()

    @classmethod
    def _diagnostic_rows(cls, members: "list[_NodeBase]",
                         indicators: np.ndarray | None) -> tuple[dict[str, np.ndarray], np.ndarray | None] | None:
        """Every member's diagnostics and attack flag as rows from their indicators
        ``(M, nf)`` (a runtime's; None: not offered; ``indicators`` None: only whether)."""
        return None


class UgrinovskiiNode(_NodeBase):
    """Controlled observer (8) with the attack detector / compensator (17)-(19) at one node.

    Parameters
    ----------
    problem : ResilientProblem
    design : dict of arrays
        From :func:`estimation.hinf_lmi.design` (or its cached copy).
    node : int, keyword-only
        0-based node index.
    dt : float, keyword-only
        Round step in seconds.
    xi0 : (n,) array, keyword-only
        Initial estimate ``xi_i`` (default 0); ``e_hat(0) = 0``, ``eps_hat(0) = 0`` (17).
    observer_attack, detector_attack : callable ``t -> (nf,)``, keyword-only
        Biasing input ``f_i(t)`` injected as ``F_i f`` into (8) and as ``F_c,i f`` into (17)
        (the attacker's side; ``None`` = not attacked).
    gain_rtol : float, keyword-only
        See the module docstring.

    Attributes
    ----------
    estimate : (n,) array        ``x_hat_i``
    attack_indicator : (nf,)     ``u_i`` of (19)
    Y, Ybar                       Riccati solutions (35), (41)
    """

    _controlled = True

    @property
    def attack_indicator(self) -> np.ndarray:
        """``u_i = Ups_i eps_hat_i`` (19), (nf,) copy."""
        n = self._pb.n
        return self._pb.Upsilon[self.node] @ self._s[2 * n:]

    @property
    def Y(self) -> np.ndarray:
        """Detector Riccati solution (35), (n + ne, n + ne) copy."""
        return self._det.Y


class UgrinovskiiBaseline(_NodeBase):
    """The same distributed observer (8) without the controller (``u = 0``): Fig. 1(a).

    Same parameters as :class:`UgrinovskiiNode` (``detector_attack`` has no target and is
    ignored); gains ``L``, ``K_j`` from (41)-(42) of the same design. Payload ``x_hat_i``.
    """

    _controlled = False

    @property
    def attack_indicator(self) -> np.ndarray:
        return np.zeros(self._nf)


def run_network(
    problem: ResilientProblem,
    design: Mapping[str, np.ndarray],
    *,
    dt: float,
    t_end: float,
    x0: np.ndarray | None = None,
    observer_attacks: Mapping[int, Attack] | None = None,
    detector_attacks: Mapping[int, Attack] | None = None,
    controlled: bool = True,
    gain_rtol: float = 1e-3,
) -> dict[str, np.ndarray]:
    """Reference loop: all nodes in one process, lockstep rounds, ideal channels, no noise.

    The plant ``x' = A x`` (``w = 0``, the paper's Section IV run) is advanced exactly
    (``expm(A dt)``); ``y_i[k] = C_i x[k]``; in round ``k`` every node receives its
    in-neighbours' payloads of round ``k - 1`` and publishes its own.

    Returns
    -------
    dict with ``t`` (K+1,), ``x`` (K+1, n), ``xhat`` (K+1, N, n), ``u`` (K+1, N, nf),
    ``refreshes`` (N,) (exponentials computed per node).
    """
    if not (dt > 0 and t_end > 0):
        raise DesignError(f"dt and t_end must be > 0, got {dt}, {t_end}")
    K = int(round(t_end / dt))
    n, N = problem.n, problem.N
    cls = UgrinovskiiNode if controlled else UgrinovskiiBaseline
    oa, da = dict(observer_attacks or {}), dict(detector_attacks or {})
    nodes = [cls(problem, design, node=i, dt=dt, observer_attack=oa.get(i),
                 detector_attack=da.get(i) if controlled else None, gain_rtol=gain_rtol) for i in range(N)]
    from scipy.linalg import expm

    Ad = expm(problem.A * dt)
    x = np.zeros(n) if x0 is None else np.asarray(x0, float).reshape(n)
    nf = problem.F[0].shape[1]
    out = {"t": np.arange(K + 1) * dt, "x": np.zeros((K + 1, n)), "xhat": np.zeros((K + 1, N, n)),
           "u": np.zeros((K + 1, N, nf))}
    msgs: list[np.ndarray] = []
    for k in range(K + 1):
        if k > 0:
            x = Ad @ x
        new = []
        for i, nd in enumerate(nodes):
            inbox = {j: Received(j, k - 1, msgs[j]) for j in problem.neighbours[i]} if k > 0 else {}
            new.append(nd.step(k, problem.C[i] @ x, inbox))
            out["xhat"][k, i] = nd.estimate
            out["u"][k, i] = nd.attack_indicator
        msgs = new
        out["x"][k] = x
    out["refreshes"] = np.array([nd.refreshes for nd in nodes])
    return out
