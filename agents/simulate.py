"""The in-process lockstep driver (``rse simulate``).

Every role of the scenario in one Python process, round by round (DESIGN.md, "One round"):

1. the plant publishes ``y[k]`` (sensor attacks applied); the monitor gets ``x[k]``;
2. every agent takes its measurement and its inbox and publishes its message stamped ``k``;
3. every message is handed to each out-neighbour's node, whose channel model decides when
   (if ever) it becomes visible;
4. the monitor records the errors of round ``k`` (and the diagnostics / attack flags of
   estimators that expose them, :func:`agents.monitor.read_diagnostics`); the plant advances.

Deterministic for a given seed.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from estimation.base import MaskedInputs
from estimation.batching import Batch, Batchable
from scenarios.build import Experiment
from transport.byzantine import Forged
from transport.channel import Channel, loss_windows

from .middleware import byzantine_strategy
from .monitor import Monitor, has_diagnostics, read_diagnostics
from .node import AgentNode
from .plant import PlantRole


def batch_groups(exp: Experiment, nodes: list[AgentNode]) -> list[Batch]:
    """The regular agents stepped together, one :class:`~estimation.batching.Batch` per
    group of estimators that declare :class:`~estimation.batching.Batchable` with equal
    ``batch_key()`` (e.g. LFRE agents by fusion rule and ``f``; every Lee-Kim-Shim agent).
    Byzantine agents always run their own ``step``."""
    keys: dict[Any, list[int]] = {}
    for i, node in enumerate(nodes):
        est = node.estimator
        if i not in exp.byzantine and isinstance(est, Batchable):
            keys.setdefault(est.batch_key(), []).append(i)
    out = []
    for members in keys.values():
        local = {i: m for m, i in enumerate(members)}
        nbrs = [[local[j] for j in exp.in_neighbours(i) if j in local] for i in members]
        rows = [np.asarray(exp.agent_rows[i]) for i in members] if exp.static else None
        est = nodes[members[0]].estimator
        out.append(type(est).batch([nodes[i].estimator for i in members], in_neighbours=nbrs, agents=members, rows=rows))
    return out


def closed_team(exp: Experiment, nodes: list[AgentNode], groups: list[Batch], channel: Channel) -> Batch | None:
    """The batch that is the whole team when it is closed: one batch of every agent,
    static sensors, a perfect channel, no Byzantine agent; then each round is one
    :meth:`~estimation.batching.Batch.step_closed` call (the same maths without the
    per-message bookkeeping)."""
    if (len(groups) != 1 or groups[0].agents != list(range(exp.N)) or not channel.perfect or exp.byzantine
            or not exp.static or any(n.strategy is not None for n in nodes)):
        return None
    return groups[0]


def make_channel(exp: Experiment) -> Channel:
    ch = exp.scenario.network.channel
    return Channel(
        seed=exp.seed,
        drop_p=ch.drop_p,
        delay_max=ch.delay_max,
        losses=loss_windows((w.rounds, w.links) for w in ch.losses),
    )


def make_nodes(exp: Experiment, channel: Channel) -> list[AgentNode]:
    index_of = {aid: i for i, aid in enumerate(exp.agent_ids)}
    nodes = []
    for i, aid in enumerate(exp.agent_ids):
        node = AgentNode(aid, exp.make_estimator(i), channel, [exp.agent_ids[j] for j in exp.in_neighbours(i)],
                         index_of=index_of, out_neighbours=[exp.agent_ids[j] for j in exp.out_neighbours(i)])
        node.strategy = byzantine_strategy(exp, i)  # fresh: a strategy keeps state (its RNG, history)
        nodes.append(node)
    return nodes


class SimulatorView:
    """The omniscient adversary's view in the simulator: every message of the round.

    Byzantine agents run after the regular ones in each round, so the messages the
    regular agents sent in round ``k`` are known when an adversary computes its own.
    A receiver's estimator may say which payload components a sender's value feeds
    (``uses(sender_index) -> bool mask``, e.g. per-mode MEDAG neighbours); the others are
    zeroed.
    """

    def __init__(self, nodes: list[AgentNode]) -> None:
        self._by_id = {n.id: n for n in nodes}
        self.k = 0

    def others_for(self, receiver: int, sender: int) -> list[np.ndarray]:
        node = self._by_id[receiver]
        uses = node.estimator.uses if isinstance(node.estimator, MaskedInputs) else None
        out = []
        for r in node.pending_from_others(self.k, sender):
            v = np.asarray(r.value, dtype=float)
            out.append(v * uses(r.sender) if uses is not None else v)
        return out


def deliver(node: AgentNode, k: int, msg, targets: list[AgentNode]) -> None:
    """Hand ``node``'s round-``k`` message(s) to its out-neighbours."""
    if isinstance(msg, dict):
        for tgt in targets:
            payload = msg.get(tgt.id)
            if payload is None:
                continue
            if isinstance(payload, Forged):
                tgt.receive(node.id, payload.stamp, payload.value)
            else:
                tgt.receive(node.id, k, payload)
    else:
        for tgt in targets:
            tgt.receive(node.id, k, msg)


@dataclass
class SimResult:
    monitor: Monitor
    regular: np.ndarray
    links: dict[str, dict[str, int]]
    elapsed: float
    rounds: int
    estimates: np.ndarray | None = None  # (rounds+1, N, n) when kept
    truth: np.ndarray | None = None  # (rounds+1, n) when kept

    @property
    def agent_rounds_per_s(self) -> float:
        return self.rounds * self.regular.size / self.elapsed if self.elapsed > 0 else float("inf")


