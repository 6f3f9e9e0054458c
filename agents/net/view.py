"""The omniscient adversary's view over the network (:class:`NetworkView`): what a
Byzantine agent's out-neighbours will use next round, read off the messages of the run as
:class:`agents.simulate.SimulatorView` reads it off the nodes."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from estimation.base import MaskedInputs

if TYPE_CHECKING:
    from scenarios.build import Experiment


def reads_view(strategy: Any) -> bool:
    """Whether a Byzantine strategy reads ``node.view`` (the omniscient adversary)."""
    return getattr(strategy, "kind", None) == "cancellation"


def simulator_order(exp: Experiment) -> dict[int, int]:
    """Agent id -> rank in the simulator's round order (regular agents first, by index,
    then the Byzantine ones, by index)."""
    order = [i for i in range(exp.N) if i not in exp.byzantine] + sorted(exp.byzantine)
    return {exp.agent_ids[i]: r for r, i in enumerate(order)}


@dataclass(frozen=True)
class ViewTopology:
    """What :class:`NetworkView` needs of the team (picklable, part of an agent's slice).

    me : the Byzantine agent's id; agent_ids : every agent id, in index order
    out : my out-neighbours; before : receiver -> its in-neighbours (not me) that act
        before me in the simulator's order, in that order
    needed : the agents whose round-``k`` messages the view waits for
    masks : receiver -> sender id -> the receiver estimator's ``uses(sender_index)`` mask
        (receivers without ``uses`` are left out: every component counts)
    """

    me: int
    agent_ids: tuple[int, ...]
    out: tuple[int, ...]
    before: dict[int, tuple[int, ...]]
    needed: tuple[int, ...]
    masks: dict[int, dict[int, Any]] = field(default_factory=dict)


def view_topology(exp: Experiment, me: int, estimators: dict[int, Any] | None = None) -> ViewTopology:
    """The :class:`ViewTopology` of Byzantine agent ``me`` in ``exp``; ``estimators``:
    agent id -> estimator of each out-neighbour (for their ``uses`` masks; built with
    ``exp.make_estimator`` when not given; ``{}``: no masks)."""
    rank = simulator_order(exp)
    ids = exp.agent_ids
    index_of = {aid: i for i, aid in enumerate(ids)}
    out = tuple(ids[j] for j in exp.out_neighbours(index_of[me]))
    before: dict[int, tuple[int, ...]] = {}
    for j in out:
        ins = [ids[s] for s in exp.in_neighbours(index_of[j])]
        before[j] = tuple(sorted((s for s in ins if s != me and rank[s] < rank[me]), key=rank.__getitem__))
    needed = tuple(sorted({s for v in before.values() for s in v}))
    masks: dict[int, dict[int, Any]] = {}
    for j in out:
        est = estimators.get(j) if estimators is not None else exp.make_estimator(index_of[j])
        uses = est.uses if isinstance(est, MaskedInputs) else None
        if uses is not None:
            masks[j] = {s: uses(index_of[s]) for s in before[j]}
    return ViewTopology(me, tuple(ids), out, before, needed, masks)


class NetworkView:
    """The omniscient adversary's view over the network: what each out-neighbour ``j``
    of Byzantine agent ``me`` will use next round, exactly as
    :class:`agents.simulate.SimulatorView` reads it off ``j``'s node.

    The agent process feeds it every estimate message of the run (:meth:`add`, broadcast
    and addressed, decoded strictly) and the done reports of the agents it depends on
    (:meth:`add_done`). For round ``k``, :meth:`others_for` returns the values stamped
    ``k`` that ``j``'s other in-neighbours sent to ``j`` and that the channel model makes
    visible to ``j`` at ``k + 1`` -- only from agents that act before ``me`` in the
    simulator's order (regular agents, then Byzantine ones by index) -- masked by ``j``'s
    estimator's ``uses(sender_index)`` when it has one (precomputed: :class:`ViewTopology`), in the simulator's order (so the
    sums are bit-identical). In lockstep the agent publishes round ``k`` only once
    :meth:`ready` (every such agent's round-``k`` messages to ``me``'s out-neighbours have
    arrived, or it is not alive) or the deadline passed.
    """

    MAX_STORED = 1 << 14

    def __init__(self, topo: ViewTopology, channel: Any) -> None:
        self.k = 0
        self.me = topo.me
        self.channel = channel
        self.index_of = {aid: i for i, aid in enumerate(topo.agent_ids)}
        self.out = list(topo.out)
        self.out_set = set(self.out)
        #: receiver -> its in-neighbours that act before me, in the simulator's order
        self.before = {j: list(v) for j, v in topo.before.items()}
        #: the agents whose round-k messages the view needs
        self.needed = list(topo.needed)
        #: receiver -> sender id -> the payload mask of the receiver's ``uses`` (None: all)
        self.masks = topo.masks
        self.bcast: dict[tuple[int, int], np.ndarray] = {}
        self.addr: dict[tuple[int, int, int], np.ndarray] = {}
        self.done: dict[int, dict[int, list[tuple[int, int]]]] = {}

    def wants(self, sender: int, receiver: int | None) -> bool:
        """Whether an estimate on ``agent/{sender}/est[/{receiver}]`` feeds the view."""
        if sender not in self.index_of or sender == self.me:
            return False
        return receiver is None or receiver in self.out_set

    def add(self, sender: int, receiver: int | None, stamp: int, value: np.ndarray) -> None:
        if stamp < self.k - 1 or len(self.bcast) + len(self.addr) >= self.MAX_STORED:
            return
        if receiver is None:
            self.bcast[(sender, stamp)] = value
        else:
            self.addr[(sender, receiver, stamp)] = value

    def add_done(self, sender: int, stamp: int, to: list[tuple[int, int]]) -> None:
        if stamp < self.k or stamp > self.k + 64:
            return
        self.done.setdefault(stamp, {})[sender] = [(j, s) for j, s in to if j in self.out_set]

    def ready(self, k: int, alive: Callable[[int], bool]) -> bool:
        """Every agent the view needs reported round ``k`` and its round-``k`` messages to
        my out-neighbours arrived (agents that are not alive are not waited for)."""
        done = self.done.get(k, {})
        bcast = self.bcast
        for s in self.needed:
            if (s, k) in bcast:
                # a broadcast round-k estimate: an agent either broadcasts or addresses its
                # messages in a round, never both, so nothing else of s is to come
                continue
            d = done.get(s)
            if d is None:
                if alive(s):
                    return False
                continue
            for j, st in d:
                if (s, j, st) not in self.addr and (s, st) not in self.bcast:
                    return False
        return True

    def others_for(self, receiver: int, sender: int) -> list[np.ndarray]:
        k = self.k
        masks = self.masks.get(receiver)
        fate = self.channel.fate
        out = []
        for s in self.before.get(receiver, ()):
            if s == sender:
                continue
            v = self.addr.get((s, receiver, k))
            if v is None:
                v = self.bcast.get((s, k))
            if v is None or fate(s, receiver, k) != k + 1:
                continue
            v = np.asarray(v, dtype=float)
            out.append(v * masks[s] if masks is not None else v)
        return out

    def forget(self, k: int) -> None:
        """Drop what rounds before ``k`` left behind."""
        self.k = k
        for store in (self.bcast, self.addr):
            for key in [key for key in store if key[-1] < k]:
                del store[key]
        for s in [s for s in self.done if s < k]:
            del self.done[s]
