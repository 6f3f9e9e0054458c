"""``rse replay``: a recorded run re-executed in-process from its delivery record
(:mod:`agents.deliveries`; DESIGN.md, "Deliveries are data").

Each agent steps at exactly the rounds it stepped in the run, on the measurement it used,
with an inbox holding, per in-neighbour, the message of the recorded stamp: a regular
sender's payload is what the replay's own estimator of that sender returned in the round
of the stamp (so a counterfactual estimator sends what it computes), a Byzantine sender's
is what it addressed to this receiver in the run (replayed as recorded). A restarted agent
(a second incarnation in the record) starts from a fresh estimator at its first recorded
round. With the scenario of the run the estimates equal the run's bit for bit.

The replay runs up to the last complete round: the run's last round when it completed,
else the last round every agent's record reached (a writer killed mid-run
leaves a record cut at some round); it stops earlier, with ``complete: false``, at the
first round that needs a payload the record does not hold.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from estimation.base import EstimatePayload, Received
from estimation.errors import RSEError
from scenarios.build import Experiment

from .deliveries import Incarnation
from .monitor import Monitor
from .plant import PlantRole
from .rounds import DashboardFeed, regular_mask, round_order


@dataclass
class ReplayResult:
    """A replay's outcome, shaped as :class:`agents.simulate.SimResult` (what a run
    directory is written from), plus where and why it ended."""

    monitor: Monitor
    regular: np.ndarray
    links: dict[str, dict[str, int]]
    elapsed: float
    rounds: int
    estimates: np.ndarray  # (rounds, N, n); NaN where an agent did not step (or its estimate was not finite)
    truth: np.ndarray  # (rounds, n)
    last_round: int
    complete: bool
    reason: str | None = None

    @property
    def agent_rounds_per_s(self) -> float:
        return self.rounds * self.regular.size / self.elapsed if self.elapsed > 0 else float("inf")


def _steps(exp: Experiment, record: dict[int, list[Incarnation]]) -> dict[int, list[tuple[int, Incarnation, int, bool]]]:
    """Round -> ``(agent index, incarnation, row, fresh)`` of every recorded step, in the
    order the agents act (:func:`agents.rounds.round_order`); ``fresh``: the first step of
    a restarted agent."""
    index = {aid: i for i, aid in enumerate(exp.agent_ids)}
    rank = {i: r for r, i in enumerate(round_order(exp.N, exp.byzantine))}
    out: dict[int, list[tuple[int, Incarnation, int, bool]]] = {}
    for aid, incs in record.items():
        i = index.get(aid)
        if i is None:
            raise RSEError(f"the record holds agent {aid}, which the scenario does not have "
                           f"(agents {', '.join(map(str, exp.agent_ids))})")
        want = [exp.agent_ids[j] for j in exp.in_neighbours(i)]
        for n, inc in enumerate(incs):
            if inc.in_ids != want:
                raise RSEError(f"the record of agent {aid} lists in-neighbours {inc.in_ids}; the scenario has {want}")
            for row, k in enumerate(inc.k):
                out.setdefault(int(k), []).append((i, inc, row, n > 0 and row == 0))
    for steps in out.values():
        steps.sort(key=lambda s: rank[s[0]])
    return out


def last_complete_round(exp: Experiment, record: dict[int, list[Incarnation]], completed: bool) -> int:
    """The last round the replay runs: the run's last (a completed run: an agent that
    skipped the final rounds has no step there), else the last that every agent's record
    reached."""
    if completed:
        return exp.n_rounds
    ends = [int(inc.k[-1]) for incs in record.values() for inc in incs[-1:] if len(inc.k)]
    return min(min(ends), exp.n_rounds) if ends else -1


def replay(exp: Experiment, record: dict[int, list[Incarnation]], *, completed: bool = True,
           links: dict[str, dict[str, int]] | None = None, reported: np.ndarray | None = None,
           dashboard: Any = None, progress: Callable[[int, float], None] | None = None) -> ReplayResult:
    """Re-execute ``record`` (:func:`agents.deliveries.read_record`) with the estimators of
    ``exp`` (the run's scenario, or a counterfactual one with the same team); see the
    module docstring. ``completed``: the run completed (else it ends at the last round all
    records reached); ``links``: the run's link counters, for the summary; ``reported``:
    ``(rounds, N)`` bool, the agent-rounds the run's monitor recorded (its own deliveries:
    a report that came after the monitor closed its round, or that died with a killed
    process, is absent from the run's metrics): within its rounds, an agent-round is in
    the replay's metrics only where it is in the run's."""
    N, n = exp.N, exp.n
    last = last_complete_round(exp, record, completed)
    steps = _steps(exp, record)
    ests = [exp.make_estimator(i) for i in range(N)]
    byz = set(exp.byzantine)
    sent: dict[tuple[int, int, int], np.ndarray] = {}  # (sender, receiver, stamp) -> a Byzantine payload
    for aid, incs in record.items():
        for inc in incs:
            for _k, to, s, v in inc.sends:
                sent.setdefault((aid, to, s), v)
    payload: dict[tuple[int, int], np.ndarray] = {}  # (regular sender id, stamp) -> what it sent
    index = {aid: i for i, aid in enumerate(exp.agent_ids)}
    plant, mon = PlantRole(exp), Monitor(exp)
    if dashboard is not None:
        live = DashboardFeed(dashboard, N, lambda: np.zeros((N, 4)))
        mon.on_chunk = lambda rows, xs, ests_: live.log(rows, mon, xs, ests_)
    traj = np.full((last + 1, N, n), np.nan)
    truth = np.full((last + 1, n), np.nan)
    est_k = np.empty((N, n))
    reason = None
    t0 = time.perf_counter()
    k = -1
    for k in range(last + 1):
        plant.measure(k)  # the plant's own state (its noise draws) as in the run
        present = np.zeros(N, dtype=bool)
        heard = reported[k] if reported is not None and k < len(reported) else None
        for i, inc, row, fresh in steps.get(k, ()):
            if fresh:  # a restarted agent: a new process, a fresh estimator
                ests[i] = exp.make_estimator(i)
            aid = exp.agent_ids[i]
            inbox = {}
            for j, s in zip(inc.in_ids, inc.stamps[row]):
                if s < 0:
                    continue
                got = sent.get((j, aid, int(s))) if index[j] in byz else payload.get((j, int(s)))
                if got is None:
                    reason = f"agent {aid}'s round {k} holds agent {j}'s message stamped {int(s)}, which the record lacks"
                    break
                inbox[index[j]] = Received(index[j], int(s), got)
            if reason is not None:
                break
            est = ests[i]
            out = est.step(k, inc.y[row], inbox)
            if i not in byz:
                payload[(aid, k)] = np.array(out, dtype=float)  # the run sent these bytes
            own = out if isinstance(est, EstimatePayload) and est.payload_is_estimate else est.estimate
            est_k[i] = own
            present[i] = bool(np.all(np.isfinite(own))) and (heard is None or bool(heard[i]))
        if reason is not None:
            k -= 1
            break
        x = plant.x
        traj[k][present] = est_k[present]
        truth[k] = x
        mon.record(k, x, est_k, present)
        if progress is not None and (k & 255 == 0 or k == last):
            progress(k, mon.current_worst())
        if k < exp.n_rounds:
            plant.advance(k)
    mon.flush()
    if reason is None and not completed:
        reason = f"the run did not complete: replayed up to round {k}, the last that every agent's record reached"
    elapsed = time.perf_counter() - t0
    return ReplayResult(mon, regular_mask(exp), links or {}, elapsed, k + 1, traj[: k + 1], truth[: k + 1], k,
                        completed and reason is None, reason)
