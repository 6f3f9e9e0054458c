"""The bus the networked roles talk through: Zenoh, or an in-memory stand-in for tests.

A role (plant, agent, monitor) needs five things from the network::

    bus.publish(key, payload)          # bytes out on a key expression
    bus.publish(key, payload, droppable=True)   # ... that may be dropped for a receiver
                                       # that cannot take it now (realtime data)
    bus.subscribe(pattern, queue)      # (key, bytes) items into an asyncio.Queue
    bus.subscribe_polled(pattern)      # (key, bytes) items held until .drain() takes them
    bus.watch(pattern, queue)          # liveliness: (key, True) on join, (key, False) on leave,
                                       # the tokens already present are reported at once
    bus.announce(key)                  # declare this process's liveliness token
    bus.close()                        # undeclare everything (idempotent)

Items of :meth:`subscribe` carry ``bytes``, items of :meth:`watch` carry a ``bool``, so a
role can feed both into one queue and tell them apart by type.

A polled subscription (:meth:`Bus.subscribe_polled`, :class:`Polled`) wakes nobody: its
samples wait in Zenoh's own ring buffer (``zenoh.handlers.RingChannel``), with no Python
callback on Zenoh's threads, until the role drains it when it wakes for another reason (a
lockstep agent: its measurement). A Python callback costs every delivery the GIL on a
Zenoh thread and, on a loaded machine, thread switches: the minimal skeleton of ``rse bench
run`` on ``mitra_cells.toml`` ran 168 to 200 rounds/s with its agents' estimates polled,
against 101 to 140 with callbacks, in turn. The ring holds :data:`POLLED_CAPACITY` samples;
a drain that finds it full counts a possible loss (``stats.dropped_full``: the oldest
samples are the ones dropped).

:class:`ZenohBus` wraps an open ``zenoh.Session`` (see :mod:`transport.zenoh_session`;
the session's owner closes it) and delivers through the one bridge
(:func:`transport.bridge.make_bridge`). Publishers are declared once per key, reliable
and ``express`` (no batching delay: a round is a chain of small messages), with congestion
control ``BLOCK`` (a lockstep run must not lose messages to a full transmit queue), or
``DROP`` for the ``droppable`` messages (a realtime run's measurements and estimates). The
congestion control travels with each message: a router forwarding a ``BLOCK`` message
to a client that cannot take it (its link down, its queue full) holds up that
publisher's messages to everyone until the link is back or the client's lease (10 s)
expires, so one unreachable agent would stall a whole realtime team; a ``DROP`` message
is dropped for that client alone (``tests/deploy/test_netns.py``).

:class:`InMemoryHub` / :class:`InMemoryBus` implement the same interface inside one event
loop, with Zenoh's ``*`` / ``**`` key matching; the in-process tests of the roles use it.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from transport.bridge import BridgeStats, liveliness_to_item, make_bridge
from transport.linkauth import sealed

__all__ = ["Bus", "Polled", "ZenohBus", "InMemoryHub", "InMemoryBus", "key_matches"]

log = logging.getLogger(__name__)

#: samples a polled subscription holds between two drains (see the module docstring)
POLLED_CAPACITY = 1024


class Polled:
    """A subscription whose ``(key, payload)`` items wait until :meth:`drain` takes them."""

    def __init__(self, pattern: str, stats: BridgeStats, capacity: int = POLLED_CAPACITY) -> None:
        self.pattern, self.stats, self.capacity = pattern, stats, capacity
        self.sub: Any = None  # the Zenoh subscriber (ZenohBus), replaced on a reconnect
        self.items: list[tuple[str, bytes]] = []  # what waits outside Zenoh's ring

    def put_nowait(self, item: tuple[str, bytes]) -> None:
        """The in-memory bus's delivery (an ``asyncio.Queue``'s, bounded alike)."""
        if len(self.items) >= self.capacity:
            raise asyncio.QueueFull
        self.items.append(item)

    def _take(self) -> None:
        sub = self.sub
        if sub is None:
            return
        got = []
        try:
            while (sample := sub.try_recv()) is not None:
                got.append((str(sample.key_expr), sample.payload.to_bytes()))
        except Exception:  # undeclared (the bus closed): nothing more comes
            self.sub = None
        if got:
            self.stats._add("received", len(got))
            if len(got) >= self.capacity:
                n = self.stats._add("dropped_full")
                if n == 1 or n % 1000 == 0:
                    log.warning("polled subscription %s: its ring of %d was full; older messages may be lost "
                                "(%d time(s))", self.pattern, self.capacity, n)
            self.items.extend(got)

    def drain(self) -> list[tuple[str, bytes]]:
        """Everything that came since the last drain, in order of arrival."""
        self._take()
        items, self.items = self.items, []
        return items


class Bus:
    """The interface (see the module docstring); both implementations subclass it."""

    stats: BridgeStats
    #: a secure team's pairwise keys (:class:`transport.linkauth.LinkAuth`): what this bus
    #: publishes on an estimate key is sealed, what its roles hear there is checked
    auth: Any = None

    def publish(self, key: str, payload: bytes, *, droppable: bool = False) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def subscribe(self, pattern: str, queue: "asyncio.Queue[Any]") -> None:  # pragma: no cover
        raise NotImplementedError

    def watch(self, pattern: str, queue: "asyncio.Queue[Any]") -> None:  # pragma: no cover
        raise NotImplementedError

    def subscribe_polled(self, pattern: str, capacity: int = POLLED_CAPACITY) -> Polled:  # pragma: no cover
        raise NotImplementedError

    def announce(self, key: str) -> None:  # pragma: no cover
        raise NotImplementedError

    def close(self) -> None:  # pragma: no cover
        raise NotImplementedError

    #: ``time.monotonic()`` of the last reconnect (0.0: none yet)
    reconnected_at = 0.0
    _generation = 0
    _reconnecting: asyncio.Lock | None = None

    async def reconnect(self) -> bool:
        """Replace the connection to the peers with a new one, with the same
        subscriptions, watches and tokens (see :meth:`ZenohBus._reconnect`); returns
        whether it did (a bus without peers has nothing to replace).

        Several agents of one process share its bus: a reconnect asked for while another
        one runs waits for it and returns True without opening a second session."""
        generation = self._generation
        if self._reconnecting is None:
            self._reconnecting = asyncio.Lock()
        async with self._reconnecting:
            if self._generation != generation:
                return True
            done = await self._reconnect()
            if done:
                self._generation += 1
                self.reconnected_at = time.monotonic()
            return done

    async def _reconnect(self) -> bool:
        return False


class ZenohBus(Bus):
    """A :class:`Bus` over an open Zenoh session (the caller owns and closes the session,
    :attr:`session`; with ``opener``, :meth:`reconnect` replaces it, closing the old one)."""

    def __init__(self, session: Any, loop: asyncio.AbstractEventLoop | None = None,
                 opener: Callable[[], Any] | None = None) -> None:
        import zenoh

        self._zenoh = zenoh
        self.session = session
        self.loop = loop or asyncio.get_running_loop()
        self.stats = BridgeStats()
        self._opener = opener
        self._publishers: dict[tuple[str, bool], Any] = {}
        self._subscribers: list[Any] = []
        self._tokens: list[Any] = []
        self._declared: list[tuple[str, str, Any]] = []  # ("sub" | "poll" | "watch" | "token", key, callback)
        self._closed = False

    def publish(self, key: str, payload: bytes, *, droppable: bool = False) -> None:
        if self._closed:
            return
        if self.auth is not None and sealed(key):
            payload = self.auth.seal(key, payload)
        pub = self._publishers.get((key, droppable))
        if pub is None:
            z = self._zenoh
            cc = z.CongestionControl.DROP if droppable else z.CongestionControl.BLOCK
            # a priority of their own: a BLOCK message waiting for room in a link's queue
            # holds up every message of its priority on that link (eclipse-zenoh/zenoh#2584)
            prio = z.Priority.DATA_HIGH if droppable else z.Priority.DATA
            pub = self.session.declare_publisher(key, congestion_control=cc, express=True, priority=prio,
                                                 reliability=z.Reliability.RELIABLE)
            self._publishers[(key, droppable)] = pub
        pub.put(payload)

    def subscribe(self, pattern: str, queue: "asyncio.Queue[Any]") -> None:
        cb = make_bridge(self.loop, queue, stats=self.stats, name=pattern)
        self._declare("sub", pattern, cb)

    def watch(self, pattern: str, queue: "asyncio.Queue[Any]") -> None:
        cb = make_bridge(self.loop, queue, convert=liveliness_to_item, stats=self.stats, name=pattern)
        self._declare("watch", pattern, cb)

    def subscribe_polled(self, pattern: str, capacity: int = POLLED_CAPACITY) -> Polled:
        polled = Polled(pattern, self.stats, capacity)
        self._declare("poll", pattern, polled)
        return polled

    def announce(self, key: str) -> None:
        self._declare("token", key, None)

    def _declare(self, what: str, key: str, cb: Any, *, record: bool = True) -> None:
        if what == "sub":
            self._subscribers.append(self.session.declare_subscriber(key, cb))
        elif what == "poll":
            cb.sub = self.session.declare_subscriber(key, self._zenoh.handlers.RingChannel(cb.capacity))
            self._subscribers.append(cb.sub)
        elif what == "watch":
            self._subscribers.append(self.session.liveliness().declare_subscriber(key, cb, history=True))
        else:
            self._tokens.append(self.session.liveliness().declare_token(key))
        if record:
            self._declared.append((what, key, cb))

    async def _reconnect(self) -> bool:
        """Close the session and open a new one (``opener``), declaring the same
        subscriptions, watches and token again; publishers are declared again at their
        next message. The others see this process leave and join again.

        For a process that rejoined a running team of peers and does not hear some of
        them (see :mod:`agents.net.agent`, :mod:`agents.net.monitor`): restarting such a
        process was the workaround, and a new session is what the restart gave it. Items
        the old session delivered stay in the queues; a token that left while no session
        watched is not reported."""
        if self._opener is None or self._closed:
            return False
        from transport.zenoh_session import close_session

        self.close()
        close_session(self.session)
        self.session = await _open_or_close(self._opener)
        self._closed = False
        for what, key, cb in self._declared:
            self._declare(what, key, cb, record=False)
        return True

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for what, _, polled in self._declared:
            if what == "poll":  # what came before the close stays for the next drain
                polled._take()
                polled.sub = None
        for group in (self._subscribers, self._tokens, list(self._publishers.values())):
            for obj in group:
                try:
                    obj.undeclare()
                except Exception:  # the session may already be closed; nothing to leak then
                    log.debug("undeclare failed", exc_info=True)
        self._subscribers.clear()
        self._tokens.clear()
        self._publishers.clear()


async def _open_or_close(opener: Callable[[], Any]) -> Any:
    """``opener()`` on a worker thread; if the caller is cancelled meanwhile (Ctrl-C or
    SIGTERM during a reconnect), the session it opens is closed, on the thread or here,
    not left to the interpreter's exit handler."""
    from transport.zenoh_session import close_session

    lock = threading.Lock()
    state: dict[str, Any] = {"cancelled": False, "session": None}

    def open_() -> Any:
        session = opener()
        with lock:
            cancelled = state["cancelled"]
            if not cancelled:
                state["session"] = session
        if cancelled:
            close_session(session)
        return session

    try:
        return await asyncio.to_thread(open_)
    except asyncio.CancelledError:
        with lock:
            state["cancelled"] = True
            session = state["session"]
        close_session(session)  # opened before the cancellation reached us (None: the thread closes it)
        raise


