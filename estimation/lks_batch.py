"""Every Lee-Kim-Shim agent of a team in one stacked step (the simulator's batched round).

The per-agent :class:`estimation.lee_kim_shim.LeeKimShim` is the definition: one round is
``[x+; z+] = M_d [x; z; sum_j x_j; u; y]`` (the exactly discretised partial observer,
eq. (5), and the consensus / model part of eq. (6) or (11)), then the correction
``x+ += G_d phi(H [x; z])`` with ``phi`` the implicit sgn (clipped, scaled by the band),
the held sgn or the identity (linear baseline). :class:`LKSBatch` stacks the members'
states as ``S = [x_1; ...; x_M; z_1; ...; z_M]`` and their matrices block-diagonally, so
one round of the whole team is three matrix-vector products (:func:`stacked_round`).

The stacked products sum the same terms in another order than the per-agent ones, so the
estimates equal the per-agent path's within 1e-12 relative, not bit for bit (the implicit
sgn is continuous; the held sgn, ``sign = "held"``, may flip where ``H [x; z]`` is within
rounding of 0 and then the two paths part).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from .base import Inbox, held
from .batching import Batch


def stacked_round(S: np.ndarray, v: np.ndarray, M: np.ndarray, H: np.ndarray, G: np.ndarray, *, nx: int,
                  mode: str) -> np.ndarray:
    """One round of eqs. (5)-(6) / (11) for stacked agents; returns the new stacked state.

    Parameters
    ----------
    S : (s,) stacked ``[x_1..x_M; z_1..z_M]`` of the previous round
    v : (c,) what ``M`` acts on (``S`` first, then neighbour sums, input, measurements)
    M : (s, c) block matrix of the members' ``M_d``;  H : (o, s) sliding variables
        ``E z - F x`` (rows scaled by ``1 / band`` for the implicit sgn);  G : (nx, o)
    nx : rows of ``S`` that are estimates ``x`` (``M n``)
    mode : "implicit" (sgn at the step's end, clipped), "held" (sgn of the old state)
        or "linear" (the innovation itself)
    """
    sn = M @ v
    if H.shape[0]:
        if mode == "implicit":
            phi = H @ sn
            np.minimum(np.maximum(phi, -1.0, out=phi), 1.0, out=phi)
        elif mode == "held":
            phi = np.sign(H @ S)
        else:
            phi = H @ S
        sn[:nx] += G @ phi
    return sn


class LKSBatch(Batch):
    """The members' states stacked; see the module docstring and :class:`Batch`."""

    def __init__(self, members: Sequence[Any], **kw: Any) -> None:
        super().__init__(members, **kw)
        ms = self.members
        first = ms[0]
        self.n, self.dt, self.max_age, self._u = first.n, first.dt, first.max_age, first._u
        self._mode = "linear" if first._linear else ("implicit" if first._implicit else "held")
        n, Mn = self.n, len(ms) * first.n
        self._nx = Mn
        self._o = [m._o for m in ms]
        self._zoff = np.concatenate([[0], np.cumsum(self._o)]).astype(int) + Mn
        self._S = np.concatenate([m._s[:n] for m in ms] + [m._s[n:] for m in ms])
        self._S.flags.writeable = False
        ks = {m._k for m in ms}
        if len(ks) != 1:
            raise ValueError(f"a batch needs its members at one round, got rounds {sorted(ks, key=str)}")
        self._k = ks.pop()
        self._y = [m._y for m in ms]
        self._p = first._Bd.shape[1]
        self._m = [m._M[0].shape[1] - (2 * n + o + self._p) for m, o in zip(ms, self._o)]
        self._cache: dict[tuple, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._closed: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._closed_y: np.ndarray | None = None  # y of the last closed round (whole plant)

    # ------------------------------------------------------------- stacked matrices
    def _idx(self, m: int) -> np.ndarray:
        n = self.n
        return np.r_[m * n:(m + 1) * n, self._zoff[m]:self._zoff[m + 1]]

    def _matrices(self, degs: tuple[int, ...], seen: tuple[bool, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Block matrices on ``v = [S; T; u; y_1..y_M]`` (``T``: neighbour sums, ``y_m``
        only for members with a measurement) for neighbour counts ``degs``."""
        key = (degs, seen)
        got = self._cache.get(key)
        if got is not None:
            return got
        n, Mn, p = self.n, self._nx, self._p
        s = int(self._zoff[-1])
        ycols = np.concatenate([[0], np.cumsum([mm if ok else 0 for mm, ok in zip(self._m, seen)])]).astype(int)
        base = s + Mn + p
        M = np.zeros((s, base + int(ycols[-1])))
        H = np.zeros((sum(self._o), s))
        G = np.zeros((Mn, sum(self._o)))
        orow = 0
        for m, (est, d, ok) in enumerate(zip(self.members, degs, seen)):
            o, idx = self._o[m], self._idx(m)
            Md = est._M[d] if ok else est._M_open[d]
            cols = np.r_[idx, s + m * n:s + (m + 1) * n, s + Mn:s + Mn + p]
            if ok:
                cols = np.r_[cols, base + ycols[m]:base + ycols[m + 1]]
            M[np.ix_(idx, cols)] = Md
            if o:
                Hm = est._H * est._inv_band[d][:, None] if self._mode == "implicit" else est._H
                H[np.ix_(np.arange(orow, orow + o), idx)] = Hm
                G[m * n:(m + 1) * n, orow:orow + o] = est._Gs[d]
            orow += o
        if len(self._cache) < 4096:
            self._cache[key] = (M, H, G)
        return M, H, G

    def _closed_matrices(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Block matrices on ``v = [S; u; y]`` (``y``: the plant's whole stacked
        measurement) with the neighbour sums folded into ``M`` (every in-neighbour heard)."""
        if self._closed is None:
            n, Mn, p = self.n, self._nx, self._p
            s = int(self._zoff[-1])
            M, H, G = self._matrices(tuple(len(nb) for nb in self.in_neighbours), (True,) * len(self.members))
            rows = self.rows
            assert rows is not None  # the closed round is taken only with static rows
            width = 1 + max((int(r.max()) for r in rows if r.size), default=-1)
            Mc = np.zeros((s, s + p + width))
            Mc[:, :s] = M[:, :s]
            for m, nb in enumerate(self.in_neighbours):  # T_m = sum_j x_j
                for j in nb:
                    Mc[:, j * n:(j + 1) * n] += M[:, s + m * n:s + (m + 1) * n]
            Mc[:, s:s + p] = M[:, s + Mn:s + Mn + p]
            c = s + Mn + p
            for r in rows:
                Mc[:, s + p + r] += M[:, c:c + r.size]
                c += r.size
            self._closed = (Mc, H, G)
        return self._closed

    # ------------------------------------------------------------------- rounds
    def _pull_closed_y(self) -> None:
        if self._closed_y is not None:
            assert self.rows is not None
            self._y = [np.asarray(self._closed_y[r], dtype=float) for r in self.rows]
            self._closed_y = None

    def step(self, k: int, measurements: Sequence[np.ndarray | None], inboxes: Sequence[Inbox]) -> list[np.ndarray]:
        self._pull_closed_y()
        if self._k is not None:
            zero = np.zeros(self.n)
            seen = tuple(y is not None for y in self._y)
            ys = [y for y in self._y if y is not None]
            for kk in range(self._k, k):  # as LeeKimShim.step: per step what holds over it
                degs, totals = [], []
                for inbox in inboxes:  # the per-agent sum, in the per-agent order
                    nb = held(inbox, kk, self.max_age)
                    total = zero
                    if nb:
                        total = nb[0]
                        for val in nb[1:]:
                            total = total + val
                    degs.append(len(nb))
                    totals.append(total)
                M, H, G = self._matrices(tuple(degs), seen)
                v = np.concatenate([self._S, *totals, self._u(kk * self.dt), *ys])
                seen, ys = (False,) * len(seen), []  # a skipped round carries no measurement
                self._S = stacked_round(self._S, v, M, H, G, nx=self._nx, mode=self._mode)
                self._S.flags.writeable = False
        self._k = k
        self._y = [None if y is None else np.asarray(y, dtype=float) for y in measurements]
        return list(self.estimates())

    def step_closed(self, k: int, y: np.ndarray) -> np.ndarray:
        if self.rows is None:
            raise ValueError("step_closed needs every member's measurement rows (static sensors)")
        if self._k is not None:
            if k != self._k + 1 or self._closed_y is None:
                raise ValueError(f"step_closed: round {k} after round {self._k} needs that round closed too")
            M, H, G = self._closed_matrices()
            v = np.concatenate((self._S, self._u(self._k * self.dt), self._closed_y))
            S = stacked_round(self._S, v, M, H, G, nx=self._nx, mode=self._mode)
            S.flags.writeable = False
            self._S = S
        self._k = k
        self._closed_y = y
        return self._S[:self._nx].reshape(len(self.members), self.n)

    def estimates(self) -> np.ndarray:
        return self._S[:self._nx].reshape(len(self.members), self.n)

    def sync(self) -> None:
        n = self.n
        self._pull_closed_y()
        for m, est in enumerate(self.members):
            s = np.concatenate([self._S[m * n:(m + 1) * n], self._S[self._zoff[m]:self._zoff[m + 1]]])
            s.flags.writeable = False
            est._s, est._k, est._y = s, self._k, self._y[m]
