"""Pairwise message authentication of a secure team (transport.linkauth)."""

from __future__ import annotations

import pytest

pytest.importorskip("cryptography", reason="a secure team needs the cryptography package (pip install '.[secure]')")

from transport.linkauth import load_link_auth, sealed, team_identities

KEY = "rse/r1/ctl/done/3"


@pytest.fixture(scope="module")
def team(tmp_path_factory):
    from transport.certs import write_certs

    d = tmp_path_factory.mktemp("certs")
    order = team_identities([3, 1, 2])
    write_certs(d, order)
    return {x: load_link_auth(d, x, order) for x in order}


def test_only_estimates_and_done_reports_are_sealed():
    assert team_identities([3, 1, 2]) == ["plant", "monitor", "agent-1", "agent-2", "agent-3"]
    assert sealed("rse/r1/agent/3/est") and sealed("rse/r1/agent/3/est/2") and sealed(KEY)
    for key in ("rse/r1/plant/loc/1", "rse/r1/plant/truth", "rse/r1/ctl/ready/3", "rse/r1/ctl/stats/3",
                "rse/r1/alive/agent/3", "rse/r1"):
        assert not sealed(key), key


def test_every_member_opens_what_the_sender_sealed(team):
    msg = team["agent-3"].seal(KEY, b"estimate")
    for me in ("plant", "monitor", "agent-1", "agent-2"):
        assert team[me].open(KEY, msg, "agent-3") == (b"estimate", "", None)


def test_an_agent_speaking_for_another_is_named(team):
    forged = team["agent-2"].seal(KEY, b"estimate + 5")  # agent 2's own keys, agent 3's key expression
    for me in ("plant", "monitor", "agent-1"):
        assert team[me].open(KEY, forged, "agent-3") == (None, "impersonation", "agent-2")


@pytest.mark.parametrize("change", ["payload", "key", "tag", "truncated", "bare", "count"])
def test_anything_changed_is_unauthenticated(team, change):
    msg = team["agent-3"].seal(KEY, b"estimate")
    key = KEY
    if change == "payload":  # agent 3's tags over other values
        msg = b"estimatf" + msg[len(b"estimate"):]
    elif change == "key":  # agent 3's done report replayed as an estimate
        key = "rse/r1/agent/3/est"
    elif change == "tag":
        i = len(b"estimate") + 16 * team["plant"].order.index("plant")
        msg = msg[:i] + bytes([msg[i] ^ 1]) + msg[i + 1:]
    elif change == "truncated":
        msg = msg[:-1]
    elif change == "bare":
        msg = b"estimate"
    else:  # a seal for a team of another size
        msg = msg[:-4] + b"\x06\x00" + msg[-2:]
    inner, reason, who = team["plant"].open(key, msg, "agent-3")
    assert (inner, reason, who) == (None, "unauthenticated", None)


def test_a_stranger_is_unauthenticated_and_a_missing_certificate_is_named(team, tmp_path):
    from transport.certs import write_certs

    order = team_identities([1, 2, 3])
    write_certs(tmp_path, order)  # another CA, the same names
    stranger = load_link_auth(tmp_path, "agent-3", order)
    assert team["plant"].open(KEY, stranger.seal(KEY, b"x"), "agent-3") == (None, "unauthenticated", None)
    (tmp_path / "agent-2.pem").unlink()
    with pytest.raises(ValueError, match=r"agent-2\.pem"):
        load_link_auth(tmp_path, "agent-3", order)


def test_a_secure_peer_accepts_estimates_from_any_agent_the_router_only_from_their_own():
    from transport.secure import access_control

    def agent3_puts(acl):
        rules = {r["id"]: r for r in acl["rules"]}
        return [k for rid in next(p for p in acl["policies"] if p["subjects"] == ["agent-3"])["rules"]
                for k in rules[rid]["key_exprs"]
                if rules[rid]["flows"] == ["ingress"] and rules[rid]["messages"] == ["put"]]

    assert agent3_puts(access_control([1, 3], run_id="r1")) == ["rse/r1/agent/3/**", "rse/r1/ctl/*/3"]
    assert agent3_puts(access_control([1, 3], run_id="r1", open_estimates=True)) == [
        "rse/r1/agent/**", "rse/r1/ctl/done/*", "rse/r1/ctl/*/3"]
