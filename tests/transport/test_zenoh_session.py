"""Zenoh sessions and the thread -> asyncio bridge, with real sessions on loopback.

Every test that opens a session closes it in ``finally`` and bounds its waits; a watchdog
fails a test that still hangs after ``WATCHDOG_S`` (every thread's stack printed), and the
run goes on with the next test.
"""

from __future__ import annotations

import asyncio
import faulthandler
import json
import logging
import signal
import subprocess
import sys
import textwrap
import threading
import time
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import zenoh

from estimation.errors import TransportError
from transport.bridge import BridgeStats, liveliness_to_item, make_bridge, sample_to_item
from transport.codec import Message, Schema, decode, encode
from transport.keys import Keys
from transport.zenoh_session import (
    SessionOptions,
    close_session,
    free_tcp_port,
    make_config,
    normalize_endpoint,
    open_session,
    tcp_endpoint,
)

ROOT = Path(__file__).resolve().parents[2]
WATCHDOG_S = 120  # per test: only a hang reaches it (the slowest test takes a few seconds)
DEADLINE_S = 10.0

SCHEMA = Schema({"est": {"x": (3,)}})


@pytest.fixture(autouse=True)
def watchdog(request):
    """A hang fails this test alone: after ``WATCHDOG_S`` a SIGALRM prints every thread's stack
    and raises in the test. A hang inside native code that never returns to the interpreter
    cannot be interrupted that way: ``faulthandler`` ends the process with the stacks at
    ``3 * WATCHDOG_S`` (better than a run that never ends)."""

    def expired(signum, frame):
        faulthandler.dump_traceback(all_threads=True)
        pytest.fail(f"{request.node.name} still running after {WATCHDOG_S} s (a hang): stacks above", pytrace=True)

    previous = signal.signal(signal.SIGALRM, expired)
    signal.setitimer(signal.ITIMER_REAL, WATCHDOG_S)
    faulthandler.dump_traceback_later(3 * WATCHDOG_S, exit=True)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
        faulthandler.cancel_dump_traceback_later()


# --------------------------------------------------------------------- configuration


def test_make_config_sets_the_documented_keys():
    conf = make_config(
        mode="peer",
        listen=["tcp/127.0.0.1:7001"],
        connect=["tcp/127.0.0.1:7002", "127.0.0.1:7003"],
    )
    assert json.loads(conf.get_json("mode")) == "peer"
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7001"]
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7002", "tcp/127.0.0.1:7003"]
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("scouting/delay")) is None  # Zenoh's default
    assert json.loads(make_config(scout_delay_ms=0).get_json("scouting/delay")) == 0


def test_session_options():
    peer = SessionOptions.peer(listen_port=7100, connect_ports=[7101, 7102])
    assert peer.mode == "peer" and peer.listen == ("tcp/127.0.0.1:7100",)
    assert peer.connect == ("tcp/127.0.0.1:7101", "tcp/127.0.0.1:7102")
    assert SessionOptions().effective_listen() == ("tcp/127.0.0.1:0",)
    client = SessionOptions.client(["10.0.0.5:7447"])
    assert client.mode == "client" and client.connect == ("tcp/10.0.0.5:7447",) and client.effective_listen() == ()
    with pytest.raises(ValueError, match="client mode needs"):
        SessionOptions(mode="client")
    with pytest.raises(ValueError, match="mode"):
        SessionOptions(mode="server")
    with pytest.raises(ValueError, match="sequence"):
        SessionOptions(connect="tcp/127.0.0.1:1")  # type: ignore[arg-type]


@pytest.mark.parametrize("bad", ["", "tcp/", "tcp/host", "tcp/host:port", 'tcp/a:1", mode: "router', "ftp/x:1", "tcp/a b:1"])
def test_bad_endpoints(bad):
    with pytest.raises(ValueError):
        normalize_endpoint(bad)


