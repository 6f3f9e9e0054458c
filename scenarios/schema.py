"""The scenario file format (TOML), as pydantic models.

Every table forbids unknown keys. The loader (:mod:`scenarios.loader`) turns validation
errors into messages that name the file, the key path, what was expected and what was
found. The README's "Scenario files" section documents every key; keep them in sync.

Ids in scenario files are 1-based (sensor banks / locations, agents), as in the papers.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Annotated, Literal, Union

from pydantic import Field, model_validator

from . import budget
from .plugins import estimator_sections, plant_model_names
from .types import EstimatorTable, Init, Matrix, Strict, UniformInit, ValueInit, Vector, ZeroInit  # noqa: F401  (the schema's types, importable from here)


# --------------------------------------------------------------------------- [run]
class RunSection(Strict):
    name: str = Field(min_length=1, pattern=r"^[A-Za-z0-9_.-]+$")
    dt: float = Field(gt=0, description="round step in seconds")
    duration: float | None = Field(default=None, gt=0, description="seconds; or give rounds")
    rounds: int | None = Field(default=None, gt=0)
    seed: int = Field(default=0, ge=0, lt=2**63)
    #: a deliberately large run: lifts the documented size limits (scenarios.budget)
    force: bool = False

    @model_validator(mode="after")
    def _one_horizon(self) -> "RunSection":
        if (self.duration is None) == (self.rounds is None):
            raise ValueError("give exactly one of 'duration' (seconds) or 'rounds'")
        keys = "rounds" if self.rounds is not None else "duration / dt"
        budget.check_count("rounds", budget.horizon_rounds(self.dt, self.duration, self.rounds), keys,
                           force=self.force, source=None)
        return self

    @property
    def n_rounds(self) -> int:
        """Number of steps; rounds 0..n_rounds are simulated."""
        if self.rounds is not None:
            return self.rounds
        return int(round(budget.horizon_rounds(self.dt, self.duration, None)))


# --------------------------------------------------------------------------- [plant]
class InputSignal(Strict):
    kind: Literal["zero", "constant", "sine"] = "zero"
    amplitude: float = 0.0
    omega: float = 0.0
    phase: float = 0.0
    offset: float = 0.0


if TYPE_CHECKING:  # the names are known at run time only (plugins add theirs); statically, a str
    PlantModelName = str
else:
    PlantModelName = Literal[("three_inertia", "lti", *plant_model_names())]


class PlantSection(Strict):
    model: PlantModelName
    #: named-model parameters (e.g. J, b, k for three_inertia; K for cells)
    params: dict[str, float] = Field(default_factory=dict)
    #: "continuous": x' = A x + B u (integrated exactly); "discrete": x[k+1] = A x[k] + B u[k]
    time: Literal["continuous", "discrete"] | None = None
    #: explicit matrices for model = "lti"
    A: Matrix | None = None
    B: Matrix | None = None
    state_names: list[str] | None = None
    input: InputSignal = Field(default_factory=InputSignal)
    #: initial state; default: the named model's own (cells, diffusion), else uniform on [-1, 1]
    x0: Init | None = None
    #: named blocks of the state, 1-based state indices, for per-block metrics
    blocks: dict[str, list[int]] = Field(default_factory=dict)
    #: model "grid": a pandapower network ("case14", "case118", ...) or a .json file saved from pandapower
    case: str | None = Field(default=None, min_length=1)
    #: model "grid": PMU buses (1-based); an entry that is a list is one bank (default: one per generator bus)
    pmus: list[int | list[int]] | None = Field(default=None, min_length=1)


# --------------------------------------------------------------------------- [[sensors]]
class SensorBank(Strict):
    name: str | None = None
    C: Matrix
    position: tuple[float, float] | None = None


# --------------------------------------------------------------------------- [[agents]]
class PatrolSpec(Strict):
    """A periodic patrol (Mitra et al. Section 3.2): location ``locations[r]`` is visited at
    rounds ``offsets[r] + q * periods[r]``; commuting in between."""

    locations: list[int] = Field(min_length=1, description="1-based location (sensor bank) ids")
    offsets: list[int]
    periods: list[int]

    @model_validator(mode="after")
    def _lengths(self) -> "PatrolSpec":
        if not len(self.locations) == len(self.offsets) == len(self.periods):
            raise ValueError(f"locations, offsets and periods must have the same length, got {len(self.locations)}, {len(self.offsets)}, {len(self.periods)}")
        return self


class AgentSpec(Strict):
    id: int | None = Field(default=None, ge=1)
    sensors: list[int] | None = Field(default=None, min_length=1, description="1-based sensor bank ids (static agent)")
    patrol: PatrolSpec | None = None

    @model_validator(mode="after")
    def _one(self) -> "AgentSpec":
        if (self.sensors is None) == (self.patrol is None):
            raise ValueError("give exactly one of 'sensors' (a static agent) or 'patrol' (a mobile agent)")
        return self


class CellPatrols(Strict):
    """Generated agents: ``per_cell`` agents per cell, each patrolling every location of its
    own cell with its cell's period (Mitra et al. Section 8.1)."""

    kind: Literal["cell_patrols"]
    per_cell: int = Field(default=4, ge=1)
    #: one period per cell; a shorter list is repeated over the cells (``[14]``: every cell 14)
    periods: list[int] = Field(min_length=1)