# ------------------------------------------------------------------------------ in memory


def key_matches(pattern: str, key: str) -> bool:
    """Zenoh key-expression matching of a concrete ``key`` against ``pattern``:
    ``*`` is exactly one chunk, ``**`` is zero or more chunks."""
    return _match(pattern.split("/"), key.split("/"))


def _match(p: list[str], k: list[str]) -> bool:
    if not p:
        return not k
    head = p[0]
    if head == "**":
        return any(_match(p[1:], k[i:]) for i in range(len(k) + 1))
    if not k:
        return False
    if head == "*" or head == k[0]:
        return _match(p[1:], k[1:])
    return False


class InMemoryHub:
    """The shared medium of several :class:`InMemoryBus` in one event loop."""

    def __init__(self) -> None:
        self.subs: list[tuple[str, "asyncio.Queue[Any]", "InMemoryBus"]] = []
        self.watchers: list[tuple[str, "asyncio.Queue[Any]", "InMemoryBus"]] = []
        self.tokens: dict[str, int] = {}
        self.published = 0
        self._routes: dict[str, list] = {}  # key -> matching subscriptions (cleared when they change)

    def routes(self, key: str) -> list:
        r = self._routes.get(key)
        if r is None:
            r = self._routes[key] = [(q, owner) for pattern, q, owner in self.subs if key_matches(pattern, key)]
        return r

    def bus(self) -> "InMemoryBus":
        return InMemoryBus(self)

    def _deliver(self, queue: "asyncio.Queue[Any]", item: Any, stats: BridgeStats) -> None:
        try:
            queue.put_nowait(item)
        except asyncio.QueueFull:
            stats.dropped_full += 1
        else:
            stats.received += 1

    def _post(self, queue: "asyncio.Queue[Any]", item: Any, stats: BridgeStats) -> None:
        # Asynchronous like the real thing: never re-enter the publisher.
        asyncio.get_running_loop().call_soon(self._deliver, queue, item, stats)

    def _token(self, key: str, alive: bool) -> None:
        for pattern, queue, owner in list(self.watchers):
            if key_matches(pattern, key):
                self._post(queue, (key, alive), owner.stats)


