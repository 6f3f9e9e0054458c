"""The runtime's middleware built from the experiment's specifications.

The built experiment (:class:`scenarios.build.Experiment`) holds what the scenario
specifies; both drivers (:mod:`agents.simulate`, :mod:`agents.net`) build the objects that
act at run time here, so they build them alike.
"""

from __future__ import annotations

from dataclasses import asdict

from scenarios.build import Experiment
from transport.byzantine import Strategy


def byzantine_strategy(exp: Experiment, i: int) -> Strategy | None:
    """A fresh Byzantine strategy for agent index ``i`` (None for an honest agent).

    Fresh on every call: a strategy keeps state (its RNG, its history of estimates).
    """
    spec = exp.byzantine_specs.get(i)
    return None if spec is None else Strategy(**asdict(spec))
