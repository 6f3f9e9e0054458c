"""Secure peer-to-peer (``rse run --secure DIR`` without a router), with real processes.

Every link is mutual TLS under the team's CA and every process enforces its own ingress
rules bound to its peers' certificate names (:mod:`agents.net.secure_team`): no router to
fail, no process without a certificate in the team, no agent speaking for another.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import SCENARIOS
from tests.deploy.conftest import Procs, rse_cmd
from tests.procs import until

pytest.importorskip("cryptography", reason="rse certs needs the cryptography package (pip install '.[secure]')")

pytestmark = pytest.mark.multiprocess

LKS = SCENARIOS / "lee_kim_shim.toml"
MITRA = SCENARIOS / "mitra_cells.toml"
WAIT_S = 60.0  # only a hang reaches it


@pytest.fixture(scope="module")
def certs(tmp_path_factory) -> Path:
    from transport.certs import write_certs

    d = tmp_path_factory.mktemp("certs")
    write_certs(d, ["plant", "monitor", *(f"agent-{i}" for i in range(1, 17))])
    return d


def _run(args: list[str], timeout: float = 600) -> tuple[int, str]:
    ps = Procs()
    try:
        p = ps.start(rse_cmd(*args))
        _so, se = p.communicate(timeout=timeout)  # a hang only
        return p.returncode, se
    finally:
        ps.kill_all()


def test_secure_peers_equal_the_simulator_and_name_no_router(certs, tmp_path):
    """mitra_cells.toml in lockstep over secure peers: every estimate equal to rse simulate's
    (max difference 0.0), nothing rejected, team.json names no router and TLS endpoints."""
    from agents.api import load_experiment
    from agents.simulate import simulate

    out = tmp_path / "run"
    code, se = _run(["run", str(MITRA), "--secure", str(certs), "--out", str(out), "--save-estimates",
                     "--no-progress", "--no-rerun", "--deadline", "30"])
    assert code == 0 and "Traceback" not in se, se
    team = json.loads((out / "team.json").read_text())
    assert team["router"] is None and "router" not in team["pids"] and team["transport"] == "peer"
    assert team["connect"] == [] and Path(team["secure"]) == certs.resolve()
    assert all(ep.startswith("tls/127.0.0.1:") for ep in team["endpoints"].values()), team["endpoints"]
    assert json.loads((out / "summary.json").read_text())["rejected"] == {}
    exp, _ = load_experiment(MITRA, (), None)
    ref = simulate(exp, keep_trajectories=True)
    diff = float(np.max(np.abs(np.load(out / "estimates.npy") - ref.estimates)))
    print(f"\nsecure peers vs rse simulate, mitra_cells: max difference {diff}")
    assert diff == 0.0
    np.testing.assert_array_equal(np.load(out / "truth.npy"), ref.truth)


def _peer(certs: Path, identity: str | None, listen: str, connect: tuple[str, ...] = (), **tls_over):
    """A secure peer of the test process (its certificate, its ingress rules), or with
    ``identity`` None and ``tls_over`` a peer configured by hand."""
    from agents.net.secure_team import peer_acl
    from transport.secure import tls_files
    from transport.zenoh_session import SessionOptions, open_session

    if identity is None:
        return open_session(tls_over["config"])
    return open_session(SessionOptions(mode="peer", listen=(listen,), connect=connect, gossip=False, retry_ms=50,
                                       tls=tls_over.get("tls") or tls_files(certs, identity), acl=peer_acl(certs, "p2p")))


def test_without_a_certificate_no_message_is_exchanged(certs, tmp_path):
    """Agent 1, a secure peer: a plain TCP peer, a TLS peer showing no certificate and one
    with another CA's certificate named agent-2 connect to it and publish; none of them
    hears agent 1 or is heard by it, while agent 2 with its own certificate is, both ways."""
    from transport.certs import write_certs
    from transport.secure import TlsFiles
    from transport.zenoh_session import close_session, free_tcp_port, make_config, tcp_endpoint

    ep = tcp_endpoint(free_tcp_port())
    tls_ep = ep.replace("tcp/", "tls/")
    rogue = tmp_path / "rogue"
    write_certs(rogue, ["agent-2"])
    forged = TlsFiles(ca=str(certs / "ca.pem"), cert=str(rogue / "agent-2.pem"), key=str(rogue / "agent-2.key"),
                      identity="agent-2")
    no_cert = make_config(mode="peer", listen=[tcp_endpoint(free_tcp_port())], connect=[tls_ep],
                          gossip=False, retry_ms=50)
    no_cert.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(certs / "ca.pem")))
    plain = make_config(mode="peer", listen=[tcp_endpoint(free_tcp_port())], connect=[ep], gossip=False, retry_ms=50)
    heard: dict[str, list[bytes]] = {"agent-1": []}
    sessions = []
    try:
        a1 = _peer(certs, "agent-1", tls_ep)
        sessions.append(a1)
        a1.declare_subscriber("rse/p2p/agent/2/**", lambda s: heard["agent-1"].append(s.payload.to_bytes()))
        outsiders = {"plain tcp": _peer(certs, None, "", config=plain),
                     "no certificate": _peer(certs, None, "", config=no_cert),
                     "another CA's agent-2": _peer(certs, "agent-2", tcp_endpoint(free_tcp_port()), (tls_ep,), tls=forged)}
        sessions += outsiders.values()
        for name, s in outsiders.items():
            heard[name] = []
            s.declare_subscriber("rse/p2p/agent/1/**", lambda smp, n=name: heard[n].append(smp.payload.to_bytes()))
        good = _peer(certs, "agent-2", tcp_endpoint(free_tcp_port()), (tls_ep,))
        sessions.append(good)
        heard["agent-2"] = []
        good.declare_subscriber("rse/p2p/agent/1/**", lambda s: heard["agent-2"].append(s.payload.to_bytes()))

        def send() -> None:
            for name, s in outsiders.items():
                s.put("rse/p2p/agent/2/est", name.encode())
            good.put("rse/p2p/agent/2/est", b"genuine")
            a1.put("rse/p2p/agent/1/est", b"from agent 1")

        assert until(lambda: b"genuine" in heard["agent-1"] and heard["agent-2"], WAIT_S, send), heard
        for _ in range(20):
            send()
            time.sleep(0.02)
        # the last words, after everything the outsiders sent on their (would-be) links
        assert until(lambda: b"last" in heard["agent-1"], WAIT_S, lambda: good.put("rse/p2p/agent/2/est", b"last"))
    finally:
        for s in sessions:
            close_session(s)
    assert set(heard["agent-1"]) == {b"genuine", b"last"}, heard["agent-1"]
    assert set(heard["agent-2"]) == {b"from agent 1"}
    for name in ("plain tcp", "no certificate", "another CA's agent-2"):
        assert heard[name] == [], (name, heard[name])


class Insider:
    """A peer with agent 4's certificate (and so agent 4's pairwise keys) that republishes
    every message of agent 3 it hears (estimates, and the done reports that carry them in
    lockstep) on agent 3's own keys, each value shifted by +5: well-formed messages agent 3
    never sent. Every other one is sealed with agent 4's own keys (an agent speaking for
    another), the others keep agent 3's tags (a copy of its seal over other values)."""

    def __init__(self, certs: Path, team: dict, last: int) -> None:
        from agents.net.secure_team import peer_acl
        from transport.linkauth import load_link_auth, team_identities
        from transport.secure import tls_files
        from transport.zenoh_session import SessionOptions, free_tcp_port, open_session, tcp_endpoint

        run = team["run_id"]
        self.sent = self.failed = 0
        self.by_key: Counter[str] = Counter()
        self.lock = threading.Lock()
        eps = tuple(team["endpoints"].values())
        self.members, self.armed_at, self.last = len(eps), None, last
        self.auth = load_link_auth(certs, "agent-4", team_identities(range(1, 6)))
        self.s = open_session(SessionOptions(mode="peer", listen=(tcp_endpoint(free_tcp_port()),), connect=eps,
                                             gossip=False, retry_ms=50, tls=tls_files(certs, "agent-4"),
                                             acl=peer_acl(certs, run)))
        import zenoh

        for key in (f"rse/{run}/agent/3/**", f"rse/{run}/ctl/done/3"):  # lockstep: the done report carries it
            self.s.declare_subscriber(key, self.forge, allowed_origin=zenoh.Locality.REMOTE)

    def forge(self, sample) -> None:
        from transport.codec import decode, encode_fields
        from transport.linkauth import MAGIC, TAG

        if not self.armed():
            return
        data, key = sample.payload.to_bytes(), str(sample.key_expr)
        try:
            assert data.endswith(MAGIC)  # agent 3's seal: 7 tags (plant, monitor, agents 1-5), count, magic
            trailer = data[-(7 * TAG + 2 + len(MAGIC)):]
            data = data[: -len(trailer)]
            m = decode(data, schema={"est": {"x": (None,)}, "done": {"x": (None,), "to": (None,), "stamps": (None,)}})
            if m.stamp > self.last:
                return
            arrays = {**m.arrays, "x": np.asarray(m.arrays["x"]) + 5.0}
            forged = encode_fields(m.kind, m.sender, m.stamp, arrays, receiver=m.receiver, meta=dict(m.meta) or None)
            forged = self.auth.seal(key, forged) if self.sent % 2 == 0 else forged + trailer
            self.s.put(key, forged)
            with self.lock:
                self.sent += 1
                self.by_key[key.split("/", 2)[2]] += 1
        except Exception:
            with self.lock:
                self.failed += 1

    def armed(self) -> bool:
        """Forge from 0.5 s after a link to every member is up (the members' subscriptions
        have reached the insider by then: each forgery goes to each of its receivers)."""
        now = time.monotonic()
        if self.armed_at is None and len(list(self.s.info.peers_zid())) >= self.members:
            self.armed_at = now
        return self.armed_at is not None and now - self.armed_at >= 0.5

    def close(self) -> None:
        from transport.zenoh_session import close_session

        close_session(self.s)


