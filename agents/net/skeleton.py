"""The bare Zenoh lockstep skeleton: ``rse run``'s processes and messages, no estimation.

The yardstick of ``rse bench run`` (part of the installed package, so the command works
outside a source checkout; the benchmark suite uses it too): the same processes (plant, monitor, one per agent,
spawned, one Zenoh peer session each on loopback, the same asyncio bridge on the same
event loop, :mod:`transport.event_loop`), the same
keys, the same message pattern per round and the same payload sizes as the runtime's
encoded messages, but payloads are opaque bytes (a round stamp in the first 8 bytes,
padding after), nothing is decoded and nothing is estimated::

    plant   -> truth (n floats), meas to each agent        (after all agents' done k-1)
    agent i -> est (broadcast), done                       (after meas k and every
                                                            in-neighbour's est k-1)
    monitor <- truth, done

A Byzantine agent of the scenario sends addressed messages (``est/{i}/{j}``, one per
out-neighbour) as the runtime's Byzantine middleware does, and an omniscient one (the
cancellation attack) also hears what the runtime's adversary hears (the estimates and
done reports of the agents its view needs, the addressed messages to its out-neighbours
from the senders its view reads) and holds its round-``k`` messages until those agents'
round-``k`` estimates arrived.

The *minimal* skeleton (``run_skeleton(..., minimal=True)``) is the least a lockstep
round can send: a clock ticks once per round, each agent publishes one estimate and one
done once it holds its in-neighbours' previous estimates, no measurement, no monitor.

Usage: ``python -m agents.net.skeleton [N] [ROUNDS]`` (a ring of N agents, n = 6),
or :func:`run_skeleton` with :func:`sizes_for` of a built experiment.
"""

from __future__ import annotations

import asyncio
import multiprocessing
import os
import struct
import sys
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from multiprocessing.connection import Connection

    from scenarios.build import Experiment
    from transport.keys import Keys
    from transport.zenoh_bus import Bus
    from transport.zenoh_session import SessionOptions

_STAMP = struct.Struct("<q")


@dataclass(frozen=True)
class Sizes:
    """Team shape and payload sizes (bytes) of one scenario's messages."""

    agents: tuple[int, ...]
    in_ids: tuple[tuple[int, ...], ...]
    meas: tuple[int, ...]
    truth: int
    est: int
    done: tuple[int, ...]
    #: per agent: its out-neighbours when it sends addressed messages (a Byzantine agent), else ()
    addressed: tuple[tuple[int, ...], ...] = ()
    #: per agent: the agents whose round-k estimates an omniscient adversary waits for, else ()
    needed: tuple[tuple[int, ...], ...] = ()
    #: per agent: the (sender, receiver) addressed keys an omniscient adversary reads, else ()
    reads: tuple[tuple[tuple[int, int], ...], ...] = ()


def sizes_for(exp: Experiment) -> Sizes:
    """The runtime's encoded message sizes for experiment ``exp``."""
    import numpy as np

    from transport.codec import PLANT_ID, Message, encode

    ids = list(exp.agent_ids)
    ins = [tuple(ids[j] for j in exp.in_neighbours(i)) for i in range(exp.N)]
    outs = [[ids[j] for j in exp.out_neighbours(i)] for i in range(exp.N)]
    x = np.ones(exp.n)
    meas = tuple(len(encode(Message(kind="meas", sender=PLANT_ID, stamp=123456, meta={"member": True, "nomeas": False},
                                    arrays={"y": np.ones(len(exp.agent_rows[i])), "wait": np.ones(len(ins[i]))})))
                 for i in range(exp.N))
    truth = len(encode(Message(kind="truth", sender=PLANT_ID, stamp=123456, arrays={"x": x})))
    est = len(encode(Message(kind="est", sender=ids[0], stamp=123456, arrays={"x": x})))
    # an honest agent's lockstep report is its broadcast estimate alone (kind "est");
    # a Byzantine agent's names its receivers and their stamps
    done = tuple(len(encode(Message(kind="done", sender=ids[i], stamp=123456,
                                    arrays={"x": x, "to": np.ones(len(outs[i])), "stamps": np.ones(len(outs[i]))})))
                 if i in exp.byzantine_specs else len(encode(Message(kind="est", sender=ids[i], stamp=123456, arrays={"x": x})))
                 for i in range(exp.N))
    from agents.middleware import byzantine_strategy
    from agents.net.view import reads_view, view_topology

    addressed = tuple(tuple(outs[i]) if i in exp.byzantine_specs else () for i in range(exp.N))
    views = [view_topology(exp, ids[i], {}) if reads_view(byzantine_strategy(exp, i)) else None for i in range(exp.N)]
    needed = tuple(tuple(v.needed) if v is not None else () for v in views)
    reads = tuple(tuple((s, j) for j in v.out for s in v.before.get(j, ())) if v is not None else () for v in views)
    return Sizes(tuple(ids), tuple(ins), meas, truth, est, done, addressed, needed, reads)


