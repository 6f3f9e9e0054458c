"""The batched round of the inverter estimators (:mod:`estimation.batching`).

* the substation (mode median): every member's bank of observers (9) as one stacked state
  (:class:`estimation.lure_batch.StackedLureObservers`), then the median (5) per member;
* the distributed median: the members' own observers stacked, then every member's sign
  median step at once (:func:`estimation.lure_batch.sign_median_stacked`).

Estimates equal the per-agent path's within 1e-12 relative (stacked products).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from estimation.batching import Batch
from estimation.lure_batch import StackedLureObservers, sign_median_stacked
from estimation.median_bank import median_fuse


def _finite_vector(value: Any, size: int) -> bool:
    """What the distributed agent accepts from a neighbour: a finite ``(size,)`` array."""
    v = np.asarray(value)
    return v.shape == (size,) and bool(np.all(np.isfinite(v)))


class SerialBatch(Batch):
    """Members stepped one by one (modes without a stacked form)."""

    def step(self, k, measurements, inboxes) -> list[np.ndarray]:
        return [m.step(k, y, inbox) for m, y, inbox in zip(self.members, measurements, inboxes)]

    def estimates(self) -> np.ndarray:
        return np.array([m.estimate for m in self.members])


class BankBatch(Batch):
    """Substations in the median mode: ``M`` banks of ``N`` observers as ``M N`` stacked rows."""

    def __init__(self, members: Sequence[Any], **kw: Any) -> None:
        super().__init__(members, **kw)
        self._stack = StackedLureObservers([o for m in self.members for o in m._core._obs])
        self._N = len(self.members[0]._core._obs)

    def step(self, k, measurements, inboxes) -> list[np.ndarray]:
        N, ms = self._N, self.members
        ys = [None if y is None else np.asarray(y, dtype=float)[m._perm] for m, y in zip(ms, measurements)]
        y = None if all(v is None for v in ys) else np.concatenate([np.full(N, np.nan) if v is None else v for v in ys])
        X = self._stack.step(k, y).reshape(len(ms), N, -1)
        out = []
        mid = N // 2
        for m, rows in zip(ms, X):
            if N % 2 and (m._core._M is None or N > 2 * m._core._M):  # the middle value: np.median's own
                m._core._x = np.partition(rows, mid, axis=0)[mid]
            else:
                m._core._x = median_fuse(rows, n_attacked=m._core._M)
            m._x = np.asarray(m._core._x.copy(), dtype=float)
            out.append(m._x.copy())
        return out

    def estimates(self) -> np.ndarray:
        return np.array([m._x for m in self.members])

    def sync(self) -> None:
        self._stack.sync()


class DistributedBatch(Batch):
    """Inverter agents of the distributed mode: observers stacked, one sign-median update."""

    def __init__(self, members: Sequence[Any], **kw: Any) -> None:
        super().__init__(members, **kw)
        ms = self.members
        self._obs = StackedLureObservers([m._obs for m in ms])
        sol = ms[0]._solver
        self._kw, self._ref, self.max_age, self.dt = sol._kw, sol._ref, sol.max_age, sol.dt
        self.n = ms[0].n
        self._XI: np.ndarray | None = None if any(m._solver._xi is None for m in ms) else np.stack([m._solver._xi for m in ms])
        self._k = ms[0]._solver._k

    def step(self, k, measurements, inboxes) -> list[np.ndarray]:
        y = None if all(v is None for v in measurements) else \
            np.array([np.nan if v is None else float(np.asarray(v, dtype=float).reshape(-1)[0]) for v in measurements])
        Z = self._obs.step(k, y).copy()  # every member's local estimate z_i[k]
        XI: np.ndarray
        if self._k is None:
            XI = Z.copy() if self._XI is None else self._XI
        else:
            oldest = k - 1 - self.max_age
            n, M = self.n, len(self.members)
            d = np.zeros(M, dtype=int)
            mean = np.zeros((M, n))
            for a, inbox in enumerate(inboxes):  # the per-agent filter and mean
                nb = [np.asarray(r.value, dtype=float) for r in (inbox or {}).values()
                      if _finite_vector(r.value, n) and r.stamp >= oldest]
                if nb:
                    d[a] = len(nb)
                    mean[a] = np.sum(nb, axis=0) / len(nb)
            assert self._XI is not None  # set with self._k
            XI, kw = self._XI, self._kw
            for kk in range(self._k, k):
                shift = None if self._ref is None else np.asarray(self._ref(kk + 1), dtype=float) - self._ref(kk)
                XI = sign_median_stacked(XI, mean, d, Z, kappa=kw["kappa"], gamma=kw["gamma"], dt=kw["dt"], t=kk * self.dt,
                                         drift=kw["drift"], substeps=kw["substeps"], sign=kw["sign"], shift=shift)
        XI = np.array(XI, dtype=float)
        XI.flags.writeable = False
        self._XI, self._k, self._Z = XI, k, Z
        return list(XI)

    def estimates(self) -> np.ndarray:
        assert self._XI is not None  # set by the first step
        return self._XI

    def sync(self) -> None:
        self._obs.sync()
        if self._XI is None:  # not stepped yet: the members hold their own state
            return
        for m, xi, z in zip(self.members, self._XI, self._Z):
            xi = xi.copy()
            xi.flags.writeable = False
            m._solver._xi, m._solver._k, m._local = xi, self._k, z.copy()
