"""The in-process lockstep driver (``rse simulate``).

Every role of the scenario in one Python process, round by round (DESIGN.md, "One round"):

1. the plant publishes ``y[k]`` (sensor attacks applied); the monitor gets ``x[k]``;
2. every agent takes its measurement and its inbox and publishes its message stamped ``k``;
3. every message is handed to each out-neighbour's node, whose channel model decides when
   (if ever) it becomes visible;
4. the monitor records the errors of round ``k``; the plant advances.

Deterministic for a given seed.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from scenarios.build import Experiment
from transport.channel import Channel, loss_windows

from .monitor import Monitor
from .node import AgentNode
from .plant import PlantRole


def make_channel(exp: Experiment) -> Channel:
    ch = exp.scenario.network.channel
    return Channel(
        seed=exp.seed,
        drop_p=ch.drop_p,
        delay_max=ch.delay_max,
        losses=loss_windows(((w.rounds, w.links) for w in ch.losses)),
    )


def make_nodes(exp: Experiment, channel: Channel) -> list[AgentNode]:
    return [
        AgentNode(aid, exp.make_estimator(i), channel, [exp.agent_ids[j] for j in exp.in_neighbours(i)])
        for i, aid in enumerate(exp.agent_ids)
    ]


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
) -> SimResult:
    """Run the scenario in-process.

    Parameters
    ----------
    progress : called as ``progress(k, worst_error_inf)`` every 256 rounds and at the end
    keep_trajectories : also return every estimate and the true state (for equivalence tests)
    record : compute the monitor's metrics (benchmarks may switch it off)
    """
    channel = make_channel(exp)
    nodes = make_nodes(exp, channel)
    plant = PlantRole(exp)
    mon = Monitor(exp)
    K = exp.n_rounds
    N, n = exp.N, exp.n
    rows = exp.agent_rows
    targets = [[nodes[j] for j in exp.out_neighbours(i)] for i in range(N)]
    ids = exp.agent_ids
    est_out = np.empty((N, n))
    traj = np.empty((K + 1, N, n)) if keep_trajectories else None
    truth = np.empty((K + 1, n)) if keep_trajectories else None
    t0 = time.perf_counter()
    for k in range(K + 1):
        y = plant.measure(k)
        for i, node in enumerate(nodes):
            est_out[i] = out = node.run_round(k, y[rows[i]])
            msg = node.publish(k, out) if node.strategy is not None else out
            if isinstance(msg, dict):
                for tgt in targets[i]:
                    payload = msg.get(tgt.id)
                    if payload is not None:
                        tgt.receive(ids[i], k, payload)
            else:
                for tgt in targets[i]:
                    tgt.receive(ids[i], k, msg)
        x = plant.x
        if record:
            mon.record(k, x, est_out)
        if keep_trajectories:
            traj[k] = est_out
            truth[k] = x
        if progress is not None and (k & 255 == 0 or k == K):
            progress(k, mon.current_worst() if record else float("nan"))
        if k < K:
            plant.advance(k)
    mon.flush()
    elapsed = time.perf_counter() - t0
    links = {f"{j}->{node.id}": c.as_dict() for node in nodes for j, c in node.links.items()}
    regular = np.array([i not in exp.byzantine for i in range(N)])
    return SimResult(mon, regular, links, elapsed, K + 1, traj, truth)