def ring_sizes(N: int, n: int = 6) -> Sizes:
    ids = tuple(range(1, N + 1))
    ins = tuple((ids[(i - 1) % N], ids[(i + 1) % N]) for i in range(N))
    return Sizes(ids, ins, tuple([90] * N), 100, 100, tuple([110] * N))


def _payload(size: int, k: int) -> bytes:
    return _STAMP.pack(k) + bytes(max(0, size - 8))


async def _done_reports(q: asyncio.Queue, k: int, N: int) -> None:
    """The plant: wait for the N done reports of round ``k``."""
    got = 0
    while got < N:
        key, p = await q.get()
        if type(p) is bytes and "/done/" in key and _STAMP.unpack_from(p)[0] == k:
            got += 1


async def _report(conn: Connection | None, rounds: int, elapsed: float) -> None:
    """The plant reports its round rate to the launcher, then lets its last messages go."""
    if conn is not None:
        conn.send({"rounds": rounds, "elapsed": elapsed, "rounds_per_s": rounds / elapsed})
    await asyncio.sleep(0.05)


async def _joined(q: asyncio.Queue, bus: Bus, keys: Keys, me: int, need: set[str]) -> AsyncIterator[tuple[str, bytes]]:
    """An agent's data items, after its join: it notes the liveliness tokens it sees, sends
    ``ready`` once every process of ``need`` is seen, and yields every other item."""
    seen: set[str] = set()
    sent_ready = False
    while True:
        if not sent_ready and need <= seen:
            bus.publish(keys.ctl("ready", me), b"r")
            sent_ready = True
        try:
            key, p = await asyncio.wait_for(q.get(), 0.1) if not sent_ready else await q.get()
        except TimeoutError:
            continue
        if type(p) is bool:
            parts = key.split("/")
            seen.add(parts[-2] if parts[-2] != "agent" else parts[-1])
            continue
        yield key, p


async def _minimal(role: str, idx: int, sizes: Sizes, rounds: int, keys: Keys, bus: Bus, q: asyncio.Queue,
                   conn: Connection | None) -> None:
    """The minimal lockstep skeleton: a clock ticks once per round (8 bytes); each agent,
    once it holds its in-neighbours' round k-1 estimates, publishes its estimate (the
    scenario's estimate size) and an 8-byte done; the clock ticks again when all are done."""
    ids = sizes.agents
    N = len(ids)
    tick = keys.plant_truth()
    if role == "plant":
        bus.subscribe(keys.ctl_pattern("done"), q)
        bus.subscribe(keys.ctl_pattern("ready"), q)
        bus.announce(keys.alive("plant", 0))
        ready: set[str] = set()
        while len(ready) < N:
            key, p = await q.get()
            if type(p) is bytes and "/ready/" in key:
                ready.add(key)
        t0 = time.perf_counter()
        for k in range(rounds):
            bus.publish(tick, _STAMP.pack(k))
            await _done_reports(q, k, N)
        elapsed = time.perf_counter() - t0
        bus.publish(tick, _STAMP.pack(-1))
        await _report(conn, rounds, elapsed)
        return
    me, ins = ids[idx], sizes.in_ids[idx]
    bus.subscribe(tick, q)
    for j in ins:
        bus.subscribe(keys.est(j), q)
    bus.watch(keys.alive_pattern(), q)
    bus.announce(keys.alive("agent", me))
    need = {"plant"} | {str(j) for j in ins}
    est_key, done_key = keys.est(me), keys.ctl("done", me)
    arrived: dict[int, int] = {}
    tick_k: int | None = None
    async for key, p in _joined(q, bus, keys, me, need):
        k = _STAMP.unpack_from(p)[0]
        if key == tick:
            if k < 0:
                return
            tick_k = k
        else:
            arrived[k] = arrived.get(k, 0) + 1
        if tick_k is not None and (tick_k == 0 or arrived.get(tick_k - 1, 0) >= len(ins)):
            arrived.pop(tick_k - 1, None)
            bus.publish(est_key, _payload(sizes.est, tick_k))
            bus.publish(done_key, _STAMP.pack(tick_k))
            tick_k = None


