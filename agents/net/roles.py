"""The three roles of the networked runtime, gathered (one module each:
:mod:`agents.net.plant`, :mod:`agents.net.agent`, :mod:`agents.net.monitor`; the protocol
and the pieces they share: :mod:`agents.net.protocol`; the omniscient adversary's view:
:mod:`agents.net.view`), and the whole team over an in-memory bus for tests.

A process that runs one role imports that role's module, not this one.
"""

from __future__ import annotations

import asyncio
import functools
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from transport.keys import Keys

from .agent import AgentProcess, run_agent, run_agent_slice
from .config import MODES, RunConfig
from .figures import maxrss_mb
from .monitor import MonitorProcess, MonitorResult, run_monitor
from .plant import PlantProcess, run_plant
from .protocol import Role
from .slices import AgentSlice, agent_slices, read_slice, write_slices
from .view import NetworkView, ViewTopology, reads_view, simulator_order, view_topology
from .wire import Rejects, Wire, _msg, diagnostics_from_meta, diagnostics_meta, who_name

if TYPE_CHECKING:
    from scenarios.build import Experiment
    from transport.zenoh_bus import InMemoryBus

__all__ = ["MODES", "AgentProcess", "AgentSlice", "ViewTopology", "agent_slices", "read_slice", "run_agent_slice",
           "view_topology", "write_slices", "MonitorProcess", "MonitorResult", "NetworkView", "PlantProcess", "Rejects", "Role",
           "RunConfig", "Wire", "_msg", "diagnostics_from_meta", "diagnostics_meta", "maxrss_mb", "reads_view",
           "run_agent", "run_monitor", "run_plant", "run_team_in_memory", "simulator_order", "who_name"]


async def run_team_in_memory(exp: Experiment, cfg: RunConfig, *, run_id: str = "mem", out_dir: Path | None = None,
                             node_hook: Callable[[Any], None] | None = None) -> MonitorResult:
    """Every role as a task of this event loop over an :class:`~transport.zenoh_bus.InMemoryHub`
    (for tests: the same protocol without processes)."""
    from transport.zenoh_bus import InMemoryHub

    hub = InMemoryHub()
    keys = Keys(run_id)
    buses = [hub.bus() for _ in range(exp.N + 2)]
    try:
        mon = asyncio.ensure_future(run_monitor(exp, buses[0], keys, cfg, out_dir=out_dir))
        agents = [asyncio.ensure_future(run_agent_slice(part, buses[2 + i], keys, cfg, node_hook=node_hook))
                  for i, part in enumerate(agent_slices(exp))]
        for task, bus in zip(agents, buses[2:]):  # an agent that ends leaves, as its process would
            task.add_done_callback(functools.partial(_leave, bus))
        plant = asyncio.ensure_future(run_plant(exp, buses[1], keys, cfg))
        await asyncio.gather(plant, *agents)
        return await mon
    finally:
        for b in buses:
            b.close()


def _leave(bus: InMemoryBus, _task: asyncio.Future[Any]) -> None:
    """An agent task that ended leaves the hub, as its process would."""
    bus.close()