# --------------------------------------------------------------------------- [network]
class RingGraph(Strict):
    kind: Literal["ring"]
    directed: bool = False


class CompleteGraph(Strict):
    kind: Literal["complete"]


class EdgesGraph(Strict):
    kind: Literal["edges"]
    edges: list[tuple[int, int]] = Field(description="1-based agent id pairs (from, to)")
    directed: bool = False


Ids = int | list[int]


class CellsGraph(Strict):
    """Mitra et al. Fig. 5: every agent talks with every agent of the adjacent cells (cells
    on a ring). ``remove`` / ``add``: ``[from, to]`` pairs, each side an id or a list of ids,
    removed / added in both directions unless ``directed``."""

    kind: Literal["cells"]
    intra: bool = False
    remove: list[tuple[Ids, Ids]] = Field(default_factory=list)
    add: list[tuple[Ids, Ids]] = Field(default_factory=list)
    directed: bool = False


class AttachmentGraph(Strict):
    """Mitra et al. Section 8: each new agent attaches to ``r`` existing ones (seeded)."""

    kind: Literal["attachment"]
    r: int = Field(ge=1)
    preferential: bool = True


Graph = Annotated[RingGraph | CompleteGraph | EdgesGraph | CellsGraph | AttachmentGraph, Field(discriminator="kind")]


class LossWindow(Strict):
    rounds: tuple[int, int] = Field(description="[first, last] round, inclusive")
    links: list[tuple[int, int]] = Field(description="(from, to) agent id pairs that drop everything")


class ChannelSection(Strict):
    drop_p: float = Field(default=0.0, ge=0.0, lt=1.0, description="Bernoulli erasure per link per round")
    delay_max: int = Field(default=0, ge=0, description="uniform random delay in rounds, 0..delay_max")
    losses: list[LossWindow] = Field(default_factory=list)


class NetworkSection(Strict):
    graph: Graph
    channel: ChannelSection = Field(default_factory=ChannelSection)


# --------------------------------------------------------------------------- [estimator]
if TYPE_CHECKING:  # a union built at run time from the registered algorithms; statically, what they share
    Estimator = EstimatorTable
else:
    Estimator = Annotated[Union[estimator_sections()], Field(discriminator="algorithm")]  # noqa: UP007


# --------------------------------------------------------------------------- [[attacks]]
class SensorAttack(Strict):
    target: Literal["sensor"]
    sensors: list[int] = Field(min_length=1, description="1-based sensor bank ids")
    kind: Literal["constant", "ramp", "sine", "random", "trajectory"]
    start: float = 0.0
    stop: float = math.inf
    value: float = 0.0
    slope: float = 0.0
    amplitude: float = 0.0
    omega: float = 0.0
    phase: float = 0.0
    scale: float = 0.0
    #: kind "trajectory": the attacked rows report the output of the plant started here
    x0_attack: Vector | None = None

    @model_validator(mode="after")
    def _window(self) -> "SensorAttack":
        if not self.start < self.stop:
            raise ValueError(f"start must be < stop, got start={self.start}, stop={self.stop}")
        if self.kind == "trajectory" and self.x0_attack is None:
            raise ValueError("kind 'trajectory' needs x0_attack (the initial state whose outputs the sensors report)")
        if self.kind != "trajectory" and self.x0_attack is not None:
            raise ValueError(f"x0_attack is only used by kind 'trajectory', not {self.kind!r}")
        return self


class AgentAttack(Strict):
    """A Byzantine agent: what it sends is replaced by a strategy (transport.byzantine)."""

    target: Literal["agent"]
    agents: list[int] = Field(min_length=1, description="1-based agent ids")
    kind: Literal["constant", "huge", "omission", "equivocation", "false_stamp", "replay", "crash", "cancellation"]
    start: float = Field(default=0.0, description="seconds (rounds when dt = 1)")
    stop: float = math.inf
    towards: list[int] | None = Field(default=None, description="receivers affected (default: all)")
    value: float = 0.0
    scale: float = Field(default=1e6, gt=0)
    shift: int = 1
    lag: int = Field(default=10, ge=1)
    payload: Literal["estimate", "huge"] = "huge"


Attack = Annotated[SensorAttack | AgentAttack, Field(discriminator="target")]