async def _main(role: str, idx: int, sizes: Sizes, rounds: int, run: str, opts: SessionOptions, conn: Connection | None,
                minimal: bool = False) -> None:
    from transport.keys import Keys
    from transport.zenoh_bus import ZenohBus
    from transport.zenoh_session import close_session, open_session

    keys = Keys(run)
    session = open_session(opts)
    bus = ZenohBus(session, asyncio.get_running_loop())
    q: asyncio.Queue = asyncio.Queue(maxsize=1 << 16)
    try:
        if minimal:
            await _minimal(role, idx, sizes, rounds, keys, bus, q, conn)
        elif role == "plant":
            await _plant(sizes, rounds, keys, bus, q, conn)
        elif role == "monitor":
            await _monitor(keys, bus, q)
        else:
            await _agent(idx, sizes, keys, bus, q)
    finally:
        bus.close()
        close_session(session)


async def _plant(sizes: Sizes, rounds: int, keys: Keys, bus: Bus, q: asyncio.Queue, conn: Connection | None) -> None:
    """The full-pattern plant: waits for every agent's ready and the monitor, then ``rounds``
    rounds of truth and measurements, each ended by every agent's done; sends the rate."""
    ids = sizes.agents
    N = len(ids)
    bus.subscribe(keys.ctl_pattern("done"), q)
    bus.subscribe(keys.ctl_pattern("ready"), q)
    bus.watch(keys.alive_pattern(), q)
    bus.announce(keys.alive("plant", 0))
    ready: set[str] = set()
    monitor = False
    while len(ready) < N or not monitor:
        key, p = await q.get()
        if type(p) is bool:
            monitor = monitor or (p and "/alive/monitor/" in key)
        elif "/ready/" in key:
            ready.add(key)
    loc = [keys.plant_loc(a) for a in ids]
    truth = keys.plant_truth()
    t0 = time.perf_counter()
    for k in range(rounds):
        bus.publish(truth, _payload(sizes.truth, k))
        for i in range(N):
            bus.publish(loc[i], _payload(sizes.meas[i], k))
        await _done_reports(q, k, N)
    elapsed = time.perf_counter() - t0
    for i in range(N):
        bus.publish(loc[i], _STAMP.pack(-1))
    bus.publish(truth, _STAMP.pack(-1))
    await _report(conn, rounds, elapsed)


async def _monitor(keys: Keys, bus: Bus, q: asyncio.Queue) -> None:
    """The full-pattern monitor: hears the truth and the done reports until the plant's stop."""
    bus.subscribe(keys.plant_truth(), q)
    bus.subscribe(keys.ctl_pattern("done"), q)
    bus.announce(keys.alive("monitor", 0))
    count = 0
    while True:
        key, p = await q.get()
        count += 1
        if key.endswith("/truth") and _STAMP.unpack_from(p)[0] < 0:
            break


