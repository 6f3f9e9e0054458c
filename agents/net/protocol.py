"""The round protocol of the networked runtime and what its three roles share.

The roles live in one module each (:mod:`agents.net.plant`, :mod:`agents.net.agent`,
:mod:`agents.net.monitor`); this module holds the protocol's configuration, message
schemas, rejection counters and the :class:`Role` base class. Each role reuses the
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
import math
import resource
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from estimation.errors import MessageError
from transport.codec import MIN_ID, MONITOR_ID, PLANT_ID, Message, Schema, decode, encode_fields
from transport.keys import Keys, ParsedKey
from transport.zenoh_bus import POLLED_CAPACITY, Bus
from transport.zenoh_session import thread_counts

if TYPE_CHECKING:
    from scenarios.build import Experiment


log = logging.getLogger("rse.net")

MODES = ("lockstep", "realtime")
QUEUE_SIZE = 1 << 16
MONITOR_LAG = 128  # the monitor closes round k once truth k + LAG arrived
ACK_EVERY = 32
#: a process that rejoined a running team and hears nothing from some peer for this long
#: opens a new session (transport.zenoh_bus.ZenohBus.reconnect), at most RECONNECTS times
UNHEARD_S = 3.0
RECONNECTS = 5
#: lazy items wake a role that set no other bound once this many wait (see Role.lazy_items)
LAZY = QUEUE_SIZE // 2
MAX_AHEAD = 512  # lockstep: the plant waits when the monitor is this many rounds behind
UNKNOWN = MIN_ID  # sender code of a message whose key names no sender
REASONS = ("size", "decode", "type", "keys", "version", "sender", "shape", "nonfinite", "key", "range", "neighbour",
           "invalid")


@dataclass(frozen=True)
class RunConfig:
    """How the team runs (picklable: handed to spawned processes).

    mode : "lockstep" or "realtime"
    rate : Hz; required for realtime (the plant's wall-clock tick); in lockstep an
        optional upper bound on the round rate (pacing)
    deadline : seconds a lockstep round waits for a missing agent or message
    startup_timeout : seconds to wait for the team to assemble
    save_estimates : the monitor also writes ``estimates.npy`` and ``truth.npy``
    linger : seconds the monitor waits for the final counters after the last round
    warmup : scenario seconds an agent that joins a running team (round > 0) listens
        before it publishes (its estimate converges first instead of disturbing its
        neighbours); the monitor records it from its first round
    deliveries : each agent process writes the delivery record (:mod:`agents.deliveries`)
        into the run directory (off: benchmarks measuring its cost)
    """

    mode: str = "lockstep"
    rate: float | None = None
    deadline: float = 1.0
    startup_timeout: float = 60.0
    save_estimates: bool = False
    linger: float = 2.0
    warmup: float = 3.0
    deliveries: bool = True

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        if self.mode == "realtime" and not self.rate:
            raise ValueError("realtime mode needs --rate HZ")
        if self.rate is not None and not (self.rate > 0 and math.isfinite(self.rate)):
            raise ValueError(f"rate must be a positive number of Hz, got {self.rate!r}")
        if not self.deadline > 0:
            raise ValueError(f"deadline must be > 0 s, got {self.deadline!r}")


def maxrss_mb() -> float:
    """Peak resident set size of this process (MB): ``VmHWM`` of ``/proc/self/status``
    (``ru_maxrss`` is inherited across ``exec`` on Linux, so a spawned child would
    report its launcher's peak), else psutil's current RSS."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    try:
        import psutil

        return psutil.Process().memory_info().rss / 2**20
    except Exception:  # pragma: no cover
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def cpu_s() -> float:
    """CPU seconds (user + system) of every thread of this process so far."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return round(usage.ru_utime + usage.ru_stime, 3)


def uss_mb() -> float:
    """Unique set size of this process now (MB): its private pages (``Private_Clean`` +
    ``Private_Dirty`` of ``/proc/self/smaps_rollup``), what it costs beyond the shared
    libraries; NaN where that file does not exist."""
    try:
        total = 0
        with open("/proc/self/smaps_rollup") as f:
            for line in f:
                if line.startswith(("Private_Clean:", "Private_Dirty:")):
                    total += int(line.split()[1])
        return total / 1024.0
    except (OSError, ValueError):
        return float("nan")


def process_figures() -> dict[str, float]:
    """This process's figures for ``summary.json`` (``processes``): peak RSS, CPU seconds, its
    threads (:func:`transport.zenoh_session.thread_counts`) and USS where the system gives it
    (the codec carries finite numbers only)."""
    figs: dict[str, float] = {"maxrss_mb": maxrss_mb(), "cpu_s": cpu_s(), **thread_counts()}
    uss = uss_mb()
    if math.isfinite(uss):
        figs["uss_mb"] = uss
    return figs


def who_name(sender: int | None) -> str:
    if sender is None or sender == UNKNOWN:
        return "unknown"
    return {PLANT_ID: "plant", MONITOR_ID: "monitor"}.get(sender, str(sender))


class Wire:
    """The schemas of one scenario's messages (``team``: the experiment, or an agent's
    slice: ``n``, ``N`` and ``ny`` or ``bank_rows``)."""

    def __init__(self, team: Any) -> None:
        n, N = team.n, team.N
        self.n, self.N = n, N
        ny = getattr(team, "ny", None)
        self.ny = int(sum(len(r) for r in team.bank_rows)) if ny is None else int(ny)
        self.loc = Schema({"meas": {"y": (None,), "wait": (None, 2)}, "ctl": {"wait": (None, 2)}})
        self.truth = Schema({"truth": {"x": (n,)}})
        self.est = Schema({"est": {"x": (None,)}})
        #: a done key carries a report ("done": the estimate, whom the round's messages went
        #: to and their stamps) or, from an agent that broadcast its estimate stamped with the
        #: round to every out-neighbour, the estimate alone ("est": see :func:`report_to`)
        self.done = Schema({"done": {"x": (n,), "to": (None,), "stamps": (None,)}, "est": {"x": (n,)}})
        self.ctl = Schema({"ctl": {}})
        self.stats = Schema({"ctl": {"links": (None, 6), "rejected": (None, 3)}})


DIAG_PREFIX = "d_"
MAX_DIAGNOSTICS = 12  # the codec carries at most 16 metadata entries


def diagnostics_meta(estimator: Any) -> dict[str, Any]:
    """An estimator's diagnostics and attack flag as done-report metadata
    (``flag``; ``d:NAME`` per finite value; a non-finite value is left out and reads as
    missing, NaN, at the monitor)."""
    from agents.monitor import read_diagnostics

    diag, flag = read_diagnostics(estimator)
    meta: dict[str, Any] = {}
    if flag is not None:
        meta["flag"] = bool(flag)
    for name, v in list((diag or {}).items())[:MAX_DIAGNOSTICS]:
        key = DIAG_PREFIX + name
        if np.isfinite(v) and len(key) <= 32 and key.replace("_", "a").isalnum() and key.isascii():
            meta[key] = float(v)  # names the codec cannot carry are left out
    return meta


def diagnostics_from_meta(meta: Any) -> tuple[dict[str, float], bool | None]:
    diag = {k[len(DIAG_PREFIX):]: float(v) for k, v in meta.items()
            if isinstance(k, str) and k.startswith(DIAG_PREFIX) and isinstance(v, (int, float)) and not isinstance(v, bool)}
    flag = meta.get("flag")
    return diag, (bool(flag) if isinstance(flag, bool) else None)


class Rejects:
    """Bad messages per claimed sender and reason."""

    def __init__(self) -> None:
        self.counts: Counter[tuple[int, str]] = Counter()

    def add(self, sender: int | None, reason: str) -> None:
        self.counts[(UNKNOWN if sender is None else sender, reason if reason in REASONS else "invalid")] += 1

    def as_array(self) -> np.ndarray:
        rows = [(s, REASONS.index(r), c) for (s, r), c in sorted(self.counts.items())]
        return np.array(rows, dtype=float).reshape(-1, 3)

    @staticmethod
    def merge(into: dict[str, dict[str, int]], rows: np.ndarray) -> None:
        for s, r, c in np.asarray(rows).reshape(-1, 3):
            s, r, c = int(s), int(r), int(c)
            if not (0 <= r < len(REASONS)) or c < 0:
                continue
            rec = into.setdefault(who_name(s), {"total": 0})
            rec["total"] += c
            rec[REASONS[r]] = rec.get(REASONS[r], 0) + c


def _msg(kind: str, sender: int, stamp: int, arrays: dict, **kw: Any) -> bytes:
    return encode_fields(kind, sender, stamp, arrays, **kw)


def out_ids_of(exp: Experiment) -> dict[int, list[int]]:
    """Agent id -> the ids of its out-neighbours (whom a broadcast report went to)."""
    ids = exp.agent_ids
    return {aid: [ids[j] for j in exp.out_neighbours(i)] for i, aid in enumerate(ids)}


def report_to(m: Message, out_ids: Sequence[int], team: int) -> tuple[list[int], list[int]] | None:
    """Whom the round of a done-key message went to and with which stamps: every one of
    ``out_ids`` (the sender's out-neighbours) stamped with the round for an "est" (a
    broadcast report), else :func:`receivers_of`."""
    if m.kind == "est":
        return list(out_ids), [m.stamp] * len(out_ids)
    return receivers_of(m, team)


def receivers_of(m: Message, team: int) -> tuple[list[int], list[int]] | None:
    """A done report's receivers and stamps as ints, or None when they do not pair up,
    are more than ``team`` or are not whole numbers in the stamps' range."""
    to, stamps = m.arrays["to"].tolist(), m.arrays["stamps"].tolist()
    if len(stamps) != len(to) or len(to) > team:
        return None
    if to:  # finite (the codec checked): whole numbers in [0, 2**53), in C loops (a report a round per peer)
        values = to + stamps
        if min(values) < 0 or max(values) >= 2**53 or not all(map(float.is_integer, values)):
            return None
    return list(map(int, to)), list(map(int, stamps))


class Role:
    """What the three roles share: one queue, strict decoding, liveliness bookkeeping."""

    name = "role"

    def __init__(self, exp: Experiment, bus: Bus, keys: Keys, cfg: RunConfig) -> None:
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
            else:
                self.handle_data(key, payload)
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

    def send_stats(self, sender: int, links: np.ndarray | None = None, **meta: Any) -> None:
        links = np.zeros((0, 6)) if links is None else links
        meta = {"cmd": "stats", **process_figures(), "bridge_dropped": int(self.bus.stats.dropped_full),
                "batches": self.batches, **meta}
        self.bus.publish(self.keys.ctl("stats", sender),
                         _msg("ctl", sender, 0, {"links": links, "rejected": self.rejects.as_array()}, meta=meta))
