"""The bridge's direct hand-over (:func:`transport.bridge.deliver_to`): a consumer takes
each burst in the call that would have queued it, while nothing is queued before it."""

from __future__ import annotations

import asyncio
import logging
from types import SimpleNamespace

from transport.bridge import deliver_to, make_bridge


def fake_sample(payload: bytes, key: str = "rse/r/agent/1/est"):
    return SimpleNamespace(key_expr=key, payload=SimpleNamespace(to_bytes=lambda: payload))


def test_a_burst_goes_to_the_consumer_in_one_call_and_not_through_the_queue():
    loop = asyncio.new_event_loop()
    try:
        queue: asyncio.Queue = asyncio.Queue(maxsize=8)
        cb1, cb2 = make_bridge(loop, queue), make_bridge(loop, queue)
        calls: list[list[bytes]] = []
        undo = deliver_to(loop, queue, lambda items: calls.append([p for _, p in items]))
        for cb, p in ((cb1, b"a"), (cb2, b"b"), (cb1, b"c")):  # the loop is not running: one burst
            cb(fake_sample(p))
        loop.run_until_complete(asyncio.sleep(0))
        assert calls == [[b"a", b"b", b"c"]] and queue.empty()
        assert (cb1.stats.received, cb2.stats.received) == (2, 1)
        undo()  # back to the queue
        cb2(fake_sample(b"d"))
        loop.run_until_complete(asyncio.sleep(0))
        assert calls == [[b"a", b"b", b"c"]] and queue.get_nowait()[1] == b"d" and cb2.stats.received == 2
    finally:
        loop.close()


def test_items_already_queued_keep_their_place():
    loop = asyncio.new_event_loop()
    try:
        queue: asyncio.Queue = asyncio.Queue(maxsize=8)
        cb = make_bridge(loop, queue)
        cb(fake_sample(b"a"))
        loop.run_until_complete(asyncio.sleep(0))  # a is queued before the consumer comes
        calls: list = []
        deliver_to(loop, queue, calls.append)
        cb(fake_sample(b"b"))
        loop.run_until_complete(asyncio.sleep(0))
        assert calls == [] and [queue.get_nowait()[1] for _ in range(2)] == [b"a", b"b"]
        cb(fake_sample(b"c"))  # the queue is empty again: straight to the consumer
        loop.run_until_complete(asyncio.sleep(0))
        assert [[p for _, p in items] for items in calls] == [[b"c"]] and cb.stats.received == 3
    finally:
        loop.close()


def test_a_failing_consumer_is_logged_and_the_next_burst_still_arrives(caplog):
    loop = asyncio.new_event_loop()
    try:
        queue: asyncio.Queue = asyncio.Queue(maxsize=8)
        cb = make_bridge(loop, queue)
        got: list[bytes] = []

        def consumer(items):
            if items[0][1] == b"bad":
                raise RuntimeError("boom")
            got.extend(p for _, p in items)

        deliver_to(loop, queue, consumer)
        with caplog.at_level(logging.ERROR, logger="transport.bridge"):
            cb(fake_sample(b"bad"))
            loop.run_until_complete(asyncio.sleep(0))
        assert any("consumer failed" in r.getMessage() and r.exc_info for r in caplog.records)
        cb(fake_sample(b"ok"))
        loop.run_until_complete(asyncio.sleep(0))
        assert got == [b"ok"] and queue.empty()
    finally:
        loop.close()


def test_a_role_handles_bursts_directly_and_queued_items_too():
    """Role.consume: bursts of the bridges straight to handle_batch, items put into its
    queue by others through the queue; after_batch once per batch; undone on cancel."""
    from agents.net.protocol import Role

    class Rec(Role):
        def __init__(self) -> None:
            self.queue = asyncio.Queue(maxsize=8)
            self.bus = SimpleNamespace(auth=None)  # no pairwise tags: the items are handled as they are
            self.changed = asyncio.Event()
            self._waiting = None
            self.seen: list[bytes] = []
            self._lazy_n = 1
            self._wake_at = None
            self.afters = 0
            self.batches = 0
            self._polled = []

        def handle_data(self, key: str, payload: bytes) -> None:
            self.seen.append(payload)

        def after_batch(self) -> bool:
            self.afters += 1
            return True

    async def main() -> None:
        loop = asyncio.get_running_loop()
        role = Rec()
        cb = make_bridge(loop, role.queue)
        task = asyncio.ensure_future(role.consume())
        await asyncio.sleep(0)
        cb(fake_sample(b"a"))
        cb(fake_sample(b"b"))
        await asyncio.wait_for(role.changed.wait(), 2)
        assert role.seen == [b"a", b"b"] and role.afters == role.batches == 1 and role.queue.empty()
        role.changed.clear()
        role.queue.put_nowait(("k", b"c"))  # not from a bridge: the consuming task takes it
        await asyncio.wait_for(role.changed.wait(), 2)
        assert role.seen == [b"a", b"b", b"c"] and role.afters == role.batches == 2
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        cb(fake_sample(b"d"))  # after the consumer stopped: queued, not handled
        await asyncio.sleep(0.01)
        assert role.seen == [b"a", b"b", b"c"] and role.queue.get_nowait()[1] == b"d"

    asyncio.run(main())