def test_endpoint_helpers():
    assert tcp_endpoint(7447) == "tcp/127.0.0.1:7447"
    assert tcp_endpoint(7447, "::1") == "tcp/[::1]:7447"
    assert normalize_endpoint("localhost:7447") == "tcp/localhost:7447"
    assert normalize_endpoint("tcp/[::1]:7447") == "tcp/[::1]:7447"
    p = free_tcp_port()
    assert 0 < p < 65536


# -------------------------------------------------------------------- sessions over TCP


async def _next(queue: asyncio.Queue, publish, timeout: float = DEADLINE_S):
    """Publish until an item arrives (routes take a moment to be set up)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        publish()
        try:
            return await asyncio.wait_for(queue.get(), 0.1)
        except TimeoutError:
            continue
    raise AssertionError(f"nothing received within {timeout} s")


def test_two_peers_exchange_a_message_through_the_bridge():
    keys = Keys("t-peers")
    port_a, port_b = free_tcp_port(), free_tcp_port()
    msg = Message(kind="est", sender=2, stamp=7, arrays={"x": np.array([1.0, 2.0, 3.0])})

    async def main() -> None:
        loop = asyncio.get_running_loop()
        queue: asyncio.Queue = asyncio.Queue(maxsize=16)
        a = b = None
        try:
            a = open_session(SessionOptions.peer(listen_port=port_a))
            b = open_session(SessionOptions.peer(listen_port=port_b, connect_ports=[port_a]))
            sub = a.declare_subscriber(keys.est_pattern(), make_bridge(loop, queue, name="est"))
            pub = b.declare_publisher(keys.est(2))
            payload = encode(msg)
            key, data = await _next(queue, lambda: pub.put(payload))
            assert isinstance(key, str) and isinstance(data, bytes)
            parsed = keys.parse(key)
            assert decode(data, schema=SCHEMA, expected_sender=parsed.sender) == msg
            assert sub.handler is None  # a callback subscriber
            assert b.zid() in a.info.peers_zid()
        finally:
            close_session(b)
            close_session(a)
        assert a.is_closed() and b.is_closed()

    asyncio.run(asyncio.wait_for(main(), 3 * DEADLINE_S))


@pytest.mark.parametrize("scout_delay_ms", [None, 0])
def test_peer_started_before_the_peer_it_connects_to(scout_delay_ms):
    """A peer's connect endpoints are retried in the background (launch order free), also
    when its session opens at once (``scout_delay_ms=0``, as in ``rse run``)."""
    keys = Keys("t-order")
    port_a = free_tcp_port()

    async def main() -> None:
        loop = asyncio.get_running_loop()
        queue: asyncio.Queue = asyncio.Queue(maxsize=16)
        a = b = None
        try:
            b = open_session(replace(SessionOptions.peer(connect_ports=[port_a]), retry_ms=50,
                                     scout_delay_ms=scout_delay_ms))
            b.declare_subscriber(keys.ctl_pattern(), make_bridge(loop, queue))
            a = open_session(SessionOptions.peer(listen_port=port_a))
            key, data = await _next(queue, lambda: a.put(keys.ctl("stop"), b"bye"))
            assert (key, data) == (keys.ctl("stop"), b"bye")
        finally:
            close_session(b)
            close_session(a)

    asyncio.run(asyncio.wait_for(main(), 3 * DEADLINE_S))


def test_clients_through_a_router():
    keys = Keys("t-router")
    port = free_tcp_port()

    async def main() -> None:
        loop = asyncio.get_running_loop()
        queue: asyncio.Queue = asyncio.Queue(maxsize=16)
        router = c1 = c2 = None
        try:
            router = open_session(SessionOptions(mode="router", listen=(tcp_endpoint(port),)))
            c1 = open_session(SessionOptions.client([tcp_endpoint(port)]))
            c2 = open_session(SessionOptions.client([f"127.0.0.1:{port}"]))
            c1.declare_subscriber(keys.plant_truth(), make_bridge(loop, queue))
            key, data = await _next(queue, lambda: c2.put(keys.plant_truth(), b"x"))
            assert (key, data) == (keys.plant_truth(), b"x")
        finally:
            for s in (c2, c1, router):
                close_session(s)

    asyncio.run(asyncio.wait_for(main(), 3 * DEADLINE_S))


def test_liveliness_joins_and_leaves_through_the_bridge():
    keys = Keys("t-alive")
    port = free_tcp_port()

    async def main() -> None:
        loop = asyncio.get_running_loop()
        queue: asyncio.Queue = asyncio.Queue(maxsize=16)
        watcher = agent = None
        try:
            watcher = open_session(SessionOptions.peer(listen_port=port))
            watcher.liveliness().declare_subscriber(
                keys.alive_pattern(), make_bridge(loop, queue, convert=liveliness_to_item), history=True
            )
            agent = open_session(SessionOptions.peer(connect_ports=[port]))
            token = agent.liveliness().declare_token(keys.alive("agent", 3))
            assert await asyncio.wait_for(queue.get(), DEADLINE_S) == (keys.alive("agent", 3), True)
            close_session(agent)  # a closed (or crashed) session withdraws its token
            assert await asyncio.wait_for(queue.get(), DEADLINE_S) == (keys.alive("agent", 3), False)
            del token
        finally:
            close_session(agent)
            close_session(watcher)

    asyncio.run(asyncio.wait_for(main(), 3 * DEADLINE_S))


def test_a_bus_reconnects_with_its_subscriptions_and_token():
    """ZenohBus.reconnect: a new session on the same endpoints, the same subscriptions,
    watches and token; the others see it leave and join again, and it hears them."""
    from transport.zenoh_bus import ZenohBus

    keys = Keys("t-reconnect")
    port_a, port_b = free_tcp_port(), free_tcp_port()
    opts_b = SessionOptions.peer(listen_port=port_b, connect_ports=[port_a])

    async def main() -> None:
        loop = asyncio.get_running_loop()
        seen: asyncio.Queue = asyncio.Queue(maxsize=64)
        heard: asyncio.Queue = asyncio.Queue(maxsize=64)
        a = open_session(SessionOptions.peer(listen_port=port_a))
        bus_b = ZenohBus(open_session(opts_b), loop, opener=lambda: open_session(opts_b))
        first = bus_b.session
        try:
            a.liveliness().declare_subscriber(keys.alive_pattern(), make_bridge(loop, seen, convert=liveliness_to_item),
                                              history=True)
            bus_b.subscribe(keys.plant_loc(3), heard)
            bus_b.announce(keys.alive("agent", 3))
            assert await asyncio.wait_for(seen.get(), DEADLINE_S) == (keys.alive("agent", 3), True)
            assert (await _next(heard, lambda: a.put(keys.plant_loc(3), b"1")))[1] == b"1"
            assert await bus_b.reconnect()
            assert first.is_closed() and bus_b.session is not first
            assert await asyncio.wait_for(seen.get(), DEADLINE_S) == (keys.alive("agent", 3), False)
            assert await asyncio.wait_for(seen.get(), DEADLINE_S) == (keys.alive("agent", 3), True)
            while not heard.empty():
                heard.get_nowait()
            assert (await _next(heard, lambda: a.put(keys.plant_loc(3), b"2")))[1] == b"2"
        finally:
            bus_b.close()
            close_session(bus_b.session)
            close_session(a)

    asyncio.run(asyncio.wait_for(main(), 3 * DEADLINE_S))


def test_a_reconnect_cancelled_while_opening_closes_the_new_session():
    """Ctrl-C or SIGTERM during ZenohBus.reconnect: the session the worker thread was
    opening is closed when it opens, not left to the interpreter's exit handler."""
    import threading

    from transport.zenoh_bus import ZenohBus

    port = free_tcp_port()
    opts = SessionOptions.peer(listen_port=port)
    opened: list = []
    done = threading.Event()

    def slow_open():
        time.sleep(0.5)
        s = open_session(opts)
        opened.append(s)
        done.set()
        return s

    async def main() -> None:
        bus = ZenohBus(open_session(opts), asyncio.get_running_loop(), opener=slow_open)
        first = bus.session
        task = asyncio.ensure_future(bus.reconnect())
        await asyncio.sleep(0.1)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        assert first.is_closed() and bus.session is first
        assert await asyncio.to_thread(done.wait, DEADLINE_S)
        for _ in range(100):  # the thread closes it right after it opened
            if opened[0].is_closed():
                break
            await asyncio.sleep(0.02)
        assert opened[0].is_closed()

    asyncio.run(main())


