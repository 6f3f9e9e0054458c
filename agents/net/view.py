"""The omniscient adversary's view over the network (:class:`NetworkView`): what a
Byzantine agent's out-neighbours will use next round, read off the messages of the run.
Which senders and components count, in which order, is :mod:`agents.omniscient`'s (the
same :meth:`~agents.omniscient.OmniscientView.others_for` as the simulator's view)."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from agents.omniscient import OmniscientView, ViewTopology, reads_view, view_topology
from agents.rounds import round_rank

if TYPE_CHECKING:
    from scenarios.build import Experiment

__all__ = ["NetworkView", "ViewTopology", "reads_view", "simulator_order", "view_topology"]


def simulator_order(exp: Experiment) -> dict[int, int]:
    """Agent id -> rank in the round order (:func:`agents.rounds.round_order`)."""
    return round_rank(exp.agent_ids, exp.byzantine)


class NetworkView(OmniscientView):
    """The omniscient adversary's view over the network.

    The agent process feeds it every estimate message of the run (:meth:`add`, broadcast
    and addressed, decoded strictly) and the done reports of the agents it depends on
    (:meth:`add_done`). A value counts for receiver ``j`` in round ``k`` when it is
    stamped ``k`` and the channel model makes it visible to ``j`` at ``k + 1``
    (:meth:`visible`); the rest is :class:`~agents.omniscient.OmniscientView`'s. In
    lockstep the agent publishes round ``k`` only once :meth:`ready` (every agent the view
    needs has its round-``k`` messages to ``me``'s out-neighbours here, or is not alive)
    or the deadline passed.
    """

    MAX_STORED = 1 << 14

    def __init__(self, topo: ViewTopology, channel: Any) -> None:
        super().__init__(topo)
        self.channel = channel
        self.bcast: dict[tuple[int, int], np.ndarray] = {}
        self.addr: dict[tuple[int, int, int], np.ndarray] = {}
        self.done: dict[int, dict[int, list[tuple[int, int]]]] = {}

    def wants(self, sender: int, receiver: int | None) -> bool:
        """Whether an estimate on ``agent/{sender}/est[/{receiver}]`` feeds the view."""
        if sender not in self.index_of or sender == self.me:
            return False
        return receiver is None or receiver in self.out_set

    def add(self, sender: int, receiver: int | None, stamp: int, value: np.ndarray) -> None:
        if stamp < self.k - 1 or len(self.bcast) + len(self.addr) >= self.MAX_STORED:
            return
        if receiver is None:
            self.bcast[(sender, stamp)] = value
        else:
            self.addr[(sender, receiver, stamp)] = value

    def add_done(self, sender: int, stamp: int, to: list[tuple[int, int]]) -> None:
        if stamp < self.k or stamp > self.k + 64:
            return
        self.done.setdefault(stamp, {})[sender] = [(j, s) for j, s in to if j in self.out_set]

    def ready(self, k: int, alive: Callable[[int], bool]) -> bool:
        """Every agent the view needs reported round ``k`` and its round-``k`` messages to
        my out-neighbours arrived (agents that are not alive are not waited for)."""
        return self.missing(k, alive) == 0

    def missing(self, k: int, alive: Callable[[int], bool]) -> int:
        """How many live agents the view needs have not reported round ``k`` yet, plus one
        if some reported messages have not arrived: at least that many messages are still
        to come before :meth:`ready` (the agent sleeps until then)."""
        done = self.done.get(k, {})
        bcast = self.bcast
        silent, late = 0, 0
        for s in self.needed:
            if (s, k) in bcast:
                # a broadcast round-k estimate: an agent either broadcasts or addresses its
                # messages in a round, never both, so nothing else of s is to come
                continue
            d = done.get(s)
            if d is None:
                if alive(s):
                    silent += 1
                continue
            if not late and any((s, j, st) not in self.addr and (s, st) not in bcast for j, st in d):
                late = 1
        return silent + late

    def visible(self, sender: int, receiver: int, k: int) -> Any:
        v = self.addr.get((sender, receiver, k))
        if v is None:
            v = self.bcast.get((sender, k))
        if v is None or self.channel.fate(sender, receiver, k) != k + 1:
            return None
        return v

    def forget(self, k: int) -> None:
        """Drop what rounds before ``k`` left behind."""
        self.k = k
        for b in [b for b in self.bcast if b[-1] < k]:
            del self.bcast[b]
        for a in [a for a in self.addr if a[-1] < k]:
            del self.addr[a]
        for s in [s for s in self.done if s < k]:
            del self.done[s]