async def _agent(idx: int, sizes: Sizes, keys: Keys, bus: Bus, q: asyncio.Queue) -> None:
    """A full-pattern agent: its round ``k`` once the measurement of ``k`` and its
    in-neighbours' (and an omniscient adversary's needed) messages of ``k - 1`` are in."""
    ids = sizes.agents
    me = ids[idx]
    ins = sizes.in_ids[idx]
    addressed = sizes.addressed[idx] if sizes.addressed else ()
    needed = set(sizes.needed[idx]) if sizes.needed else set()
    bus.subscribe(keys.plant_loc(me), q)
    for j in sorted(set(ins) | needed):
        bus.subscribe(keys.est(j), q)
    bus.subscribe(keys.est_pattern(to=me), q)
    if needed:  # the omniscient adversary's subscriptions (its receivers' messages by sender, as the runtime's)
        for s, j in sizes.reads[idx]:
            bus.subscribe(keys.est(s, j), q)
        for j in sorted(needed):
            bus.subscribe(keys.ctl("done", j), q)
    bus.watch(keys.alive_pattern(), q)
    bus.announce(keys.alive("agent", me))
    need = {"plant", "monitor"} | {str(j) for j in ins}
    est_key, done_key = keys.est(me), keys.ctl("done", me)
    arrived: dict[int, int] = {}
    heard: dict[int, set[int]] = {}  # round -> needed agents whose estimate arrived
    addr_keys = [keys.est(me, j) for j in addressed]
    meas_k: int | None = None
    async for key, p in _joined(q, bus, keys, me, need):
        k = _STAMP.unpack_from(p)[0]
        if "/plant/loc/" in key:
            if k < 0:
                break
            meas_k = k
        elif "/ctl/done/" not in key:
            parts = key.split("/")
            sender = int(parts[-2] if parts[-1] == "est" else parts[-3])
            to_me = parts[-1] == "est" or int(parts[-1]) == me
            if to_me and sender in ins:
                arrived[k] = arrived.get(k, 0) + 1
            if sender in needed:
                heard.setdefault(k, set()).add(sender)
        if (meas_k is not None and (meas_k == 0 or arrived.get(meas_k - 1, 0) >= len(ins))
                and needed <= heard.get(meas_k, set())):
            arrived.pop(meas_k - 1, None)
            heard.pop(meas_k, None)
            if addressed:
                for ak in addr_keys:
                    bus.publish(ak, _payload(sizes.est, meas_k))
            else:
                bus.publish(est_key, _payload(sizes.est, meas_k))
            bus.publish(done_key, _payload(sizes.done[idx], meas_k))
            meas_k = None


def _child(role: str, idx: int, sizes: Sizes, rounds: int, run: str, opts: SessionOptions, conn: Connection | None, minimal: bool = False) -> None:
    from transport.event_loop import run as run_loop

    run_loop(_main(role, idx, sizes, rounds, run, opts, conn, minimal))  # the runtime's event loop
    os._exit(0)


def run_skeleton(sizes: Sizes, rounds: int = 2000, *, timeout: float = 120.0, minimal: bool = False) -> dict[str, float]:
    """Run the skeleton; returns ``{"rounds", "elapsed", "rounds_per_s"}`` (lockstep, timed by the plant).

    minimal : the minimal skeleton (:func:`_minimal`: a clock and the agents, one estimate
        and one done per agent and round, no monitor) instead of the runtime's full pattern
    """
    import uuid

    from transport.zenoh_session import SessionOptions, free_tcp_port, tcp_endpoint

    N = len(sizes.agents)
    names = ["plant", "monitor"] + [f"agent{i}" for i in range(N)]
    if minimal:
        names.remove("monitor")
    ports: list[int] = []
    while len(ports) < len(names):
        port = free_tcp_port()
        if port not in ports:
            ports.append(port)
    eps = [tcp_endpoint(port) for port in ports]
    ctx = multiprocessing.get_context("spawn")
    recv, send = ctx.Pipe(duplex=False)
    run = f"skeleton-{uuid.uuid4().hex[:8]}"
    procs = []
    try:
        for c, name in enumerate(names):
            opts = SessionOptions(mode="peer", listen=(eps[c],), connect=tuple(e for i, e in enumerate(eps) if i != c))
            role = name if not name.startswith("agent") else "agent"
            idx = c - (1 if minimal else 2)
            p = ctx.Process(target=_child, args=(role, idx, sizes, rounds, run, opts, send if c == 0 else None, minimal),
                            daemon=True)
            p.start()
            procs.append(p)
        send.close()
        if not recv.poll(timeout):
            raise TimeoutError(f"the skeleton did not finish within {timeout:g} s")
        return recv.recv()
    finally:
        for p in procs:
            p.join(3.0)
            if p.exitcode is None:
                p.kill()
                p.join(1.0)
        recv.close()


if __name__ == "__main__":
    N = int(sys.argv[1]) if len(sys.argv) > 1 else 5
    R = int(sys.argv[2]) if len(sys.argv) > 2 else 2000
    print(run_skeleton(ring_sizes(N), R))