# --------------------------------------------------------------------------- [output] / [[expect]]
class StatePlot(Strict):
    """A linear combination of the state drawn against agents' estimates (dashboard, report)."""

    name: str = Field(pattern=r"^[A-Za-z0-9_.+-]+$")
    states: list[int] = Field(min_length=1, description="1-based state indices")
    weights: list[float] | None = None
    agents: list[int] | None = Field(default=None, description="agent ids (default: the first agent)")

    @model_validator(mode="after")
    def _weights(self) -> "StatePlot":
        if self.weights is not None and len(self.weights) != len(self.states):
            raise ValueError(f"weights must have one entry per state, got {len(self.weights)} for {len(self.states)}")
        return self


class OutputSection(Strict):
    window: tuple[float, float] | None = Field(default=None, description="[t0, t1] seconds")
    plots: list[StatePlot] = Field(default_factory=list)
    convergence_threshold: float = Field(default=1e-2, gt=0)


class Expectation(Strict):
    metric: Literal["error_2", "error_inf", "relative_error_2", "error_ratio"]
    block: str = "x"
    agents: Literal["regular"] | Annotated[list[int], Field(min_length=1)] = "regular"
    over: Literal["window", "final"] | tuple[float, float] = "window"
    max: float | None = None
    min: float | None = None
    label: str | None = None

    @model_validator(mode="after")
    def _bound(self) -> "Expectation":
        if self.max is None and self.min is None:
            raise ValueError("give 'max' and/or 'min'")
        return self


# --------------------------------------------------------------------------- [redteam]
SensorKind = Literal["constant", "ramp", "sine", "random", "trajectory"]
AgentKind = Literal["constant", "huge", "omission", "equivocation", "false_stamp", "replay", "crash", "cancellation"]


class RedteamSection(Strict):
    """Overrides of the search space ``rse redteam`` derives from the scenario (every key
    optional; docs/redteam.md). Budgets above the algorithm's threat model need ``--beyond``."""

    #: attacked sensor banks per candidate (default: the algorithm's budget, e.g. estimator.q)
    sensors: int | None = Field(default=None, ge=0)
    #: banks that may be attacked (1-based; default: all)
    banks: list[int] | None = Field(default=None, min_length=1)
    kinds: list[SensorKind] | None = Field(default=None, min_length=1)
    #: bound on |value|, amplitude, random scale and a ramp's value at the horizon
    #: (default: the largest of the scenario's own sensor attacks, else 1)
    amplitude: float | None = Field(default=None, gt=0)
    #: [low, high] rad/s of sine attacks (default: [0, 2 x the largest modal frequency])
    omega: tuple[float, float] | None = None
    #: [low, high] seconds of attack start times (default: [0, start of the output window])
    start: tuple[float, float] | None = None
    #: Byzantine agents per candidate (default: estimator.f where the algorithm has one)
    agents: int | None = Field(default=None, ge=0)
    #: agents that may be Byzantine (default: all)
    candidates: list[int] | None = Field(default=None, min_length=1)
    strategies: list[AgentKind] | None = Field(default=None, min_length=1)
    #: bound on |value| of the constant strategy and on the scale of huge / equivocation
    value: float = Field(default=1e6, gt=0)
    #: largest Bernoulli erasure probability searched (default: network.channel.drop_p)
    drop_p: float | None = Field(default=None, ge=0.0, lt=1.0)
    #: search run.seed (which seeds the channel) when erasures are searched
    seed: bool = True
    #: deterministic loss windows per candidate, each on one link, at most loss_length rounds
    losses: int = Field(default=0, ge=0)
    loss_length: int = Field(default=10, ge=1)
    #: the maximised metric: the worst regular agent's `metric` over `over` in `block`
    metric: Literal["error_2", "error_inf", "relative_error_2", "error_ratio"] | None = None
    over: Literal["window", "final"] | tuple[float, float] | None = None
    block: str | None = None
    #: a candidate whose metric exceeds this violates (default: the paper's bound, if any)
    threshold: float | None = Field(default=None, gt=0)

    @model_validator(mode="after")
    def _ranges(self) -> "RedteamSection":
        for name in ("omega", "start"):
            r = getattr(self, name)
            if r is not None and not 0 <= r[0] <= r[1]:
                raise ValueError(f"{name} must be [low, high] with 0 <= low <= high, got {list(r)}")
        return self


# --------------------------------------------------------------------------- whole file
class Scenario(Strict):
    run: RunSection
    plant: PlantSection
    sensors: list[SensorBank] | None = None
    agents: Annotated[list[AgentSpec], Field(min_length=1)] | CellPatrols | None = None
    network: NetworkSection
    estimator: Estimator
    attacks: list[Attack] = Field(default_factory=list)
    output: OutputSection = Field(default_factory=OutputSection)
    expect: list[Expectation] = Field(default_factory=list)
    redteam: RedteamSection | None = None
