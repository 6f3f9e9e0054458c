"""The channel model's draws made ahead (Channel.prepare) are the draws fate() makes."""

import subprocess
import sys

from transport.channel import Channel

LINKS = [(j, i) for i in range(1, 6) for j in range(1, 6) if i != j]


def _fates(ch: Channel, stamps: range) -> list:
    return [ch.fate(j, i, k) for j, i in LINKS for k in stamps]


def test_prepared_links_decide_as_lazily_drawn_ones() -> None:
    stamps = range(0, 2100, 7)  # blocks 0, 1 and 2 of every link
    lazy = Channel(seed=11, drop_p=0.3, delay_max=2)
    ahead = Channel(seed=11, drop_p=0.3, delay_max=2)
    ahead.prepare(LINKS[:7])
    assert len(ahead._blocks) == 7 and all(b == 0 for b, _ in ahead._blocks.values())
    got = _fates(ahead, stamps)
    assert got == _fates(lazy, stamps)
    assert {None} < set(got) and max(k for k in got if k is not None) > 2  # drops and delays both drawn
    ahead.prepare(LINKS)  # a link past block 0 keeps its block
    assert any(b == 2 for b, _ in ahead._blocks.values())
    assert _fates(ahead, stamps) == got


def test_a_perfect_channel_prepares_nothing() -> None:
    ch = Channel(seed=3)
    ch.prepare(LINKS)
    assert ch._blocks == {}
    assert ch.fate(1, 2, 5) == 6


def test_prepare_imports_numpy_random() -> None:
    # what keeps it out of an agent's first round (20-40 ms of CPU in each process)
    code = ("import sys; from transport.channel import Channel; assert 'numpy.random' not in sys.modules; "
            "Channel(seed=1, drop_p=0.1).prepare([(1, 2)]); assert 'numpy.random' in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)
