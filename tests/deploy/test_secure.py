"""``--secure``: mutual TLS and the router's access control, with real processes.

A router (``rse router --secure DIR``) in a child process; the test process opens Zenoh
client sessions with the certificates of ``rse certs`` (or none, or forged ones) and
checks what gets through. Every test is bounded (under 60 s); the router's process group
is killed in ``finally`` and every session is closed.
"""

from __future__ import annotations

import contextlib
import json
import signal
import time
from pathlib import Path

import pytest

from tests.conftest import SCENARIOS
from tests.deploy.conftest import Procs, rse_cmd
from tests.procs import until

pytest.importorskip("cryptography", reason="rse certs needs the cryptography package (pip install '.[secure]')")

pytestmark = pytest.mark.multiprocess

RUN = "sec-test"
WAIT_S = 60.0  # for a message to get through: only a hang reaches it
LKS = SCENARIOS / "lee_kim_shim.toml"
SMALL = ("run.dt=0.01", "run.duration=6", "output.window=[4.0, 6.0]", "expect=[]")


@pytest.fixture(scope="module")
def certs(tmp_path_factory) -> Path:
    from transport.certs import write_certs

    d = tmp_path_factory.mktemp("certs")
    write_certs(d, ["router", "plant", "monitor", *(f"agent-{i}" for i in range(1, 6))])
    return d


@pytest.fixture(scope="module")
def router(certs):
    """``rse router --secure`` on a free loopback port (tcp/ is taken as tls/): its endpoint."""
    ps = Procs()
    try:
        p, ep = ps.router("--listen", "tcp/127.0.0.1:0", "--secure", str(certs))
        assert ep.startswith("tls/127.0.0.1:")
        yield ep
        assert p.poll() is None, p.communicate()[1]
    finally:
        ps.kill_all()


class Net:
    """Client sessions of the test process, all closed at the end."""

    def __init__(self, endpoint: str, certs: Path) -> None:
        self.endpoint, self.certs = endpoint, certs
        self.stack = contextlib.ExitStack()

    def open(self, identity: str | None = None, tls=None):
        from transport.secure import tls_files
        from transport.zenoh_session import SessionOptions, close_session, open_session

        files = tls if tls is not None else (tls_files(self.certs, identity) if identity else None)
        s = open_session(SessionOptions.client([self.endpoint], tls=files))
        self.stack.callback(close_session, s)
        return s

    def listen(self, session, *patterns: str) -> list[tuple[str, bytes]]:
        got: list[tuple[str, bytes]] = []
        for pat in patterns:
            session.declare_subscriber(pat, lambda smp: got.append((str(smp.key_expr), smp.payload.to_bytes())))
        return got


@pytest.fixture
def net(router, certs):
    n = Net(router, certs)
    with n.stack:
        yield n


def test_without_credentials_nothing_connects_or_gets_through(net, certs, tmp_path):
    """No certificate, a certificate of another CA (even with the CN agent-2), plain TCP:
    the router refuses the session; a real subscriber (agent 1) hears nothing of them,
    while agent 2 with its own credentials does get through."""
    from estimation.errors import TransportError
    from transport.certs import write_certs
    from transport.secure import TlsFiles
    from transport.zenoh_session import SessionOptions, close_session, make_config, open_session

    sub = net.open("agent-1")
    got = net.listen(sub, f"rse/{RUN}/agent/*/est", f"rse/{RUN}/agent/*/est/1")
    rogue = tmp_path / "rogue"
    write_certs(rogue, ["agent-2"])
    forged = TlsFiles(ca=str(certs / "ca.pem"), cert=str(rogue / "agent-2.pem"), key=str(rogue / "agent-2.key"),
                      identity="agent-2")
    no_cert = make_config(mode="client", connect=[net.endpoint])  # trusts the router, shows no certificate
    no_cert.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(certs / "ca.pem")))
    port = net.endpoint.rsplit(":", 1)[1]
    attempts = {
        "another CA's certificate": SessionOptions.client([net.endpoint], tls=forged),
        "no certificate": no_cert,
        "plain tcp": SessionOptions.client([f"tcp/127.0.0.1:{port}"]),
    }
    for _what, opts in attempts.items():
        s = None
        try:
            with pytest.raises(TransportError):
                s = open_session(opts)
                for _ in range(10):  # were it open: try to inject
                    s.put(f"rse/{RUN}/agent/2/est", b"injected")
        finally:
            close_session(s)
    # none of them got a session: once agent 2's genuine message is heard, nothing else was
    good = net.open("agent-2")
    assert until(lambda: got, WAIT_S, lambda: good.put(f"rse/{RUN}/agent/2/est", b"genuine"))
    assert {v for _, v in got} == {b"genuine"}


