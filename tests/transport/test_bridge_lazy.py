"""Lazy items (:func:`transport.bridge.batch_lazily`): items the consumer does not need yet
wait without waking the loop until enough wait or an item it needs comes; then all go in
one batch, in their order of arrival."""

from __future__ import annotations

import asyncio

from tests.transport.test_bridge_direct import fake_sample
from transport.bridge import batch_lazily, deliver_to, make_bridge

NEEDED = "rse/r/plant/loc/1"


def _setup(maxsize: int = 64):
    loop = asyncio.new_event_loop()
    queue: asyncio.Queue = asyncio.Queue(maxsize=maxsize)
    cb = make_bridge(loop, queue)
    batches: list[list[bytes]] = []
    deliver_to(loop, queue, lambda items: batches.append([p for _, p in items]))
    wake_at = batch_lazily(loop, queue, lambda item: item[0] != NEEDED)
    return loop, queue, cb, batches, wake_at


def _turn(loop) -> None:
    loop.run_until_complete(asyncio.sleep(0))


def test_without_a_bound_every_item_still_wakes_the_loop():
    loop, _, cb, batches, _ = _setup()
    try:  # wake_at starts at 1: as without batch_lazily
        cb(fake_sample(b"a"))
        _turn(loop)
        cb(fake_sample(b"b"))
        _turn(loop)
        assert batches == [[b"a"], [b"b"]]
    finally:
        loop.close()


def test_lazy_items_wait_for_the_item_that_is_needed_and_keep_their_order():
    loop, queue, cb, batches, wake_at = _setup()
    try:
        wake_at(1000)
        for p in (b"r1", b"r2", b"r3"):
            cb(fake_sample(p))
            _turn(loop)
        assert batches == [] and queue.empty()  # nothing woke the loop
        cb(fake_sample(b"meas", NEEDED))
        _turn(loop)
        assert batches == [[b"r1", b"r2", b"r3", b"meas"]]
        assert cb.stats.received == 4
    finally:
        loop.close()


def test_lazy_items_wake_the_loop_once_as_many_as_asked_for_wait():
    loop, _, cb, batches, wake_at = _setup()
    try:
        wake_at(3)
        for p in (b"a", b"b"):
            cb(fake_sample(p))
            _turn(loop)
        assert batches == []
        cb(fake_sample(b"c"))
        _turn(loop)
        assert batches == [[b"a", b"b", b"c"]]
    finally:
        loop.close()


def test_asking_for_fewer_than_already_wait_takes_them_at_once():
    loop, _, cb, batches, wake_at = _setup()
    try:
        wake_at(1000)
        for p in (b"a", b"b"):
            cb(fake_sample(p))
        _turn(loop)
        assert batches == []
        wake_at(1)  # e.g. an agent that now waits for a missing in-neighbour
        assert batches == []  # not in this call: in a callback of the loop
        _turn(loop)
        assert batches == [[b"a", b"b"]]
        cb(fake_sample(b"c"))  # and every item wakes it again
        _turn(loop)
        assert batches == [[b"a", b"b"], [b"c"]]
    finally:
        loop.close()


def test_items_waiting_count_against_the_bound_of_the_queue():
    loop, _, cb, batches, wake_at = _setup(maxsize=2)
    try:
        wake_at(1000)
        for p in (b"a", b"b", b"c"):
            cb(fake_sample(p))
        assert cb.stats.dropped_full == 1
        cb(fake_sample(b"meas", NEEDED))  # dropped too: the queue is full
        wake_at(1)
        _turn(loop)
        assert batches == [[b"a", b"b"]] and cb.stats.dropped_full == 2
    finally:
        loop.close()


def test_items_waiting_when_the_loop_closes_are_counted_as_dropped():
    loop, _, cb, _, wake_at = _setup()
    wake_at(1000)
    cb(fake_sample(b"a"))
    loop.close()
    cb(fake_sample(b"b"))
    assert cb.stats.dropped_closed == 2 and cb.stats.errors == 0
