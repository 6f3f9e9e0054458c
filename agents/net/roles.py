"""The plant, agent and monitor processes as async functions over a :class:`Bus`.

Each role reuses the in-process simulator's pieces (:class:`~agents.plant.PlantRole`,
:class:`~agents.node.AgentNode`, :class:`~agents.monitor.Monitor`), so both drivers share
the round logic and the channel model (drops and delays are decided receiver-side by
``AgentNode.receive`` from ``(seed, sender, receiver, stamp)``).

The round protocol (keys from :class:`transport.keys.Keys`)::

    plant   -> rse/{run}/plant/truth        "truth" x[k]                       (monitor)
    plant   -> rse/{run}/plant/loc/{i}      "meas"  y_i[k], wait list, member  (agent i)
    agent i -> rse/{run}/agent/{i}/est      "est"   payload stamped k (broadcast)
            or rse/{run}/agent/{i}/est/{j}  "est"   addressed payloads (Byzantine)
    agent i -> rse/{run}/ctl/done/{i}       "done"  own estimate x_i[k], receivers  (plant, monitor)
    agent i -> rse/{run}/ctl/ready/{i}      joining the team                    (plant)
    monitor -> rse/{run}/ctl/ack/monitor    rounds recorded (flow control)      (plant)
    plant   -> rse/{run}/plant/loc/{i}      "ctl" cmd=stop, wait list           (agent i)
    plant   -> rse/{run}/ctl/stop/plant     the last round                      (monitor)
    every   -> rse/{run}/ctl/stats/{who}    link and rejection counters, RSS    (monitor)
    every   -> rse/{run}/alive/{role}/{i}   liveliness token

**Lockstep**: the plant publishes round ``k`` once every member agent reported round
``k - 1`` done (or the deadline passed; a member whose token went away is not waited
for). The meas message to agent ``i`` lists the in-neighbours whose round ``k - 1``
messages were sent to ``i`` (from their done reports); the agent runs round ``k`` when
all of them have physically arrived (or the deadline passed), so every message reaches
``AgentNode.receive`` before the round in which the channel model makes it visible, and
the estimates equal ``rse simulate``'s. **Realtime**: the plant ticks at ``rate`` Hz on
the wall clock, agents run a round as soon as its measurement arrives, with whatever
has arrived (late messages are placed by their stamps).

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
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from estimation.errors import MessageError, RSEError, TransportError
from transport.codec import MIN_ID, MONITOR_ID, PLANT_ID, Message, Schema, decode, encode
from transport.keys import Keys, ParsedKey
from transport.zenoh_bus import Bus

if TYPE_CHECKING:
    from scenarios.build import Experiment

log = logging.getLogger("rse.net")

MODES = ("lockstep", "realtime")
QUEUE_SIZE = 1 << 16
MONITOR_LAG = 128  # the monitor closes round k once truth k + LAG arrived
ACK_EVERY = 32
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
    """

    mode: str = "lockstep"
    rate: float | None = None
    deadline: float = 1.0
    startup_timeout: float = 60.0
    save_estimates: bool = False
    linger: float = 2.0
    warmup: float = 3.0

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


def who_name(sender: int | None) -> str:
    if sender is None or sender == UNKNOWN:
        return "unknown"
    return {PLANT_ID: "plant", MONITOR_ID: "monitor"}.get(sender, str(sender))


class Wire:
    """The schemas of one scenario's messages."""

    def __init__(self, exp: Experiment) -> None:
        n, N = exp.n, exp.N
        self.n, self.N = n, N
        self.ny = int(sum(len(r) for r in exp.bank_rows))
        self.loc = Schema({"meas": {"y": (None,), "wait": (None, 2)}, "ctl": {"wait": (None, 2)}})
        self.truth = Schema({"truth": {"x": (n,)}})
        self.est = Schema({"est": {"x": (None,)}})
        self.done = Schema({"done": {"x": (n,), "to": (None,), "stamps": (None,)}})
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
    return encode(Message(kind=kind, sender=sender, stamp=stamp, arrays=arrays, **kw))


class Role:
    """What the three roles share: one queue, strict decoding, liveliness bookkeeping."""

    name = "role"

    def __init__(self, exp: Experiment, bus: Bus, keys: Keys, cfg: RunConfig) -> None:
        self.exp, self.bus, self.keys, self.cfg = exp, bus, keys, cfg
        self.wire = Wire(exp)
        self.queue: asyncio.Queue = asyncio.Queue(maxsize=QUEUE_SIZE)
        self.rejects = Rejects()
        self.alive: set[tuple[str, int]] = set()
        self.changed = asyncio.Event()
        self.ids = set(exp.agent_ids)
        self._waiting: Callable[[], bool] | None = None  # the predicate wait_for waits on

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
        q = self.queue
        while True:
            self.handle(await q.get())
            while not q.empty():
                self.handle(q.get_nowait())
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
                except asyncio.TimeoutError:
                    return pred()
            return True
        finally:
            self._waiting = None

    def send_stats(self, sender: int, links: np.ndarray | None = None, **meta: Any) -> None:
        links = np.zeros((0, 6)) if links is None else links
        meta = {"cmd": "stats", "maxrss_mb": maxrss_mb(), "bridge_dropped": int(self.bus.stats.dropped_full), **meta}
        self.bus.publish(self.keys.ctl("stats", sender),
                         _msg("ctl", sender, 0, {"links": links, "rejected": self.rejects.as_array()}, meta=meta))


# ------------------------------------------------------------------------------- plant


