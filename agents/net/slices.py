"""An agent's slice of a built experiment: what one agent process needs, nothing more.

The launcher builds the experiment once (the offline design included) and hands each agent
process its :class:`AgentSlice`: its :class:`~agents.node.AgentNode` (its estimator with
its design, the channel model with the run's seeds, its in- and out-neighbours, its
Byzantine strategy), the team's ids and message sizes, and, for an omniscient adversary,
the :class:`~agents.net.view.ViewTopology` of its receivers. Unpickling a slice imports
numpy, the estimator's module and the round logic; not the scenario schema (pydantic),
the design stack (cvxpy, networkx, scipy's design routines), Rerun or pyarrow.

A slice is written to ``RUN_DIR/team/agent-I.pkl`` (:func:`write_slices`; with several
agents per process one file per process, ``agents-A-B.pkl``, whose agents share their
design), so that ``rse agent --id I --team RUN_DIR/team.json`` (on this host, in a
container or on another host with a copy of the team directory) starts the agent without
the scenario file or its design.
"""

from __future__ import annotations

import copy
import pickle
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from agents.omniscient import ViewTopology, reads_view, view_topology
from estimation.errors import ScenarioError

if TYPE_CHECKING:
    from agents.node import AgentNode
    from estimation.attacks import SensorAttackSignal
    from estimation.patrols import PatrolSchedule
    from estimation.signals import Signal
    from scenarios.build import Experiment
    from scenarios.common import PlantStepper

#: the "format" of a slice file (a pickled dict; another format is refused)
FORMAT = "rse-agent-slice/1"


@dataclass
class AgentSlice:
    """One agent's part of a built experiment (picklable).

    agent_id : the agent's id; agent_ids : the team's ids, in index order
    n, N, ny : state dimension, team size, total measurement rows (message bounds)
    dt : the scenario's step (s); payload_shape : the shape of the agent's estimate message
    in_ids, out_ids : its in- and out-neighbours' ids
    node : its :class:`~agents.node.AgentNode` (estimator, channel model, strategy)
    view : the omniscient adversary's topology (None for every other agent)
    """

    agent_id: int
    agent_ids: tuple[int, ...]
    n: int
    N: int
    ny: int
    dt: float
    payload_shape: tuple[int, ...]
    in_ids: tuple[int, ...]
    out_ids: tuple[int, ...]
    node: AgentNode
    view: ViewTopology | None = None
    #: agents (this one, its in-neighbours, its view's) whose lockstep done report carries
    #: their broadcast estimate: honest agents whose payload is their estimate publish it
    #: once, in the done report, not also on their estimate key
    merged: frozenset[int] = frozenset()


def merges(node: AgentNode) -> bool:
    """Whether an agent's lockstep done report carries its broadcast estimate (an honest
    agent whose payload is its estimate: the one message is both)."""
    return node.strategy is None and bool(node.payload_is_estimate)


def payload_shape(estimator: Any, n: int) -> tuple[int, ...]:
    """The shape of an estimate message: a dry run of a copy of ``estimator`` (every agent
    of a scenario publishes the same shape; others are rejected)."""
    try:
        return tuple(np.shape(copy.deepcopy(estimator).step(0, None, {})))
    except Exception:
        return (n,)


