"""The round protocol of the networked runtime and what its three roles share.

The roles live in one module each (:mod:`agents.net.plant`, :mod:`agents.net.agent`,
:mod:`agents.net.monitor`); this module describes the protocol and holds the :class:`Role`
base class. The run configuration is :mod:`agents.net.config`, what goes on the wire
(schemas, reports, rejection counters) :mod:`agents.net.wire`, a process's own figures
:mod:`agents.net.figures`, and how an agent schedules its rounds :mod:`agents.net.schedule`. Each role reuses the
in-process simulator's pieces (:class:`~agents.plant.PlantRole`,
:class:`~agents.node.AgentNode`, :class:`~agents.monitor.Monitor`), so both drivers share
the round logic and the channel model (drops and delays are decided receiver-side by
``AgentNode.receive`` from ``(seed, sender, receiver, stamp)``).

The round protocol (keys from :class:`transport.keys.Keys`)::

    plant   -> rse/{run}/plant/truth        "truth" x[k]                       (monitor)
    plant   -> rse/{run}/plant/loc/{i}      "meas"  y_i[k], wait list, member  (agent i)
    agent i -> rse/{run}/agent/{i}/est      "est"   payload stamped k (broadcast)
            or rse/{run}/agent/{i}/est/{j}  "est"   addressed payloads (Byzantine)
    agent i -> rse/{run}/ctl/done/{i}       "done"  own estimate x_i[k], receivers  (plant, monitor;
                                            and, in lockstep, i's out-neighbours when i's payload
                                            is its estimate: then i sends no "est", and when it
                                            went to every out-neighbour the report is an "est"
                                            of x_i[k] alone: see report_to)
    agent i -> rse/{run}/ctl/ready/{i}      joining the team                    (plant)
    monitor -> rse/{run}/ctl/ack/monitor    rounds recorded (flow control)      (plant)
    plant   -> rse/{run}/plant/loc/{i}      "ctl" cmd=stop, wait list           (agent i)
    plant   -> rse/{run}/ctl/stop/plant     the last round                      (monitor)
    every   -> rse/{run}/ctl/stats/{who}    link and rejection counters, RSS    (monitor)
    every   -> rse/{run}/alive/{role}/{i}   liveliness token

**Lockstep**: the plant publishes round ``k``'s measurement to agent ``i`` once every
member in-neighbour of ``i`` reported round ``k - 1`` done, and starts round ``k + 1`` once
every member did (or the deadline passed; a member whose token went away is not waited
for): an agent whose in-neighbours are done runs ahead while a straggler elsewhere (the
omniscient adversary, whose round comes after the honest ones) finishes. Unpaced only; with
``rate`` the whole round goes out at once. The meas message to agent ``i`` lists the
in-neighbours whose round ``k - 1`` messages were sent to ``i`` (from their done reports);
the agent runs round ``k`` when all of them have physically arrived (or the deadline
passed), so every message reaches ``AgentNode.receive`` before the round in which the
channel model makes it visible, and the estimates equal ``rse simulate``'s. A lockstep
agent wakes about once a round, the plant two or three times (once all but one report
came, then at the last), the omniscient adversary once for its measurement and then
once as many messages came as its view still misses: what a role does not need yet waits
in the bridge (:meth:`Role.lazy_items`). **Realtime**: the plant ticks at ``rate`` Hz on
the wall clock, agents run a round as soon as its measurement arrives, with whatever has
arrived (late messages are placed by their stamps).

**Joining**: an agent subscribes, declares its token, waits until it sees the plant's and
the monitor's tokens (and its neighbours', or the team is already running), then sends
``ready`` until a meas message says it is a member; it runs rounds from there on. A
killed agent's token disappears and the team goes on; ``rse agent --id I`` rejoins.

Every received payload is decoded strictly (:func:`transport.codec.decode` with the key's
sender); a bad one is dropped and counted per sender (``summary.json``: ``rejected``).
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Generic, TypeVar

import numpy as np

from estimation.errors import MessageError
from transport.codec import Message, Schema, decode
from transport.keys import Keys, ParsedKey
from transport.linkauth import sealed
from transport.zenoh_bus import POLLED_CAPACITY, Bus

from .config import QUEUE_SIZE, RECONNECTS, RunConfig
from .figures import process_figures
from .wire import Rejects, Wire, _msg

if TYPE_CHECKING:
    from agents.rounds import Team


log = logging.getLogger("rse.net")


#: what a role is handed of its team: the experiment (the monitor), the plant's slice or
#: the experiment (the plant), an agent's slice (an agent); see agents.rounds.Team
T = TypeVar("T", bound="Team")


class Role(Generic[T]):
    """What the three roles share: one queue, strict decoding, liveliness bookkeeping."""

    name = "role"

    def __init__(self, exp: T, bus: Bus, keys: Keys, cfg: RunConfig) -> None:
        self.exp, self.bus, self.keys, self.cfg = exp, bus, keys, cfg
        self.wire = Wire(exp)
        self.queue: asyncio.Queue = asyncio.Queue(maxsize=QUEUE_SIZE)
        self.rejects = Rejects()
        self.alive: set[tuple[str, int]] = set()
        self.reconnects = 0  # Bus.reconnect calls of a process that rejoined (at most RECONNECTS)
        self.changed = asyncio.Event()
        self.ids = set(exp.agent_ids)
        self._waiting: Callable[[], bool] | None = None  # the predicate wait_for waits on
        self._wake_at: Callable[[int], None] | None = None  # see lazy_items
        self._lazy_n = 1
        self.batches = 0  # the batches handled: the wake-ups that brought messages
        self._polled: list[Any] = []  # polled subscriptions (subscribe), drained with each batch

    def decode(self, key: str, payload: bytes, schema: Schema) -> tuple[ParsedKey, Message] | None:
        try:
            parsed = self.keys.parse(key)
        except MessageError:
            self.rejects.add(None, "key")
            return None
        try:
            msg = decode(payload, schema=schema, expected_sender=parsed.sender, expected_receiver=parsed.receiver)
        except MessageError as exc:
            self.rejects.add(parsed.sender, exc.reason)
            self.on_reject(parsed.sender)
            log.debug("%s: dropped a message on %s: %s", self.name, key, exc)
            return None
        return parsed, msg

    def on_reject(self, sender: int | None) -> None:
        pass

    def authentic(self, key: str, payload: bytes) -> bytes | None:
        """A secure team's estimate or done report without its tags, if the agent its key
        names sealed it for this process (:mod:`transport.linkauth`); else None, counted
        under ``impersonation`` or ``unauthenticated``."""
        try:
            j = self.keys.parse(key).sender
        except MessageError:
            return payload  # handle_data rejects the key
        inner, reason, who = self.bus.auth.open(key, payload, f"agent-{j}")
        if inner is None:
            self.rejects.add(j, reason)
            self.on_reject(j)
            n = self.rejects.counts[(j, reason)] if j is not None else 0
            if n == 1 or n % 1000 == 0:
                log.warning("%s: rejected a message on %s: %s (%d from agent %s)", self.name, key,
                            f"authenticated as {who}, not agent-{j}" if who else "no valid tag of its sender", n, j)
        return inner

    def on_alive(self, role: str, i: int, alive: bool) -> None:
        pass

    def handle_token(self, key: str, alive: bool) -> None:
        try:
            parsed = self.keys.parse(key)
        except MessageError:
            return
        who = (parsed.name or "", parsed.ids[0])
        if alive and who not in self.alive:
            self.alive.add(who)
            self.on_alive(who[0], who[1], True)
        elif not alive and who in self.alive:
            self.alive.discard(who)
            self.on_alive(who[0], who[1], False)

    def handle_data(self, key: str, payload: bytes) -> None:  # pragma: no cover - overridden
        raise NotImplementedError

    def handle(self, item: Any) -> None:
        try:
            key, payload = item
            if type(payload) is bool:
                self.handle_token(key, payload)
            elif self.bus.auth is None or not sealed(key):
                self.handle_data(key, payload)
            else:
                inner = self.authentic(key, payload)
                if inner is not None:
                    self.handle_data(key, inner)
        except Exception:  # a bug in handling one item must not stop the process
            log.exception("%s: error while handling a message", self.name)

    async def consume(self) -> None:
        """Handle what the bus brings: each batch of a Zenoh bus straight from its bridges
        (:func:`~transport.bridge.deliver_to`), anything else through the queue."""
        from transport.bridge import batch_lazily, deliver_to  # imports zenoh: only where a role runs

        q = self.queue
        loop = asyncio.get_running_loop()
        undo = deliver_to(loop, q, self.handle_batch)
        lazy = self.lazy_items()
        if lazy is not None:
            self._wake_at = batch_lazily(loop, q, lazy)
            self._wake_at(self._lazy_n)
        try:
            while True:
                batch = [await q.get()]
                while not q.empty():
                    batch.append(q.get_nowait())
                self.handle_batch(batch)
        finally:
            undo()

    def lazy_items(self) -> Callable[[Any], bool] | None:
        """The items (``(key, payload)``) that may wait for the next batch without waking
        this role (:func:`transport.bridge.batch_lazily`; on a Zenoh thread), or None: every
        item wakes it. A role that returns one steers it with :meth:`wake_at`."""
        return None

    def wake_at(self, n: int) -> None:
        """Lazy items wake this role once ``n`` wait (1: each one does)."""
        if n != self._lazy_n:
            self._lazy_n = n
            if self._wake_at is not None:
                self._wake_at(n)

    def subscribe(self, pattern: str, *, polled: bool = False, capacity: int = POLLED_CAPACITY) -> None:
        """Subscribe to ``pattern``: into the queue (each item may wake this role), or
        ``polled`` (:meth:`transport.zenoh_bus.Bus.subscribe_polled`): its items wait
        without a callback and are handled first in the next batch (what this role's
        wake-ups bring, or :meth:`handle_batch` of nothing)."""
        if polled:
            self._polled.append(self.bus.subscribe_polled(pattern, capacity))
        else:
            self.bus.subscribe(pattern, self.queue)

    def handle_batch(self, items: list[Any]) -> None:
        got = len(items)
        for polled in self._polled:
            drained = polled.drain()
            got += len(drained)
            for item in drained:
                self.handle(item)
        self.batches += got > 0
        for item in items:
            self.handle(item)
        if self.after_batch():
            self.changed.set()

    def after_batch(self) -> bool:
        """Called by the consumer after each batch of messages; returns whether the role's
        main loop must wake up (a role may do its work here and spare that wake-up). While
        :meth:`wait_for` waits, only when its predicate holds."""
        pred = self._waiting
        if pred is None:
            return True
        try:
            return bool(pred())
        except Exception:  # let the waiter see it
            return True

    async def wait_for(self, pred: Callable[[], bool], timeout: float | None) -> bool:
        """Wait until ``pred()`` holds (re-checked after each batch of messages)."""
        end = None if timeout is None else time.monotonic() + timeout
        self._waiting = pred
        try:
            while not pred():
                self.changed.clear()
                if pred():
                    return True
                remaining = None if end is None else end - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return False
                try:
                    await asyncio.wait_for(self.changed.wait(), remaining)
                except TimeoutError:
                    return pred()
            return True
        finally:
            self._waiting = None

    async def reconnect(self, why: str) -> bool:
        """A process that rejoined a running team and does not hear a peer: a new session
        (:meth:`transport.zenoh_bus.Bus.reconnect`), counted against :data:`RECONNECTS`;
        returns whether the bus reconnected."""
        self.reconnects += 1
        log.info("%s: %s; reconnecting (%d of at most %d)", self.name, why, self.reconnects, RECONNECTS)
        return await self.bus.reconnect()

    def send_stats(self, sender: int, links: np.ndarray | None = None,
                   health: tuple[np.ndarray, np.ndarray] | None = None, **meta: Any) -> None:
        """The process's final figures to the monitor: its link rows, rejects, ``health``
        (an agent's :meth:`~agents.net.health.LinkHealth.ages_rows` and ``out_rows``) and
        ``meta`` (counters, memory, CPU)."""
        links = np.zeros((0, 6)) if links is None else links
        ages, out = health if health is not None else (np.zeros((0, 6)), np.zeros((0, 2)))
        meta = {"cmd": "stats", **process_figures(), "bridge_dropped": int(self.bus.stats.dropped_full),
                "batches": self.batches, **meta}
        arrays = {"links": links, "rejected": self.rejects.as_array(), "ages": ages, "out": out}
        self.bus.publish(self.keys.ctl("stats", sender), _msg("ctl", sender, 0, arrays, meta=meta))
