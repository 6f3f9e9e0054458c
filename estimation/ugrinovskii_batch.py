"""Every Ugrinovskii node of a team in one stacked round (the simulator's batched round).

The per-node definition is :meth:`estimation.ugrinovskii._NodeBase.step`: the held inputs
(measurement, neighbour innovations (10), (18), attack signals), the exponential
integrator of the node dynamics (8), (17) with the gains frozen over the step, then one
exact step of each Riccati flow (35), (41). :class:`UgrinovskiiBatch` keeps the per-node
code for the inputs and for the gain refresh (each node re-discretises when its own
Riccati solution moved; whether it moved is tested for every node's flows at once), and
stacks the rest: the node states ``s+ = Phi s + Gd v`` of all
nodes in one product and every observer and detector Riccati flow in one batched step
(:class:`estimation.hinf_riccati.FlowStack`, the smaller flows padded to the largest size).

The stacked products and the batched solve differ from the per-node calls in rounding,
so the estimates equal the per-node path's within 1e-12 relative, not bit for bit.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from .batching import Batch
from .hinf_riccati import FlowStack
from .ugrinovskii_system import Template, system, template


class UgrinovskiiBatch(Batch):
    """See the module docstring and :class:`estimation.batching.Batch`."""

    def __init__(self, members: Sequence[Any], **kw: Any) -> None:
        super().__init__(members, **kw)
        ms = self.members
        m0 = ms[0]
        self._n = m0._pb.n
        dims = {(m._state_dim, m._input_dim()) for m in ms}
        self._same = len(dims) == 1
        slots = [(i, a) for i, m in enumerate(ms) for a in range(len(m._flows()))]  # every flow's owner
        self._flows = FlowStack([ms[i]._flows()[a] for i, a in slots])  # every flow, padded to one size
        self._owner = np.array([i for i, _ in slots])
        self._slot = slots
        self._ref: tuple[np.ndarray, np.ndarray] | None = None  # the flows' padded Delta_0 and tolerances
        self._S: np.ndarray | None = None  # the stacked states after a stacked step
        self._finite = True  # ... all finite (so are the payloads, their leading parts)
        # the stacked discretisations [Phi], [Gd] (rows refreshed with their member's)
        self._Phi: np.ndarray | None = None
        self._Gd: np.ndarray | None = None
        self._disc_of: list[Any] = [None] * len(ms)
        # every member's constant part of (M, G) stacked (the stale ones re-discretised together)
        for m in ms:
            if m._tpl is None:
                m._tpl = template(m)
        tp = [m._tpl for m in ms]
        self._tpl: Template | None = None
        if self._same and len({(t.Z.shape, t.n, t.p, t.controlled) for t in tp}) == 1:
            self._tpl = tp[0]._replace(**{f: np.stack([getattr(t, f) for t in tp]) for f in ("M0", "G0", "Z", "Ro", "Rd")})
        # the attack indicators u = Ups eps_hat (19) of all members at once
        ctl = m0._controlled
        self._Ups = np.stack([m._pb.Upsilon[m.node] for m in ms]) if ctl and self._same else None
        self.diagnostic_rows = self._same and type(m0)._diagnostic_rows(ms, None) is not None
        # the closed team's inputs without the per-node code (:meth:`_closed_inputs`)
        self._vec = self._closed_plan()

    # -- the closed team's inputs, stacked ------------------------------------------------
    def _closed_plan(self) -> tuple | None:
        """Index arrays for :meth:`_closed_inputs`, or None where the per-node
        :meth:`~estimation.ugrinovskii._NodeBase._inputs` must run (members of different
        sizes, an in-neighbour outside the batch, receiver-side noise)."""
        ms = self.members
        if not self._same or self.rows is None or not all(m._plain_inputs() for m in ms):
            return None
        if len({len(m._nb) for m in ms}) != 1 or len({m._p for m in ms}) != 1 or \
                len({tuple(m._pj) for m in ms}) != 1 or len({m._nf for m in ms}) != 1:
            return None
        local = {a: i for i, a in enumerate(self.agents)}
        if any(j not in local for m in ms for j in m._nb):
            return None
        if any(self.agents[i] != m.node for i, m in enumerate(ms)):
            return None
        m0 = ms[0]
        p, pj, nf = m0._p, m0._pj, m0._nf
        rows = np.stack(self.rows) if len({len(r) for r in self.rows}) == 1 else None
        if rows is None or rows.shape[1] != p:
            return None
        src = [np.array([local[m._nb[a]] for m in ms]) for a in range(len(pj))]
        W = [np.stack([m._pb.W[(m.node, m._nb[a])] for m in ms]) for a in range(len(pj))]
        cols = np.cumsum([0, p] + pj + pj + [nf, nf])  # y | c_j | eta_j | f | f_c (_system's)
        attacked = [(i, m._fa, m._fd) for i, m in enumerate(ms) if m._fa is not None or m._fd is not None]
        return rows, src, W, cols, attacked

    def _closed_inputs(self, S: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Every member's :meth:`~estimation.ugrinovskii._NodeBase._inputs` of a closed
        round after a stacked one: the measurement rows, ``c_j = W_j x_hat_j`` (3),
        ``eta_j = W_j e_hat_j`` (18) from every in-neighbour's newest payload (its row of
        ``S``), the attack signals at ``t_{k-1}``."""
        assert self._vec is not None
        rows, src, W, cols, attacked = self._vec
        ms, n = self.members, self._n
        V = np.zeros((len(ms), cols[-1]))
        V[:, : cols[1]] = y[rows]
        q = len(src)
        X = S[:, :n, None]
        E = S[:, n: 2 * n, None] if ms[0]._controlled else None
        for a in range(q):
            V[:, cols[1 + a]: cols[2 + a]] = (W[a] @ X[src[a]])[:, :, 0]
            if E is not None:
                V[:, cols[1 + q + a]: cols[2 + q + a]] = (W[a] @ E[src[a]])[:, :, 0]
        if attacked:
            t0 = ms[0].t
            for i, fa, fd in attacked:
                if fa is not None:
                    V[i, cols[-3]: cols[-2]] = np.asarray(fa(t0), float).reshape(-1)
                if fd is not None:
                    V[i, cols[-2]: cols[-1]] = np.asarray(fd(t0), float).reshape(-1)
        return V

    # -- the gain refresh --------------------------------------------------------------------
    def _stale(self) -> np.ndarray:
        """Every member's :meth:`~estimation.ugrinovskii._NodeBase._stale`, every flow tested
        in one stacked norm (``|Delta - Delta_0|_F > tol``)."""
        ms = self.members
        ref = self._ref
        if ref is None:  # no stacked references (yet): each member's own test
            self._flows.sync()
            return np.array([m._stale() for m in ms])
        stale = np.zeros(len(ms), dtype=bool)  # (with references, every member has a discretisation)
        d = self._flows.deviations - ref[0]
        moved = np.sqrt(np.einsum("fij,fij->f", d, d)) > ref[1]
        if moved.any():
            stale[self._owner[moved]] = True
        return stale

    def _keep_refs(self, refreshed: np.ndarray) -> None:
        """The reference solutions of the members just re-discretised (their ``_ref``)."""
        ms = self.members
        ref = self._ref
        if ref is None:
            if any(m._disc is None for m in ms):
                return
            m = self._flows.m
            ref = self._ref = (np.zeros((len(self._slot), m, m)), np.zeros(len(self._slot)))
            refreshed = np.ones(len(ms), dtype=bool)
        for s, (i, a) in enumerate(self._slot):
            if refreshed[i]:
                D0, tol = ms[i]._ref[a]
                mi = D0.shape[0]
                ref[0][s, :mi, :mi], ref[1][s] = D0, tol

    def _discretisations(self) -> tuple[np.ndarray, np.ndarray]:
        """The stacked ``(Phi, Gd)`` of this round: each member's
        :meth:`~estimation.ugrinovskii._NodeBase._discretisation`, re-computed where it is stale."""
        ms = self.members
        stale = self._stale()
        idx = np.flatnonzero(stale)
        if not len(idx) and self._Phi is not None and self._Gd is not None and self._ref is not None:
            return self._Phi, self._Gd
        self._flows.sync()  # the stale members read their flows
        if len(idx) > 1 and self._tpl is not None:  # the stale members' (M, G) in one stacked call
            t = self._tpl
            sub = t._replace(M0=t.M0[idx], G0=t.G0[idx], Z=t.Z[idx], Ro=t.Ro[idx], Rd=t.Rd[idx])
            Yd = np.stack([ms[i]._det.Y for i in idx]) if t.controlled else None
            M, G = system(sub, np.stack([ms[i]._obs.Y for i in idx]), Yd)
            bal = [ms[i]._balanced(M[j], G[j]) for j, i in enumerate(idx)]
            from scipy.linalg import expm  # not at import (see hinf_riccati)

            expbal = expm(np.stack([b for b, _ in bal]))  # slice by slice as the nodes' own calls
            for j, i in enumerate(idx):
                ms[i]._refreshed(expbal[j], bal[j][1])
        else:
            for i in idx:
                ms[i]._discretisation(True)
        if stale.any() or self._ref is None:
            self._keep_refs(stale)
        if self._Phi is None:
            self._Phi = np.stack([m._disc[0] for m in ms])
            self._Gd = np.stack([m._disc[1] for m in ms])
            self._disc_of = [m._disc for m in ms]
        else:
            assert self._Gd is not None
            for a in idx:
                m = ms[a]
                if m._disc is not self._disc_of[a]:
                    self._Phi[a], self._Gd[a] = m._disc
                    self._disc_of[a] = m._disc
        assert self._Gd is not None
        return self._Phi, self._Gd

    # -- one round ---------------------------------------------------------------------------
    def _aligned(self, k: int) -> bool:
        return self._same and all(m._k is not None and k == m._k + 1 for m in self.members)

    def step(self, k: int, measurements, inboxes) -> list[np.ndarray]:
        ms = self.members
        if not self._aligned(k):
            self._flows.sync()
            self._S = None
            self._ref = None  # the members keep their own references
            self._Phi = None
            return [m.step(k, y, inbox) for m, y, inbox in zip(ms, measurements, inboxes)]
        V = np.stack([m._inputs(y, inbox) for m, y, inbox in zip(ms, measurements, inboxes)])
        S = self._S if self._S is not None else np.stack([m._s for m in ms])
        self._advance(k, S, V)
        return [m._payload() for m in ms]

    def _advance(self, k: int, S: np.ndarray, V: np.ndarray) -> np.ndarray:
        """``s+ = Phi s + Gd v`` for every member, one exact step of every Riccati flow, the
        members' state, round and round-end hook; returns the stacked new states."""
        ms = self.members
        Phi, Gd = self._discretisations()
        Snew = (Phi @ S[:, :, None])[:, :, 0] + (Gd @ V[:, :, None])[:, :, 0]
        self._flows.step()
        self._S, self._finite = Snew, bool(np.isfinite(Snew).all())
        for m, s in zip(ms, Snew):
            m._s, m._k = s, k
        type(ms[0])._after_steps(ms, self._indicators())
        return Snew

    def _indicators(self) -> np.ndarray:
        """``(M, nf)``: every member's ``u = Ups eps_hat`` (19) (the baseline's: 0)."""
        if self._Ups is None:
            return np.zeros((len(self.members), self.members[0]._nf))
        n = self._n
        S = self._S if self._S is not None else np.stack([m._s for m in self.members])
        return (self._Ups @ S[:, 2 * n:, None])[:, :, 0]

    def diagnostics(self) -> tuple[dict[str, np.ndarray], np.ndarray | None] | None:
        """Every member's diagnostics and attack flag as rows (what each member's
        ``diagnostics()`` and ``flagged`` read), or None when the members do not offer them."""
        if not self.diagnostic_rows:
            return None
        ms = self.members
        return type(ms[0])._diagnostic_rows(ms, self._indicators())

    def step_closed(self, k: int, y: np.ndarray) -> np.ndarray:
        """The closed team: every in-neighbour's payload of round ``k - 1`` is handed to the
        node's store of newest payloads directly (what its inbox would deliver; the
        per-message checks are skipped only while every payload is finite)."""
        ms = self.members
        last = self._last
        finite = last is None or (self._finite if self._S is not None else all(np.all(np.isfinite(v)) for v in last))
        if self.rows is None or not finite:
            return super().step_closed(k, y)
        S = self._S
        if self._vec is not None and S is not None and last is not None and self._aligned(k):
            pd = ms[0]._payload_dim
            P = S[:, :pd]
            for m, nb in zip(ms, self.in_neighbours):
                for j in nb:
                    m._last[self.agents[j]] = P[j]
            Snew = self._advance(k, S, self._closed_inputs(S, y))
            self._last = list(Snew[:, :pd])
            return Snew[:, : self._n].copy()
        if last is not None:
            for m, nb in zip(ms, self.in_neighbours):
                for j in nb:
                    if self.agents[j] in m._nb:
                        m._last[self.agents[j]] = last[j]
        self._last = self.step(k, [y[r] for r in self.rows], [{}] * len(ms))
        return self.estimates()

    def sync(self) -> None:
        """Every Riccati flow's solution and time written back into its member."""
        self._flows.sync()

    def estimates(self) -> np.ndarray:
        n = self._n
        if self._S is not None:  # the stacked states of the last step (each member's _s is a row)
            return self._S[:, :n].copy()
        return np.stack([m._s[:n] for m in self.members])
