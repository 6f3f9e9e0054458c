"""From a validated :class:`~scenarios.schema.Scenario` to the objects a run needs.

:func:`build` does every offline step once (matrices, seeded initial states, graph,
observer design) and checks what a run cannot do without (shapes, ids, connectivity,
the redundancy the estimator needs). Errors are :class:`ScenarioError` naming the key path.
:func:`conditions` evaluates the papers' conditions for ``rse check`` without raising.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from estimation import graphs
from estimation.attacks import SensorAttackSignal
from estimation.errors import DesignError, ScenarioError
from estimation.lee_kim_shim import LeeKimShim, LKSDesign, design as lks_design, theorem3_bound
from estimation.lti import ContinuousLTI, three_inertia, zoh
from estimation.median_solver import theorem1_bound
from estimation.observability import redundancy_violations
from estimation.signals import Signal

from .schema import Init, Scenario

# Stream tags for seeded generators: every random quantity has its own stream derived
# from (run seed, tag, index), so both drivers draw identical numbers in any order.
STREAM_PLANT_X0 = 1
STREAM_AGENT_X0 = 2
STREAM_SENSOR_ATTACK = 3
STREAM_CHANNEL = 4


def rng_for(seed: int, tag: int, *index: int) -> np.random.Generator:
    """A generator for one stream (see the stream tags above)."""
    return np.random.default_rng([seed, tag, *index])


@dataclass
class Experiment:
    """Everything a run of a scenario needs, built once.

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
    lks: LKSDesign | None = None
    byzantine: set[int] = field(default_factory=set)  # agent indices

    # ------------------------------------------------------------------ derived
    @property
    def n(self) -> int:
        return self.plant.n

    @property
    def N(self) -> int:
        return len(self.agent_ids)

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

    def make_estimator(self, i: int):
        """A fresh estimator for agent index ``i`` (its initial estimate is seeded)."""
        est = self.scenario.estimator
        if est.algorithm == "lee_kim_shim":
            x0 = init_vector(est.x0, self.n, rng_for(self.seed, STREAM_AGENT_X0, i), where="estimator.x0")
            return LeeKimShim(
                self.lks,
                agent=i,
                kappa=est.kappa,
                gamma=est.gamma,
                dt=self.dt,
                variant=est.variant,
                sign=est.sign,
                input_fn=self.input,
                x0=x0,
                max_age=est.max_age,
                max_degree=int(self.Adj[i].sum()),
            )
        raise ScenarioError(f"estimator.algorithm: {est.algorithm!r} is not built yet", source=self.source)


def init_vector(spec: Init, n: int, rng: np.random.Generator, *, where: str) -> np.ndarray:
    if spec.kind == "uniform":
        return rng.uniform(spec.low, spec.high, size=n)
    if spec.kind == "zero":
        return np.zeros(n)
    v = np.asarray(spec.value, dtype=float)
    if v.shape != (n,):
        raise ScenarioError(f"{where}.value: expected {n} numbers (the state dimension), got {len(v)}")
    return v


def _matrix(rows: Any, where: str, source: str, *, cols: int | None = None, nrows: int | None = None) -> np.ndarray:
    try:
        M = np.array(rows, dtype=float)
    except ValueError:
        raise ScenarioError(f"{where}: rows have different lengths", source=source) from None
    if M.ndim != 2:
        raise ScenarioError(f"{where}: expected a matrix (list of rows), got shape {M.shape}", source=source)
    if cols is not None and M.shape[1] != cols:
        raise ScenarioError(f"{where}: expected rows of length {cols}, got {M.shape[1]}", source=source)
    if nrows is not None and M.shape[0] != nrows:
        raise ScenarioError(f"{where}: expected {nrows} rows, got {M.shape[0]}", source=source)
    if not np.all(np.isfinite(M)):
        raise ScenarioError(f"{where}: entries must be finite", source=source)
    return M


def _plant(sc: Scenario, source: str) -> ContinuousLTI:
    pl = sc.plant
    if pl.model == "three_inertia":
        if pl.A is not None or pl.B is not None:
            raise ScenarioError("plant: A and B are given by model 'three_inertia'; use model = 'lti' for explicit matrices", source=source)
        allowed = {"J", "b", "k"}
        unknown = set(pl.params) - allowed
        if unknown:
            raise ScenarioError(f"plant.params: unknown parameter(s) {sorted(unknown)}; expected some of {sorted(allowed)}", source=source)
        base = three_inertia(**pl.params)
    else:
        if pl.A is None:
            raise ScenarioError("plant.A: required for model = 'lti'", source=source)
        A = _matrix(pl.A, "plant.A", source)
        if A.shape[0] != A.shape[1]:
            raise ScenarioError(f"plant.A: expected a square matrix, got shape {A.shape}", source=source)
        n = A.shape[0]
        B = _matrix(pl.B, "plant.B", source, nrows=n) if pl.B is not None else np.zeros((n, 0))
        names = tuple(pl.state_names) if pl.state_names else tuple(f"x{i + 1}" for i in range(n))
        base = ContinuousLTI(A=A, B=B, banks=(), state_names=names)
    n = base.n
    if sc.sensors is not None:
        banks = tuple(_matrix(s.C, f"sensors[{k}].C", source, cols=n) for k, s in enumerate(sc.sensors))
    else:
        if not base.banks:
            raise ScenarioError("sensors: required for model = 'lti' (one [[sensors]] table per bank)", source=source)
        banks = base.banks
    if pl.state_names and len(pl.state_names) != n:
        raise ScenarioError(f"plant.state_names: expected {n} names, got {len(pl.state_names)}", source=source)
    return ContinuousLTI(A=base.A, B=base.B, banks=banks, state_names=base.state_names)


