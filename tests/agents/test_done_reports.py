"""A done report's receivers and stamps (``agents.net.wire.receivers_of``): what the
plant builds its wait lists from and an in-neighbour reads its estimate's stamp from, taken
from untrusted bytes (the codec has checked shapes and finite values, not the numbers)."""

from __future__ import annotations

import numpy as np
import pytest

from agents.net.wire import receivers_of
from transport.codec import Message


def report(to, stamps) -> Message:
    arrays = {"x": np.zeros(3), "to": np.asarray(to, dtype=float), "stamps": np.asarray(stamps, dtype=float)}
    return Message(kind="done", sender=4, stamp=7, arrays=arrays)


def test_whole_numbers_in_range_come_back_as_ints():
    got = receivers_of(report([1, 2, 16], [7, 7, 5]), team=3)
    assert got == ([1, 2, 16], [7, 7, 5])
    assert all(type(v) is int for v in (*got[0], *got[1]))
    assert receivers_of(report([], []), team=3) == ([], [])
    top = 2.0**53 - 1
    assert receivers_of(report([0], [top]), team=1) == ([0], [2**53 - 1])


@pytest.mark.parametrize(("to", "stamps", "team"), [
    ([1, 2], [7], 3),              # receivers and stamps do not pair up
    ([1, 2, 3, 4], [7] * 4, 3),    # more receivers than the sender has out-neighbours
    ([1, -1], [7, 7], 3),          # a negative receiver
    ([1, 2], [7, -7], 3),          # a negative stamp
    ([1.5, 2], [7, 7], 3),         # not a whole number
    ([1, 2], [7, 7.25], 3),
    ([1, 2], [7, 2.0**53], 3),     # beyond the stamps' range (2**53 - 1)
    ([2.0**60], [7], 3),
    ([-0.5], [7], 3),
])
def test_a_report_whose_receivers_or_stamps_are_not_whole_numbers_in_range_is_refused(to, stamps, team):
    assert receivers_of(report(to, stamps), team=team) is None
