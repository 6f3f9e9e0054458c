"""When an agent that joined a running team reconnects (:class:`RejoinChecks`, mixed into
:class:`~agents.net.agent.AgentProcess`): the plant not heard after asking to join, or a
realtime member's measurements stopped."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

from .config import RECONNECTS, UNHEARD_S

if TYPE_CHECKING:
    from transport.zenoh_bus import Bus

    from .config import RunConfig


class RejoinChecks:
    """The reconnect predicates of an agent process (they read the process's fields; the
    tests call them as ``AgentProcess._plant_unheard(namespace)``)."""

    rejoin: bool
    running_team: bool
    member: bool
    stop: Any
    _first_ready: float
    _last_loc: float
    reconnects: int
    alive: set[tuple[str, int]]
    bus: Bus
    cfg: RunConfig

    def _plant_unheard(self) -> bool:
        """A rejoining agent asked to join :data:`UNHEARD_S` ago and nothing came on its
        measurement key (no ``running_team`` yet), though the plant's token is there (a
        running team's plant publishes there every round, to members and others). Seen 4 times in 32 scripted rejoins of a realtime
        team: the plant's droppable (``CongestionControl.DROP``) messages never reached the
        restarted process, though the plant admitted it and its blocking messages (its
        token) did; with blocking measurements 25 rejoins in 25 got them. A new session
        gets them, as restarting the process did. Agents that share a process share its
        session: each waits :data:`UNHEARD_S` after the last reconnect of any of them."""
        return (self.rejoin and not self.running_team and self.stop is None and bool(self._first_ready)
                and RejoinChecks._unheard_for(self, self._first_ready, UNHEARD_S))

    def _unheard_for(self, since: float, wait: float) -> bool:
        """The plant's token is there, this process may still reconnect, and ``wait``
        seconds have gone by since ``since`` and since the process's last reconnect. (Called
        as ``RejoinChecks._unheard_for(self, ...)``: the tests give the predicates a plain
        namespace for ``self``.)"""
        return (self.reconnects < RECONNECTS and ("plant", 0) in self.alive
                and time.monotonic() - max(since, self.bus.reconnected_at) >= wait)

    def _measurements_stopped(self) -> bool:
        """A member of a realtime team whose measurements stopped twice :data:`UNHEARD_S` ago
        (or 10 rounds, at a slow rate) though the plant's token is there: the plant publishes
        on this agent's key every round. Twice: a cable pulled for 3 s (tests/deploy) is an
        outage that ends by itself, and a reconnect costs the agent its warm-up again.

        Seen in scripted restarts of agent 3 and the monitor of a loaded realtime team (6 of
        78 with two or three busy processes beside it, 19 of 74 with the test suite): agents
        that had run all along stopped getting measurements for good, used no CPU and so
        sent nothing (a restarted monitor heard none of them, however often it reconnected),
        while a fresh process joining the team saw the plant publish on their keys. The
        plant's measurements are droppable in realtime (``CongestionControl.DROP``) and its
        socket toward those agents held nothing to send: Zenoh's pipeline toward them dropped
        every one (eclipse-zenoh/zenoh#1738 describes a publisher stuck that way). A new
        session is a new link."""
        rate = self.cfg.rate or 1.0
        return (self.member and self.cfg.mode == "realtime" and self.stop is None and self._last_loc > 0.0
                and RejoinChecks._unheard_for(self, self._last_loc, max(2 * UNHEARD_S, 10.0 / rate)))
