"""The runtime's middleware built from the experiment's specifications.

The built experiment (:class:`scenarios.build.Experiment`) holds what the scenario
specifies; both drivers (:mod:`agents.simulate`, :mod:`agents.net`) build the objects that
act at run time here, so they build them alike: the channel model, the agents' nodes and
their Byzantine strategies.
"""

from __future__ import annotations

from dataclasses import asdict

from scenarios.build import Experiment
from transport.byzantine import Strategy
from transport.channel import Channel, loss_windows

from .node import AgentNode


def byzantine_strategy(exp: Experiment, i: int) -> Strategy | None:
    """A fresh Byzantine strategy for agent index ``i`` (None for an honest agent).

    Fresh on every call: a strategy keeps state (its RNG, its history of estimates).
    """
    spec = exp.byzantine_specs.get(i)
    return None if spec is None else Strategy(**asdict(spec))


def make_channel(exp: Experiment) -> Channel:
    """The scenario's channel model, seeded with the run's seed."""
    ch = exp.scenario.network.channel
    return Channel(
        seed=exp.seed,
        drop_p=ch.drop_p,
        delay_max=ch.delay_max,
        losses=loss_windows((w.rounds, w.links) for w in ch.losses),
    )


def make_nodes(exp: Experiment, channel: Channel) -> list[AgentNode]:
    """Every agent's fresh :class:`~agents.node.AgentNode` (estimator, in- and
    out-neighbours, Byzantine strategy), in index order."""
    index_of = {aid: i for i, aid in enumerate(exp.agent_ids)}
    nodes = []
    for i, aid in enumerate(exp.agent_ids):
        node = AgentNode(aid, exp.make_estimator(i), channel, [exp.agent_ids[j] for j in exp.in_neighbours(i)],
                         index_of=index_of, out_neighbours=[exp.agent_ids[j] for j in exp.out_neighbours(i)])
        node.strategy = byzantine_strategy(exp, i)  # fresh: a strategy keeps state (its RNG, history)
        nodes.append(node)
    return nodes