def test_open_failures_are_transport_errors():
    port = free_tcp_port()
    holder = open_session(SessionOptions.peer(listen_port=port))
    try:
        with pytest.raises(TransportError, match="cannot open a Zenoh session"):
            open_session(SessionOptions.peer(listen_port=port))  # address in use
    finally:
        close_session(holder)
    t0 = time.monotonic()
    with pytest.raises(TransportError, match=str(port)):
        open_session(SessionOptions.client([tcp_endpoint(port)]))  # no router there
    assert time.monotonic() - t0 < DEADLINE_S


def test_session_is_a_context_manager():
    with open_session() as session:
        assert not session.is_closed()
    assert session.is_closed()
    close_session(session)  # idempotent
    close_session(None)


@pytest.mark.multiprocess
def test_a_session_left_open_does_not_hang_the_interpreter_at_exit():
    """The known pitfall: a forgotten session with a callback subscriber used to keep a
    non-daemon Zenoh thread alive forever. The exit hook closes it before the join."""
    code = textwrap.dedent(
        """
        from transport.zenoh_session import open_session
        s = open_session()
        s.declare_subscriber("rse/x/**", lambda sample: None)
        print("opened", flush=True)
        """
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=30
    )
    assert proc.returncode == 0, proc.stderr
    assert "opened" in proc.stdout


