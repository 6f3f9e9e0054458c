"""Pieces shared by the builder and the algorithm plugins: seeded streams, the plant as
built, and the conditions ``rse check`` reports."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol, TypeVar

import numpy as np

from estimation.lti import ContinuousLTI

if TYPE_CHECKING:
    from scenarios.build import Experiment

# Stream tags for seeded generators: every random quantity has its own stream derived
# from (run seed, tag, index), so both drivers draw identical numbers in any order.
STREAM_PLANT_X0 = 1
STREAM_AGENT_X0 = 2
STREAM_SENSOR_ATTACK = 3
STREAM_CHANNEL = 4  # used by transport.channel
STREAM_BYZANTINE = 5  # used by transport.byzantine
STREAM_MAP = 6
STREAM_GRAPH = 7
STREAM_PLANT_NOISE = 8
STREAM_ESTIMATOR = 9


def rng_for(seed: int, tag: int, *index: int) -> np.random.Generator:
    """A generator for one stream (see the stream tags above)."""
    return np.random.default_rng([seed, tag, *index])


class PlantStepper(Protocol):
    """A plant that is not a plain LTI system (nonlinear, noisy): the plant role calls
    ``measure(k, x)`` for ``y[k]`` (before sensor attacks) and ``advance(k, x)`` for
    ``x[k+1]``. Both are called once per round, in increasing round order."""

    def measure(self, k: int, x: np.ndarray) -> np.ndarray: ...

    def advance(self, k: int, x: np.ndarray) -> np.ndarray: ...


@dataclass
class PlantModel:
    """The plant as built from ``[plant]`` and ``[[sensors]]``.

    ``lti`` carries ``A``, ``B`` and the sensor banks (for a nonlinear plant: its linear
    part and output rows). ``stepper`` replaces the exact LTI step when given.
    """

    lti: ContinuousLTI
    discrete: bool
    positions: np.ndarray | None = None
    x0: np.ndarray | None = None  # the model's own initial state
    blocks: dict[str, np.ndarray] = field(default_factory=dict)
    cell_of_location: np.ndarray | None = None
    stepper: PlantStepper | None = None
    info: dict[str, Any] = field(default_factory=dict)  # model data plugins need later
    substeps: int = 1  # integration steps of the plant per round (the size budget's time estimate)


@dataclass(frozen=True)
class ByzantineSpec:
    """A Byzantine agent's strategy as the scenario specifies it (``[[attacks]]`` with
    ``target = "agent"``), times converted to rounds. The runtime builds the middleware
    from it (``agents.middleware.byzantine_strategy``); the fields are those of
    ``transport.byzantine.Strategy``."""

    kind: str
    start: int = 0
    stop: int | None = None
    targets: frozenset[int] | None = None  # receivers affected (None: all)
    value: float = 0.0
    scale: float = 1e6
    shift: int = 1
    lag: int = 10
    payload: str = "huge"
    seed: int = 0
    agent: int = 0


S = TypeVar("S")

#: the Byzantine strategies of the runtime (transport.byzantine.KINDS and the schema's
#: agent attack kinds; a test keeps the three equal): what a ThreatModel may name
STRATEGIES = ("constant", "huge", "omission", "equivocation", "false_stamp", "replay", "crash", "cancellation")


def estimator_section(exp: Experiment, cls: type[S]) -> S:
    """The scenario's ``[estimator]`` table as the plugin's own section type ``cls`` (the
    schema types it as the union of every plugin's); a plugin asked for another algorithm's
    experiment is a bug, said as a ``TypeError``."""
    est = exp.scenario.estimator
    if not isinstance(est, cls):
        raise TypeError(f"expected an [estimator] section of type {cls.__name__}, got {type(est).__name__}")
    return est


@dataclass(frozen=True)
class ThreatModel:
    """What an algorithm is proven to tolerate: a plugin's optional ``THREAT_MODEL``.

    ``rse redteam`` searches inside it (and one step outside with ``--beyond``):

    * ``sensors``: the ``[estimator]`` key whose value is how many sensor banks may be
      attacked (``None``: the algorithm trusts its sensors);
    * ``agents``: the ``[estimator]`` key whose value is how many Byzantine agents any
      neighbourhood may hold (``None``: every agent is regular);
    * ``strategies``: the Byzantine strategies the proof covers (names of
      ``transport.byzantine``; ``None``: all of them).

    Erasures up to the scenario's ``network.channel.drop_p`` are searched for every algorithm.
    """

    sensors: str | None = None
    agents: str | None = None
    strategies: tuple[str, ...] | None = None


@dataclass
class Condition:
    """One paper condition as reported by ``rse check``."""

    name: str
    holds: bool | None  # None: a figure, not a pass/fail condition
    detail: str


def checked_design(exp: Experiment, design: Any, label: str) -> tuple[Any, list[Condition]]:
    """The design ``rse check`` reports on: the experiment's own, else ``design(exp,
    check=True)``. A design that fails is one failed condition named ``label``:
    returns ``(None, [that condition])``, else ``(design, [])``."""
    from estimation.errors import ScenarioError

    if exp.design is not None:
        return exp.design, []
    try:
        return design(exp, check=True), []
    except ScenarioError as exc:
        return None, [Condition(label, False, exc.detail)]
