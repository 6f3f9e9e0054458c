"""The omniscient adversary's view, once for both drivers.

A Byzantine strategy that reads ``node.view`` (``cancellation``: Mitra et al., Section
8.1) asks, for each of its receivers ``j``, which values stamped ``k`` ``j``'s other
in-neighbours sent to ``j`` that ``j`` will use in round ``k + 1``
(:class:`transport.byzantine.AdversaryView`). What that is, is decided here for both
drivers:

* which senders count: ``j``'s in-neighbours that act before the adversary in the round
  (:func:`agents.rounds.round_order`), in that order (so the sums are bit-identical);
* which components count: the receiver's estimator may declare
  :class:`~estimation.base.MaskedInputs`; the others are zeroed;
* :class:`ViewTopology` holds both (picklable: part of an agent process's slice).

:class:`OmniscientView` is the one ``others_for``; a driver says only where a sender's
value is found (:meth:`OmniscientView.visible`): :class:`NodesView` reads it off the
receivers' nodes in the simulator, :class:`agents.net.view.NetworkView` off the messages
of the run and the channel model.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from estimation.base import MaskedInputs
from transport.byzantine import Strategy

from .rounds import round_rank

if TYPE_CHECKING:
    from scenarios.build import Experiment

#: the Byzantine strategies that read the view
OMNISCIENT = frozenset({"cancellation"})


def reads_view(strategy: Any) -> bool:
    """Whether a Byzantine strategy reads ``node.view`` (the omniscient adversary)."""
    return isinstance(strategy, Strategy) and strategy.kind in OMNISCIENT


@dataclass(frozen=True)
class ViewTopology:
    """What the view of one adversary needs of the team (picklable).

    me : the Byzantine agent's id; agent_ids : every agent id, in index order
    out : my out-neighbours; before : receiver -> its in-neighbours (not me) that act
        before me in the round (:func:`agents.rounds.round_order`), in that order
    needed : the agents whose round-``k`` messages the view waits for
    masks : receiver -> sender id -> the receiver estimator's ``uses(sender_index)`` mask
        (receivers that do not declare :class:`~estimation.base.MaskedInputs` are left
        out: every component counts)
    """

    me: int
    agent_ids: tuple[int, ...]
    out: tuple[int, ...]
    before: dict[int, tuple[int, ...]]
    needed: tuple[int, ...]
    masks: dict[int, dict[int, Any]] = field(default_factory=dict)


def view_topology(exp: Experiment, me: int, estimators: dict[int, Any] | None = None) -> ViewTopology:
    """The :class:`ViewTopology` of Byzantine agent ``me`` in ``exp``; ``estimators``:
    agent id -> estimator of each out-neighbour (for their masks; built with
    ``exp.make_estimator`` when not given)."""
    ids = exp.agent_ids
    rank = round_rank(ids, exp.byzantine)
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
        if isinstance(est, MaskedInputs):
            masks[j] = {s: est.uses(index_of[s]) for s in before[j]}
    return ViewTopology(me, tuple(ids), out, before, needed, masks)


class OmniscientView:
    """What each out-neighbour of the adversary will use next round (see the module
    docstring). ``k``: the current round (set by the driver)."""

    def __init__(self, topo: ViewTopology) -> None:
        self.k = 0
        self.me = topo.me
        self.index_of = {aid: i for i, aid in enumerate(topo.agent_ids)}
        self.out = list(topo.out)
        self.out_set = set(self.out)
        #: receiver -> its in-neighbours that act before me, in the round's order
        self.before = {j: list(v) for j, v in topo.before.items()}
        #: the agents whose round-k messages the view needs
        self.needed = list(topo.needed)
        #: receiver -> sender id -> the payload mask of the receiver's ``uses`` (absent: all)
        self.masks = topo.masks

    def visible(self, sender: int, receiver: int, k: int) -> Any:
        """The value stamped ``k`` that ``sender`` sent to ``receiver`` and that
        ``receiver`` will use from round ``k + 1`` on (None: none)."""
        raise NotImplementedError

    def others_for(self, receiver: int, sender: int) -> list[np.ndarray]:
        k = self.k
        masks = self.masks.get(receiver)
        out = []
        for s in self.before.get(receiver, ()):
            if s == sender:
                continue
            v = self.visible(s, receiver, k)
            if v is None:
                continue
            v = np.asarray(v, dtype=float)
            out.append(v * masks[s] if masks is not None else v)
        return out


class NodesView(OmniscientView):
    """The view in the simulator: read off the receivers' :class:`~agents.node.AgentNode`
    (the messages their channel model makes visible next round)."""

    def __init__(self, topo: ViewTopology, nodes: list[Any]) -> None:
        super().__init__(topo)
        self._by_id = {n.id: n for n in nodes}

    def visible(self, sender: int, receiver: int, k: int) -> Any:
        node = self._by_id[receiver]
        s = node.index_of.get(sender)
        found = None
        for r in node.pending_from_others(k, self.me):
            if r.sender == s:
                found = r.value  # the newest of a sender (as the network's store keeps it)
        return found
