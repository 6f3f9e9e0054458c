"""From a validated :class:`~scenarios.schema.Scenario` to the objects a run needs.

:func:`build` does every offline step once (matrices, seeded initial states, graph,
observer design) and checks what a run cannot do without (shapes, ids, connectivity,
the redundancy the estimator needs). Errors are :class:`ScenarioError` naming the key path.
:func:`conditions` evaluates the papers' conditions for ``rse check`` without raising.

The helpers algorithm plugins build on (``matrix``, ``explicit_AB``, ``init_vector``, ...)
are public in :mod:`scenarios.helpers`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from estimation import graphs
from estimation.attacks import SensorAttackSignal
from estimation.errors import DesignError, ScenarioError
from estimation.lti import FLOAT_SIGNAL_LIMIT, ContinuousLTI, dense, float_horizon, three_inertia, zoh
from estimation.patrols import Patrol, PatrolSchedule, cell_patrols
from estimation.robustness import attachment_graph, cell_graph
from estimation.signals import Signal

from . import budget, plugins
from .common import (  # noqa: F401  (re-exported for the drivers and tests)
    STREAM_AGENT_X0,
    STREAM_GRAPH,
    STREAM_PLANT_X0,
    STREAM_SENSOR_ATTACK,
    ByzantineSpec,
    Condition,
    PlantModel,
    PlantStepper,
    rng_for,
)
from .helpers import check_size, explicit_AB, init_vector, matrix
from .schema import Scenario


@dataclass(frozen=True)
class Experiment:
    """Everything a run of a scenario needs, built once (and never changed: a variant is
    ``dataclasses.replace(exp, ...)``).

    Ids: ``agent_ids[i]`` is the 1-based id of agent index ``i``; ``Adj`` is indexed by
    agent index (``Adj[i, j] = 1``: ``i`` receives from ``j``).
    """

    scenario: Scenario
    source: str
    plant: ContinuousLTI
    Ad: np.ndarray
    Bd: np.ndarray
    x0: np.ndarray
    input: Signal
    bank_rows: list[np.ndarray]  # rows of the stacked y per sensor bank
    bank_names: list[str]
    agent_ids: list[int]
    agent_rows: list[np.ndarray]  # rows of the stacked y each agent reads
    Adj: np.ndarray
    blocks: dict[str, np.ndarray]
    sensor_attacks: list[SensorAttackSignal]
    design: Any = None  # the algorithm plugin's offline design
    stepper: PlantStepper | None = None  # a nonlinear or noisy plant's own step
    byzantine: frozenset[int] = frozenset()  # agent indices
    #: agent index -> its Byzantine strategy, as specified (the runtime builds the middleware)
    byzantine_specs: Mapping[int, ByzantineSpec] = field(default_factory=dict)
    discrete: bool = False
    positions: np.ndarray | None = None  # (banks, 2) map positions of the sensing locations
    patrols: list[Patrol | None] = field(default_factory=list)  # per agent (None: static)
    schedules: list[PatrolSchedule | None] = field(default_factory=list)
    cell_of_location: np.ndarray | None = None
    #: the validated scenario as plain data (what ``manifest.json`` freezes) and the
    #: overrides it was loaded with (``KEY=VALUE`` strings, ``run.seed`` included)
    frozen: Mapping[str, Any] = field(default_factory=dict)
    overrides: tuple[str, ...] = ()
    #: the horizon in seconds of the scenario file itself, before overrides (None: unknown);
    #: a shorter run lists the bounds meant for the file's horizon as not evaluated
    nominal_horizon: float | None = None
    #: the run's estimated memory and time (scenarios.budget), checked when it was built
    cost: budget.Cost | None = None

    # ------------------------------------------------------------------ derived
    @property
    def n(self) -> int:
        return self.plant.n

    @property
    def N(self) -> int:
        return len(self.agent_ids)

    @property
    def ny(self) -> int:
        """Rows of the stacked measurement ``y``."""
        return int(sum(len(r) for r in self.bank_rows))

    @property
    def C(self) -> np.ndarray:
        """The stacked output matrix (every bank's rows)."""
        return self.plant.C

    @property
    def dt(self) -> float:
        return self.scenario.run.dt

    @property
    def n_rounds(self) -> int:
        return self.scenario.run.n_rounds

    @property
    def seed(self) -> int:
        return self.scenario.run.seed

    @property
    def window(self) -> tuple[float, float]:
        w = self.scenario.output.window
        T = self.n_rounds * self.dt
        return (float(w[0]), float(w[1])) if w is not None else (0.75 * T, T)

    def in_neighbours(self, i: int) -> list[int]:
        return graphs.in_neighbours(self.Adj, i)

    def out_neighbours(self, i: int) -> list[int]:
        return [int(j) for j in np.flatnonzero(self.Adj[:, i])]

    def rows_at(self, i: int, k: int) -> np.ndarray | None:
        """Rows of the stacked ``y`` agent ``i`` reads in round ``k`` (None: commuting)."""
        sched = self.schedules[i] if self.schedules else None
        if sched is None:
            return self.agent_rows[i]
        loc = sched.location(k)
        return None if loc is None else self.bank_rows[loc]

    @property
    def static(self) -> bool:
        return not any(s is not None for s in self.schedules)

    @property
    def plugin(self):
        return plugins.algorithm(self.scenario.estimator.algorithm)

    def make_estimator(self, i: int):
        """A fresh estimator for agent index ``i`` (its initial estimate is seeded)."""
        return self.plugin.make_estimator(self, i)


def _plant(sc: Scenario, source: str) -> PlantModel:
    pl = sc.plant
    if pl.model != "grid" and (pl.case is not None or pl.pmus is not None):
        raise ScenarioError(f"plant: case and pmus belong to model 'grid', not {pl.model!r}", source=source)
    if pl.model not in ("three_inertia", "lti"):
        _, build_plant = plugins.plant(pl.model)
        return build_plant(sc, source)
    if pl.model == "three_inertia":
        if pl.A is not None or pl.B is not None:
            raise ScenarioError("plant: A and B are given by model 'three_inertia'; use model = 'lti' for explicit matrices", source=source)
        allowed = {"J", "b", "k"}
        unknown = set(pl.params) - allowed
        if unknown:
            raise ScenarioError(f"plant.params: unknown parameter(s) {sorted(unknown)}; expected some of {sorted(allowed)}", source=source)
        base = three_inertia(**pl.params)
    else:
        A, B = explicit_AB(pl, source)
        n = A.shape[0]
        names = tuple(pl.state_names) if pl.state_names else tuple(f"x{i + 1}" for i in range(n))
        base = ContinuousLTI(A=A, B=B, banks=(), state_names=names)
    n = base.n
    if sc.sensors is not None:
        banks = tuple(matrix(s.C, f"sensors[{k}].C", source, cols=n) for k, s in enumerate(sc.sensors))
    else:
        if not base.banks:
            raise ScenarioError("sensors: required for model = 'lti' (one [[sensors]] table per bank)", source=source)
        banks = base.banks
    if pl.state_names and len(pl.state_names) != n:
        raise ScenarioError(f"plant.state_names: expected {n} names, got {len(pl.state_names)}", source=source)
    if pl.model == "three_inertia" and pl.time == "discrete":
        raise ScenarioError("plant.time: model 'three_inertia' is a continuous-time plant", source=source)
    positions = None
    if sc.sensors is not None and any(s.position is not None for s in sc.sensors):
        positions = np.array([s.position if s.position is not None else (np.nan, np.nan) for s in sc.sensors], dtype=float)
    return PlantModel(lti=ContinuousLTI(A=base.A, B=base.B, banks=banks, state_names=base.state_names),
                      discrete=pl.time == "discrete", positions=positions)


def build(sc: Scenario, *, source: str = "<scenario>", check_conditions: bool = True) -> Experiment:
    """Build the experiment. With ``check_conditions`` (the default for runs), a
    disconnected graph or a violated redundancy assumption is an error."""
    model = _plant(sc, source)
    plant = model.lti
    n = plant.n
    # sensor banks -> rows of the stacked output
    sizes = [C.shape[0] for C in plant.banks]
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
    bank_rows = [np.arange(offsets[b], offsets[b + 1]) for b in range(len(sizes))]
    given: list[str | None] = [s.name for s in sc.sensors] if sc.sensors is not None else [None] * len(sizes)
    bank_names = [name or f"sensor{b + 1}" for b, name in enumerate(given)]
    nb = len(sizes)
    # agents: static (banks) or mobile (patrols)
    patrols: list[Patrol | None] = []
    per_cell = None
    if sc.agents is None:
        agent_ids = list(range(1, nb + 1))
        agent_banks = [[b] for b in range(nb)]
        patrols = [None] * nb
    elif not isinstance(sc.agents, list):  # generated cell patrols
        if model.cell_of_location is None:
            raise ScenarioError(f"agents: kind 'cell_patrols' needs a plant with cells (cells, diffusion), got {sc.plant.model!r}", source=source)
        try:
            K = int(model.cell_of_location.max()) + 1
            per = list(sc.agents.periods)
            check_size("agents", K * sc.agents.per_cell, "agents.per_cell x cells", run=sc.run, source=source)
            if K % len(per):
                raise ScenarioError(f"agents.periods: {len(per)} periods do not repeat evenly over {K} cells", source=source)
            gen = cell_patrols(model.cell_of_location, agents_per_cell=sc.agents.per_cell, periods=per * (K // len(per)))
        except DesignError as exc:
            raise ScenarioError(f"agents: {exc}", source=source) from None
        patrols = list(gen)
        per_cell = sc.agents.per_cell
        agent_ids = list(range(1, len(patrols) + 1))
        agent_banks = [[] for _ in patrols]
    else:
        agent_ids, agent_banks = [], []
        for k, a in enumerate(sc.agents):
            agent_ids.append(a.id if a.id is not None else k + 1)
            if a.sensors is not None:
                for s_ in a.sensors:
                    if not 1 <= s_ <= nb:
                        raise ScenarioError(f"agents[{k}].sensors: no sensor bank {s_}; banks are 1..{nb}", source=source)
                agent_banks.append([s_ - 1 for s_ in a.sensors])
                patrols.append(None)
            elif (spec := a.patrol) is not None:  # the schema gives one of sensors / patrol
                bad = [l for l in spec.locations if not 1 <= l <= nb]
                if bad:
                    raise ScenarioError(f"agents[{k}].patrol.locations: no location(s) {bad}; locations are 1..{nb}", source=source)
                try:
                    patrols.append(Patrol(tuple(l - 1 for l in spec.locations), tuple(spec.offsets), tuple(spec.periods), agent=agent_ids[-1]))
                except DesignError as exc:
                    raise ScenarioError(f"agents[{k}].patrol: {exc}", source=source) from None
                agent_banks.append([])
        dup = {i for i in agent_ids if agent_ids.count(i) > 1}
        if dup:
            raise ScenarioError(f"agents: duplicate agent id(s) {sorted(dup)}", source=source)
    N = len(agent_ids)
    if N == 0:
        raise ScenarioError("agents: the team has no agents (no [[agents]] and no sensor banks)", source=source)
    index_of = {aid: i for i, aid in enumerate(agent_ids)}
    agent_rows = [np.concatenate([bank_rows[b] for b in banks]).astype(int) if banks else np.zeros(0, dtype=int) for banks in agent_banks]
    for k, patrol in enumerate(patrols):  # a schedule tabulates its first offset + hyper-period rounds
        if patrol is not None:
            keys = "agents.periods" if per_cell is not None else f"agents[{k}].patrol.periods, offsets"
            check_size("rounds", max(patrol.offsets) + patrol.hyper_period, f"{keys} (largest offset + hyper-period)",
                       run=sc.run, source=source)
    schedules = [PatrolSchedule(pt, model.positions) if pt is not None else None for pt in patrols]
    check_size("agents", N, "agents", run=sc.run, source=source)
    # graph
    Adj = _graph(sc, N, index_of, source, per_cell=per_cell)
    cost = _check_cost(sc, model, Adj, source)
    # input, initial state
    inp = sc.plant.input
    p = plant.B.shape[1]
    if inp.kind == "zero" or p == 0:
        signal = Signal.zero(p)
    elif inp.kind == "constant":
        signal = Signal.constant(p, inp.offset)
    else:
        signal = Signal.sine(p, amplitude=inp.amplitude, omega=inp.omega, phase=inp.phase, offset=inp.offset)
    if sc.plant.x0 is not None:
        x0 = init_vector(sc.plant.x0, n, rng_for(sc.run.seed, STREAM_PLANT_X0), where="plant.x0")
    elif model.x0 is not None:
        x0 = model.x0.copy()
    else:
        x0 = rng_for(sc.run.seed, STREAM_PLANT_X0).uniform(-1.0, 1.0, size=n)
    if model.discrete:
        Ad, Bd = plant.A, plant.B  # shared, never written (a 1,024-agent team's A is 200 MB)
    else:
        with np.errstate(all="ignore"):
            Ad, Bd = zoh(plant.A, plant.B, sc.run.dt)
        if not (np.all(np.isfinite(Ad)) and np.all(np.isfinite(Bd))):
            raise ScenarioError(f"run.dt: the plant's one-round transition expm(A dt) overflows float64 at dt = {sc.run.dt:g}; "
                                "use a shorter step", source=source)
    # blocks
    blocks: dict[str, np.ndarray] = {"x": np.arange(n), **model.blocks}
    for name, idx in sc.plant.blocks.items():
        if name == "x":
            raise ScenarioError("plant.blocks: the name 'x' is reserved for the whole state", source=source)
        bad = [i for i in idx if not 1 <= i <= n]
        if bad or not idx:
            raise ScenarioError(f"plant.blocks.{name}: state indices must be in 1..{n}, got {idx}", source=source)
        blocks[name] = np.array([i - 1 for i in idx])
    # sensor attacks
    attacks = []
    byzantine: set[int] = set()
    specs: dict[int, ByzantineSpec] = {}
    for k, at in enumerate(sc.attacks):
        if at.target == "agent":
            for aid in at.agents:
                if aid not in index_of:
                    raise ScenarioError(f"attacks[{k}].agents: no agent {aid}; agents are {agent_ids[0]}..{agent_ids[-1]}", source=source)
                i = index_of[aid]
                if i in specs:
                    raise ScenarioError(f"attacks[{k}].agents: agent {aid} already has a Byzantine strategy", source=source)
                bad = [r for r in (at.towards or []) if r not in index_of]
                if bad:
                    raise ScenarioError(f"attacks[{k}].towards: no agent(s) {bad}", source=source)
                dt = sc.run.dt
                specs[i] = ByzantineSpec(
                    kind=at.kind, start=int(np.ceil(at.start / dt - 1e-9)),
                    stop=None if np.isinf(at.stop) else int(np.ceil(at.stop / dt - 1e-9)),
                    targets=frozenset(at.towards) if at.towards else None, value=at.value, scale=at.scale,
                    shift=at.shift, lag=at.lag, payload=at.payload, seed=sc.run.seed, agent=aid,
                )
                byzantine.add(i)
            continue
        if at.target == "sensor":
            for s in at.sensors:
                if not 1 <= s <= nb:
                    raise ScenarioError(f"attacks[{k}].sensors: no sensor bank {s}; banks are 1..{nb}", source=source)
            rows = np.concatenate([bank_rows[s - 1] for s in at.sensors])
            traj: dict[str, Any] = {}
            if at.kind == "trajectory":
                traj = _trajectory_attack(at, k, rows, plant.C, Ad, x0, model, sc, source)
            attacks.append(
                SensorAttackSignal(
                    rows=rows, kind=at.kind, start=at.start, stop=at.stop, value=at.value, slope=at.slope,
                    amplitude=at.amplitude, omega=at.omega, phase=at.phase, scale=at.scale,
                    rng=rng_for(sc.run.seed, STREAM_SENSOR_ATTACK, k) if at.kind == "random" else None, **traj,
                )
            )
    exp = Experiment(
        scenario=sc, source=source, plant=plant, Ad=Ad, Bd=Bd, x0=x0, input=signal, bank_rows=bank_rows,
        bank_names=bank_names, agent_ids=agent_ids, agent_rows=agent_rows, Adj=Adj, blocks=blocks,
        sensor_attacks=attacks, byzantine=frozenset(byzantine), byzantine_specs=specs, discrete=model.discrete,
        positions=model.positions, patrols=patrols, schedules=schedules, cell_of_location=model.cell_of_location,
        cost=cost, stepper=model.stepper,
    )
    _check_expectations(exp, source)
    if check_conditions:
        comps = graphs.components(Adj)
        if len(comps) > 1:
            names = " and ".join("{" + ", ".join(str(agent_ids[i]) for i in c) + "}" for c in comps)
            raise ScenarioError(f"network.graph: the graph is disconnected: agents {names}", source=source)
    exp = replace(exp, design=exp.plugin.design(exp, check=check_conditions))
    if check_conditions and model.stepper is None:
        _check_float_horizon(exp, source)
    return exp


def _check_cost(sc: Scenario, model: PlantModel, Adj: np.ndarray, source: str) -> budget.Cost:
    """The whole run's estimated memory and time within the budget (:mod:`scenarios.budget`)."""
    n, N = model.lti.n, Adj.shape[0]
    cost = budget.estimate(rounds=sc.run.n_rounds, agents=N, states=n, fused=float(np.count_nonzero(Adj)) * n,
                           substeps=model.substeps)
    keys = "run.rounds" if sc.run.rounds is not None else "run.duration / run.dt"
    budget.check_run(cost, f"{keys} ({sc.run.n_rounds:,} rounds) x {N:,} agents x {n:,} states"
                     + (f" x plant.params.substeps ({model.substeps:,})" if model.substeps > 1 else ""),
                     force=sc.run.force, source=source)
    return cost


def safe_horizon(exp: Experiment, max_rounds: int) -> int:
    """The last round ``k <= max_rounds`` up to which the plant's state stays representable:
    ``|x0|`` plus one round of the largest input, bounded by ``||Ad^k||`` times it, below
    :data:`~estimation.lti.FLOAT_SIGNAL_LIMIT` (``max_rounds`` for a plant that stays there;
    ``rse chaos`` splits a longer soak into teams of at most this many rounds)."""
    return float_horizon(exp.Ad, x_norm=max(_state_bound(exp), 1e-300), max_rounds=max_rounds)


def _state_bound(exp: Experiment) -> float:
    """``|x0|`` plus one round of the largest input."""
    u = exp.input
    u_max = float(np.linalg.norm(np.abs(u.offset) + np.abs(u.amplitude))) if u.p else 0.0
    return float(np.linalg.norm(exp.x0)) + float(np.linalg.norm(exp.Bd, 2) if exp.Bd.size else 0.0) * u_max


def _check_float_horizon(exp: Experiment, source: str) -> None:
    """An unstable linear plant must not outgrow float64 within the horizon
    (:func:`safe_horizon`), else ``run.rounds`` is refused with the safe horizon (the same
    rule as the Mao-Tabuada plugin's own check)."""
    h = safe_horizon(exp, exp.n_rounds)
    if h < exp.n_rounds:
        raise ScenarioError(
            f"run.rounds: the horizon {exp.n_rounds} passes the safe horizon {h} of this unstable plant: by then its "
            f"state (|x0| = {_state_bound(exp):.3g}, growing like ||Ad^k||) would pass {FLOAT_SIGNAL_LIMIT:g}, past which squared "
            f"norms overflow float64; shorten the run to at most {h} rounds", source=source)


def _trajectory_attack(at: Any, k: int, rows: np.ndarray, C: np.ndarray, Ad: np.ndarray, x0: np.ndarray,
                       model: PlantModel, sc: Scenario, source: str) -> dict[str, Any]:
    """Keyword arguments of a ``trajectory`` sensor attack: the outputs of the plant
    started from ``x0_attack`` (an LTI plant only: the known input cancels in the offset)."""
    if model.stepper is not None:
        raise ScenarioError(f"attacks[{k}].kind: 'trajectory' needs an LTI plant; model {sc.plant.model!r} has its own "
                            "(nonlinear or noisy) step", source=source)
    xa = np.asarray(at.x0_attack, dtype=float)
    if xa.shape != x0.shape:
        raise ScenarioError(f"attacks[{k}].x0_attack: expected {x0.shape[0]} numbers (the state dimension), got {xa.shape[0]}",
                            source=source)
    if not np.all(np.isfinite(xa)):
        raise ScenarioError(f"attacks[{k}].x0_attack: entries must be finite", source=source)
    return {"C": C[rows].copy(), "Ad": np.array(dense(Ad), dtype=float), "d0": xa - x0, "dt": float(sc.run.dt)}


def _ids(v: Any) -> list[int]:
    return [int(v)] if isinstance(v, int) else [int(x) for x in v]


def _graph(sc: Scenario, N: int, index_of: dict[int, int], source: str, *, per_cell: int | None = None) -> np.ndarray:
    g = sc.network.graph
    try:
        if g.kind == "attachment":
            return attachment_graph(N, r=g.r, rng=rng_for(sc.run.seed, STREAM_GRAPH), preferential=g.preferential)
        if g.kind == "cells":
            if per_cell is None:
                raise ScenarioError("network.graph: kind 'cells' needs agents = {kind = 'cell_patrols', ...}", source=source)
            Adj = cell_graph(N // per_cell, per_cell, intra=g.intra)
            for key, pairs, val in (("remove", g.remove, 0), ("add", g.add, 1)):
                for k, (a, b) in enumerate(pairs):
                    for v in _ids(a) + _ids(b):
                        if v not in index_of:
                            raise ScenarioError(f"network.graph.{key}[{k}]: no agent {v}", source=source)
                    for x in _ids(a):
                        for y in _ids(b):
                            if x == y:
                                continue
                            Adj[index_of[y], index_of[x]] = val
                            if not g.directed:
                                Adj[index_of[x], index_of[y]] = val
            return Adj
        if g.kind == "ring":
            return graphs.ring(N, directed=g.directed)
        if g.kind == "complete":
            return graphs.complete(N)
        edges = []
        for k, (a, b) in enumerate(g.edges):
            for v in (a, b):
                if v not in index_of:
                    raise ScenarioError(
                        f"network.graph.edges[{k}]: no agent {v}; agents are {sorted(index_of)}", source=source
                    )
            edges.append((index_of[a], index_of[b]))
        return graphs.from_edges(N, edges, directed=g.directed)
    except DesignError as exc:
        raise ScenarioError(f"network.graph: {exc}", source=source) from None


def _check_expectations(exp: Experiment, source: str) -> None:
    for k, e in enumerate(exp.scenario.expect):
        if e.block not in exp.blocks and e.block != "all":
            raise ScenarioError(
                f"expect[{k}].block: unknown block {e.block!r}; expected one of {', '.join(list(exp.blocks) + ['all'])}",
                source=source,
            )
        if isinstance(e.agents, list):
            bad = [a for a in e.agents if a not in exp.agent_ids]
            if bad:
                raise ScenarioError(f"expect[{k}].agents: no agent(s) {bad}", source=source)
        if isinstance(e.over, tuple):
            t0, t1 = e.over
            if not 0 <= t0 <= t1:  # a window beyond the horizon is reported as not evaluated
                raise ScenarioError(f"expect[{k}].over: expected 0 <= t0 <= t1, got [{t0:g}, {t1:g}]", source=source)


def conditions(exp: Experiment) -> list[Condition]:
    """Evaluate the scenario's conditions (never raises for a failed condition)."""
    out: list[Condition] = []
    graph_conditions = getattr(exp.plugin, "graph_conditions", None)
    if graph_conditions is not None:  # the plugin states its own graph assumption (e.g. directed graphs)
        out.extend(graph_conditions(exp))
        out.extend(exp.plugin.conditions(exp))
        return out
    Adj = exp.Adj
    comps = graphs.components(Adj)
    undirected = graphs.is_undirected(Adj)
    connected = len(comps) == 1
    out.append(Condition("network connected (Assumption 3)", connected and undirected,
                         f"{'undirected' if undirected else 'directed'}, {len(comps)} component(s)"))
    lam2 = graphs.algebraic_connectivity(Adj) if undirected else float("nan")
    out.append(Condition("lambda_2(L)", None, f"{lam2:.6g}"))
    out.extend(exp.plugin.conditions(exp))
    return out