def simulate(
    exp: Experiment,
    *,
    progress: Callable[[int, float], None] | None = None,
    keep_trajectories: bool = False,
    record: bool = True,
    dashboard: Any = None,
    batched: bool = True,
) -> SimResult:
    """Run the scenario in-process.

    Parameters
    ----------
    progress : called as ``progress(k, worst_error_inf)`` every 256 rounds and at the end
    keep_trajectories : also return every estimate and the true state (for equivalence tests)
    record : compute the monitor's metrics (benchmarks may switch it off)
    dashboard : an :class:`agents.dashboard.Dashboard` to stream to (or None)
    batched : step the regular agents whose estimators declare
        :class:`~estimation.batching.Batchable` in one call per group and round
        (:func:`batch_groups`; a closed team, :func:`closed_team`, without the
        per-message bookkeeping); the estimates equal ``batched=False`` (each agent's
        own ``step``) bit for bit or within 1e-12 relative, as each algorithm's docs say
    """
    channel = make_channel(exp)
    nodes = make_nodes(exp, channel)
    plant = PlantRole(exp)
    mon = Monitor(exp)
    K = exp.n_rounds
    N, n = exp.N, exp.n
    targets = [[nodes[j] for j in exp.out_neighbours(i)] for i in range(N)]
    # regular agents first, Byzantine ones last (they may read the round's messages)
    order = [i for i in range(N) if i not in exp.byzantine] + sorted(exp.byzantine)
    view = SimulatorView(nodes)
    for i in exp.byzantine:
        nodes[i].view = view
    static = exp.static
    rows = exp.agent_rows
    diag = [(i, nodes[i].estimator) for i in range(N) if has_diagnostics(nodes[i].estimator)]
    frames: dict[int, np.ndarray] = {}
    if dashboard is not None:
        def on_chunk(chunk_rows, xs, ests):
            counters = np.array([[sum(getattr(c, f) for c in node.links.values())
                                  for f in ("delivered", "dropped", "late", "rejected")] for node in nodes], dtype=float)
            dashboard.log_chunk(chunk_rows, mon, x=xs, est=ests, delivered=frames, counters=counters)
            frames.clear()
        mon.on_chunk = on_chunk
    groups = batch_groups(exp, nodes) if batched else []
    in_batch = {i for g in groups for i in g.agents}
    singles = [i for i in order if i not in in_batch]
    closed = closed_team(exp, nodes, groups, channel) if batched else None
    est_out = np.empty((N, n))
    traj = np.empty((K + 1, N, n)) if keep_trajectories else None
    truth = np.empty((K + 1, n)) if keep_trajectories else None
    heard = np.zeros((N, N), dtype=bool)  # a perfect channel delivers every link (closed team)
    for i in range(N):
        heard[i, exp.in_neighbours(i)] = True

    def measurement(i: int, k: int, y: np.ndarray) -> np.ndarray | None:
        if static:
            return y[rows[i]]
        r = exp.rows_at(i, k)
        return None if r is None else y[r]

    t0 = last_flush = time.perf_counter()
    for k in range(K + 1):
        y = plant.measure(k)
        if closed is not None:
            est_k = closed.step_closed(k, y)
        else:
            view.k = k
            est_k = est_out
            for g in groups:  # every batch in one call, then the agents stepped alone
                outs = g.step(k, [measurement(i, k, y) for i in g.agents], [nodes[i].open_round(k) for i in g.agents])
                got = g.estimates()
                if isinstance(got, list):
                    for i, e in zip(g.agents, got):
                        est_out[i] = e
                else:
                    est_out[g.agents] = got
                for i, out in zip(g.agents, outs):
                    deliver(nodes[i], k, out, targets[i])
            for i in singles:
                node = nodes[i]
                out = node.run_round(k, measurement(i, k, y))
                est_out[i] = node.estimate(out)
                msg = node.publish(k, out) if node.strategy is not None else out
                deliver(node, k, msg, targets[i])
        x = plant.x
        if dashboard is not None and dashboard.is_map_frame(k):
            if closed is not None:
                D = heard.copy() if k > 0 else np.zeros((N, N), dtype=bool)
            else:
                D = np.zeros((N, N), dtype=bool)
                for i, node in enumerate(nodes):
                    for j in node.arrived:
                        D[i, j] = True
            frames[k] = D
        if record:
            mon.record(k, x, est_k)
            for i, est in diag:
                mon.record_diagnostics(k, i, *read_diagnostics(est))
        if keep_trajectories:
            traj[k] = est_k
            truth[k] = x
        if progress is not None and (k & 255 == 0 or k == K):
            progress(k, mon.current_worst() if record else float("nan"))
            if dashboard is not None and time.perf_counter() - last_flush > 0.5:
                mon.flush()  # keep the live view fresh
                last_flush = time.perf_counter()
        if k < K:
            plant.advance(k)
    for g in groups:
        g.sync()
    if closed is not None:  # every message of every link was sent and delivered the next round
        for node in nodes:
            for c in node.links.values():
                c.sent += K + 1
                c.delivered += K + 1
    mon.flush()
    elapsed = time.perf_counter() - t0
    links = {f"{j}->{node.id}": c.as_dict() for node in nodes for j, c in node.links.items()}
    regular = np.array([i not in exp.byzantine for i in range(N)])
    return SimResult(mon, regular, links, elapsed, K + 1, traj, truth)