class InMemoryBus(Bus):
    """A :class:`Bus` on an :class:`InMemoryHub` (messages are copied as bytes)."""

    def __init__(self, hub: InMemoryHub) -> None:
        self.hub = hub
        self.stats = BridgeStats()
        self._tokens: list[str] = []
        self._closed = False

    def publish(self, key: str, payload: bytes, *, droppable: bool = False) -> None:
        if self._closed:
            return
        if self.auth is not None and sealed(key):
            payload = self.auth.seal(key, payload)
        self.hub.published += 1
        data = bytes(payload)
        for queue, owner in self.hub.routes(key):
            self.hub._post(queue, (key, data), owner.stats)

    def subscribe(self, pattern: str, queue: "asyncio.Queue[Any]") -> None:
        self.hub.subs.append((pattern, queue, self))
        self.hub._routes.clear()

    def subscribe_polled(self, pattern: str, capacity: int = POLLED_CAPACITY) -> Polled:
        polled = Polled(pattern, self.stats, capacity)
        self.hub.subs.append((pattern, polled, self))  # type: ignore[arg-type]  # a queue's put_nowait
        self.hub._routes.clear()
        return polled

    def watch(self, pattern: str, queue: "asyncio.Queue[Any]") -> None:
        self.hub.watchers.append((pattern, queue, self))
        for key, count in self.hub.tokens.items():
            if count > 0 and key_matches(pattern, key):
                self.hub._post(queue, (key, True), self.stats)

    def announce(self, key: str) -> None:
        self._tokens.append(key)
        self.hub.tokens[key] = self.hub.tokens.get(key, 0) + 1
        if self.hub.tokens[key] == 1:
            self.hub._token(key, True)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self.hub.subs = [s for s in self.hub.subs if s[2] is not self]
        self.hub._routes.clear()
        self.hub.watchers = [w for w in self.hub.watchers if w[2] is not self]
        for key in self._tokens:
            self.hub.tokens[key] -= 1
            if self.hub.tokens[key] == 0:
                del self.hub.tokens[key]
                try:
                    self.hub._token(key, False)
                except RuntimeError:  # no running loop: nobody is listening any more
                    pass
        self._tokens.clear()
