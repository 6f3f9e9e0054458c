"""The channel model: what happens to a message on a directed link ``j -> i``.

Decided receiver-side, so the simulator's in-memory delivery and the Zenoh driver share
one implementation: every message that physically arrives is passed to
:meth:`Channel.fate`, which says in which round it becomes visible to the receiver, or
that it is lost. The decision is a pure function of ``(seed, sender, receiver, stamp)``:

* erasure: Bernoulli with probability ``drop_p`` (i.i.d. per link and round);
* delay: uniform integer in ``0..delay_max`` extra rounds; a message stamped ``k`` is
  visible from round ``k + 1 + delay``;
* deterministic loss windows: during rounds ``[r0, r1]`` the listed links drop
  everything (to write the bounded-loss patterns of Mitra et al., Assumption 2).

Draws come in blocks of 1024 rounds per link from ``default_rng([seed, 4, j, i, block])``,
so the outcome does not depend on the order in which links are queried.
"""

from __future__ import annotations

from array import array
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np

_BLOCK = 1024  # rounds per block of draws (fate() indexes with >> 10 and & 1023)
_STREAM = 4


@dataclass
class LinkCounters:
    """Per-link counters: sent, delivered, dropped, late (delayed), rejected (bad bytes)."""

    sent: int = 0
    delivered: int = 0
    dropped: int = 0
    late: int = 0
    rejected: int = 0

    def as_dict(self) -> dict[str, int]:
        return {"sent": self.sent, "delivered": self.delivered, "dropped": self.dropped,
                "late": self.late, "rejected": self.rejected}


@dataclass
class Channel:
    """Erasure / delay / loss-window model for every directed link (ids are agent ids)."""

    seed: int
    drop_p: float = 0.0
    delay_max: int = 0
    #: (first round, last round, links (sender, receiver)) during which links drop all
    losses: list[tuple[int, int, frozenset[tuple[int, int]]]] = field(default_factory=list)
    _blocks: dict[tuple[int, int], tuple[int, Sequence[int]]] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        self.perfect = self.drop_p == 0.0 and self.delay_max == 0 and not self.losses

    def _block(self, sender: int, receiver: int, b: int) -> Sequence[int]:
        """Extra delays of rounds ``b*1024 .. b*1024+1023`` on one link (-1: erased)."""
        u = np.random.default_rng([self.seed, _STREAM, sender, receiver, b]).random((_BLOCK, 2))
        delay = (u[:, 1] * (self.delay_max + 1)).astype(np.int64) if self.delay_max else np.zeros(_BLOCK, dtype=np.int64)
        if self.drop_p:
            delay[u[:, 0] < self.drop_p] = -1
        # a compact array of machine ints (indexing gives a Python int, as a list does):
        # 8 k links of a 1,024-agent team held 64 MB of lists
        return array("b" if self.delay_max < 2**7 else "q", delay.tolist())

    def prepare(self, links: Iterable[tuple[int, int]]) -> None:
        """Draw the first block of each ``(sender, receiver)`` link now: a process calls
        this before its first round, which then does not pay for the draws (nor, in a
        process whose parent did not import it, for importing ``numpy.random``: 15 to 40 ms
        of CPU; the runtime's fork server preloads it)."""
        if self.perfect:
            return
        for sender, receiver in links:
            if (sender, receiver) not in self._blocks:
                self._blocks[(sender, receiver)] = (0, self._block(sender, receiver, 0))

    def fate(self, sender: int, receiver: int, stamp: int) -> int | None:
        """Round from which the message is visible to ``receiver``, or None if lost."""
        if self.perfect:
            return stamp + 1
        if stamp < 0:
            return None
        for r0, r1, links in self.losses:
            if r0 <= stamp <= r1 and (sender, receiver) in links:
                return None
        b = stamp >> 10
        cached = self._blocks.get((sender, receiver))
        if cached is None or cached[0] != b:
            cached = (b, self._block(sender, receiver, b))
            self._blocks[(sender, receiver)] = cached
        extra = cached[1][stamp & 1023]
        return None if extra < 0 else stamp + 1 + extra


def loss_windows(spec: Iterable[tuple[tuple[int, int], Iterable[tuple[int, int]]]]) -> list:
    """Normalise ``[((r0, r1), [(from, to), ...]), ...]`` into :attr:`Channel.losses`."""
    return [(int(r0), int(r1), frozenset((int(a), int(b)) for a, b in links)) for (r0, r1), links in spec]