def agent_slices(exp: Experiment, nodes: Sequence[AgentNode] | None = None) -> list[AgentSlice]:
    """Every agent's slice of ``exp`` (``nodes``: fresh nodes built as the simulator builds
    them, :func:`agents.middleware.make_nodes`; built here when not given)."""
    if nodes is None:
        from agents.middleware import make_channel, make_nodes

        nodes = make_nodes(exp, make_channel(exp))
    ids = tuple(exp.agent_ids)
    ny = int(sum(len(r) for r in exp.bank_rows))
    by_id = {nd.id: nd for nd in nodes}
    shape = payload_shape(nodes[0].estimator, exp.n) if nodes else (exp.n,)
    merged = {nd.id for nd in nodes if merges(nd)}
    out = []
    for i, (aid, node) in enumerate(zip(ids, nodes)):
        view = None
        if node.strategy is not None and reads_view(node.strategy):
            view = view_topology(exp, aid, {j: by_id[j].estimator for j in by_id})
        ins = tuple(ids[j] for j in exp.in_neighbours(i))
        near = {aid, *ins, *(view.needed if view is not None else ())}
        out.append(AgentSlice(aid, ids, exp.n, exp.N, ny, float(exp.dt), shape, ins,
                              tuple(ids[j] for j in exp.out_neighbours(i)), node, view, frozenset(near & merged)))
    return out


def agent_slice(exp: Experiment, agent_id: int, node: AgentNode | None = None) -> AgentSlice:
    """Agent ``agent_id``'s slice of ``exp`` (``node``: its node if already built)."""
    if agent_id not in exp.agent_ids:
        raise ScenarioError(f"no agent {agent_id} in this scenario; agents are {', '.join(map(str, exp.agent_ids))}")
    if node is None:
        return agent_slices(exp)[exp.agent_ids.index(agent_id)]
    from agents.middleware import make_channel, make_nodes

    nodes = make_nodes(exp, make_channel(exp))
    nodes[exp.agent_ids.index(agent_id)] = node
    return agent_slices(exp, nodes)[exp.agent_ids.index(agent_id)]


def slice_path(team_dir: Path, agent_ids: Sequence[int]) -> Path:
    """``team_dir/agent-I.pkl`` for one agent, ``team_dir/agents-A-B.pkl`` for a group of
    consecutive ids (``agents-1,3,5.pkl`` otherwise)."""
    ids = sorted(agent_ids)
    if len(ids) == 1:
        return Path(team_dir) / f"agent-{ids[0]}.pkl"
    span = f"{ids[0]}-{ids[-1]}" if ids == list(range(ids[0], ids[-1] + 1)) else ",".join(map(str, ids))
    return Path(team_dir) / f"agents-{span}.pkl"


INDEX = "slices.json"  # in the team directory: agent id -> the file holding its slice


def dumps_slices(parts: Sequence[AgentSlice]) -> bytes:
    """The bytes of a slice file (read back with :func:`read_slices`). The agents of one
    file share what their nodes share (e.g. the design of every agent's estimator): one
    file per process keeps a large team's files and processes small."""
    return pickle.dumps({"format": FORMAT, "slices": list(parts)}, protocol=pickle.HIGHEST_PROTOCOL)


def dumps_slice(part: AgentSlice) -> bytes:
    return dumps_slices([part])


def write_slices(team_dir: Path, slices: Sequence[AgentSlice],
                 groups: Sequence[Sequence[int]] | None = None) -> dict[int, Path]:
    """Write the slices, one file per group of agents (default: one per agent; see
    :func:`slice_path`) and the index ``slices.json``; returns agent id -> path."""
    import json

    team_dir = Path(team_dir)
    team_dir.mkdir(parents=True, exist_ok=True)
    by_id = {s.agent_id: s for s in slices}
    groups = groups or [(s.agent_id,) for s in slices]
    paths: dict[int, Path] = {}
    for g in groups:
        p = slice_path(team_dir, g)
        p.write_bytes(dumps_slices([by_id[a] for a in g]))
        paths.update({a: p.resolve() for a in g})
    (team_dir / INDEX).write_text(json.dumps({str(a): p.name for a, p in paths.items()}))
    return paths