def build(sc: Scenario, *, source: str = "<scenario>", check_conditions: bool = True) -> Experiment:
    """Build the experiment. With ``check_conditions`` (the default for runs), a
    disconnected graph or a violated redundancy assumption is an error."""
    plant = _plant(sc, source)
    n = plant.n
    # sensor banks -> rows of the stacked output
    sizes = [C.shape[0] for C in plant.banks]
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
    bank_rows = [np.arange(offsets[b], offsets[b + 1]) for b in range(len(sizes))]
    bank_names = [
        (sc.sensors[b].name if sc.sensors is not None and sc.sensors[b].name else f"sensor{b + 1}")
        for b in range(len(sizes))
    ]
    nb = len(sizes)
    # agents
    if sc.agents is None:
        agent_ids = list(range(1, nb + 1))
        agent_banks = [[b] for b in range(nb)]
    else:
        agent_ids, agent_banks = [], []
        for k, a in enumerate(sc.agents):
            agent_ids.append(a.id if a.id is not None else k + 1)
            for s in a.sensors:
                if not 1 <= s <= nb:
                    raise ScenarioError(f"agents[{k}].sensors: no sensor bank {s}; banks are 1..{nb}", source=source)
            agent_banks.append([s - 1 for s in a.sensors])
        dup = {i for i in agent_ids if agent_ids.count(i) > 1}
        if dup:
            raise ScenarioError(f"agents: duplicate agent id(s) {sorted(dup)}", source=source)
    N = len(agent_ids)
    index_of = {aid: i for i, aid in enumerate(agent_ids)}
    agent_rows = [np.concatenate([bank_rows[b] for b in banks]) for banks in agent_banks]
    # graph
    Adj = _graph(sc, N, index_of, source)
    # input, initial state
    inp = sc.plant.input
    p = plant.B.shape[1]
    if inp.kind == "zero" or p == 0:
        signal = Signal.zero(p)
    elif inp.kind == "constant":
        signal = Signal.constant(p, inp.offset)
    else:
        signal = Signal.sine(p, amplitude=inp.amplitude, omega=inp.omega, phase=inp.phase, offset=inp.offset)
    x0 = init_vector(sc.plant.x0, n, rng_for(sc.run.seed, STREAM_PLANT_X0), where="plant.x0")
    Ad, Bd = zoh(plant.A, plant.B, sc.run.dt)
    # blocks
    blocks: dict[str, np.ndarray] = {"x": np.arange(n)}
    for name, idx in sc.plant.blocks.items():
        if name == "x":
            raise ScenarioError("plant.blocks: the name 'x' is reserved for the whole state", source=source)
        bad = [i for i in idx if not 1 <= i <= n]
        if bad or not idx:
            raise ScenarioError(f"plant.blocks.{name}: state indices must be in 1..{n}, got {idx}", source=source)
        blocks[name] = np.array([i - 1 for i in idx])
    # sensor attacks
    attacks = []
    for k, at in enumerate(sc.attacks):
        if at.target == "sensor":
            for s in at.sensors:
                if not 1 <= s <= nb:
                    raise ScenarioError(f"attacks[{k}].sensors: no sensor bank {s}; banks are 1..{nb}", source=source)
            rows = np.concatenate([bank_rows[s - 1] for s in at.sensors])
            attacks.append(
                SensorAttackSignal(
                    rows=rows, kind=at.kind, start=at.start, stop=at.stop, value=at.value, slope=at.slope,
                    amplitude=at.amplitude, omega=at.omega, phase=at.phase, scale=at.scale,
                    rng=rng_for(sc.run.seed, STREAM_SENSOR_ATTACK, k) if at.kind == "random" else None,
                )
            )
    exp = Experiment(
        scenario=sc, source=source, plant=plant, Ad=Ad, Bd=Bd, x0=x0, input=signal, bank_rows=bank_rows,
        bank_names=bank_names, agent_ids=agent_ids, agent_rows=agent_rows, Adj=Adj, blocks=blocks,
        sensor_attacks=attacks,
    )
    _check_expectations(exp, source)
    if check_conditions:
        comps = graphs.components(Adj)
        if len(comps) > 1:
            names = " and ".join("{" + ", ".join(str(agent_ids[i]) for i in c) + "}" for c in comps)
            raise ScenarioError(f"network.graph: the graph is disconnected: agents {names}", source=source)
    est = sc.estimator
    if est.algorithm == "lee_kim_shim":
        agent_C = [plant.C[rows] for rows in agent_rows]
        if check_conditions:
            bad = redundancy_violations(plant.A, agent_C, est.q)
            if bad:
                subset, dim = bad[0]
                who = ", ".join(str(agent_ids[i]) for i in subset) or "(none)"
                raise ScenarioError(
                    f"estimator.q: the sensor set is not {2 * est.q}-redundantly observable (Assumption 2): "
                    f"agents {who} alone leave a {dim}-dimensional unobservable subspace "
                    f"({len(bad)} such set(s) of {N - 2 * est.q} agents); lower q or add sensors",
                    source=source,
                )
        try:
            exp.lks = lks_design(plant.A, plant.B, agent_C, real_part=est.observer.real_part)
        except DesignError as exc:
            raise ScenarioError(f"estimator: {exc}", source=source) from None
    return exp