# ------------------------------------------------------------ the bridge, without zenoh


def fake_sample(key: str = "rse/r/agent/1/est", payload: bytes = b"p"):
    return SimpleNamespace(key_expr=key, payload=SimpleNamespace(to_bytes=lambda: payload))


def test_bridge_needs_a_bounded_queue():
    loop = asyncio.new_event_loop()
    try:
        with pytest.raises(ValueError, match="bounded"):
            make_bridge(loop, asyncio.Queue())
    finally:
        loop.close()


def test_bridge_drops_and_counts_when_full():
    loop = asyncio.new_event_loop()
    try:
        queue: asyncio.Queue = asyncio.Queue(maxsize=2)
        stats = BridgeStats()
        cb = make_bridge(loop, queue, stats=stats)
        assert cb.stats is stats
        for i in range(5):  # the loop is not running: items pile up in flight
            cb(fake_sample(payload=bytes([i])))
        assert stats.dropped_full == 3
        loop.run_until_complete(asyncio.sleep(0))
        assert queue.qsize() == 2 and stats.received == 2
        assert [queue.get_nowait()[1] for _ in range(2)] == [b"\x00", b"\x01"]
        cb(fake_sample())
        loop.run_until_complete(asyncio.sleep(0))
        assert stats.snapshot() == {"received": 3, "dropped_full": 3, "dropped_closed": 0, "errors": 0}
    finally:
        loop.close()


