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

from estimation.batching import Batch, Batchable
from scenarios.build import Experiment
from transport.channel import Channel

from .middleware import make_channel, make_nodes
from .monitor import Monitor, has_diagnostics, read_diagnostics
from .node import AgentNode
from .omniscient import NodesView, reads_view, view_topology
from .plant import PlantRole
from .rounds import DashboardFeed, Reads, addressed, links_of, receiver_counters, regular_mask, round_order

__all__ = ["SimResult", "batch_groups", "closed_team", "deliver", "make_channel", "make_nodes", "simulate"]


def batch_groups(exp: Experiment, nodes: list[AgentNode]) -> list[Batch]:
    """The regular agents stepped together, one :class:`~estimation.batching.Batch` per
    group of estimators that declare :class:`~estimation.batching.Batchable` with equal
    ``batch_key()`` (e.g. LFRE agents by fusion rule and ``f``; Lee-Kim-Shim agents of up to 64
    states); an estimator whose key is None steps on its own.
    Byzantine agents always run their own ``step``."""
    keys: dict[Any, list[int]] = {}
    for i, node in enumerate(nodes):
        est = node.estimator
        key = est.batch_key() if i not in exp.byzantine and isinstance(est, Batchable) else None
        if key is not None:  # None: this estimator steps on its own
            keys.setdefault(key, []).append(i)
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


def deliver(node: AgentNode, k: int, msg: Any, targets: list[AgentNode]) -> None:
    """Hand ``node``'s round-``k`` message(s) to its out-neighbours (an addressed
    publication as :func:`agents.rounds.addressed` unpacks it)."""
    if isinstance(msg, dict):
        by_id = {t.id: t for t in targets}
        for j, stamp, value in addressed(msg, k, by_id):
            by_id[j].receive(node.id, stamp, value)
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
    deliveries: Any = None,
    evidence: Any = None,
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
    deliveries : a run directory to write the delivery record into (:mod:`agents.deliveries`,
        as ``rse run`` does; each agent then runs its own ``step``)
    evidence : an :class:`agents.evidence.EquivocationWatch` through which every message is
        delivered (signed, digested, compared one round later)
    """
    channel = make_channel(exp)
    nodes = make_nodes(exp, channel)
    writers = []
    if deliveries is not None:
        from .deliveries import attach

        writers, batched = attach(nodes, deliveries), False
    plant = PlantRole(exp)
    mon = Monitor(exp)
    K = exp.n_rounds
    N, n = exp.N, exp.n
    targets = [[nodes[j] for j in exp.out_neighbours(i)] for i in range(N)]
    order = round_order(N, exp.byzantine)  # an omniscient adversary reads the messages of those before it
    views = []
    for i in exp.byzantine:
        if reads_view(nodes[i].strategy):
            topo = view_topology(exp, nodes[i].id, {nd.id: nd.estimator for nd in nodes})
            nodes[i].view = view = NodesView(topo, nodes)
            views.append(view)
    reads = Reads(exp)
    measurement = reads.measurement
    feed: DashboardFeed | None = None
    if dashboard is not None:
        feed = live = DashboardFeed(dashboard, N, lambda: receiver_counters(nodes))
        mon.on_chunk = lambda rows, xs, ests: live.log(rows, mon, xs, ests)
    groups = batch_groups(exp, nodes) if batched else []
    in_batch = {i for g in groups for i in g.agents}
    singles = [i for i in order if i not in in_batch]
    closed = closed_team(exp, nodes, groups, channel) if batched and evidence is None else None
    send = deliver if evidence is None else evidence.deliver
    rows_diag = [(g, np.asarray(g.agents)) for g in groups if g.diagnostic_rows]  # read all at once
    by_rows = {i for g, _ in rows_diag for i in g.agents}
    diag = [(i, nodes[i].estimator) for i in range(N) if i not in by_rows and has_diagnostics(nodes[i].estimator)]
    est_out = np.empty((N, n))
    traj = np.empty((K + 1, N, n)) if keep_trajectories else None
    truth = np.empty((K + 1, n)) if keep_trajectories else None
    heard = np.zeros((N, N), dtype=bool)  # a perfect channel delivers every link (closed team)
    for i in range(N):
        heard[i, exp.in_neighbours(i)] = True

    try:
        t0 = last_flush = time.perf_counter()
        for k in range(K + 1):
            y = plant.measure(k)
            if closed is not None:
                est_k = closed.step_closed(k, y)
            else:
                for view in views:
                    view.k = k
                est_k = est_out
                for g in groups:  # every batch in one call, then the agents stepped alone
                    outs = g.step(k, [measurement(i, k, y) for i in g.agents], [nodes[i].open_round(k) for i in g.agents])
                    batch = g.estimates()
                    if isinstance(batch, list):
                        for i, e in zip(g.agents, batch):
                            est_out[i] = e
                    else:
                        est_out[g.agents] = batch
                    for i, out in zip(g.agents, outs):
                        send(nodes[i], k, out, targets[i])
                for i in singles:
                    node = nodes[i]
                    out = node.run_round(k, measurement(i, k, y))
                    est_out[i] = node.estimate(out)
                    msg = node.publish(k, out) if node.strategy is not None else out
                    send(node, k, msg, targets[i])
            x = plant.x
            if feed is not None and feed.wants(k):
                if closed is not None:
                    if k > 0:
                        feed.frame(k)[:] = heard
                else:
                    feed.set_arrivals(k, (node.arrived for node in nodes))
            if record:
                mon.record(k, x, est_k)
                for g, idx in rows_diag:
                    got = g.diagnostics()
                    if got is not None:
                        mon.record_diagnostic_rows(k, idx, *got)
                for i, est in diag:
                    mon.record_diagnostics(k, i, *read_diagnostics(est))
            if traj is not None and truth is not None:  # keep_trajectories
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
        if evidence is not None:
            evidence.finish(K)
    finally:
        for w in writers:
            w.close()
    if closed is not None:  # every message of every link was sent and delivered the next round
        for node in nodes:
            for c in node.links.values():
                c.sent += K + 1
                c.delivered += K + 1
    mon.flush()
    elapsed = time.perf_counter() - t0
    return SimResult(mon, regular_mask(exp), links_of(nodes), elapsed, K + 1, traj, truth)