def test_an_agent_cannot_speak_for_another_agent_or_the_plant(net):
    """agent 2 (its own certificate) puts on agent 3's estimate, done and ready keys, on
    the plant's keys, and declares agent 3's liveliness token: the router refuses all of it
    (agent 1 and the monitor hear none, and the router's answer to a liveliness query lists
    no such token), while agent 2's own estimate and token get through."""
    a1, mon, a2 = net.open("agent-1"), net.open("monitor"), net.open("agent-2")
    heard = net.listen(a1, f"rse/{RUN}/agent/*/est", f"rse/{RUN}/agent/*/est/1", f"rse/{RUN}/ctl/done/*",
                       f"rse/{RUN}/plant/loc/1")
    heard_mon = net.listen(mon, f"rse/{RUN}/ctl/**", f"rse/{RUN}/plant/truth")
    tokens: list[str] = []
    a1.liveliness().declare_subscriber(f"rse/{RUN}/alive/**", lambda s: tokens.append(str(s.key_expr)), history=True)
    forged = [f"rse/{RUN}/agent/3/est", f"rse/{RUN}/agent/3/est/1", f"rse/{RUN}/ctl/done/3", f"rse/{RUN}/ctl/ready/3",
              f"rse/{RUN}/plant/loc/1", f"rse/{RUN}/plant/truth", f"rse/{RUN}/ctl/stop/plant", f"rse/{RUN}/ctl/ack/monitor"]
    # held until the end of the test: a token whose object is dropped is undeclared (this test
    # once lost agent 2's own token that way, before agent 1 had subscribed)
    held = [a2.liveliness().declare_token(f"rse/{RUN}/alive/agent/3"),
            a2.liveliness().declare_token(f"rse/{RUN}/alive/agent/2")]

    def send() -> None:
        for key in forged:
            a2.put(key, b"forged")
        a2.put(f"rse/{RUN}/agent/2/est", b"own")
        a2.put(f"rse/{RUN}/ctl/done/2", b"own")

    def send_and_ask() -> None:  # and ask the router for the tokens it holds
        send()
        with contextlib.suppress(Exception):
            for reply in a1.liveliness().get(f"rse/{RUN}/alive/**", timeout=1.0):
                if reply.ok is not None:
                    tokens.append(str(reply.ok.key_expr))

    ok = until(lambda: (f"rse/{RUN}/agent/2/est", b"own") in heard and (f"rse/{RUN}/ctl/done/2", b"own") in heard_mon
                and f"rse/{RUN}/alive/agent/2" in tokens, WAIT_S, send_and_ask)
    for _ in range(5):
        send()
    # the last word, after the forged ones on the same session: once it is heard, whatever the
    # router let through before it has been heard too
    assert until(lambda: (f"rse/{RUN}/agent/2/est", b"last") in heard, WAIT_S, lambda: a2.put(f"rse/{RUN}/agent/2/est", b"last"))
    assert ok, (heard, heard_mon, tokens)
    assert not [k for k, v in heard + heard_mon if v == b"forged"], (heard, heard_mon)
    assert f"rse/{RUN}/alive/agent/2" in tokens and f"rse/{RUN}/alive/agent/3" not in tokens, tokens
    for token in held:
        token.undeclare()


def test_only_the_monitor_hears_the_true_state(net):
    """The plant publishes the true state and agent 3's measurement: the monitor receives
    the state, agent 3 (subscribed to plant/truth, plant/* and everything of the run)
    receives its measurement only."""
    mon, a3, plant = net.open("monitor"), net.open("agent-3"), net.open("plant")
    got_mon = net.listen(mon, f"rse/{RUN}/plant/truth")
    got_a3 = net.listen(a3, f"rse/{RUN}/plant/truth", f"rse/{RUN}/plant/*", f"rse/{RUN}/**", f"rse/{RUN}/plant/loc/3")

    def send() -> None:
        plant.put(f"rse/{RUN}/plant/truth", b"x")
        plant.put(f"rse/{RUN}/plant/loc/3", b"y3")

    assert until(lambda: got_mon and (f"rse/{RUN}/plant/loc/3", b"y3") in got_a3, WAIT_S, send), (got_mon, got_a3)
    send()
    # the last word on the one key agent 3 may hear, after the truth: once it is heard, a truth
    # the router let through would have been heard too
    assert until(lambda: (f"rse/{RUN}/plant/loc/3", b"last") in got_a3, WAIT_S,
                  lambda: plant.put(f"rse/{RUN}/plant/loc/3", b"last"))
    assert {k for k, _ in got_mon} == {f"rse/{RUN}/plant/truth"}
    assert {k for k, _ in got_a3} == {f"rse/{RUN}/plant/loc/3"}, got_a3