def find_slices(team_dir: Path, agent_ids: Sequence[int]) -> bytes | None:
    """The slices of ``agent_ids`` from a team directory written by :func:`write_slices`,
    as the bytes of one slice file (None if some agent has none there)."""
    import json

    team_dir = Path(team_dir)
    try:
        index = json.loads((team_dir / INDEX).read_text())
    except (OSError, ValueError):
        index = {str(a): slice_path(team_dir, [a]).name for a in agent_ids}
    names = {index.get(str(a)) for a in agent_ids}
    if None in names or not all((team_dir / n).is_file() for n in names):
        return None
    files = sorted(names)
    if len(files) == 1 and len(read_slices(team_dir / files[0])) == len(agent_ids):
        return (team_dir / files[0]).read_bytes()
    got = {s.agent_id: s for n in files for s in read_slices(team_dir / n)}
    return dumps_slices([got[a] for a in agent_ids])


def read_slices(src: str | Path | bytes) -> list[AgentSlice]:
    """The slices of a file written by :func:`write_slices` (a path or its bytes)."""
    where = "an agent slice" if isinstance(src, (bytes, bytearray)) else str(src)
    try:
        data = pickle.loads(src if isinstance(src, (bytes, bytearray)) else Path(src).read_bytes())
    except FileNotFoundError:
        raise ScenarioError(f"{where}: no such agent slice (rse run writes RUN_DIR/team/agent-I.pkl)") from None
    except Exception as exc:  # a truncated or foreign file
        raise ScenarioError(f"{where}: cannot read the agent slice: {exc}") from None
    parts = data.get("slices") if isinstance(data, dict) and data.get("format") == FORMAT else None
    if not isinstance(parts, list) or not parts or not all(isinstance(p, AgentSlice) for p in parts):
        raise ScenarioError(f"{where}: not an agent slice of this version ({FORMAT})")
    return parts


def read_slice(src: str | Path | bytes) -> AgentSlice:
    """The one slice of a file written for one agent."""
    parts = read_slices(src)
    if len(parts) != 1:
        raise ScenarioError(f"{'an agent slice' if isinstance(src, (bytes, bytearray)) else src}: {len(parts)} agents, expected one")
    return parts[0]


@dataclass
class PlantSlice:
    """What the plant process needs of a built experiment (picklable): the plant's model,
    input and sensor attacks, who reads which rows when, the team's ids and out-neighbours.
    Read like the experiment by :class:`~agents.plant.PlantRole` and
    :class:`~agents.net.plant.PlantProcess`; unpickling it imports no scenario schema."""

    agent_ids: list[int]
    n: int
    N: int
    ny: int
    dt: float
    n_rounds: int
    x0: np.ndarray
    C: np.ndarray
    Ad: np.ndarray
    Bd: np.ndarray
    input: Signal
    sensor_attacks: list[SensorAttackSignal]
    stepper: PlantStepper | None
    agent_rows: list[np.ndarray]
    bank_rows: list[np.ndarray]
    schedules: list[PatrolSchedule | None]
    out_ids: list[list[int]]  # per agent index: its out-neighbours' indices

    @property
    def static(self) -> bool:
        return not any(s is not None for s in self.schedules)

    def out_neighbours(self, i: int) -> list[int]:
        return self.out_ids[i]

    def rows_at(self, i: int, k: int) -> np.ndarray | None:
        """Rows of the stacked ``y`` agent ``i`` reads in round ``k`` (None: commuting), as
        :meth:`scenarios.build.Experiment.rows_at`."""
        sched = self.schedules[i] if self.schedules else None
        if sched is None:
            return self.agent_rows[i]
        loc = sched.location(k)
        return None if loc is None else self.bank_rows[loc]


def plant_slice(exp: Experiment) -> PlantSlice:
    return PlantSlice(list(exp.agent_ids), exp.n, exp.N, exp.ny, float(exp.dt),
                      int(exp.n_rounds), exp.x0, exp.plant.C, exp.Ad, exp.Bd, exp.input, list(exp.sensor_attacks),
                      exp.stepper, list(exp.agent_rows), list(exp.bank_rows), list(exp.schedules or []),
                      [exp.out_neighbours(i) for i in range(exp.N)])
