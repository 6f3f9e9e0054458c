"""The declared capability of stepping many agents of one estimator class together.

An estimator class opts in by inheriting :class:`Batchable` (a nominal declaration: the
simulator selects batched groups by ``isinstance(est, Batchable)``, never by probing for
methods). Its :meth:`Batchable.batch` builds a :class:`Batch` over several agents' estimator
objects; the simulator then calls the batch once per round instead of each agent's
``step``::

    batch = LeeKimShim.batch(estimators, in_neighbours=...)   # member-local indices
    payloads = batch.step(k, measurements, inboxes)            # any channel, any inbox
    estimates = batch.estimates()                              # x_hat[k] of the members, (M, n)

    X = batch.step_closed(k, y)    # the members hear only each other, perfect channel

Contract (what makes the batched simulator equal to the per-agent one):

* The per-agent ``step`` stays the one definition of the maths. A batch holds the same
  state as its members (stacked) and applies the same equations to all of them at once,
  either with the very same floating-point operations (bit-identical) or with stacked
  matrix products whose sums run in another order (equal within 1e-12 relative); each
  algorithm's docs say which.
* :meth:`Batch.step` takes exactly what each member's ``step`` would take and returns
  exactly its payloads (list, member order).
* :meth:`Batch.step_closed` is round ``k`` of a team made of the members alone over a
  perfect channel: member ``m``'s inbox holds, from every in-neighbour, its payload of
  round ``k - 1`` (nothing at ``k = 0``); ``y`` is the plant's whole stacked measurement
  of round ``k`` and :meth:`Batchable.batch` was told each member's rows. The default
  builds those inboxes and calls :meth:`step`.
* After every step each member's diagnostics (``diagnostics()``, ``flagged``) read as
  after its own ``step`` (the simulator reads them from the members every round, or from
  :meth:`Batch.diagnostics` all at once where :attr:`Batch.diagnostic_rows` is set).
* :meth:`Batch.sync` writes the stacked state back into the member objects (the
  simulator calls it after the last round, so ``est.estimate`` reads the end state).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Hashable, Sequence
from typing import Any

import numpy as np

from .base import Inbox, Received


class Batch(ABC):
    """Several agents of one estimator class stepped together (see the module docstring).

    Parameters
    ----------
    members : the agents' estimator objects (the batch steps them; do not step them apart)
    in_neighbours : per member, the member-local indices of its in-neighbours (what
        :meth:`step_closed` delivers); the agent indices of the inboxes are ``agents``
    agents : per member, its agent index (the sender index in the others' inboxes)
    rows : per member, the rows of the plant's stacked ``y`` it reads (static sensors),
        or None when a member moves (then :meth:`step_closed` is not available)
    """

    def __init__(self, members: Sequence[Any], *, in_neighbours: Sequence[Sequence[int]], agents: Sequence[int],
                 rows: Sequence[np.ndarray] | None = None) -> None:
        self.members = list(members)
        self.in_neighbours = [list(nb) for nb in in_neighbours]
        self.agents = list(agents)
        self.rows = None if rows is None else [np.asarray(r, dtype=int) for r in rows]
        self._last: list[np.ndarray] | None = None

    @abstractmethod
    def step(self, k: int, measurements: Sequence[np.ndarray | None], inboxes: Sequence[Inbox]) -> list[np.ndarray]:
        """Round ``k`` of every member; returns their payloads (member order)."""

    @abstractmethod
    def estimates(self) -> np.ndarray | list[np.ndarray]:
        """The members' estimates ``x_hat[k]`` after the last step: an ``(M, n)`` array, or
        a list of ``M`` read-only ``(n,)`` arrays (no stacked copy for large teams)."""

    def step_closed(self, k: int, y: np.ndarray) -> np.ndarray:
        """Round ``k`` of the members alone over a perfect channel; returns the ``(M, n)`` estimates."""
        if self.rows is None:
            raise ValueError("step_closed needs every member's measurement rows (static sensors)")
        last = self._last
        inboxes = [{} if last is None else
                   {self.agents[j]: Received(self.agents[j], k - 1, last[j]) for j in nb} for nb in self.in_neighbours]
        self._last = self.step(k, [y[r] for r in self.rows], inboxes)
        got = self.estimates()
        return np.stack(got) if isinstance(got, list) else got

    #: whether :meth:`diagnostics` reads every member's diagnostics at once
    diagnostic_rows = False

    def diagnostics(self) -> tuple[dict[str, np.ndarray], np.ndarray | None] | None:
        """Every member's ``diagnostics()`` as ``name -> (M,)`` rows and ``flagged`` as an
        ``(M,)`` bool array (None: no flags), equal to what each member reads after the last
        step; None when :attr:`diagnostic_rows` is False (then each member is read)."""
        return None

    def sync(self) -> None:
        """Write the stacked state back into the member objects (default: nothing to write)."""


class Batchable(ABC):
    """Declares that an estimator class can be stepped in a :class:`Batch`.

    Estimators with equal :meth:`batch_key` go into one batch (e.g. LFRE agents with the
    same fusion rule and ``f``); :meth:`batch` builds it. A key of None: this estimator steps
    on its own (e.g. where its stacked product would cost more than the per-agent ones).
    """

    def batch_key(self) -> Hashable | None:
        return type(self)

    @classmethod
    @abstractmethod
    def batch(cls, members: Sequence[Any], *, in_neighbours: Sequence[Sequence[int]], agents: Sequence[int],
              rows: Sequence[np.ndarray] | None = None) -> Batch:
        """A :class:`Batch` over ``members`` (estimators of this class with one key)."""