def test_rse_run_secure_equals_the_simulator_and_records_the_router_in_the_team_file(certs, tmp_path):
    """`rse run --secure DIR --router` (a TLS router child, every process its client with its own
    certificate, access control on) in lockstep: the same run directory as rse simulate,
    every estimate equal; team.json names the router and the certificates."""
    from tests.agents.test_run_processes import _compare

    out = tmp_path / "run"
    ps = Procs()
    try:
        args = ["run", str(LKS), "--secure", str(certs), "--router", "--out", str(out), "--save-estimates", "--no-progress",
                "--deadline", "30"]
        for ov in SMALL:
            args += ["--set", ov]
        p = ps.start(rse_cmd(*args))
        so, se = p.communicate(timeout=600)  # a hang only
        assert p.returncode == 0, se
        assert "Traceback" not in se
    finally:
        ps.kill_all()
    team = json.loads((out / "team.json").read_text())
    assert team["transport"] == "client" and team["router"].startswith("tls/127.0.0.1:")
    assert team["connect"] == [team["router"]] and Path(team["secure"]) == certs.resolve()
    assert json.loads((out / "summary.json").read_text())["rejected"] == {}
    _compare(out, LKS, SMALL, tmp_path / "sim")


def test_rse_run_secure_sigterm_stops_every_process_and_the_router_within_2_s(certs, tmp_path):
    import psutil

    out = tmp_path / "run"
    ps = Procs()
    try:
        p = ps.start(rse_cmd("run", str(LKS), "--set", "run.dt=0.01", "--mode", "realtime", "--rate", "50",
                             "--secure", str(certs), "--router", "--out", str(out), "--no-progress", "--no-rerun"))
        assert until(lambda: _round(out) > 5, 300), p.poll() is None or p.communicate()
        team = json.loads((out / "team.json").read_text())
        assert "router" in team["pids"]
        children = [psutil.Process(pid) for pid in team["pids"].values()]
        t0 = time.monotonic()
        p.send_signal(signal.SIGTERM)
        so, se = p.communicate(timeout=30)
        stop_s = time.monotonic() - t0
        print(f"\nSIGTERM -> every process gone in {stop_s:.2f} s")
        # the feature (README: every command ends within 2 s of SIGTERM), not loosened. Measured
        # on two cores at load average 27 to 80: every child gone within 0.5 s, the launcher's
        # stop (SIGTERM, 1 s grace, SIGKILL, join) done within 0.94 s, but the launcher's own
        # exit took 1.95 to 8.1 s in all: the interpreter's finalisation (native code, after
        # the atexit handlers), not the grace
        assert stop_s < 2.0
        assert p.returncode == 130 and "Traceback" not in se
        gone, alive = psutil.wait_procs(children, timeout=0.5)
        assert not alive
    finally:
        ps.kill_all()


def _round(out: Path) -> int:
    try:
        return int(json.loads((out / "status.json").read_text())["round"])
    except (OSError, ValueError, KeyError):
        return -1


def test_secure_bad_input_is_one_line(certs, tmp_path):
    ps = Procs()
    try:
        cases = [
            (["run", str(LKS), "--secure", str(tmp_path / "none"), "--out", str(tmp_path / "r")], "no such directory"),
            (["agent", "--id", "9", str(LKS), "--run-id", "x", "--client", "--connect", "tcp/127.0.0.1:1",
              "--secure", str(certs)], "missing agent-9.pem, agent-9.key"),
            (["plant", str(LKS), "--run-id", "x", "--secure", str(certs)], "--secure needs --connect"),
            (["plant", str(LKS), "--run-id", "x", "--client", "--connect", "udp/127.0.0.1:1", "--secure", str(certs)],
             "every endpoint is tls/"),
            (["monitor", str(LKS), "--run-id", "x", "--out", str(tmp_path / "m"), "--client", "--connect",
              "tcp/127.0.0.1:1", "--secure", str(certs), "--identity", "root"], "invalid identity"),
            (["run", str(LKS), "--router", "--connect", "tcp/127.0.0.1:1"], "give one of them"),
        ]
        for args, words in cases:
            p = ps.start(rse_cmd(*args))
            so, se = p.communicate(timeout=30)
            assert p.returncode == 2, (args, se)
            assert words in se and "Traceback" not in se, (args, se)
    finally:
        ps.kill_all()