def test_an_insider_cannot_speak_for_another_agent(certs, tmp_path):
    """lee_kim_shim.toml in lockstep over secure peers while an insider holding agent 4's
    certificate republishes agent 3's messages on agent 3's keys shifted by +5: every
    receiver rejects them (agent 3's messages carry tags only agent 3 can make) and counts
    each with its reason, so both bounds hold and every estimate equals rse simulate's."""
    from agents.api import load_experiment
    from agents.simulate import simulate

    out = tmp_path / "run"
    ov = ("run.dt=0.01",)
    ps = Procs()
    insider = None
    try:
        p = ps.start(rse_cmd("run", str(LKS), "--set", ov[0], "--secure", str(certs), "--out", str(out),
                             "--save-estimates", "--no-progress", "--no-rerun", "--deadline", "30", "--rate", "400"))
        assert until(lambda: (out / "team.json").is_file(), WAIT_S), p.poll() is None or p.communicate()
        time.sleep(0.2)
        # the forgeries stop 200 rounds before the end, so that each reaches its receivers
        # before they stop (at most 400 rounds/s: 0.5 s)
        insider = Insider(certs, json.loads((out / "team.json").read_text()), last=4000 - 200)
        so, se = p.communicate(timeout=600)
    finally:
        if insider is not None:
            insider.close()
        ps.kill_all()
    assert insider is not None
    assert p.returncode == 0 and "Traceback" not in se, se  # 3: a bound failed
    assert insider.sent > 1000 and insider.failed == 0
    summary = json.loads((out / "summary.json").read_text())
    assert [e["ok"] for e in summary["expectations"]] == [True, True], summary["expectations"]
    rejected = summary["rejected"]
    print(f"\ninsider (agent 4's certificate): {insider.sent} well-formed messages on agent 3's keys "
          f"({dict(insider.by_key)}); "
          f"rejected: {rejected}; by receiver: "
          f"{ {who: p['rejected'] for who, p in summary['processes'].items() if p['rejected']} }")
    # in lockstep agent 3's estimate travels in its done report: every forgery goes to the
    # plant, the monitor and agents 2 and 4 (agent 3's neighbours), and each counts every one
    # with its reason
    assert set(rejected) == {"3"} and set(insider.by_key) == {"ctl/done/3"}, (rejected, insider.by_key)
    for who in ("plant", "monitor", "agent 2", "agent 4"):
        mine = summary["processes"][who]["rejected"]
        assert set(mine) == {"3"} and set(mine["3"]) == {"total", "impersonation", "unauthenticated"}, (who, mine)
        assert mine["3"]["total"] == insider.sent, (who, mine, insider.sent)
        assert mine["3"]["impersonation"] == (insider.sent + 1) // 2, (who, mine)
    assert rejected["3"]["total"] == sum(p["rejected"].get("3", {}).get("total", 0)
                                         for p in summary["processes"].values())
    assert "3: " in so and "impersonation" in so, so
    exp, _ = load_experiment(LKS, ov, None)
    ref = simulate(exp, keep_trajectories=True)
    # the bound of every lockstep equality test of lee_kim_shim (tests/agents/test_run_processes.py:
    # the processes sum in another order); one forged estimate (+5) would be off by 1e-3 or more
    assert float(np.max(np.abs(np.load(out / "estimates.npy") - ref.estimates))) <= 1e-12


