"""The networked runtime (``rse run``): plant, monitor and agents as asyncio processes
talking over a :class:`transport.zenoh_bus.Bus` (Zenoh, or in memory for tests).

* :mod:`agents.net.protocol`: the round protocol and the roles' base class;
  :mod:`agents.net.config` (the run configuration), :mod:`agents.net.wire` (schemas, reports,
  rejection counters), :mod:`agents.net.figures` (a process's own figures),
  :mod:`agents.net.schedule` (lockstep and realtime rounds of an agent);
* :mod:`agents.net.plant`, :mod:`agents.net.agent` (with :mod:`agents.net.view`, the
  omniscient adversary's view), :mod:`agents.net.monitor`: one module per role, each an
  async function reusing the round logic of the in-process simulator
  (:class:`~agents.plant.PlantRole`, :class:`~agents.node.AgentNode`,
  :class:`~agents.monitor.Monitor`); :mod:`agents.net.roles` gathers them and runs a team
  over the in-memory bus (tests);
* :mod:`agents.net.launcher`: composes the team plan (:mod:`agents.net.plan`) and the
  supervisor (:mod:`agents.net.supervisor`): one process per role, supervised, stopped.

See ``docs/networked-runtime.md`` for the protocol and the commands.
"""