class PlantProcess(Role):
    name = "plant"

    def __init__(self, exp: Experiment, bus: Bus, keys: Keys, cfg: RunConfig) -> None:
        super().__init__(exp, bus, keys, cfg)
        from agents.plant import PlantRole

        self.plant = PlantRole(exp)
        self.ready: set[int] = set()  # agents that asked to join
        self.members: set[int] = set()
        self.done: dict[int, dict[int, list[tuple[int, int]]]] = {}  # round -> agent -> (receiver, stamp)
        self.monitor_ack = -1
        self.missed: Counter[int] = Counter()
        out_ids = {aid: {exp.agent_ids[j] for j in exp.out_neighbours(i)} for i, aid in enumerate(exp.agent_ids)}
        self.out_ids = out_ids

    def on_alive(self, role: str, i: int, alive: bool) -> None:
        if role == "agent" and not alive:
            self.ready.discard(i)
            if i in self.members:
                self.members.discard(i)
                log.info("plant: agent %d left", i)

    def handle_data(self, key: str, payload: bytes) -> None:
        if "/ctl/done/" in key:
            got = self.decode(key, payload, self.wire.done)
            if got is None:
                return
            p, m = got
            to, stamps = m.arrays["to"], m.arrays["stamps"]
            allowed = self.out_ids.get(p.sender)
            tl, sl = to.tolist(), stamps.tolist()
            if (allowed is None or len(tl) > len(allowed) or len(sl) != len(tl)
                    or not all(t.is_integer() and int(t) in allowed for t in tl)
                    or not all(s.is_integer() and 0 <= s < 2**53 for s in sl)):
                self.rejects.add(p.sender, "range")
                return
            rnd = self.done.get(m.stamp)
            if rnd is not None:
                rnd[p.sender] = [(int(t), int(s)) for t, s in zip(tl, sl)]
        elif "/ctl/ready/" in key:
            got = self.decode(key, payload, self.wire.ctl)
            if got is not None and got[0].sender in self.ids:
                self.ready.add(got[0].sender)
        elif "/ctl/ack/" in key:
            got = self.decode(key, payload, self.wire.ctl)
            if got is not None and got[0].sender == MONITOR_ID:
                self.monitor_ack = max(self.monitor_ack, got[1].stamp)
        else:
            self.rejects.add(None, "key")

    def _wait_lists(self, prev: dict[int, list[tuple[int, int]]]) -> dict[int, np.ndarray]:
        """Per receiver, the (sender, stamp) pairs of the messages sent to it last round."""
        lists: dict[int, list[tuple[int, int]]] = {aid: [] for aid in self.exp.agent_ids}
        for sender, to in prev.items():
            for r, stamp in to:
                if r in lists:
                    lists[r].append((sender, stamp))
        return {r: np.array(sorted(v), dtype=float).reshape(-1, 2) for r, v in lists.items()}

    async def run(self) -> dict[str, Any]:
        exp, keys, bus, cfg = self.exp, self.keys, self.bus, self.cfg
        bus.subscribe(keys.ctl_pattern("done"), self.queue)
        bus.subscribe(keys.ctl_pattern("ready"), self.queue)
        bus.subscribe(keys.ctl_pattern("ack"), self.queue)
        bus.watch(keys.alive_pattern(), self.queue)
        consumer = asyncio.ensure_future(self.consume())
        try:
            bus.announce(keys.alive("plant", 0))
            everyone = set(exp.agent_ids)
            ok = await self.wait_for(lambda: ("monitor", 0) in self.alive and self.ready >= everyone, cfg.startup_timeout)
            if not ok:
                missing = sorted(everyone - self.ready)
                what = ([f"agent(s) {', '.join(map(str, missing))}"] if missing else []) + \
                       (["the monitor"] if ("monitor", 0) not in self.alive else [])
                raise TransportError(f"{' and '.join(what)} did not join within {cfg.startup_timeout:g} s")
            log.debug("plant: the team is complete")
            return await self._rounds()
        finally:
            consumer.cancel()

    async def _rounds(self) -> dict[str, Any]:
        exp, keys, bus, cfg, plant = self.exp, self.keys, self.bus, self.cfg, self.plant
        K = exp.n_rounds
        ids = exp.agent_ids
        static = getattr(exp, "static", True)
        lockstep = cfg.mode == "lockstep"
        period = 1.0 / cfg.rate if cfg.rate else None
        loc_keys = {aid: keys.plant_loc(aid) for aid in ids}
        truth_key = keys.plant_truth()
        prev: dict[int, list[tuple[int, int]]] = {}
        empty = np.zeros(0)
        nowait = np.zeros((0, 2))
        t0 = time.monotonic()
        for k in range(K + 1):
            joined = (self.ready & {a for (r, a) in self.alive if r == "agent"}) - self.members
            if joined:
                self.members |= joined
                log.info("plant: agent(s) %s joined at round %d", ", ".join(map(str, sorted(joined))), k)
            self.done[k] = {}
            y = plant.measure(k)
            bus.publish(truth_key, _msg("truth", PLANT_ID, k, {"x": plant.x}))
            waits = self._wait_lists(prev) if lockstep else {}
            # realtime: a measurement an agent cannot take now is dropped for it alone
            # (an unreachable agent must not hold up the others' measurements)
            for i, aid in enumerate(ids):
                rows = exp.agent_rows[i] if static else exp.rows_at(i, k)
                meas = empty if rows is None else y[rows]
                member = aid in self.members
                bus.publish(loc_keys[aid], _msg("meas", PLANT_ID, k, {"y": meas, "wait": waits.get(aid, nowait) if member else nowait},
                                                meta={"member": member, "nomeas": rows is None}), droppable=not lockstep)
            if lockstep:
                expected = set(self.members)
                rnd = self.done[k]
                finished = await self.wait_for(lambda: all(a in rnd or a not in self.members for a in expected),
                                               cfg.deadline)
                if not finished:
                    late = sorted(a for a in expected if a not in rnd and a in self.members)
                    for a in late:
                        self.missed[a] += 1
                        if self.missed[a] in (1, 10, 100, 1000):
                            log.warning("plant: agent %d missed the %g s deadline in round %d (%d time(s))",
                                        a, cfg.deadline, k, self.missed[a])
                if k - self.monitor_ack > MAX_AHEAD:
                    if not await self.wait_for(lambda: k - self.monitor_ack <= MAX_AHEAD // 2, cfg.startup_timeout):
                        raise TransportError(f"the monitor stopped acknowledging rounds (last {self.monitor_ack})")
            if period is not None:
                delay = t0 + (k + 1) * period - time.monotonic()
                if delay > 0:
                    await asyncio.sleep(delay)
            prev = self.done[k]
            self.done.pop(k - 1, None)
            if k < K:
                plant.advance(k)
        elapsed = time.monotonic() - t0
        # the end: final wait lists (messages stamped K), then stop
        waits = self._wait_lists(self.done.get(K, {})) if lockstep else {}
        self.send_stats(PLANT_ID, elapsed=elapsed, rounds=K + 1, missed=int(sum(self.missed.values())))
        for aid in ids:
            bus.publish(loc_keys[aid], _msg("ctl", PLANT_ID, K, {"wait": waits.get(aid, nowait)}, meta={"cmd": "stop"}))
        bus.publish(keys.ctl("stop", PLANT_ID), _msg("ctl", PLANT_ID, K, {}, meta={"cmd": "stop"}))
        await asyncio.sleep(0.05)  # let the last messages leave before the session closes
        return {"elapsed": elapsed, "rounds": K + 1}


# ------------------------------------------------------------------- adversary view


def reads_view(strategy: Any) -> bool:
    """Whether a Byzantine strategy reads ``node.view`` (the omniscient adversary)."""
    return getattr(strategy, "kind", None) == "cancellation"


def simulator_order(exp: Experiment) -> dict[int, int]:
    """Agent id -> rank in the simulator's round order (regular agents first, by index,
    then the Byzantine ones, by index)."""
    order = [i for i in range(exp.N) if i not in exp.byzantine] + sorted(exp.byzantine)
    return {exp.agent_ids[i]: r for r, i in enumerate(order)}


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
    estimator's ``uses(sender_index)`` when it has one, in the simulator's order (so the
    sums are bit-identical). In lockstep the agent publishes round ``k`` only once
    :meth:`ready` (every such agent's round-``k`` messages to ``me``'s out-neighbours have
    arrived, or it is not alive) or the deadline passed.
    """

    MAX_STORED = 1 << 14

    def __init__(self, exp: Experiment, me: int, channel: Any, uses: dict[int, Any] | None = None) -> None:
        self.k = 0
        self.me = me
        self.channel = channel
        rank = simulator_order(exp)
        ids = exp.agent_ids
        self.index_of = {aid: i for i, aid in enumerate(ids)}
        i_me = self.index_of[me]
        self.out = [ids[j] for j in exp.out_neighbours(i_me)]
        self.out_set = set(self.out)
        #: receiver -> its in-neighbours that act before me, in the simulator's order
        self.before: dict[int, list[int]] = {}
        for j in self.out:
            ins = [ids[s] for s in exp.in_neighbours(self.index_of[j])]
            self.before[j] = sorted((s for s in ins if s != me and rank[s] < rank[me]), key=rank.__getitem__)
        #: the agents whose round-k messages the view needs
        self.needed = sorted({s for v in self.before.values() for s in v})
        if uses is None:
            uses = {j: getattr(exp.make_estimator(self.index_of[j]), "uses", None) for j in self.out}
        self.uses = uses
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
        uses = self.uses.get(receiver)
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
            out.append(v * uses(self.index_of[s]) if uses is not None else v)
        return out

    def forget(self, k: int) -> None:
        """Drop what rounds before ``k`` left behind."""
        self.k = k
        for store in (self.bcast, self.addr):
            for key in [key for key in store if key[-1] < k]:
                del store[key]
        for s in [s for s in self.done if s < k]:
            del self.done[s]


# ------------------------------------------------------------------------------- agent


class AgentProcess(Role):
    name = "agent"

    def __init__(self, exp: Experiment, agent_id: int, bus: Bus, keys: Keys, cfg: RunConfig,
                 *, node_hook: Callable[[Any], None] | None = None, node: Any = None) -> None:
        super().__init__(exp, bus, keys, cfg)
        if agent_id not in exp.agent_ids:
            raise RSEError(f"no agent {agent_id} in this scenario; agents are {', '.join(map(str, exp.agent_ids))}")
        self.id = agent_id
        self.index = i = exp.agent_ids.index(agent_id)
        self.name = f"agent {agent_id}"
        if node is None:
            from agents.simulate import make_channel, make_nodes

            node = make_nodes(exp, make_channel(exp))[i]
        self.node = node
        self.est_schema = Schema({"est": {"x": self._payload_shape()}})
        if node_hook is not None:
            node_hook(self.node)
        self.in_ids = [exp.agent_ids[j] for j in exp.in_neighbours(i)]
        self.out_ids = [exp.agent_ids[j] for j in exp.out_neighbours(i)]
        self.member = False
        self.meas: dict[int, tuple[np.ndarray | None, np.ndarray, float]] = {}
        self.arrived: dict[int, set[int]] = {}
        self.last = -1
        self.stop: tuple[int, np.ndarray, float] | None = None
        self.finished = asyncio.Event()
        self.plant_seen_at: float | None = None
        self.running_team = False
        self.rounds_run = 0
        self.skipped = 0
        self.waited_out = 0
        self._timer: asyncio.TimerHandle | None = None
        self._own_estimate = getattr(self.node, "estimate", None)
        from agents.monitor import has_diagnostics

        self._diagnostics = has_diagnostics(self.node.estimator)
        self._est_key = keys.est(agent_id)
        self._done_key = keys.ctl("done", agent_id)
        self._ready_key = keys.ctl("ready", agent_id)
        self._loc_key = keys.plant_loc(agent_id)
        self._last_ready = 0.0
        self.silent_until = 0
        #: an omniscient Byzantine strategy's view of its receivers (see NetworkView)
        self.view: NetworkView | None = None
        self._held: tuple[int, np.ndarray, float] | None = None  # lockstep: a round waiting for the view
        self._error: Exception | None = None  # raised in the consumer's _step
        if node.strategy is not None and reads_view(node.strategy):
            self.view = NetworkView(exp, agent_id, node.channel)
            node.view = self.view
            self._done_schema = self.wire.done

    def _payload_shape(self) -> tuple[int, ...]:
        """The shape of an estimate message: a dry run of a copy of this agent's estimator
        (every agent of a scenario publishes the same shape; others are rejected)."""
        import copy

        try:
            est = copy.deepcopy(self.node.estimator)
            return tuple(np.shape(est.step(0, None, {})))
        except Exception:
            return (self.exp.n,)

    def on_reject(self, sender: int | None) -> None:
        if sender is not None:
            self.node.reject(sender)

    def on_alive(self, role: str, i: int, alive: bool) -> None:
        if role == "plant":
            if alive:
                self.plant_seen_at = time.monotonic()
            elif self.stop is None:
                log.warning("agent %d: the plant left", self.id)

    def handle_data(self, key: str, payload: bytes) -> None:
        if key == self._loc_key:
            got = self.decode(key, payload, self.wire.loc)
            if got is None:
                return
            m = got[1]
            wait = m.arrays["wait"]
            if len(wait) > 64 * max(1, len(self.in_ids)):
                self.rejects.add(PLANT_ID, "range")
                return
            now = time.monotonic()
            if m.kind == "ctl":
                if m.meta.get("cmd") == "stop":
                    self.stop = (m.stamp, wait, now)
                return
            self.running_team = True
            member = bool(m.meta.get("member", False))
            if member and not self.member:
                self.member = True
                if m.stamp > 0:
                    self.silent_until = m.stamp + int(math.ceil(self.cfg.warmup / self.exp.dt))
                log.info("agent %d: joined the team at round %d", self.id, m.stamp)
            elif not member and self.member:
                self.member = False
                log.warning("agent %d: the plant no longer counts this agent; rejoining", self.id)
            if not self.member or m.stamp <= self.last:
                return
            y = m.arrays["y"]
            if y.size > self.wire.ny:
                self.rejects.add(PLANT_ID, "range")
                return
            self.meas[m.stamp] = (None if m.meta.get("nomeas") else y, wait, now)
            return
        if self.view is not None:
            self._handle_view(key, payload)
            return
        got = self.decode(key, payload, self.est_schema)
        if got is None:
            return
        p, m = got
        j = p.sender
        if j not in self.node.links:
            self.rejects.add(j, "neighbour")
            return
        self._take(j, m.stamp, m.arrays["x"])

    def _take(self, j: int, stamp: int, x: np.ndarray) -> None:
        """Hand a decoded estimate of in-neighbour ``j`` to the node (its channel decides)
        and note its arrival for the lockstep wait lists."""
        self.node.receive(j, stamp, x)
        if stamp >= self.last - 2 and len(self.arrived) < 4096:
            self.arrived.setdefault(stamp, set()).add(j)

    def _handle_view(self, key: str, payload: bytes) -> None:
        """A Byzantine agent with a view hears every estimate of the run and the done
        reports of the agents it depends on: its own inbox, and the view's store."""
        try:
            p = self.keys.parse(key)
        except MessageError:
            self.rejects.add(None, "key")
            return
        if p.kind == "ctl":
            try:
                m = decode(payload, schema=self._done_schema, expected_sender=p.sender)
            except MessageError as exc:
                self.rejects.add(p.sender, exc.reason)
                return
            to, stamps = m.arrays["to"], m.arrays["stamps"]
            if (p.sender not in self.view.index_of or stamps.size != to.size or to.size > self.exp.N
                    or not all(float(v).is_integer() and 0 <= v < 2**53 for v in (*to, *stamps))):
                self.rejects.add(p.sender, "range")
                return
            self.view.add_done(p.sender, m.stamp, [(int(t), int(st)) for t, st in zip(to, stamps)])
            return
        j, receiver = p.sender, p.receiver
        mine = receiver == self.id or (receiver is None and j in self.node.links)
        if not mine and not (self.view.wants(j, receiver)):
            return
        try:
            m = decode(payload, schema=self.est_schema, expected_sender=j, expected_receiver=receiver)
        except MessageError as exc:
            self.rejects.add(j, exc.reason)
            if mine:
                self.node.reject(j)
            return
        if self.view.wants(j, receiver):
            self.view.add(j, receiver, m.stamp, m.arrays["x"])
        if not mine:
            return
        if j not in self.node.links:
            self.rejects.add(j, "neighbour")
            return
        self._take(j, m.stamp, m.arrays["x"])

    def _release_held(self, now: float) -> bool:
        """Lockstep, phase two of round k for an omniscient adversary: publish once the
        view is complete (or the deadline passed). Returns whether it was published."""
        k, out, t0 = self._held
        view = self.view
        if not view.ready(k, lambda s: ("agent", s) in self.alive):
            if now < t0 + self.cfg.deadline:
                self._tick_at(t0 + self.cfg.deadline)
                return False
            self.waited_out += 1
            if self.waited_out in (1, 10, 100, 1000):
                log.warning("agent %d: round %d published without a complete view (%d time(s))", self.id, k,
                            self.waited_out)
        self._held = None
        self._publish_round(k, out)
        return True

    def _arrived_all(self, wait: np.ndarray) -> bool:
        arrived = self.arrived
        return all(int(j) in arrived.get(int(s), ()) for j, s in wait)

    def _tick_at(self, when: float) -> None:
        if self._timer is not None:
            self._timer.cancel()
        loop = asyncio.get_running_loop()
        self._timer = loop.call_at(loop.time() + max(0.0, when - time.monotonic()), self.changed.set)

    def _publish_round(self, k: int, out: np.ndarray) -> None:
        node, bus = self.node, self.bus
        if self.view is not None:
            self.view.forget(k)
        own = self._own_estimate(out) if self._own_estimate is not None else out
        msg = node.publish(k, out) if node.strategy is not None else out
        aid = self.id
        drop = self.cfg.mode == "realtime"  # an estimate a neighbour cannot take now is dropped for it alone
        try:
            if k < self.silent_until:  # warming up after a late join: listen only
                to, stamps = [], []
            elif isinstance(msg, dict):
                to, stamps = [], []
                for tgt in self.out_ids:
                    payload = msg.get(tgt)
                    if payload is None:
                        continue
                    stamp = getattr(payload, "stamp", k)
                    value = getattr(payload, "value", payload)
                    bus.publish(self.keys.est(aid, tgt), _msg("est", aid, int(stamp), {"x": value}, receiver=tgt),
                                droppable=drop)
                    to.append(tgt)
                    stamps.append(int(stamp))
            else:
                bus.publish(self._est_key, _msg("est", aid, k, {"x": msg}), droppable=drop)
                to, stamps = self.out_ids, [k] * len(self.out_ids)
        except MessageError as exc:  # a non-finite estimate cannot go on the wire
            log.warning("agent %d: round %d message not sent: %s", aid, k, exc)
            to, stamps = [], []
        meta: dict[str, Any] = {}
        if not np.all(np.isfinite(own)):
            own, meta = np.zeros_like(own), {"nonfinite": True}
        if self._diagnostics:
            meta.update(diagnostics_meta(node.estimator))
        bus.publish(self._done_key, _msg("done", aid, k, {"x": own, "to": np.array(to, dtype=float), "stamps": np.array(stamps, dtype=float)}, meta=meta or None))

    def _step(self) -> None:
        """Run every round that can run now."""
        lockstep = self.cfg.mode == "lockstep"
        now = time.monotonic()
        if self._held is not None and not self._release_held(now):
            return
        while self.meas:
            if lockstep:
                k = min(self.meas)
                y, wait, t_arr = self.meas[k]
                if not self._arrived_all(wait):
                    if now < t_arr + self.cfg.deadline:
                        self._tick_at(t_arr + self.cfg.deadline)
                        return
                    self.waited_out += 1
                    if self.waited_out in (1, 10, 100, 1000):
                        log.warning("agent %d: round %d went on without some neighbours' messages (%d time(s))",
                                    self.id, k, self.waited_out)
                del self.meas[k]
            else:
                k = max(self.meas)
                y = self.meas[k][0]
                self.skipped += len(self.meas) - 1
                self.meas.clear()
            out = self.node.run_round(k, y)
            self.last = k
            self.rounds_run += 1
            for s in [s for s in self.arrived if s < k - 2]:
                del self.arrived[s]
            if self.view is not None and lockstep and k >= self.silent_until:
                self._held = (k, out, now)
                if not self._release_held(now):
                    return
            else:
                self._publish_round(k, out)
        if self.stop is not None and not self.meas:
            K, wait, t_arr = self.stop
            if lockstep and self.member and not self._arrived_all(wait) and now < t_arr + self.cfg.deadline:
                self._tick_at(t_arr + self.cfg.deadline)
                return
            self.finished.set()

    def after_batch(self) -> bool:
        # a member runs its rounds right here (the main loop wakes only when it must)
        if not self.member or self._error is not None or ("plant", 0) not in self.alive:
            return True
        try:
            self._step()
        except Exception as exc:  # re-raised by the main loop
            self._error = exc
            return True
        return self.finished.is_set() or not self.member

    def _maybe_ready(self) -> None:
        if self.member or self.plant_seen_at is None or ("monitor", 0) not in self.alive:
            return
        now = time.monotonic()
        neighbours = set(self.in_ids) | set(self.out_ids)
        seen = {i for (r, i) in self.alive if r == "agent"}
        if not neighbours <= seen and not (self.running_team and now - self.plant_seen_at > 1.0):
            return
        if now - self._last_ready >= 0.1:
            if not self._last_ready:
                log.debug("agent %d: ready", self.id)
            self._last_ready = now
            self.bus.publish(self._ready_key, _msg("ctl", self.id, 0, {}))

    async def run(self) -> dict[str, Any]:
        exp, keys, bus, cfg = self.exp, self.keys, self.bus, self.cfg
        bus.subscribe(self._loc_key, self.queue)
        if self.view is None:
            for j in self.in_ids:
                bus.subscribe(keys.est(j), self.queue)
            bus.subscribe(keys.est_pattern(to=self.id), self.queue)
        else:  # also the estimates its receivers will use, and the reports it waits for
            for j in sorted(set(self.in_ids) | set(self.view.needed)):
                bus.subscribe(keys.est(j), self.queue)
            for j in sorted({self.id} | self.view.out_set):
                bus.subscribe(keys.est_pattern(to=j), self.queue)
            for s in self.view.needed:
                bus.subscribe(keys.ctl("done", s), self.queue)
        bus.watch(keys.alive_pattern(), self.queue)
        bus.announce(keys.alive("agent", self.id))
        consumer = asyncio.ensure_future(self.consume())
        t_start = time.monotonic()
        try:
            while not self.finished.is_set():
                self.changed.clear()
                if self._error is not None:
                    raise self._error
                self._step()
                if self.finished.is_set():
                    break
                if not self.member:
                    self._maybe_ready()
                    if self.stop is not None:
                        break
                    if not self.running_team and time.monotonic() - t_start > cfg.startup_timeout:
                        raise TransportError(f"agent {self.id}: no plant found within {cfg.startup_timeout:g} s")
                    timeout = 0.1
                else:
                    timeout = None
                if ("plant", 0) not in self.alive and self.plant_seen_at is not None and self.stop is None:
                    # the plant left without stopping the team: give it a moment, then leave
                    await asyncio.sleep(max(0.5, cfg.deadline))
                    if ("plant", 0) not in self.alive and self.stop is None:
                        raise TransportError(f"agent {self.id}: the plant left before the end of the run")
                try:
                    await asyncio.wait_for(self.changed.wait(), timeout)
                except asyncio.TimeoutError:
                    pass
            links = np.array([[j, c.sent, c.delivered, c.dropped, c.late, c.rejected] for j, c in self.node.links.items()],
                             dtype=float).reshape(-1, 6)
            self.send_stats(self.id, links, rounds=self.rounds_run, skipped=self.skipped, waited_out=self.waited_out)
            await asyncio.sleep(0.05)
            return {"rounds": self.rounds_run}
        finally:
            consumer.cancel()
            if self._timer is not None:
                self._timer.cancel()


# ----------------------------------------------------------------------------- monitor


@dataclass
class _Round:
    x: np.ndarray | None = None
    est: np.ndarray | None = None
    present: np.ndarray | None = None
    diag: dict[int, tuple[dict[str, float], bool | None]] = field(default_factory=dict)


@dataclass
class MonitorResult:
    summary: dict[str, Any]
    out_dir: Path | None
    estimates: np.ndarray | None = None
    truth: np.ndarray | None = None


class MonitorProcess(Role):
    name = "monitor"

    def __init__(self, exp: Experiment, bus: Bus, keys: Keys, cfg: RunConfig, *, out_dir: Path | None = None,
                 progress: Callable[[str, Any], None] | None = None, dashboard: Any = None) -> None:
        super().__init__(exp, bus, keys, cfg)
        from agents.monitor import Monitor

        self.mon = Monitor(exp)
        self.dashboard = dashboard
        self._last_flush = time.monotonic()
        if dashboard is not None:
            self._setup_dashboard(dashboard)
        self.out_dir = out_dir
        self.progress = progress or (lambda kind, data: None)
        self.rounds: dict[int, _Round] = {}
        self.next_k = 0
        self.max_truth = -1
        self.stop_round: int | None = None
        self.stats: dict[str, Message] = {}
        self.membership: list[dict[str, Any]] = []
        self.index = {aid: i for i, aid in enumerate(exp.agent_ids)}
        self.t0 = time.monotonic()
        K = exp.n_rounds + 1
        self.traj = np.full((K, exp.N, exp.n), np.nan) if cfg.save_estimates else None
        self.truth = np.full((K, exp.n), np.nan) if cfg.save_estimates else None
        self._last_progress = 0.0

    def after_batch(self) -> bool:
        # rounds are recorded by handle_data; the main loop only watches for the end
        if self._waiting is not None:
            return super().after_batch()
        return self.stop_round is not None or self.next_k == 0 or ("plant", 0) not in self.alive

    def _setup_dashboard(self, dash: Any) -> None:
        """Stream to the Rerun dashboard as ``rse simulate`` does: per chunk of recorded
        rounds the metrics, state plots, map frames and counters. The links delivered in a
        round and the link counters are reconstructed from the done reports (who sent what
        to whom, stamped when) with the channel model, as each receiver's node decides."""
        from agents.simulate import make_channel

        exp, mon = self.exp, self.mon
        self._channel = make_channel(exp)
        self._frames: dict[int, np.ndarray] = {}
        self._counters = np.zeros((exp.N, 4))  # delivered, dropped, late, rejected (per receiver)
        N = exp.N

        def on_chunk(rows: Any, xs: np.ndarray, ests: np.ndarray) -> None:
            frames = {int(k): self._frames.pop(int(k), None) for k in rows if dash.is_map_frame(int(k))}
            for k, D in frames.items():
                if D is None:
                    frames[k] = np.zeros((N, N), dtype=bool)
            try:
                dash.log_chunk(rows, mon, x=xs, est=ests, delivered=frames, counters=self._counters.copy())
            except Exception:  # the dashboard must not stop the monitor
                log.exception("monitor: could not log to the dashboard")

        mon.on_chunk = on_chunk

    def _links_of(self, sender: int, stamp: int, to: np.ndarray, stamps: np.ndarray) -> None:
        """Dashboard bookkeeping of one done report (see :meth:`_setup_dashboard`)."""
        fate, index, dash = self._channel.fate, self.index, self.dashboard
        s = index[sender]
        for t, st in zip(to, stamps):
            r = index.get(int(t))
            if r is None:
                continue
            when = fate(sender, int(t), int(st))
            c = self._counters[r]
            if when is None:
                c[1] += 1
                continue
            c[0] += 1
            if when > int(st) + 1:
                c[2] += 1
            if when >= self.next_k and dash.is_map_frame(when) and when <= self.exp.n_rounds:
                D = self._frames.get(when)
                if D is None:
                    D = self._frames[when] = np.zeros((self.exp.N, self.exp.N), dtype=bool)
                D[r, s] = True

    def on_alive(self, role: str, i: int, alive: bool) -> None:
        event = {"t_wall": round(time.monotonic() - self.t0, 3), "round": self.next_k, "role": role, "id": i,
                 "event": "join" if alive else "leave"}
        self.membership.append(event)
        label = role if role != "agent" else f"agent {i}"
        log.info("monitor: %s %s (round %d)", label, "joined" if alive else "left", self.next_k)
        self.progress("member", event)

    def _rec(self, k: int) -> _Round:
        r = self.rounds.get(k)
        if r is None:
            r = self.rounds[k] = _Round(est=np.full((self.exp.N, self.exp.n), np.nan),
                                        present=np.zeros(self.exp.N, dtype=bool))
        return r

    def handle_data(self, key: str, payload: bytes) -> None:
        K = self.exp.n_rounds
        if key.endswith("/plant/truth"):
            got = self.decode(key, payload, self.wire.truth)
            if got is None:
                return
            k = got[1].stamp
            if k > K or k < self.next_k:
                self.rejects.add(PLANT_ID, "range")
                return
            self._rec(k).x = got[1].arrays["x"]
            self.max_truth = max(self.max_truth, k)
        elif "/ctl/done/" in key:
            got = self.decode(key, payload, self.wire.done)
            if got is None:
                return
            p, m = got
            k = m.stamp
            if p.sender not in self.index or k > K:
                self.rejects.add(p.sender, "range")
                return
            if k < self.next_k:
                return  # too late for the record
            r = self._rec(k)
            i = self.index[p.sender]
            if not m.meta.get("nonfinite"):
                r.est[i] = m.arrays["x"]
            r.present[i] = True
            if m.meta:
                diag, flag = diagnostics_from_meta(m.meta)
                if diag or flag is not None:
                    r.diag[i] = (diag, flag)
            if self.dashboard is not None:
                self._links_of(p.sender, k, m.arrays["to"], m.arrays["stamps"])
        elif "/ctl/stats/" in key:
            got = self.decode(key, payload, self.wire.stats)
            if got is not None:
                self.stats[who_name(got[0].sender)] = got[1]
        elif "/ctl/stop/" in key:
            got = self.decode(key, payload, self.wire.ctl)
            if got is not None and got[0].sender == PLANT_ID:
                self.stop_round = got[1].stamp
        else:
            self.rejects.add(None, "key")
        self._close_rounds(final=False)

    def _complete(self, r: _Round) -> bool:
        # not before the plant's token: until then this process does not know the team (a
        # monitor that subscribes late gets the tokens present in one batch, which through
        # a loaded router can come rounds after the first truth and done reports)
        if r.x is None or ("plant", 0) not in self.alive:
            return False
        for (role, aid) in self.alive:
            if role == "agent" and aid in self.index and not r.present[self.index[aid]]:
                return False
        return True

    def _close_rounds(self, final: bool) -> None:
        closed = False
        while True:
            k = self.next_k
            if k > self.exp.n_rounds:
                break
            r = self.rounds.get(k)
            complete = r is not None and self._complete(r)
            if not complete and not final and self.max_truth < k + MONITOR_LAG:
                break
            if r is not None and r.x is not None:
                self.mon.record(k, r.x, r.est, r.present)
                for i, (diag, flag) in r.diag.items():
                    self.mon.record_diagnostics(k, i, diag, flag)
                if self.traj is not None:
                    self.traj[k] = np.where(r.present[:, None], r.est, np.nan)
                    self.truth[k] = r.x
            self.rounds.pop(k, None)
            self.next_k = k + 1
            closed = True
            if self.next_k % ACK_EVERY == 0:
                self.bus.publish(self.keys.ctl("ack", MONITOR_ID), _msg("ctl", MONITOR_ID, self.next_k - 1, {}))
            if final and self.stop_round is not None and self.next_k > self.stop_round:
                break
        if closed:
            now = time.monotonic()
            if self.dashboard is not None and now - self._last_flush > 0.5:
                self._last_flush = now
                self.mon.flush()  # keep the live view fresh
            if now - self._last_progress > 0.1 or final:
                self._last_progress = now
                self.progress("round", (self.next_k - 1, self.mon.current_worst()))

    async def run(self) -> MonitorResult:
        keys, bus, cfg, exp = self.keys, self.bus, self.cfg, self.exp
        bus.subscribe(keys.plant_truth(), self.queue)
        bus.subscribe(keys.ctl_pattern("done"), self.queue)
        bus.subscribe(keys.ctl_pattern("stats"), self.queue)
        bus.subscribe(keys.ctl_pattern("stop"), self.queue)
        bus.watch(keys.alive_pattern(), self.queue)
        bus.announce(keys.alive("monitor", 0))
        consumer = asyncio.ensure_future(self.consume())
        try:
            # the whole run, bounded only by the plant: it stops the team (or leaves)
            while self.stop_round is None:
                if self.next_k == 0 and ("plant", 0) not in self.alive and time.monotonic() - self.t0 > cfg.startup_timeout:
                    raise TransportError(f"no plant found within {cfg.startup_timeout:g} s")
                if self.next_k > 0 and ("plant", 0) not in self.alive:
                    await asyncio.sleep(max(0.5, cfg.deadline))
                    if self.stop_round is None and ("plant", 0) not in self.alive:
                        raise TransportError("the plant left before the end of the run")
                self.changed.clear()
                try:
                    await asyncio.wait_for(self.changed.wait(), 0.25)
                except asyncio.TimeoutError:
                    pass
            K = self.stop_round
            await self.wait_for(lambda: self.next_k > K or (K in self.rounds and self._complete(self.rounds[K])), cfg.deadline)
            self._close_rounds(final=True)
            agents_alive = lambda: {str(a) for (r, a) in self.alive if r == "agent"}  # noqa: E731
            await self.wait_for(lambda: "plant" in self.stats and agents_alive() <= set(self.stats), cfg.linger)
            return self._finish()
        finally:
            consumer.cancel()

    def _finish(self) -> MonitorResult:
        from agents.summary import evaluate, summarise

        exp, mon = self.exp, self.mon
        if self.dashboard is not None:  # the final rejected counts per receiver, for the last chunk
            for who, m in self.stats.items():
                if who.isdigit() and int(who) in self.index:
                    self._counters[self.index[int(who)], 3] = float(np.sum(m.arrays["links"][:, 5]))
        mon.flush()
        if self.dashboard is not None:
            self.dashboard.flush()
        regular = np.array([i not in exp.byzantine for i in range(exp.N)])
        links: dict[str, dict[str, int]] = {}
        rejected: dict[str, dict[str, int]] = {}
        processes: dict[str, Any] = {"monitor": {"maxrss_mb": maxrss_mb()}}
        Rejects.merge(rejected, self.rejects.as_array())
        perf: dict[str, Any] = {}
        for who, m in sorted(self.stats.items()):
            Rejects.merge(rejected, m.arrays["rejected"])
            processes[who if who == "plant" else f"agent {who}"] = {k: v for k, v in m.meta.items() if k != "cmd"}
            for row in m.arrays["links"]:
                j, sent, delivered, dropped, late, rej = (int(v) for v in row)
                links[f"{j}->{who}"] = {"sent": sent, "delivered": delivered, "dropped": dropped, "late": late,
                                        "rejected": rej}
            if who == "plant":
                perf = {"elapsed_s": m.meta.get("elapsed"), "rounds": m.meta.get("rounds"),
                        "deadline_misses": m.meta.get("missed")}
        if perf.get("elapsed_s"):
            perf["rounds_per_s"] = perf["rounds"] / perf["elapsed_s"]
            perf["agent_rounds_per_s"] = perf["rounds_per_s"] * exp.N
        # order links like the simulator: by receiver, then sender
        order = {f"{j}->{aid}": (exp.agent_ids.index(aid), jj) for aid in exp.agent_ids
                 for jj, j in enumerate([exp.agent_ids[x] for x in exp.in_neighbours(exp.agent_ids.index(aid))])}
        links = dict(sorted(links.items(), key=lambda kv: order.get(kv[0], (1 << 30, 0))))
        results = evaluate(exp, mon, regular)
        summary = summarise(exp, mon, regular, links, rejected)
        summary["expectations"] = [r.as_dict() for r in results]
        summary["performance"] = perf
        summary["driver"] = "run"
        summary["mode"] = self.cfg.mode
        summary["membership"] = self.membership
        summary["processes"] = processes
        if self.out_dir is not None:
            from agents.rundir import write_json, write_metrics

            self.out_dir.mkdir(parents=True, exist_ok=True)
            write_metrics(self.out_dir, exp, mon, regular)
            write_json(self.out_dir / "summary.json", summary)
            if self.traj is not None:
                np.save(self.out_dir / "estimates.npy", self.traj[: mon.last_round + 1])
                np.save(self.out_dir / "truth.npy", self.truth[: mon.last_round + 1])
        return MonitorResult(summary, self.out_dir, self.traj, self.truth)


# ------------------------------------------------------------------------ entry points


async def run_plant(exp: Experiment, bus: Bus, keys: Keys, cfg: RunConfig) -> dict[str, Any]:
    """The plant process (see the module docstring); returns elapsed time and rounds."""
    return await PlantProcess(exp, bus, keys, cfg).run()


async def run_agent(exp: Experiment, agent_id: int, bus: Bus, keys: Keys, cfg: RunConfig,
                    *, node_hook: Callable[[Any], None] | None = None, node: Any = None) -> dict[str, Any]:
    """Agent ``agent_id`` (1-based id) until the plant stops the team. ``node``: its
    :class:`~agents.node.AgentNode` if already built (else built here, as the simulator does)."""
    return await AgentProcess(exp, agent_id, bus, keys, cfg, node_hook=node_hook, node=node).run()


async def run_monitor(exp: Experiment, bus: Bus, keys: Keys, cfg: RunConfig, *, out_dir: Path | None = None,
                      progress: Callable[[str, Any], None] | None = None, dashboard: Any = None) -> MonitorResult:
    """The monitor until the plant stops the team; writes metrics and summary to ``out_dir``;
    streams to ``dashboard`` (an :class:`agents.dashboard.Dashboard`) when given."""
    return await MonitorProcess(exp, bus, keys, cfg, out_dir=out_dir, progress=progress, dashboard=dashboard).run()


async def run_team_in_memory(exp: Experiment, cfg: RunConfig, *, run_id: str = "mem", out_dir: Path | None = None,
                             node_hook: Callable[[Any], None] | None = None) -> MonitorResult:
    """Every role as a task of this event loop over an :class:`~transport.zenoh_bus.InMemoryHub`
    (for tests: the same protocol without processes)."""
    from transport.zenoh_bus import InMemoryHub

    hub = InMemoryHub()
    keys = Keys(run_id)
    buses = [hub.bus() for _ in range(exp.N + 2)]
    try:
        mon = asyncio.ensure_future(run_monitor(exp, buses[0], keys, cfg, out_dir=out_dir))
        agents = [asyncio.ensure_future(run_agent(exp, aid, buses[2 + i], keys, cfg, node_hook=node_hook))
                  for i, aid in enumerate(exp.agent_ids)]
        plant = asyncio.ensure_future(run_plant(exp, buses[1], keys, cfg))
        await asyncio.gather(plant, *agents)
        return await mon
    finally:
        for b in buses:
            b.close()
