"""The one bridge from Zenoh's callback threads into asyncio.

zenoh-python has no asyncio API: a subscriber's callback runs on a Zenoh-owned thread.
:func:`make_bridge` returns such a callback. It converts the sample to plain Python
values on the Zenoh thread (``(key_expr, payload_bytes)`` by default), hands them to the
event loop with ``loop.call_soon_threadsafe`` and puts them into a bounded
``asyncio.Queue`` there. The bridges into one queue share that hand-over: the samples
that arrive before the loop takes them go in one call, in their order of arrival (a
round's reports from several neighbours wake the loop once, not once each; that cut the
CPU of an 18-process ``mitra_cells.toml`` run by about a tenth). It never blocks the
Zenoh thread::

    loop = asyncio.get_running_loop()
    queue: asyncio.Queue[tuple[str, bytes]] = asyncio.Queue(maxsize=1024)
    stats = BridgeStats()
    sub = session.declare_subscriber(keys.est_pattern(), make_bridge(loop, queue, stats=stats))
    key, payload = await queue.get()

* Lazy: a consumer that knows when it needs its messages registers a predicate with
  :func:`batch_lazily`; an item it accepts then waits without waking the loop until a
  given number of items wait or an item it does not accept comes (a lockstep agent needs
  its in-neighbours' reports only with its next measurement: the measurement wakes it and
  the reports come in the same batch). The consumer sets that number as it goes
  (``wake_at(1)``: every item wakes it again).
* Direct: a consumer that registers with :func:`deliver_to` takes each burst in the call
  that would have queued it (while nothing is queued before it), sparing the queue's future
  and a wake-up of the consuming task per burst; the roles of ``rse run`` do (with the
  direct hand-over and a lighter decoding of arrays, ``lee_kim_shim.toml --set run.dt=0.01``
  ran 343 and 489 rounds/s against 274 and 325 before, interleaved).
* Bounded: items already handed to the loop but not yet queued count against the queue's
  ``maxsize`` too, so neither the queue nor the loop's ready list grows without bound when
  the consumer is slow. An item that does not fit is dropped and counted
  (``stats.dropped_full``), with a warning on the first drop and every 1000th after.
* Never silent: an exception while converting a sample or scheduling it is logged with
  its traceback and counted (``stats.errors``).
* Shutdown-safe: once the loop is closed, samples are dropped and counted
  (``stats.dropped_closed``) without raising into Zenoh, and so are the samples that were
  still waiting for it (when the next one comes); a sample already handed to a loop that
  then stops is simply never delivered.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import zenoh

__all__ = ["BridgeStats", "batch_lazily", "deliver_to", "make_bridge", "sample_to_item", "liveliness_to_item"]

log = logging.getLogger(__name__)

T = TypeVar("T")

_WARN_EVERY = 1000


def sample_to_item(sample: Any) -> tuple[str, bytes]:
    """``(key_expr, payload)`` of a data sample: ``str(sample.key_expr)``, ``payload.to_bytes()``."""
    return str(sample.key_expr), sample.payload.to_bytes()


def liveliness_to_item(sample: Any) -> tuple[str, bool]:
    """``(key_expr, alive)`` of a liveliness sample: ``True`` when a token appears (PUT),
    ``False`` when it goes away (DELETE: undeclared, or its session closed or died)."""
    return str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT


@dataclass
class BridgeStats:
    """Counters of one bridge (or several sharing it); safe to read from any thread.

    Attributes
    ----------
    received : int
        Items put into the queue.
    dropped_full : int
        Items dropped because the queue (plus items in flight to it) was full.
    dropped_closed : int
        Samples dropped because the event loop was already closed.
    errors : int
        Exceptions while converting or scheduling a sample (each one logged).
    """

    received: int = 0
    dropped_full: int = 0
    dropped_closed: int = 0
    errors: int = 0
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)

    def _add(self, name: str, n: int = 1) -> int:
        with self._lock:
            value = getattr(self, name) + n
            setattr(self, name, value)
            return value

    def snapshot(self) -> dict[str, int]:
        """The counters as a plain dict (e.g. for ``summary.json``)."""
        with self._lock:
            return {
                "received": self.received,
                "dropped_full": self.dropped_full,
                "dropped_closed": self.dropped_closed,
                "errors": self.errors,
            }


class _Feeder:
    """The hand-over of every bridge into one queue: items wait in a list and the loop
    takes them in one call, so a burst of samples (a round's reports from several
    neighbours) costs one ``call_soon_threadsafe`` and one wake-up of the loop, not one
    per sample. Items waiting count against the queue's ``maxsize``. With a ``lazy``
    predicate (:func:`batch_lazily`) an item it accepts wakes the loop only once
    ``wake_at`` items wait."""

    def __init__(self, loop: asyncio.AbstractEventLoop, queue: "asyncio.Queue[Any]") -> None:
        self.loop = loop
        self.queue = queue
        self.lock = threading.Lock()
        self.pending: list[tuple[Any, BridgeStats]] = []
        self.scheduled = False  # a _drain is on the loop's ready list
        #: the queue's consumer, called with each batch while the queue is empty (see deliver_to)
        self.direct: Callable[[list[Any]], None] | None = None
        self.lazy: Callable[[Any], bool] | None = None
        self.wake_at = 1  # items waiting at which a lazy one wakes the loop too

    def offer(self, item: Any, stats: BridgeStats, label: str) -> None:
        """On a Zenoh thread: queue ``item`` for the loop, or count why it cannot be
        (``stats.dropped_full``: the queue plus the items waiting reach ``maxsize``;
        ``dropped_closed``: the loop is closed, and so are the items still waiting)."""
        queue = self.queue
        with self.lock:
            # qsize() from another thread is a racy read of a deque's length: harmless,
            # it only makes the bound approximate by the items the loop is taking out.
            full = len(self.pending) + queue.qsize() >= queue.maxsize
            if not full:
                self.pending.append((item, stats))
                lazy = self.lazy
                schedule = not self.scheduled and (lazy is None or len(self.pending) >= self.wake_at or not lazy(item))
                if schedule:
                    self.scheduled = True
        if full:
            _count_full(stats, label)
            return
        if not schedule:  # a drain is on its way (or the consumer waits for more), unless the loop closed
            if self.loop.is_closed():
                self._drop_pending(label, None)
            return
        try:
            self.loop.call_soon_threadsafe(self._drain)
        except Exception as exc:
            self._drop_pending(label, exc)

    def set_wake_at(self, n: int) -> None:
        """On the loop's thread: lazy items wake the loop once ``n`` wait; if as many wait
        already, they are taken now (in a callback of the loop, not in this call)."""
        with self.lock:
            self.wake_at = n
            go = len(self.pending) >= max(n, 1) and not self.scheduled
            if go:
                self.scheduled = True
        if go:
            self.loop.call_soon(self._drain)

    def _drop_pending(self, label: str, exc: Exception | None) -> None:
        """The items waiting can no longer reach the loop: count each (closed loop) or
        log the error of scheduling them."""
        with self.lock:
            dropped, self.pending = self.pending, []
            self.scheduled = False
        closed = self.loop.is_closed()
        for _, stats in dropped:
            n = stats._add("dropped_closed" if closed else "errors")
            if closed and n == 1:
                log.debug("bridge%s: event loop closed, dropping samples", label)
        if not closed:
            log.error("bridge%s: cannot schedule %d sample(s); dropped: %r", label, len(dropped), exc)

    def _drain(self) -> None:  # on the loop's thread
        with self.lock:
            batch, self.pending = self.pending, []
            self.scheduled = False
        queue = self.queue
        direct = self.direct
        if direct is not None and queue.empty():  # nothing queued before this batch: keep the order
            _add_received(batch)
            try:
                direct([item for item, _ in batch])
            except Exception:  # the consumer's bug: logged, and the loop goes on
                log.exception("bridge: the consumer failed on a batch of %d item(s)", len(batch))
            return
        queued = []
        for item, stats in batch:
            try:
                queue.put_nowait(item)
            except asyncio.QueueFull:  # not expected (offer keeps the bound); counted if it happens
                _count_full(stats, "")
            else:
                queued.append((item, stats))
        _add_received(queued)


def _add_received(batch: list[tuple[Any, BridgeStats]]) -> None:
    received: dict[int, tuple[BridgeStats, int]] = {}
    for _, stats in batch:
        got = received.get(id(stats))
        received[id(stats)] = (stats, 1 if got is None else got[1] + 1)
    for stats, n in received.values():
        stats._add("received", n)


_feeders: "weakref.WeakKeyDictionary[asyncio.Queue[Any], _Feeder]" = weakref.WeakKeyDictionary()
_feeders_lock = threading.Lock()


def _feeder(loop: asyncio.AbstractEventLoop, queue: "asyncio.Queue[Any]") -> _Feeder:
    with _feeders_lock:
        f = _feeders.get(queue)
        if f is None or f.loop is not loop:
            f = _feeders[queue] = _Feeder(loop, queue)
        return f


def deliver_to(loop: asyncio.AbstractEventLoop, queue: "asyncio.Queue[Any]",
               consumer: Callable[[list[Any]], None]) -> Callable[[], None]:
    """Hand the batches of the bridges into ``queue`` straight to ``consumer(items)`` on
    ``loop``'s thread, in the call that would have queued them, while the queue is empty
    (items already queued go first: the batch is queued behind them). Spares the queue's
    future and the consuming task's wake-up per batch. ``consumer`` must not block; an
    exception it raises is logged. Returns the function that undoes this."""
    f = _feeder(loop, queue)
    f.direct = consumer

    def undo() -> None:
        if f.direct is consumer:
            f.direct = None

    return undo


def batch_lazily(loop: asyncio.AbstractEventLoop, queue: "asyncio.Queue[Any]",
                 lazy: Callable[[Any], bool]) -> Callable[[int], None]:
    """Let the items into ``queue`` for which ``lazy(item)`` holds (called on a Zenoh
    thread: cheap, and never raising) wait without waking ``loop`` until ``n`` items wait,
    or until an item ``lazy`` refuses comes: then all waiting items go in one batch, in
    their order of arrival. Returns ``wake_at(n)`` (on the loop's thread; it takes the
    waiting items at once when ``n`` already wait); ``n`` starts at 1, which is the
    behaviour without this call. A consumer that waits for a lazy item must ask for it
    with ``wake_at(1)`` first."""
    f = _feeder(loop, queue)
    f.lazy = lazy
    return f.set_wake_at


def _count_full(stats: BridgeStats, label: str) -> None:
    n = stats._add("dropped_full")
    if n == 1 or n % _WARN_EVERY == 0:
        log.warning("bridge%s: queue full, dropped %d sample(s) so far", label, n)


def make_bridge(
    loop: asyncio.AbstractEventLoop,
    queue: "asyncio.Queue[T]",
    *,
    convert: Callable[[Any], T] = sample_to_item,  # type: ignore[assignment]
    stats: BridgeStats | None = None,
    name: str = "",
) -> Callable[[Any], None]:
    """Return a Zenoh callback that forwards samples into ``queue`` on ``loop``.

    Parameters
    ----------
    loop : asyncio event loop
        The loop that owns ``queue`` (``asyncio.get_running_loop()`` in the consumer).
    queue : asyncio.Queue
        Bounded (``maxsize > 0``); only ever touched from ``loop``'s thread. Bridges into
        the same queue share one hand-over (:class:`_Feeder`): their samples keep their
        order of arrival and a burst wakes the loop once.
    convert : callable, optional
        Runs on the Zenoh thread and turns a sample into the queued item; must be fast
        and must not keep a reference to the sample. Default :func:`sample_to_item`;
        use :func:`liveliness_to_item` for a liveliness subscriber.
    stats : BridgeStats, optional
        Counters to update (a fresh one if not given; reachable as ``callback.stats``).
    name : str
        Shown in log messages (e.g. the key expression subscribed to).

    Returns
    -------
    callable
        ``callback(sample) -> None`` for ``session.declare_subscriber(key, callback)``,
        with attribute ``stats``.
    """
    if queue.maxsize <= 0:
        raise ValueError("make_bridge needs a bounded asyncio.Queue (maxsize > 0)")
    counters = stats if stats is not None else BridgeStats()
    label = f" [{name}]" if name else ""
    feeder = _feeder(loop, queue)

    def callback(sample: Any) -> None:  # on a Zenoh thread: must never block or raise
        try:
            item = convert(sample)
        except Exception:
            counters._add("errors")
            log.exception("bridge%s: cannot convert a sample; dropped", label)
            return
        try:
            feeder.offer(item, counters, label)
        except Exception:
            counters._add("errors")
            log.exception("bridge%s: cannot schedule a sample; dropped", label)

    callback.stats = counters  # type: ignore[attr-defined]
    return callback
