"""The shape every estimator has, shared by both drivers.

An estimator is an object with explicit, inspectable state and a ``step`` (filterpy's
``predict/update`` style)::

    est = SomeEstimator(...)                 # built once from the scenario (validated)
    out = est.step(k, measurement, inbox)    # one round
    est.estimate                             # current x_hat, shape (n,)

Conventions (both drivers rely on them):

* Round ``k`` corresponds to time ``t_k = k * dt``. The message an agent publishes in
  round ``k`` carries its estimate of ``x[k]`` and is stamped ``k``.
* ``measurement`` is what the agent's sensing location(s) read in round ``k``
  (``y[k]``, a 1-D float array), or ``None`` when the agent is at no location this
  round (a mobile agent commuting) -- missing data is ordinary input.
* ``inbox`` maps an in-neighbour id to the newest :class:`Received` message the channel
  delivered by round ``k``; it may be empty (all dropped). Messages published in round
  ``k - 1`` are the freshest an agent can have in round ``k``.
* ``step`` returns the outgoing payload (a float array) stamped ``k``. An estimator never
  mutates the arrays it receives and never hands out an internal array it may still
  modify (a payload is a copy, or a read-only array the estimator never writes again).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping
from typing import NamedTuple, Protocol, runtime_checkable

import numpy as np


class Received(NamedTuple):
    """A neighbour's message as delivered to a receiver.

    Attributes
    ----------
    sender : int
        The neighbour's agent id.
    stamp : int
        The round in which the sender published it.
    value : (d,) float array
        The payload (usually the sender's estimate). Treat as read-only.
    """

    sender: int
    stamp: int
    value: np.ndarray


Inbox = Mapping[int, Received]


def held(inbox: Inbox, kk: int, max_age: int) -> list[np.ndarray]:
    """The values that hold over the step from round ``kk`` to ``kk + 1``: each sender's
    newest message, if stamped within ``max_age`` rounds of ``kk``. In round ``k`` after
    ``k - 1`` (every driver without skipped rounds) that is every message not older than
    ``k - 1 - max_age`` (the inbox holds nothing newer than ``k - 1``). Over the steps of
    rounds a realtime agent skipped, a message stamped up to ``max_age`` rounds after the
    step also holds (the estimate nearest in time that the agent has: without it, each
    skip of a round or two cut the agent's coupling for those steps, and the attacked
    agent of ``lee_kim_shim.toml`` drifted above its bound after every burst of skips),
    but not one stamped later: an estimate of ``x`` at the end of a long gap, coupled in
    over the whole gap, pulls the agent off as far as a stale measurement does. In the
    senders' order, whatever order the messages arrived in, so that a sum over them
    rounds alike in every driver."""
    return [r.value for _, r in sorted(inbox.items()) if abs(r.stamp - kk) <= max_age]


@runtime_checkable
class Estimator(Protocol):
    """Protocol of a per-agent estimator (see the module docstring)."""

    @property
    def estimate(self) -> np.ndarray:  # (n,) copy of the current estimate
        ...

    def step(self, k: int, measurement: np.ndarray | None, inbox: Inbox) -> np.ndarray:
        ...


# ---------------------------------------------------------------- optional capabilities
# An estimator declares what else it offers by inheriting these classes (a nominal
# declaration: the drivers ask ``isinstance(est, Capability)``, they never probe for
# attributes). Batching is declared the same way (:class:`estimation.batching.Batchable`).


class EstimatePayload:
    """The published payload is the estimate ``x_hat_i[k]`` itself (shape ``(n,)``): a
    driver records it without reading ``estimate`` and, in lockstep, may carry it in the
    agent's done report instead of a second message.

    An estimator whose payload is the estimate in some configurations only inherits this
    and says which in :attr:`payload_is_estimate` (LFRE: its modal estimate ``z_hat`` is
    ``x_hat`` when the modal transform is the identity)."""

    @property
    def payload_is_estimate(self) -> bool:
        """Whether this instance's payload is its estimate (equal values, every round)."""
        return True


class MaskedInputs(ABC):
    """The fusion uses only some components of a neighbour's payload: :meth:`uses` says
    which (an omniscient adversary's view masks the others, as the receiver does)."""

    @abstractmethod
    def uses(self, sender: int) -> np.ndarray:
        """``(d,)`` float mask (1.0: component used) of the payload from agent index ``sender``."""


class Diagnostics(ABC):
    """Per-round scalars the monitor records (``diagnostics.parquet``, summary)."""

    @abstractmethod
    def diagnostics(self) -> dict[str, float]:
        """Name -> value after the last step (NaN where not defined yet)."""


class Flags(ABC):
    """A local attack detector: :attr:`flagged` after each step (the summary's
    ``detected_attacks``)."""

    @property
    @abstractmethod
    def flagged(self) -> bool:
        """Whether this agent considers its own measurement or inputs attacked now."""
