"""The networked runtime (``rse run``): plant, monitor and agents as asyncio processes
talking over a :class:`transport.zenoh_bus.Bus` (Zenoh, or in memory for tests).

* :mod:`agents.net.roles`: the three roles as async functions, reusing the round logic
  of the in-process simulator (:class:`~agents.node.AgentNode`,
  :class:`~agents.plant.PlantRole`, :class:`~agents.monitor.Monitor`);
* :mod:`agents.net.launcher`: starts one process per role, supervises them, stops them.

See ``docs/networked-runtime.md`` for the protocol and the commands.
"""
