"""Lazy items (:func:`transport.bridge.batch_lazily`): items the consumer does not need yet
wait without waking the loop until enough wait or an item it needs comes; then all go in
one batch, in their order of arrival."""

from __future__ import annotations

import asyncio
from types import SimpleNamespace

import pytest

from tests.transport.test_bridge_direct import fake_sample
from transport.bridge import batch_lazily, deliver_to, make_bridge

NEEDED = "rse/r/plant/loc/1"


@pytest.fixture
def lazy(request):
    """A loop, a bounded queue (``maxsize`` 64, or the indirect parameter), one bridge into
    it, a direct consumer recording its batches, and ``wake_at`` of items lazy unless on
    :data:`NEEDED`; ``arrive(*payloads, key=...)`` hands each to the bridge and lets the
    loop run once after it; the loop is closed afterwards."""
    loop = asyncio.new_event_loop()
    queue: asyncio.Queue = asyncio.Queue(maxsize=getattr(request, "param", 64))
    batches: list[list[bytes]] = []
    deliver_to(loop, queue, lambda items: batches.append([p for _, p in items]))
    ns = SimpleNamespace(loop=loop, queue=queue, cb=make_bridge(loop, queue), batches=batches,
                         wake_at=batch_lazily(loop, queue, lambda item: item[0] != NEEDED),
                         turn=lambda: loop.run_until_complete(asyncio.sleep(0)))

    def arrive(*payloads: bytes, key: str = "rse/r/agent/1/est") -> None:
        for p in payloads:
            ns.cb(fake_sample(p, key))
            ns.turn()

    ns.arrive = arrive
    yield ns
    loop.close()


def test_without_a_bound_every_item_still_wakes_the_loop(lazy):
    # wake_at starts at 1: as without batch_lazily
    lazy.arrive(b"a", b"b")
    assert lazy.batches == [[b"a"], [b"b"]]


def test_lazy_items_wait_for_the_item_that_is_needed_and_keep_their_order(lazy):
    lazy.wake_at(1000)
    lazy.arrive(b"r1", b"r2", b"r3")
    assert lazy.batches == [] and lazy.queue.empty()  # nothing woke the loop
    lazy.arrive(b"meas", key=NEEDED)
    assert lazy.batches == [[b"r1", b"r2", b"r3", b"meas"]]
    assert lazy.cb.stats.received == 4


def test_lazy_items_wake_the_loop_once_as_many_as_asked_for_wait(lazy):
    lazy.wake_at(3)
    lazy.arrive(b"a", b"b")
    assert lazy.batches == []
    lazy.arrive(b"c")
    assert lazy.batches == [[b"a", b"b", b"c"]]


def test_asking_for_fewer_than_already_wait_takes_them_at_once(lazy):
    lazy.wake_at(1000)
    for p in (b"a", b"b"):
        lazy.cb(fake_sample(p))
    lazy.turn()
    assert lazy.batches == []
    lazy.wake_at(1)  # e.g. an agent that now waits for a missing in-neighbour
    assert lazy.batches == []  # not in this call: in a callback of the loop
    lazy.turn()
    assert lazy.batches == [[b"a", b"b"]]
    lazy.arrive(b"c")  # and every item wakes it again
    assert lazy.batches == [[b"a", b"b"], [b"c"]]


@pytest.mark.parametrize("lazy", [2], indirect=True, ids=["maxsize=2"])
def test_items_waiting_count_against_the_bound_of_the_queue(lazy):
    lazy.wake_at(1000)
    for p in (b"a", b"b", b"c"):
        lazy.cb(fake_sample(p))
    assert lazy.cb.stats.dropped_full == 1
    lazy.cb(fake_sample(b"meas", NEEDED))  # dropped too: the queue is full
    lazy.wake_at(1)
    lazy.turn()
    assert lazy.batches == [[b"a", b"b"]] and lazy.cb.stats.dropped_full == 2


def test_items_waiting_when_the_loop_closes_are_counted_as_dropped(lazy):
    lazy.wake_at(1000)
    lazy.cb(fake_sample(b"a"))
    lazy.loop.close()
    lazy.cb(fake_sample(b"b"))
    assert lazy.cb.stats.dropped_closed == 2 and lazy.cb.stats.errors == 0
