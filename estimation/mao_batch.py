"""Every Mao-Tabuada node of a team in one stacked round (the simulator's batched round).

The per-node definition is :class:`estimation.mao_tabuada.MaoTabuadaEstimator`: the
measurement window and its sanity check, the dynamic consensus of the compressed windows
(eqs. (6)-(10), :func:`estimation.dynamic_consensus.consensus_update`) and the secure
decoder. :class:`MaoBatch` keeps the per-node code for the window (its latched flag and
residual are per node; the push runs for all nodes at once with the per-node dot
products) and stacks the consensus of all nodes as ``(M, v, n)`` arrays. In a closed team
(perfect channel) the innovations ``u``, ``w`` are formed from the stacked ``J``, ``eta``
in the per-node order of the neighbours (the same sums: ``Ahat^0`` is the identity); over
any other channel each node forms them from its own inbox
(:meth:`~estimation.dynamic_consensus.ConsensusNode.innovations`). The decoder computes
every node's residual norms exactly as the node does (its support choice is an argmin:
near-ties in the first rounds must break as they do per node), for all nodes in one
stacked call whose slices are the per-node matrix-vector products.

Every operation is the per-node one on the same values (a stacked ``(M, v, n) @ (n, n)``
product is the per-node product slice by slice), so the estimates, the diagnostics and
the flags are bit-identical to the per-node path (the equivalence test asserts it).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from .batching import Batch
from .dynamic_consensus import consensus_update
from .errors import NumericalError


def _dots(Y: np.ndarray, a: np.ndarray) -> np.ndarray:
    """``[a @ y for y in Y]`` in one call: ``(M, 1, n) @ (n, 1)`` runs the same dot as each
    1-D ``a @ y`` (a plain ``Y @ a`` is a matrix-vector product that may sum in another
    order)."""
    return np.matmul(Y[:, None, :], a[:, None])[:, 0, 0]


def _matvecs(A: np.ndarray, X: np.ndarray) -> np.ndarray:
    """``[A_m @ x_m for m]`` (``A``: ``(M, r, c)`` or ``(1, r, c)``, ``X``: ``(M, c)``) in one
    stacked call: each ``(r, c) @ (c, 1)`` slice is the per-node matrix-vector product."""
    return np.matmul(A, X[:, :, None])[:, :, 0]


class MaoBatch(Batch):
    """See the module docstring and :class:`estimation.batching.Batch`."""

    def __init__(self, members: Sequence[Any], **kw: Any) -> None:
        super().__init__(members, **kw)
        ms = self.members
        first = ms[0]
        des = first.design
        self._des, self._secure = des, first.decoder == "secure"
        cons = [m._cons for m in ms]
        self._A_T, self._g = cons[0]._Ahat_T, cons[0].gains
        self._J = np.stack([c._J for c in cons])
        self._b = np.stack([c._b for c in cons])
        self._eta = np.stack([c._eta for c in cons])
        self._Dcol = np.stack([des.D[:, m.node] for m in ms])  # (M, v)
        # neighbour slots: member-local index and weight of each member's a-th neighbour
        # (the per-node order of ConsensusNode._w), padded with weight 0
        local = {a: i for i, a in enumerate(self.agents)}
        width = max((len(c._w) for c in cons), default=0)
        self._slot_j = np.zeros((len(ms), width), dtype=int)
        self._slot_a = np.zeros((len(ms), width))
        self._closable = True
        for i, c in enumerate(cons):
            for s, (j, a) in enumerate(c._w.items()):
                if j not in local:
                    self._closable = False
                    continue
                self._slot_j[i, s], self._slot_a[i, s] = local[j], a
        self._k = first._k
        dec = des.decoder if self._secure else None
        if dec is not None:
            self._R, self._X, self._supports = dec._R, dec._X, dec._supports

    # ----------------------------------------------------------------- one round
    def _windows(self, k: int, measurements: Sequence[np.ndarray | None]) -> np.ndarray:
        """Every node's window push (:meth:`MeasurementWindow.push`, stacked; each node's
        window object is kept current); returns ``phi`` ``(M, v, n)``."""
        ms = self.members
        yv = np.array([np.nan if v is None else v for v in (m._measurement_value(k, y) for m, y in zip(ms, measurements))])
        for m in ms:
            if m._k is not None and k != m._k + 1:
                raise ValueError(f"node {m.node}: a batched round needs consecutive rounds, got {k} after {m._k}")
        wins = [m._window for m in ms]
        Y = np.stack([w._Y for w in wins])
        count = np.array([w._count for w in wins])
        flagged = np.array([w.flagged for w in wins])
        alpha, rtol = wins[0]._alpha, wins[0].rtol
        n = alpha.shape[0]
        full = count >= n
        have = ~np.isnan(yv)
        pred = -_dots(Y, alpha)
        check = full & have & ~flagged
        if check.any():
            aa = np.abs(alpha)
            scale = np.abs(yv) + _dots(np.abs(Y), aa)
            r = np.abs(yv - pred)
            with np.errstate(invalid="ignore", divide="ignore"):
                resid = np.where(scale > 0, r / scale, 0.0)
            newly = check & (r > rtol * scale)
            for i in map(int, np.flatnonzero(check)):
                wins[i].last_residual = float(resid[i])
            for i in map(int, np.flatnonzero(newly)):
                wins[i].flagged, wins[i].flag_round = True, int(k)
            flagged = flagged | newly
        value = np.where(full & (~have | flagged), pred, yv)
        restart = ~full & ~have  # samples must be consecutive: start again
        shift = ~restart
        Y2 = np.where(shift[:, None], np.concatenate([Y[:, 1:], value[:, None]], axis=1), Y)
        for i, w in enumerate(wins):
            if restart[i]:
                w._count = 0
            else:
                w._Y, w._count = Y2[i], w._count + 1
        ok = np.array([w._count >= n for w in wins])
        return np.where(ok[:, None, None], self._Dcol[:, :, None] * Y2[:, None, :], 0.0)

    def _finish(self, k: int, u: np.ndarray, w: np.ndarray, phi: np.ndarray) -> np.ndarray:
        self._J, self._b, self._eta = consensus_update(self._J, self._b, u, w, phi, self._A_T, self._g)
        des = self._des
        Z = (des.p * self._J).reshape(len(self.members), -1)  # every node's compressed window
        if self._secure:  # the per-node residual norms, stacked (the argmin sees the per-node values)
            R, Xs, sups = self._R, self._X, self._supports
            M, T, q = Z.shape[0], R.shape[0], R.shape[1]
            r = _matvecs(R.reshape(T * q, q)[None], Z).reshape(M, T, q)
            t = np.argmin(np.sqrt(np.add.reduce(r * r, axis=2)), axis=1)  # np.linalg.norm(R @ z, axis=1)
            xs = _matvecs(Xs[t], Z)
            supports = [sups[ti] for ti in t]
        else:
            from .secure_decoder import least_squares_decode

            out = [least_squares_decode(z.reshape(des.v, -1), des.O_blocks, des.D) for z in Z]
            xs, supports = np.array([r.x for r in out]), [r.support for r in out]
        Aw = des.A_window
        X = _matvecs(Aw[None], xs)
        limit = self.members[0].signal_limit
        bad = ~np.isfinite(X).all(axis=1) | (np.abs(X).max(axis=1, initial=0.0) > limit)
        if bad.any():
            m = self.members[int(np.flatnonzero(bad)[0])]
            raise NumericalError(f"node {m.node}, round {k}: estimate beyond the signal limit {limit:g}")
        for m, x, sup in zip(self.members, X, supports):
            m._x, m.support, m._k = x, sup, k
        self._k = k
        self._X_now = X
        return X

    def step(self, k: int, measurements, inboxes) -> list[np.ndarray]:
        phi = self._windows(k, measurements)
        us, ws = [], []
        for i, (m, inbox) in enumerate(zip(self.members, inboxes)):
            c = m._cons
            c._J, c._eta = self._J[i], self._eta[i]
            for msg in inbox.values():
                c.receive(int(msg.sender), int(msg.stamp), msg.value)
            u, w = c.innovations(k)
            us.append(u)
            ws.append(w)
        self._finish(k, np.stack(us), np.stack(ws), phi)
        for i, m in enumerate(self.members):
            m._cons._J, m._cons._b, m._cons._eta, m._cons._k = self._J[i], self._b[i], self._eta[i], k
        return [np.concatenate([J.ravel(), e.ravel()]) for J, e in zip(self._J, self._eta)]

    def step_closed(self, k: int, y: np.ndarray) -> np.ndarray:
        if self.rows is None or not self._closable:
            return super().step_closed(k, y)
        phi = self._windows(k, [y[r] for r in self.rows])
        J, eta = self._J, self._eta
        u = np.zeros(J.shape)
        w = np.zeros(J.shape)
        if self._k is not None:  # every neighbour's values of round k - 1: tau = 0
            for s in range(self._slot_j.shape[1]):  # the per-node order of the sums
                a, j = self._slot_a[:, s, None, None], self._slot_j[:, s]
                u += a * (J - J[j])
                w += a * (eta - eta[j])
        return self._finish(k, u, w, phi)

    def estimates(self) -> np.ndarray:
        return self._X_now

    def sync(self) -> None:
        for i, m in enumerate(self.members):
            c = m._cons
            c._J, c._b, c._eta, c._k = self._J[i].copy(), self._b[i].copy(), self._eta[i].copy(), self._k
