"""The pieces of a round that both drivers share (DESIGN.md, "One round, both drivers").

The in-process simulator (:mod:`agents.simulate`) and the networked runtime
(:mod:`agents.net`) run the same :class:`~agents.node.AgentNode`; what lies around a node
in a round is here, once, so that ``rse run`` in lockstep equals ``rse simulate`` by
construction:

* :func:`round_order` / :func:`round_rank`: the order in which the agents act in a round
  (regular agents first, by index, then the Byzantine ones, by index: an omniscient
  adversary may read what the others sent this round);
* :class:`Reads`: which rows of the stacked measurement ``y[k]`` an agent reads in round
  ``k`` (its bank's rows, or its patrol's location, or none while commuting);
* :func:`addressed`: what a published message sends to each receiver (an honest agent's
  broadcast; a Byzantine strategy's addressed payloads, :class:`~transport.byzantine.Forged`
  ones with their own round stamp, ``None`` for nothing);
* :func:`count_fate`, :func:`link_rows`, :func:`links_table`, :func:`receiver_counters`:
  the per-link counters (a receiver's node counts them; the summary and the dashboard
  read them in one format);
* :class:`DashboardFeed`: the links delivered per map frame and the counters handed to the
  dashboard with every chunk of recorded rounds;
* :class:`Team`, :class:`PlantTeam`: what a role reads of the team it is handed (the
  built experiment, or a picklable slice of it: :mod:`agents.net.slices`).

The omniscient adversary's view is :mod:`agents.omniscient`. Nothing here imports the
scenario schema, pyarrow, Rerun or the design stack: an agent process imports this module.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from transport.byzantine import Forged
from transport.channel import LinkCounters

if TYPE_CHECKING:
    from estimation.attacks import SensorAttackSignal
    from estimation.signals import Signal
    from scenarios.build import Experiment
    from scenarios.common import PlantStepper

#: the per-link counters, in the order of a link row after the sender's id (:func:`link_rows`)
LINK_FIELDS = ("sent", "delivered", "dropped", "late", "rejected")
#: a receiver's counters on the dashboard (summed over its in-links)
DASHBOARD_FIELDS = ("delivered", "dropped", "late", "rejected")


# ------------------------------------------------------------------ what a role is handed


class Team(Protocol):
    """What every role reads of its team (:class:`~scenarios.build.Experiment`, an agent's
    :class:`~agents.net.slices.AgentSlice`, the plant's :class:`~agents.net.slices.PlantSlice`):
    the agents' ids in index order, the state dimension ``n``, the team size ``N`` and the
    rows ``ny`` of the stacked measurement (the bounds of the messages' shapes)."""

    @property
    def agent_ids(self) -> Sequence[int]: ...
    @property
    def n(self) -> int: ...
    @property
    def N(self) -> int: ...
    @property
    def ny(self) -> int: ...


class PlantTeam(Team, Protocol):
    """What the plant reads (the experiment or its :class:`~agents.net.slices.PlantSlice`):
    the model, input and sensor attacks, the horizon, who reads which rows when, and the
    out-neighbours (agent indices) whose lockstep rounds wait for each agent."""

    @property
    def dt(self) -> float: ...
    @property
    def n_rounds(self) -> int: ...
    @property
    def x0(self) -> np.ndarray: ...
    @property
    def C(self) -> np.ndarray: ...
    @property
    def Ad(self) -> np.ndarray: ...
    @property
    def Bd(self) -> np.ndarray: ...
    @property
    def input(self) -> Signal: ...
    @property
    def sensor_attacks(self) -> Sequence[SensorAttackSignal]: ...
    @property
    def stepper(self) -> PlantStepper | None: ...
    @property
    def static(self) -> bool: ...
    @property
    def agent_rows(self) -> Sequence[np.ndarray]: ...
    def out_neighbours(self, i: int) -> list[int]: ...
    def rows_at(self, i: int, k: int) -> np.ndarray | None: ...


# ------------------------------------------------------------------ who acts when


def round_order(N: int, byzantine: Iterable[int]) -> list[int]:
    """Agent indices in the order they act in a round: regular agents first (by index),
    then the Byzantine ones (by index), which may read the regular agents' messages."""
    byz = set(byzantine)
    return [i for i in range(N) if i not in byz] + sorted(byz)


def round_rank(agent_ids: Sequence[int], byzantine: Iterable[int]) -> dict[int, int]:
    """Agent id -> its rank in :func:`round_order`."""
    return {agent_ids[i]: r for r, i in enumerate(round_order(len(agent_ids), byzantine))}


def regular_mask(exp: Experiment) -> np.ndarray:
    """``(N,)`` bool: the agents that are not Byzantine."""
    return np.array([i not in exp.byzantine for i in range(exp.N)])


# ------------------------------------------------------------------ what an agent reads


class Reads:
    """Which rows of the stacked ``y[k]`` each agent reads (``team``: an experiment or a
    plant slice, :class:`agents.net.slices.PlantSlice`: ``static``, ``agent_rows`` and
    ``rows_at``)."""

    def __init__(self, team: PlantTeam) -> None:
        self.static = bool(team.static)
        self._rows = list(team.agent_rows)
        self._rows_at = team.rows_at

    def rows(self, i: int, k: int) -> np.ndarray | None:
        """Rows agent index ``i`` reads in round ``k`` (None: at no location)."""
        return self._rows[i] if self.static else self._rows_at(i, k)

    def measurement(self, i: int, k: int, y: np.ndarray) -> np.ndarray | None:
        """Agent index ``i``'s measurement in round ``k`` (None: at no location)."""
        if self.static:
            return y[self._rows[i]]
        r = self._rows_at(i, k)
        return None if r is None else y[r]


# ------------------------------------------------------------------ what an agent sends


def addressed(msg: Mapping[int, Any], k: int, receivers: Iterable[int]) -> list[tuple[int, int, np.ndarray]]:
    """The ``(receiver, stamp, value)`` messages of an addressed round-``k`` publication
    (:meth:`agents.node.AgentNode.publish`'s mapping), in the order of ``receivers``: a
    missing receiver or ``None`` gets nothing, a :class:`~transport.byzantine.Forged`
    payload carries its own stamp, any other payload is stamped ``k``."""
    out = []
    for j in receivers:
        p = msg.get(j)
        if p is None:
            continue
        if isinstance(p, Forged):
            out.append((j, int(p.stamp), p.value))
        else:
            out.append((j, k, p))
    return out


# ------------------------------------------------------------------ link counters


def count_fate(c: LinkCounters, when: int | None, stamp: int) -> None:
    """Count one message stamped ``stamp`` on link counters ``c`` that the channel makes
    visible from round ``when`` (None: lost). ``sent`` is the caller's."""
    if when is None:
        c.dropped += 1
        return
    c.delivered += 1
    if when > stamp + 1:
        c.late += 1


def link_rows(links: Mapping[int, LinkCounters]) -> np.ndarray:
    """A receiver's counters as rows ``[sender, sent, delivered, dropped, late, rejected]``
    (in its in-neighbours' order; the agent process reports them so)."""
    return np.array([[j, *(c.as_dict()[f] for f in LINK_FIELDS)] for j, c in links.items()],
                    dtype=float).reshape(-1, 1 + len(LINK_FIELDS))


def links_table(receivers: Iterable[tuple[int, np.ndarray]]) -> dict[str, dict[str, int]]:
    """``summary.json``'s ``links`` (``"j->i"`` -> counters) from each receiver's
    :func:`link_rows`, in the order given (by receiver index: see :func:`links_of`)."""
    out: dict[str, dict[str, int]] = {}
    for receiver, rows in receivers:
        for row in rows:
            j, *vals = (int(v) for v in row)
            out[f"{j}->{receiver}"] = dict(zip(LINK_FIELDS, vals))
    return out


def links_of(nodes: Sequence[Any]) -> dict[str, dict[str, int]]:
    """:func:`links_table` of a team of :class:`~agents.node.AgentNode` (the simulator)."""
    return links_table((node.id, link_rows(node.links)) for node in nodes)


def receiver_counters(nodes: Sequence[Any]) -> np.ndarray:
    """``(N, 4)``: per receiver, its :data:`DASHBOARD_FIELDS` summed over its in-links."""
    return counters_array([total(node.links.values()) for node in nodes])


def total(links: Iterable[LinkCounters]) -> LinkCounters:
    """The sum of some link counters."""
    sums = dict.fromkeys(LINK_FIELDS, 0)
    for c in links:
        for f, v in c.as_dict().items():
            sums[f] += v
    return LinkCounters(**sums)


def counters_array(per_receiver: Sequence[LinkCounters]) -> np.ndarray:
    """``(N, 4)``: :data:`DASHBOARD_FIELDS` of one aggregate :class:`LinkCounters` per receiver."""
    return np.array([[c.as_dict()[f] for f in DASHBOARD_FIELDS] for c in per_receiver],
                    dtype=float).reshape(-1, len(DASHBOARD_FIELDS))


# ------------------------------------------------------------------ dashboard frames


class DashboardFeed:
    """What a driver hands an :class:`agents.dashboard.Dashboard` with each chunk of
    recorded rounds: the links that delivered in each map-frame round (``(N, N)`` bool,
    ``D[receiver, sender]``; a round with no frame recorded shows none) and the link
    counters (``counters()``: ``(N, 4)``, :data:`DASHBOARD_FIELDS`)."""

    def __init__(self, dash: Any, N: int, counters: Callable[[], np.ndarray]) -> None:
        self.dash = dash
        self.N = N
        self.counters = counters
        self.frames: dict[int, np.ndarray] = {}

    def wants(self, k: int) -> bool:
        """Whether round ``k`` is a map frame of the dashboard."""
        return bool(self.dash.is_map_frame(k))

    def frame(self, k: int) -> np.ndarray:
        """The (mutable) frame of round ``k``, empty at first."""
        D = self.frames.get(k)
        if D is None:
            D = self.frames[k] = np.zeros((self.N, self.N), dtype=bool)
        return D

    def set_arrivals(self, k: int, arrived: Iterable[Iterable[int]]) -> None:
        """Round ``k``'s frame from each receiver's senders whose message became visible."""
        D = self.frame(k)
        for i, senders in enumerate(arrived):
            for j in senders:
                D[i, j] = True

    def log(self, rows: Any, mon: Any, xs: np.ndarray, ests: np.ndarray) -> None:
        """Hand a chunk of recorded rounds to the dashboard (a monitor's ``on_chunk``)."""
        delivered = {}
        for k in rows:
            k = int(k)
            if self.dash.is_map_frame(k):
                D = self.frames.pop(k, None)
                delivered[k] = D if D is not None else np.zeros((self.N, self.N), dtype=bool)
        self.dash.log_chunk(rows, mon, x=xs, est=ests, delivered=delivered, counters=self.counters())
