"""Byzantine injection middleware: what a compromised agent sends instead of the truth.

Each strategy is one small object, stacked from the scenario's ``[[attacks]]`` tables with
``target = "agent"`` and identical in both drivers. A strategy is called after the agent's
own estimator ran round ``k``::

    strategy(k, estimate, node) -> dict receiver_id -> payload

where a payload is an array (stamped ``k``), a :class:`Forged` ``(stamp, value)`` pair (a
false or replayed round stamp), or ``None`` (nothing sent to that receiver). Before its
``start`` round a strategy behaves honestly. Adversaries may be omniscient: ``node.view``
(set by the driver) exposes what every receiver will use next round.

Strategies (``kind``):

* ``constant``: sends ``value`` in every component;
* ``huge``: i.i.d. uniform values on ``[-scale, scale]`` (default 1e6), a fresh draw per
  receiver and round, seeded from ``(seed, agent)``;
* ``omission``: sends nothing to the listed receivers (all when none listed);
* ``equivocation``: a different value to each receiver: the estimate plus
  ``scale * (+1 or -1)`` alternating over the receivers' ids, times a per-receiver factor;
* ``false_stamp``: its values (``value = "estimate"`` or ``"huge"``) stamped ``shift``
  rounds in the future (``shift > 0``) or the past (``shift < 0``);
* ``replay``: re-sends the estimate it had ``lag`` rounds ago, stamped as fresh;
* ``crash``: silent from ``start`` on;
* ``cancellation`` (Mitra et al., Section 8.1): to each receiver, the value equal and
  opposite to the sum of the other values that receiver will use next round, which keeps
  the receiver's (non-resilient) estimate static.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any, NamedTuple, Protocol

import numpy as np


class Forged(NamedTuple):
    """A payload sent with an explicit (possibly false) round stamp."""

    stamp: int
    value: np.ndarray


class AdversaryView(Protocol):
    """What an omniscient adversary can read (provided by the driver)."""

    def others_for(self, receiver: int, sender: int) -> list[np.ndarray]:
        """Values stamped this round that ``receiver`` got from its other in-neighbours."""
        ...


@dataclass
class Strategy:
    kind: str
    start: int = 0
    stop: int | None = None
    targets: frozenset[int] | None = None  # receivers affected (None: all)
    value: float = 0.0
    scale: float = 1e6
    shift: int = 1
    lag: int = 10
    payload: str = "huge"
    seed: int = 0
    agent: int = 0
    _rng: np.random.Generator | None = field(default=None, repr=False)
    _history: deque = field(default_factory=lambda: deque(maxlen=4096), repr=False)

    def active(self, k: int) -> bool:
        return k >= self.start and (self.stop is None or k < self.stop)

    @property
    def rng(self) -> np.random.Generator:
        if self._rng is None:
            self._rng = np.random.default_rng([self.seed, 5, self.agent])
        return self._rng

    def __call__(self, k: int, estimate: np.ndarray, node: Any) -> dict[int, Any]:
        self._history.append(estimate)
        receivers = node.out_neighbours
        if not self.active(k):
            return {j: estimate for j in receivers}
        out: dict[int, Any] = {}
        for j in receivers:
            if self.targets is not None and j not in self.targets:
                out[j] = estimate
            else:
                out[j] = self._payload(k, j, estimate, node)
        return out

    def _payload(self, k: int, j: int, est: np.ndarray, node: Any) -> Any:
        kind = self.kind
        if kind == "constant":
            return np.full_like(est, self.value)
        if kind == "huge":
            return self.rng.uniform(-self.scale, self.scale, size=est.shape)
        if kind in ("omission", "crash"):
            return None
        if kind == "equivocation":
            sign = 1.0 if j % 2 else -1.0
            return est + sign * self.scale * (1.0 + 0.1 * j)
        if kind == "false_stamp":
            v = est if self.payload == "estimate" else self.rng.uniform(-self.scale, self.scale, size=est.shape)
            return Forged(k + self.shift, v)
        if kind == "replay":
            h = self._history
            old = h[0] if len(h) <= self.lag else h[-1 - self.lag]
            return old
        if kind == "cancellation":
            others = node.view.others_for(j, node.id) if node.view is not None else []
            return -np.sum(others, axis=0) if others else np.zeros_like(est)
        raise ValueError(f"unknown Byzantine strategy {kind!r}")


KINDS = ("constant", "huge", "omission", "equivocation", "false_stamp", "replay", "crash", "cancellation")