def _graph(sc: Scenario, N: int, index_of: dict[int, int], source: str) -> np.ndarray:
    g = sc.network.graph
    try:
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
    T = exp.n_rounds * exp.dt
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
            if not (0 <= t0 <= t1 <= T + 1e-9):
                raise ScenarioError(f"expect[{k}].over: expected 0 <= t0 <= t1 <= {T:g}, got [{t0:g}, {t1:g}]", source=source)


@dataclass
class Condition:
    """One paper condition as reported by ``rse check``."""

    name: str
    holds: bool | None  # None: a figure, not a pass/fail condition
    detail: str


def conditions(exp: Experiment) -> list[Condition]:
    """Evaluate the scenario's conditions (never raises for a failed condition)."""
    out: list[Condition] = []
    Adj = exp.Adj
    comps = graphs.components(Adj)
    undirected = graphs.is_undirected(Adj)
    connected = len(comps) == 1
    out.append(Condition("network connected (Assumption 3)", connected and undirected,
                         f"{'undirected' if undirected else 'directed'}, {len(comps)} component(s)"))
    lam2 = graphs.algebraic_connectivity(Adj) if undirected else float("nan")
    out.append(Condition("lambda_2(L)", None, f"{lam2:.6g}"))
    est = exp.scenario.estimator
    if est.algorithm == "lee_kim_shim":
        agent_C = [exp.plant.C[rows] for rows in exp.agent_rows]
        bad = redundancy_violations(exp.plant.A, agent_C, est.q)
        detail = (f"every set of {exp.N - 2 * est.q} agents observes x" if not bad else
                  f"{len(bad)} set(s) of {exp.N - 2 * est.q} agents do not, e.g. agents "
                  + ", ".join(str(exp.agent_ids[i]) for i in bad[0][0]))
        out.append(Condition(f"{2 * est.q}-redundant observability, q = {est.q} (Assumption 2)", not bad, detail))
        des = exp.lks
        if des is None:
            try:
                des = lks_design(exp.plant.A, exp.plant.B, agent_C, real_part=est.observer.real_part)
            except DesignError as exc:
                out.append(Condition("common basis (Assumption 4)", False, str(exc)))
                return out
        S = des.basis.S
        counts = S.sum(axis=0)
        out.append(Condition("common basis (Assumption 4)", True,
                             f"{des.basis.method} basis; banks observing each basis direction: {counts.tolist()}"))
        out.append(Condition(f"each direction observed by >= 2q+1 = {2 * est.q + 1} agents (Lemma 1)",
                             bool(np.all(counts >= 2 * est.q + 1)), f"min {int(counts.min())}"))
        if connected and undirected:
            out.append(Condition(f"Theorem 1 bound 2 sqrt(N)/(gamma lambda_2), gamma = {est.gamma:g}", None,
                                 f"{theorem1_bound(Adj, est.gamma):.6g}"))
            b3 = theorem3_bound(des, Adj, est.gamma)
            out.append(Condition("plant Lyapunov stable (Theorem 3 / eq. 11)", des.sqrt_Pbar is not None,
                                 "P_bar = I in the modal basis" if des.sqrt_Pbar is not None and np.allclose(des.sqrt_Pbar, np.eye(exp.n)) else ""))
            if b3 is not None:
                out.append(Condition("Theorem 3 steady-state bound on |x_hat_i - x|", None, f"{b3:.6g}"))
    return out
