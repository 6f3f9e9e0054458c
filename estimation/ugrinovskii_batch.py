"""Every Ugrinovskii node of a team in one stacked round (the simulator's batched round).

The per-node definition is :meth:`estimation.ugrinovskii._NodeBase.step`: the held inputs
(measurement, neighbour innovations (10), (18), attack signals), the exponential
integrator of the node dynamics (8), (17) with the gains frozen over the step, then one
exact step of each Riccati flow (35), (41). :class:`UgrinovskiiBatch` keeps the per-node
code for the inputs and for the gain refresh (each node re-discretises when its own
Riccati solution moved; whether it moved is tested for every node's flows at once), and
stacks the rest: the node states ``s+ = Phi s + Gd v`` of all
nodes in one product and every observer / detector Riccati flow in one batched step
(:class:`estimation.hinf_riccati.FlowStack`).

The stacked products and the batched solve differ from the per-node calls in rounding,
so the estimates equal the per-node path's within 1e-12 relative, not bit for bit.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from .batching import Batch
from .hinf_riccati import FlowStack


class UgrinovskiiBatch(Batch):
    """See the module docstring and :class:`estimation.batching.Batch`."""

    def __init__(self, members: Sequence[Any], **kw: Any) -> None:
        super().__init__(members, **kw)
        ms = self.members
        self._n = ms[0]._pb.n
        dims = {m._state_dim for m in ms}
        self._same = len(dims) == 1
        groups: dict[tuple, list] = {}
        owner: dict[tuple, list] = {}  # per group: (member, position among its flows) of every flow
        for i, m in enumerate(ms):
            for a, fl in enumerate(m._flows()):
                groups.setdefault(fl._Delta.shape, []).append(fl)
                owner.setdefault(fl._Delta.shape, []).append((i, a))
        self._flows = [FlowStack(g) for g in groups.values()]
        self._owner = [np.array([i for i, _ in owner[key]]) for key in groups]
        self._slot = [owner[key] for key in groups]
        self._ref: list[tuple[np.ndarray, np.ndarray] | None] = [None] * len(self._flows)
        self._S: np.ndarray | None = None  # the stacked states after a stacked step
        self._finite = True  # ... all finite (so are the payloads, their leading parts)

    def _stale(self) -> np.ndarray:
        """Every member's :meth:`~estimation.ugrinovskii._NodeBase._stale`, the flows of one
        size tested in one stacked norm (``|Delta - Delta_0|_F > tol``)."""
        ms = self.members
        stale = np.array([m._disc is None for m in ms])
        if stale.all():
            return stale
        for g, (stack, own) in enumerate(zip(self._flows, self._owner)):
            ref = self._ref[g]
            if ref is None:
                continue
            d = np.stack([f._Delta for f in stack.flows]) - ref[0]
            moved = np.sqrt(np.einsum("fij,fij->f", d, d)) > ref[1]
            stale[own[moved]] = True
        return stale

    def _keep_refs(self, refreshed: np.ndarray) -> None:
        """The reference solutions of the members just re-discretised (their ``_ref``)."""
        ms = self.members
        for g, slots in enumerate(self._slot):
            ref = self._ref[g]
            if ref is None:
                if any(ms[i]._disc is None for i, _ in slots):
                    continue
                self._ref[g] = (np.stack([ms[i]._ref[a][0] for i, a in slots]),
                                np.array([ms[i]._ref[a][1] for i, a in slots]))
                continue
            for s, (i, a) in enumerate(slots):
                if refreshed[i]:
                    ref[0][s], ref[1][s] = ms[i]._ref[a]

    def step(self, k: int, measurements, inboxes) -> list[np.ndarray]:
        ms = self.members
        self._S = None
        if any(m._k is None or k != m._k + 1 for m in ms) or not self._same:
            self._ref = [None] * len(self._flows)  # the members keep their own references
            return [m.step(k, y, inbox) for m, y, inbox in zip(ms, measurements, inboxes)]
        V = [m._inputs(y, inbox) for m, y, inbox in zip(ms, measurements, inboxes)]
        stale = self._stale()
        disc = [m._discretisation(bool(st)) for m, st in zip(ms, stale)]
        if stale.any():
            self._keep_refs(stale)
        Phi = np.stack([d[0] for d in disc])
        Gd = np.stack([d[1] for d in disc]) if len({d[1].shape for d in disc}) == 1 else None
        S = np.stack([m._s for m in ms])
        if Gd is not None:
            Snew = (Phi @ S[:, :, None])[:, :, 0] + (Gd @ np.stack(V)[:, :, None])[:, :, 0]
        else:  # nodes with different neighbour counts: the input products node by node
            Snew = (Phi @ S[:, :, None])[:, :, 0] + np.stack([g @ v for (_, g), v in zip(disc, V)])
        for stack in self._flows:
            stack.step()
        self._S, self._finite = Snew, bool(np.isfinite(Snew).all())
        out = []
        for m, s in zip(ms, Snew):
            m._s, m._k = s, k
            m._after_step()
            out.append(m._payload())
        return out

    def step_closed(self, k: int, y: np.ndarray) -> np.ndarray:
        """The closed team: every in-neighbour's payload of round ``k - 1`` is handed to the
        node's store of newest payloads directly (what its inbox would deliver; the
        per-message checks are skipped only while every payload is finite)."""
        ms = self.members
        last = self._last
        finite = last is None or (self._finite if self._S is not None else all(np.all(np.isfinite(v)) for v in last))
        if self.rows is None or not finite:
            return super().step_closed(k, y)
        if last is not None:
            for m, nb in zip(ms, self.in_neighbours):
                for j in nb:
                    if self.agents[j] in m._nb:
                        m._last[self.agents[j]] = last[j]
        self._last = self.step(k, [y[r] for r in self.rows], [{}] * len(ms))
        return self.estimates()

    def estimates(self) -> np.ndarray:
        n = self._n
        if self._S is not None:  # the stacked states of the last step (each member's _s is a row)
            return self._S[:, :n].copy()
        return np.stack([m._s[:n] for m in self.members])
