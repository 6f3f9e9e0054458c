"""The round logic of one agent, shared by both drivers (DESIGN.md, "One round").

An :class:`AgentNode` owns its estimator, its receiver-side view of the channel and its
inbox. A driver hands it every message that physically reaches it (:meth:`receive`) and
calls :meth:`run_round` once per round; the node makes messages visible in the round the
channel model says (:class:`transport.channel.Channel`), keeps the newest message of each
in-neighbour, steps the estimator and returns the outgoing payload stamped ``k``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from estimation.base import EstimatePayload, Received
from transport.channel import Channel, LinkCounters

from .rounds import count_fate


class AgentNode:
    """One agent's round logic.

    Parameters
    ----------
    agent_id : int  the 1-based id used on the network and in outputs
    estimator : an :class:`estimation.base.Estimator`
    channel : the shared :class:`Channel` model
    in_neighbours : ids this agent accepts estimates from (others are rejected, counted)
    """

    def __init__(self, agent_id: int, estimator: Any, channel: Channel, in_neighbours: list[int],
                 *, index_of: dict[int, int] | None = None, out_neighbours: list[int] | None = None) -> None:
        self.id = agent_id
        self.estimator = estimator
        self.channel = channel
        #: agent id -> index (the estimation layer numbers agents 0..N-1, as the graph does)
        self.index_of = index_of if index_of is not None else {j: j for j in in_neighbours}
        self.out_neighbours = list(out_neighbours or [])
        #: what an omniscient adversary may read (set by the driver for Byzantine agents)
        self.view: Any = None
        #: the estimate itself is the payload (no separate ``estimator.estimate`` call)
        self.payload_is_estimate = isinstance(estimator, EstimatePayload) and bool(estimator.payload_is_estimate)
        self.inbox: dict[int, Received] = {}
        #: indices of the in-neighbours whose message became visible in the current round
        self.arrived: set[int] = set()
        self._pending: dict[int, list[Received]] = {}
        self.links: dict[int, LinkCounters] = {j: LinkCounters() for j in in_neighbours}
        self.round: int | None = None
        self._perfect = channel.perfect
        #: Byzantine middleware (None for an honest agent): ``strategy(k, estimate, node)``
        self.strategy: Any = None
        #: the delivery record (:class:`agents.deliveries.DeliveryWriter`; None: not recorded)
        self.tap: Any = None

    def receive(self, sender: int, stamp: int, value: np.ndarray) -> None:
        """A message from ``sender`` stamped ``stamp`` reached this agent."""
        c = self.links.get(sender)
        if c is None:  # not an in-neighbour: not ours to use
            return
        c.sent += 1
        when = stamp + 1 if self._perfect else self.channel.fate(sender, self.id, stamp)
        count_fate(c, when, stamp)
        if when is None:
            return
        self._pending.setdefault(when, []).append(Received(self.index_of[sender], stamp, value))

    def reject(self, sender: int) -> None:
        """Count a message from ``sender`` that failed validation."""
        c = self.links.get(sender)
        if c is not None:
            c.rejected += 1

    def _release(self, k: int) -> None:
        arrived = self.arrived
        arrived.clear()
        for when in [w for w in self._pending if w <= k]:
            for r in self._pending.pop(when):
                arrived.add(r.sender)
                old = self.inbox.get(r.sender)
                if old is None or r.stamp > old.stamp:
                    self.inbox[r.sender] = r

    def run_round(self, k: int, measurement: np.ndarray | None) -> np.ndarray:
        """Run round ``k``; returns the payload the estimator publishes, stamped ``k``.

        The agent's estimate of ``x[k]`` (what the monitor records) is :meth:`estimate`.
        What goes on the network is :meth:`publish`'s business. The inbox is keyed by the
        in-neighbours' agent *indices* (``Received.sender`` likewise).
        """
        inbox = self.open_round(k)
        if self.tap is not None:
            self.tap.stepped(k, measurement, inbox)
        return self.estimator.step(k, measurement, inbox)

    def open_round(self, k: int) -> dict[int, Received]:
        """Make the messages visible in round ``k`` visible; returns the inbox of round
        ``k`` (the first half of :meth:`run_round`, for a driver that batches estimators)."""
        if self._pending:
            self._release(k)
        elif self.arrived:
            self.arrived.clear()
        self.round = k
        return self.inbox

    def estimate(self, payload: np.ndarray) -> np.ndarray:
        """The estimate of ``x[k]`` after :meth:`run_round` returned ``payload``."""
        return payload if self.payload_is_estimate else self.estimator.estimate

    def pending_from_others(self, k: int, exclude: int) -> list[Received]:
        """Messages stamped ``k`` that will be visible in round ``k + 1``, other than
        ``exclude``'s (the omniscient adversary's view of this receiver)."""
        ex = self.index_of.get(exclude)
        return [r for r in self._pending.get(k + 1, []) if r.stamp == k and r.sender != ex]

    def publish(self, k: int, estimate: np.ndarray) -> np.ndarray | dict[int, np.ndarray | None]:
        """What this agent sends in round ``k``.

        Returns the estimate itself for a broadcast to every out-neighbour (an honest
        agent), or a mapping ``receiver id -> payload`` for addressed messages, where a
        missing receiver or ``None`` means nothing is sent to it (a Byzantine strategy may
        equivocate or omit). Both drivers call this after :meth:`run_round`.
        """
        if self.strategy is None:
            return estimate
        msg = self.strategy(k, estimate, self)
        if self.tap is not None:
            self.tap.sent(k, msg, self.out_neighbours)
        return msg