def _round(out: Path) -> int:
    try:
        return int(json.loads((out / "status.json").read_text())["round"])
    except (OSError, ValueError, KeyError):
        return -1


@pytest.mark.slow
def test_a_realtime_secure_team_survives_sigkill_of_an_agent_and_of_the_monitor(certs, tmp_path):
    """Realtime over secure peers: SIGKILL of agent 3 and of the monitor, and the team goes on
    (there is no router to kill); a monitor restarted with --team (the team's certificates)
    rejoins at a later round."""
    out = tmp_path / "run"
    ps = Procs()
    try:
        p = ps.start(rse_cmd("run", str(LKS), "--set", "run.dt=0.01", "--set", "run.duration=600", "--set", "expect=[]",
                             "--mode", "realtime", "--rate", "100", "--secure", str(certs), "--out", str(out),
                             "--no-progress", "--no-rerun"))
        assert until(lambda: _round(out) > 100, 300), p.poll() is None or p.communicate()
        team = json.loads((out / "team.json").read_text())
        assert team["router"] is None
        killed_at = _round(out)
        os.kill(team["pids"]["agent 3"], signal.SIGKILL)
        os.kill(team["pids"]["monitor"], signal.SIGKILL)
        time.sleep(2.0)
        mon = ps.start(rse_cmd("monitor", "--team", str(out / "team.json"), "--no-rerun", "--verbose"))
        lines: list[str] = []
        reader = threading.Thread(target=lambda: lines.extend(iter(mon.stderr.readline, "")), daemon=True)
        reader.start()
        assert until(lambda: any("rejoined the team at round" in ln for ln in lines) or mon.poll() is not None, 120)
        line = next((ln for ln in lines if "rejoined the team at round" in ln), "")
        assert line, lines
        at = int(line.split("rejoined the team at round")[1].split()[0].strip(" .,:;"))
        print(f"\nagent 3 and the monitor killed at round {killed_at}; a new monitor rejoined at round {at}")
        assert at > killed_at + 100  # 2 s at 100 Hz: the team went on
        assert p.poll() is None
        mon.send_signal(signal.SIGTERM)
        with contextlib.suppress(Exception):
            mon.wait(10)
        p.send_signal(signal.SIGTERM)
        _so, se = p.communicate(timeout=30)
        assert "agent 3 was killed by SIGKILL" in se and "the monitor was killed by SIGKILL" in se, se
        assert "Traceback" not in se and "router" not in se, se
    finally:
        ps.kill_all()


