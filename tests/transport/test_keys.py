"""Key expressions: one builder, round trips through the parser, strict rejection."""

from __future__ import annotations

import pytest
import zenoh
from hypothesis import given, settings
from hypothesis import strategies as st

from estimation.errors import MessageError
from transport.codec import LAUNCHER_ID, MAX_ID, MONITOR_ID, PLANT_ID
from transport.keys import (
    KEY_ALIVE,
    KEY_CTL,
    KEY_EST,
    KEY_LOC,
    KEY_TRUTH,
    Keys,
    ParsedKey,
    parse_key,
    validate_run_id,
)

RUN = "lks-2026.01_01"
keys = Keys(RUN)


@pytest.mark.parametrize(
    "key, expected, parsed",
    [
        (keys.plant_loc(3), f"rse/{RUN}/plant/loc/3", ParsedKey(RUN, KEY_LOC, (3,))),
        (keys.plant_truth(), f"rse/{RUN}/plant/truth", ParsedKey(RUN, KEY_TRUTH)),
        (keys.est(0), f"rse/{RUN}/agent/0/est", ParsedKey(RUN, KEY_EST, (0,))),
        (keys.est(2, to=5), f"rse/{RUN}/agent/2/est/5", ParsedKey(RUN, KEY_EST, (2, 5))),
        (keys.ctl("stop"), f"rse/{RUN}/ctl/stop", ParsedKey(RUN, KEY_CTL, (), "stop")),
        (keys.ctl("done", 7), f"rse/{RUN}/ctl/done/7", ParsedKey(RUN, KEY_CTL, (7,), "done")),
        (keys.ctl("round", PLANT_ID), f"rse/{RUN}/ctl/round/plant", ParsedKey(RUN, KEY_CTL, (PLANT_ID,), "round")),
        (keys.ctl("stop", LAUNCHER_ID), f"rse/{RUN}/ctl/stop/launcher", ParsedKey(RUN, KEY_CTL, (LAUNCHER_ID,), "stop")),
        (keys.alive("agent", 4), f"rse/{RUN}/alive/agent/4", ParsedKey(RUN, KEY_ALIVE, (4,), "agent")),
        (keys.alive("plant"), f"rse/{RUN}/alive/plant/0", ParsedKey(RUN, KEY_ALIVE, (0,), "plant")),
    ],
)
def test_build_and_parse(key, expected, parsed):
    assert key == expected
    assert keys.parse(key) == parsed
    assert parse_key(key) == parsed
    zenoh.KeyExpr(key)  # a valid, canonical Zenoh key expression


def test_implied_sender_receiver_loc():
    assert keys.parse(keys.plant_loc(2)).sender == PLANT_ID
    assert keys.parse(keys.plant_loc(2)).loc == 2
    assert keys.parse(keys.plant_truth()).sender == PLANT_ID
    p = keys.parse(keys.est(3, to=9))
    assert (p.sender, p.receiver, p.loc) == (3, 9, None)
    p = keys.parse(keys.est(3))
    assert (p.sender, p.receiver) == (3, None)
    assert keys.parse(keys.ctl("stop")).sender is None
    assert keys.parse(keys.ctl("done", 4)).sender == 4
    assert keys.parse(keys.ctl("report", MONITOR_ID)).sender == MONITOR_ID
    assert keys.parse(keys.alive("agent", 6)).sender == 6
    assert keys.parse(keys.alive("monitor", 0)).sender == MONITOR_ID


@given(
    i=st.integers(0, MAX_ID),
    j=st.integers(0, MAX_ID),
    run=st.from_regex(r"[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}", fullmatch=True),
)
@settings(max_examples=200, deadline=None)
def test_round_trip_property(i, j, run):
    k = Keys(run)
    assert k.parse(k.est(i, to=j)) == ParsedKey(run, KEY_EST, (i, j))
    assert k.parse(k.plant_loc(i)) == ParsedKey(run, KEY_LOC, (i,))
    assert k.parse(k.ctl("done", i)).sender == i


