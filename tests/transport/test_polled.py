"""Polled subscriptions (transport.zenoh_bus.Polled): samples wait without a callback until
drained, in order; a full ring is counted; a reconnect keeps what came before it."""

from __future__ import annotations

import asyncio
import time

from transport.keys import Keys
from transport.zenoh_bus import InMemoryHub, ZenohBus
from transport.zenoh_session import SessionOptions, close_session, free_tcp_port, open_session

DEADLINE_S = 10.0


async def _drain_until(polled, n: int) -> list[tuple[str, bytes]]:
    """Drain until ``n`` items came (or the deadline: what came)."""
    got: list[tuple[str, bytes]] = []
    end = time.monotonic() + DEADLINE_S
    while len(got) < n and time.monotonic() < end:
        got += polled.drain()
        await asyncio.sleep(0.01)
    return got


def test_a_polled_zenoh_subscription_holds_samples_in_order_counts_a_full_ring_and_survives_a_reconnect():
    keys = Keys("t-polled")
    port_a, port_b = free_tcp_port(), free_tcp_port()
    opts_b = SessionOptions.peer(listen_port=port_b, connect_ports=[port_a])

    async def main() -> None:
        loop = asyncio.get_running_loop()
        a = open_session(SessionOptions.peer(listen_port=port_a))
        bus = ZenohBus(open_session(opts_b), loop, opener=lambda: open_session(opts_b))
        try:
            polled = bus.subscribe_polled(keys.ctl_pattern("done"), capacity=4)
            assert polled.drain() == []
            pub3, pub4 = a.declare_publisher(keys.ctl("done", 3)), a.declare_publisher(keys.ctl("done", 4))
            # the subscription reaches the other peer asynchronously: put until one arrives
            end = time.monotonic() + DEADLINE_S
            while not polled.drain() and time.monotonic() < end:
                pub3.put(b"probe")
                await asyncio.sleep(0.05)
            await asyncio.sleep(0.1)
            polled.drain()
            received = bus.stats.received
            pub3.put(b"1")
            pub4.put(b"2")
            pub3.put(b"3")
            got = await _drain_until(polled, 3)
            assert got == [(keys.ctl("done", 3), b"1"), (keys.ctl("done", 4), b"2"), (keys.ctl("done", 3), b"3")]
            assert bus.stats.received == received + 3 and bus.stats.dropped_full == 0
            # ten before a drain: the ring keeps the newest four and the loss is counted
            for i in range(10):
                pub3.put(bytes([i]))
            await asyncio.sleep(0.5)
            assert [p for _, p in polled.drain()] == [bytes([i]) for i in range(6, 10)]
            assert bus.stats.dropped_full == 1
            # what came before a reconnect is still drained after it; the new session delivers
            pub3.put(b"before")
            await asyncio.sleep(0.3)
            first = bus.session
            assert await bus.reconnect()
            assert first.is_closed()
            assert polled.drain() == [(keys.ctl("done", 3), b"before")]
            end = time.monotonic() + DEADLINE_S
            after: list = []
            while not after and time.monotonic() < end:
                pub3.put(b"after")
                await asyncio.sleep(0.05)
                after = polled.drain()
            assert after and {p for _, p in after} == {b"after"}
        finally:
            bus.close()
            close_session(bus.session)
            close_session(a)
        assert polled.drain() == []  # closed: nothing, no error

    asyncio.run(asyncio.wait_for(main(), 3 * DEADLINE_S))


def test_a_polled_in_memory_subscription_and_a_role_draining_it_first():
    from agents.net.protocol import Role

    hub = InMemoryHub()
    keys = Keys("t-polled-mem")

    class Recorder(Role):
        def __init__(self, bus):  # the parts of a Role that handle_batch uses
            self.bus, self.queue, self._polled, self.batches = bus, asyncio.Queue(maxsize=8), [], 0
            self._waiting, self.seen, self.changed = None, [], asyncio.Event()

        def handle_data(self, key, payload):
            self.seen.append(payload)

    async def main() -> None:
        a, b = hub.bus(), hub.bus()
        polled = b.subscribe_polled(keys.ctl_pattern("done"), capacity=2)
        role = Recorder(b)
        role.subscribe(keys.plant_loc(1), polled=True)
        for i in range(3):
            a.publish(keys.ctl("done", 2), bytes([i]))
        a.publish(keys.plant_loc(1), b"m")
        await asyncio.sleep(0)
        assert [p for _, p in polled.drain()] == [b"\x00", b"\x01"]
        assert b.stats.dropped_full == 1 and b.stats.received == 3
        # a batch handles what its polled subscriptions hold before its own items
        role.handle_batch([(keys.ctl("done", 9), b"q")])
        assert role.seen == [b"m", b"q"] and role.batches == 1
        role.handle_batch([])  # nothing came: not a batch
        assert role.batches == 1

    asyncio.run(main())