def test_plain_mode_says_what_it_is_off_loopback():
    """A plain endpoint off this host: one line saying that plain mode authenticates nobody
    (here before a bad-input error, exit 2); on loopback, none."""
    for ep, warned in (("tcp/192.0.2.1:7447", True), ("tcp/127.0.0.1:7447", False)):
        code, se = _run(["run", str(LKS), "--connect", ep, "--router"], timeout=60)
        assert code == 2 and "give one of them" in se, se
        assert ("plain mode authenticates nobody" in se) is warned, se
        assert "Traceback" not in se


@pytest.mark.slow
def test_single_roles_are_secure_peers_with_explicit_endpoints(certs, tmp_path):
    """rse plant, rse monitor and five rse agent processes, each with --secure and --sign, its
    own --listen tls/ endpoint and the others' as --connect (as across hosts): the team runs
    in lockstep, nothing is rejected (every estimate's pairwise tag checks), the signed copies
    are compared and agree, and every estimate equals rse simulate's."""
    from agents.api import load_experiment
    from agents.simulate import simulate
    from transport.zenoh_session import free_tcp_port

    ov = ("run.dt=0.01", "run.duration=3", "expect=[]")
    names = ["plant", "monitor", *(f"agent {i}" for i in range(1, 6))]
    eps = {nm: f"tls/127.0.0.1:{free_tcp_port()}" for nm in names}
    out = tmp_path / "run"
    ps = Procs()
    try:
        procs = {}
        for nm in names:
            role, *aid = nm.split()
            args = [role, *(["--id", aid[0]] if aid else []), str(LKS), "--run-id", "p2p-roles", "--secure", str(certs),
                    "--listen", eps[nm], *(a for other in names if other != nm for a in ("--connect", eps[other])),
                    "--deadline", "30", "--sign", str(certs)]
            for o in ov:
                args += ["--set", o]
            if role == "monitor":
                args += ["--out", str(out), "--no-rerun", "--save-estimates"]
            procs[nm] = ps.start(rse_cmd(*args))
        for nm, p in procs.items():
            _so, se = p.communicate(timeout=300)  # a hang only
            assert p.returncode == 0 and "Traceback" not in se, (nm, se)
    finally:
        ps.kill_all()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["complete"] and summary["rejected"] == {}, summary["rejected"]
    # --sign: every estimate signed, the regular receivers' copies compared, all equal
    ev = summary["evidence"]
    assert ev["convicted"] == {} and ev["bad_signatures"] == ev["verifications"] == 0 and ev["copies"] > 1000, ev
    exp, _ = load_experiment(LKS, ov, None)
    ref = simulate(exp, keep_trajectories=True)
    assert float(np.max(np.abs(np.load(out / "estimates.npy") - ref.estimates))) <= 1e-12
