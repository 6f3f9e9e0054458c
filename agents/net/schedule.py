"""How an agent process schedules its rounds: one strategy per mode of ``rse run``.

* :class:`Lockstep`: round ``k`` runs once the plant's measurement of ``k`` is in and every
  message it waits for has arrived (or the deadline passed); no round is skipped, and the
  estimates equal the simulator's. The measurement wakes the agent; its in-neighbours'
  estimates wait in polled subscriptions, and a done report may carry the estimate.
* :class:`Realtime`: the plant ticks on the wall clock; the agent runs the newest round it
  has a measurement for and skips the older ones (their count is reported); an estimate a
  neighbour cannot take now is dropped for it alone; a member that stops hearing the
  plant reconnects.

The agent (:class:`agents.net.agent.AgentProcess`) asks its strategy, never ``cfg.mode``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from .config import UNHEARD_S

if TYPE_CHECKING:
    from .agent import AgentProcess

__all__ = ["Lockstep", "Realtime", "schedule_for"]


class Lockstep:
    """Rounds in order, each when its messages are in (or its deadline passed)."""

    name = "lockstep"
    merges = True  # done reports may carry the estimate (agents.net.slices.merges)
    polled = True  # in-neighbours' estimates wait in polled subscriptions; the measurement wakes the agent
    droppable = False  # the transport never drops an estimate
    holds_for_view = True  # an omniscient adversary publishes once its view is complete

    @staticmethod
    def lazy(loc_key: str) -> Callable[[Any], bool] | None:
        # what the next round needs comes before its measurement, which wakes the agent
        return lambda item: item[0] != loc_key and type(item[1]) is bytes

    @staticmethod
    def next_round(agent: AgentProcess, now: float) -> tuple[int, Any] | None:
        """The oldest measured round once its messages are in; None: wait (a wake-up is set)."""
        k = min(agent.meas)
        y, wait, t_arr = agent.meas[k]
        if not agent._arrived_all(wait):
            agent.wake_at(1)  # each message may be the one missing
            agent._poll_later()
            if now < t_arr + agent.cfg.deadline:
                agent._tick_at(t_arr + agent.cfg.deadline)
                return None
            agent.went_on_without(k)
        del agent.meas[k]
        return k, y

    @staticmethod
    def waits_before_stop(agent: AgentProcess, now: float) -> bool:
        """At the plant's stop: wait for the last round's messages (until the deadline)."""
        if agent.stop is None:
            return False
        _, wait, t_arr = agent.stop
        if agent.member and not agent._arrived_all(wait) and now < t_arr + agent.cfg.deadline:
            agent.wake_at(1)
            agent._poll_later()
            agent._tick_at(t_arr + agent.cfg.deadline)
            return True
        return False

    @staticmethod
    async def idle(agent: AgentProcess) -> float | None:
        """A member between rounds: how long to wait for a change (None: until one comes)."""
        return None


class Realtime:
    """The newest measured round now; older ones are skipped."""

    name = "realtime"
    merges = False
    polled = False
    droppable = True  # an estimate a neighbour cannot take now is dropped for it alone
    holds_for_view = False

    @staticmethod
    def lazy(loc_key: str) -> Callable[[Any], bool] | None:
        return None

    @staticmethod
    def next_round(agent: AgentProcess, now: float) -> tuple[int, Any] | None:
        k = max(agent.meas)
        y = agent.meas[k][0]
        agent.skipped += len(agent.meas) - 1
        agent.meas.clear()
        return k, y

    @staticmethod
    def waits_before_stop(agent: AgentProcess, now: float) -> bool:
        return False

    @staticmethod
    async def idle(agent: AgentProcess) -> float | None:
        if agent._measurements_stopped():
            import time

            gap = time.monotonic() - agent._last_loc
            await agent.reconnect(f"no measurement from the plant for {gap:.1f} s")
        return UNHEARD_S / 4


def schedule_for(mode: str) -> type[Lockstep] | type[Realtime]:
    """The strategy of ``mode`` (``RunConfig.mode``)."""
    return Lockstep if mode == "lockstep" else Realtime