def test_bridges_into_one_queue_wake_the_loop_once_per_burst():
    loop = asyncio.new_event_loop()
    try:
        calls = []
        schedule = loop.call_soon_threadsafe
        loop.call_soon_threadsafe = lambda *a: (calls.append(a), schedule(*a))[1]  # type: ignore[method-assign]
        queue: asyncio.Queue = asyncio.Queue(maxsize=8)
        s1, s2 = BridgeStats(), BridgeStats()
        cb1, cb2 = make_bridge(loop, queue, stats=s1), make_bridge(loop, queue, stats=s2)
        for cb, p in ((cb1, b"a"), (cb2, b"b"), (cb1, b"c")):  # the loop is not running: one burst
            cb(fake_sample(payload=p))
        assert len(calls) == 1
        loop.run_until_complete(asyncio.sleep(0))
        assert [queue.get_nowait()[1] for _ in range(3)] == [b"a", b"b", b"c"]  # in order of arrival
        assert (s1.received, s2.received) == (2, 1)
        cb2(fake_sample(payload=b"d"))  # after the drain: a new burst, a new wake-up
        assert len(calls) == 2
        loop.run_until_complete(asyncio.sleep(0))
        assert queue.get_nowait()[1] == b"d" and s2.received == 2
    finally:
        loop.close()


def test_bridge_tolerates_a_closed_loop():
    loop = asyncio.new_event_loop()
    queue: asyncio.Queue = asyncio.Queue(maxsize=4)
    cb = make_bridge(loop, queue)
    loop.close()
    cb(fake_sample())  # must not raise into the Zenoh thread
    cb(fake_sample())
    assert cb.stats.dropped_closed == 2 and cb.stats.errors == 0


def test_samples_still_waiting_when_the_loop_closes_are_counted():
    loop = asyncio.new_event_loop()
    queue: asyncio.Queue = asyncio.Queue(maxsize=8)
    cb = make_bridge(loop, queue)
    cb(fake_sample(payload=b"a"))  # a drain is scheduled, and never runs
    loop.close()
    cb(fake_sample(payload=b"b"))  # the loop closed meanwhile: a and b are dropped, and counted
    assert (cb.stats.dropped_closed, cb.stats.received, cb.stats.errors) == (2, 0, 0)
    cb(fake_sample(payload=b"c"))
    assert cb.stats.dropped_closed == 3 and cb.stats.errors == 0


def test_bridge_logs_conversion_errors(caplog):
    loop = asyncio.new_event_loop()
    try:
        cb = make_bridge(loop, asyncio.Queue(maxsize=4), name="est")
        with caplog.at_level(logging.ERROR, logger="transport.bridge"):
            cb(object())  # not a sample
        assert cb.stats.errors == 1
        assert any("cannot convert" in r.getMessage() and r.exc_info for r in caplog.records)
    finally:
        loop.close()


def test_bridge_from_foreign_threads_delivers_everything_in_bounds():
    n_threads, per_thread = 4, 500

    async def main() -> None:
        loop = asyncio.get_running_loop()
        queue: asyncio.Queue = asyncio.Queue(maxsize=n_threads * per_thread)
        cb = make_bridge(loop, queue)

        def produce(t: int) -> None:
            for i in range(per_thread):
                cb(fake_sample(key=f"k/{t}", payload=i.to_bytes(2, "little")))

        threads = [threading.Thread(target=produce, args=(t,)) for t in range(n_threads)]
        for th in threads:
            th.start()
        got = []
        while len(got) < n_threads * per_thread:
            got.append(await asyncio.wait_for(queue.get(), DEADLINE_S))
        for th in threads:
            th.join(DEADLINE_S)
        assert cb.stats.received == n_threads * per_thread and cb.stats.dropped_full == 0
        for t in range(n_threads):  # per-thread order is preserved
            seq = [int.from_bytes(p, "little") for k, p in got if k == f"k/{t}"]
            assert seq == list(range(per_thread))

    asyncio.run(asyncio.wait_for(main(), 3 * DEADLINE_S))


def test_sample_converters():
    assert sample_to_item(fake_sample("a/b", b"xyz")) == ("a/b", b"xyz")
    put = SimpleNamespace(key_expr="rse/r/alive/agent/1", kind=zenoh.SampleKind.PUT)
    delete = SimpleNamespace(key_expr="rse/r/alive/agent/1", kind=zenoh.SampleKind.DELETE)
    assert liveliness_to_item(put) == ("rse/r/alive/agent/1", True)
    assert liveliness_to_item(delete) == ("rse/r/alive/agent/1", False)
