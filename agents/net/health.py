"""An agent process's realtime health (:class:`LinkHealth`): per in-link, the age of each
estimate when a round uses it and the estimates that came after the round meant to use
them had run; per out-link, the estimates published.

The **age** of an estimate stamped ``s`` is measured from the start of round ``s`` (the
arrival here of the plant's measurement of round ``s``: every process reads the round's
start on its own clock, so no clocks need to agree across hosts) to the start of the
round that takes it in (:meth:`LinkHealth.used`). A message of a round whose measurement
did not reach this agent (it skipped or missed that round) is dated from the plant's
period before the newest round whose start is known. Ages are kept in a fixed histogram
of :data:`EDGES` (log-spaced, 4% wide bins from 0.1 ms to 100 s): bounded memory
however long the run, percentiles read at a bin's upper edge.

An estimate stamped ``s`` is meant for the receiver's round ``s + 1``; one that arrives
after that round has run here is **late** (it can only be taken by a later round).

A **stall**: a live in-neighbour (its token present) from which nothing arrived for
:data:`STALL_S` seconds and at least :data:`STALL_ROUNDS` rounds (:meth:`LinkHealth.stalled`);
each silence is counted once and logged, and ends with the next estimate from it. (A
frozen or cut-off neighbour stalls its links; a transmission queue stuck dropping did,
before the droppable messages had a priority of their own: docs/networked-runtime.md.)

The monitor joins these figures with the receivers' link counters into ``summary.json``'s
``health`` (:func:`agents.health.health_section`).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable

import numpy as np

__all__ = ["EDGES", "LinkHealth", "percentile_ms"]

STALL_S, STALL_ROUNDS = 1.0, 10
EDGES = np.geomspace(1e-4, 100.0, 353)  # seconds: bin b holds ages in [EDGES[b-1], EDGES[b])
_KEEP = 4096  # the round starts kept (older rounds are dated from the newest)


def percentile_ms(hist: np.ndarray, q: float) -> float | None:
    """The ``q``-th percentile (0..100) of a histogram over :data:`EDGES` (ms, the bin's
    upper edge; None: empty)."""
    n = int(hist.sum())
    if n == 0:
        return None
    b = int(np.searchsorted(np.cumsum(hist), q / 100.0 * n, side="left"))
    edge = EDGES[min(b, len(EDGES) - 1)]
    return round(float(edge) * 1e3, 3)


class LinkHealth:
    """Ages and lateness of the estimates one agent takes, and what it publishes."""

    def __init__(self, in_ids: list[int], period: float) -> None:
        self.period = period
        self.hist = {j: np.zeros(len(EDGES) + 1, dtype=np.int64) for j in in_ids}
        self.late = dict.fromkeys(in_ids, 0)
        self.published: Counter[int] = Counter()
        self._starts: dict[int, float] = {}
        self._newest = (-1, 0.0)
        self._pending: list[tuple[int, int]] = []
        self.stalls = dict.fromkeys(in_ids, 0)
        self._heard: dict[int, tuple[int, float]] = {}  # in-neighbour -> (round, time) last heard or first checked
        self._silent: set[int] = set()

    def measured(self, k: int, t: float) -> None:
        """The plant's measurement of round ``k`` arrived at ``t`` (time.monotonic)."""
        self._starts[k] = t
        if k > self._newest[0]:
            self._newest = (k, t)
        if len(self._starts) > _KEEP:
            for old in sorted(self._starts)[: len(self._starts) - _KEEP // 2]:
                del self._starts[old]

    def arrived(self, j: int, stamp: int, last: int) -> None:
        """An estimate of in-neighbour ``j`` stamped ``stamp`` arrived; ``last``: the
        newest round this agent has run."""
        if j not in self.hist:
            return
        if last >= stamp + 1:
            self.late[j] += 1
        self._heard.pop(j, None)
        self._silent.discard(j)
        if len(self._pending) < 65536:
            self._pending.append((j, stamp))

    def used(self, now: float) -> None:
        """A round starts at ``now``: it takes in every estimate arrived since the last."""
        if not self._pending:
            return
        k_new, t_new = self._newest
        for j, s in self._pending:
            start = self._starts.get(s)
            if start is None:
                start = t_new - (k_new - s) * self.period
            self.hist[j][int(np.searchsorted(EDGES, max(now - start, 0.0), side="right"))] += 1
        self._pending.clear()

    def stalled(self, k: int, now: float, live: Callable[[int], bool]) -> list[int]:
        """The in-neighbours that are ``live`` (their token present) and newly silent at round ``k``: nothing from them for
        :data:`STALL_S` seconds and :data:`STALL_ROUNDS` rounds (each silence counted once)."""
        out = []
        for j in self.hist:
            if j in self._silent or not live(j):
                continue
            since = self._heard.setdefault(j, (k, now))
            if k - since[0] >= STALL_ROUNDS and now - since[1] >= STALL_S:
                self._silent.add(j)
                self.stalls[j] += 1
                out.append(j)
        return out

    def sent(self, receivers: list[int]) -> None:
        """One estimate went out to each of ``receivers``."""
        self.published.update(receivers)

    def ages_rows(self) -> np.ndarray:
        """Rows ``[sender, age p50 (ms), age p99 (ms), estimates aged, late, stalls]`` (-1:
        none aged; the wire carries no NaN)."""
        rows = []
        for j, h in self.hist.items():
            p50, p99 = percentile_ms(h, 50), percentile_ms(h, 99)
            rows.append([j, -1.0 if p50 is None else p50, -1.0 if p99 is None else p99, int(h.sum()), self.late[j],
                         self.stalls[j]])
        return np.array(rows, dtype=float).reshape(-1, 6)

    def out_rows(self) -> np.ndarray:
        """Rows ``[receiver, estimates published to it]``."""
        return np.array(sorted(self.published.items()), dtype=float).reshape(-1, 2)