def test_patterns_match_what_they_should():
    def hits(pattern: str, key: str) -> bool:
        return zenoh.KeyExpr(pattern).intersects(zenoh.KeyExpr(key))

    assert hits(keys.est_pattern(), keys.est(4))
    assert not hits(keys.est_pattern(), keys.est(4, to=1))
    assert hits(keys.est_pattern(to=1), keys.est(4, to=1))
    assert not hits(keys.est_pattern(to=1), keys.est(4, to=2))
    assert hits(keys.est_pattern(sender=4), keys.est(4)) and not hits(keys.est_pattern(sender=4), keys.est(5))
    assert hits(keys.plant_loc_pattern(), keys.plant_loc(0))
    assert hits(keys.ctl_pattern(), keys.ctl("stop")) and hits(keys.ctl_pattern(), keys.ctl("done", 2))
    assert hits(keys.ctl_pattern("done"), keys.ctl("done")) and hits(keys.ctl_pattern("done"), keys.ctl("done", 2))
    assert not hits(keys.ctl_pattern("done"), keys.ctl("stop"))
    assert hits(keys.alive_pattern(), keys.alive("agent", 1)) and hits(keys.alive_pattern("agent"), keys.alive("agent", 1))
    assert not hits(keys.alive_pattern("agent"), keys.alive("plant"))
    assert hits(keys.all_pattern(), keys.plant_truth())
    # two runs never overlap
    other = Keys("lks-2026.01_02")
    for pattern in (keys.all_pattern(), keys.est_pattern(), keys.alive_pattern()):
        assert not hits(pattern, other.est(1)) and not hits(pattern, other.alive("agent", 1))


@pytest.mark.parametrize(
    "run",
    ["", "a/b", "a*", "a$b", "a#b", "a?b", "a b", "a\tb", "a\nb", "-a", ".a", "é", "x" * 65, "**", None, 3],
)
def test_bad_run_ids_are_rejected(run):
    with pytest.raises(ValueError, match="invalid run id"):
        validate_run_id(run)
    with pytest.raises(ValueError):
        Keys(run)


def test_good_run_ids():
    for run in ["a", "A1", "lee_kim_shim-20260101T120000-1a2b", "x" * 64, "0.1-b_c"]:
        assert validate_run_id(run) == run


@pytest.mark.parametrize(
    "call",
    [
        lambda: keys.est(-1),
        lambda: keys.est(True),
        lambda: keys.est(MAX_ID + 1),
        lambda: keys.est(1, to="2"),
        lambda: keys.plant_loc(1.0),
        lambda: keys.ctl("Stop"),
        lambda: keys.ctl("a/b"),
        lambda: keys.ctl("stop", -7),
        lambda: keys.alive("robot", 1),
        lambda: keys.alive_pattern("robot"),
    ],
)
def test_bad_builder_arguments(call):
    with pytest.raises(ValueError):
        call()


@pytest.mark.parametrize(
    "key",
    [
        "",
        "rse",
        f"rse/{RUN}",
        f"xyz/{RUN}/plant/truth",
        "rse/bad run/plant/truth",
        f"rse/{RUN}/plant",
        f"rse/{RUN}/plant/loc",
        f"rse/{RUN}/plant/loc/x",
        f"rse/{RUN}/plant/loc/03",
        f"rse/{RUN}/plant/loc/-3",
        f"rse/{RUN}/plant/loc/+3",
        f"rse/{RUN}/plant/loc/\u0663",  # an Arabic-Indic digit
        f"rse/{RUN}/plant/truth/1",
        f"rse/{RUN}/agent/1",
        f"rse/{RUN}/agent/1/est/2/3",
        f"rse/{RUN}/agent/*/est",
        f"rse/{RUN}/agent/1/estimate",
        f"rse/{RUN}/agent/{MAX_ID + 1}/est",
        f"rse/{RUN}/agent/99999999999999999999/est",
        f"rse/{RUN}/ctl",
        f"rse/{RUN}/ctl/Stop",
        f"rse/{RUN}/ctl/stop/agent",
        f"rse/{RUN}/ctl/stop/1/2",
        f"rse/{RUN}/alive/agent",
        f"rse/{RUN}/alive/robot/1",
        f"rse/{RUN}/alive/agent/1/2",
        f"rse/{RUN}/other/1",
        f"rse/{RUN}/agent/1/est/" + "1" * 300,
    ],
)
def test_bad_received_keys_are_rejected(key):
    with pytest.raises(MessageError) as info:
        parse_key(key)
    assert info.value.reason == "key"


def test_key_of_another_run_is_rejected():
    with pytest.raises(MessageError) as info:
        keys.parse(Keys("other").est(1))
    assert info.value.reason == "key"


@given(st.text(max_size=80))
@settings(max_examples=300, deadline=None)
def test_parse_never_raises_anything_else(text):
    try:
        parsed = parse_key(text)
    except MessageError:
        return
    assert parsed.kind in {KEY_LOC, KEY_TRUTH, KEY_EST, KEY_CTL, KEY_ALIVE}
