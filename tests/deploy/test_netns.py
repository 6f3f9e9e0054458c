"""A team across real network hosts: Linux network namespaces on a bridge (tests/deploy/netns.py).

Host 0 runs ``rse router``, ``rse plant`` and ``rse monitor``; hosts 1, 2 and 3 run the
agents of ``lee_kim_shim.toml`` (agents 1 and 2; 3; 4 and 5: a ring 1-2-3-4-5-1 whose
agent 1 has its sensor attacked from t = 10 s); every process is a Zenoh client of the
router at ``tcp/10.A.B.1:7447``, started with ``ip netns exec HOST rse ...``.

1. lockstep across the hosts equals ``rse simulate`` (every estimate within 1e-12);
2. realtime at the calibrated rate (100 Hz on a quiet machine), host 2's cable (agent 3) pulled for 3 s under attack (t = 13 s):
   the others keep running, agent 3 comes back by itself, each agent within ``BOUND_END``
   over [22, 24] (the attacked agent 1 within the scenario's 0.25, the others tighter);
3. realtime, host 3 (agents 4 and 5) partitioned from the router's host for 3 s by bridge
   port isolation (every link stays up): the same.

As in the kill/restart test (tests/agents/test_run_processes.py) the bounds are checked
before the fault (0.01 at t = 10) and after healing (0.25, 6 s after), not during it:
cutting agents off a team under attack raises the others' errors for a while (the
attacked agent 1 reached 0.237 to 0.246 with agent 3 cut and 0.284 to 0.293 with agents 4
and 5 cut, against 0.2165 without a fault); the test prints those peaks. An agent back
from the cut steps once over the rounds it missed: open loop, each step coupling in only
the estimates stamped within max_age rounds of it (estimation/lee_kim_shim.py). Before, it held its last
measurement and coupled in its neighbours' fresh estimates over the whole 3.4 s gap, came
back up to 0.6 off, and agent 1's peak and its error over [22, 24] depended on which
message came first (peaks 0.28 to 0.43; over the window 0.217 to 0.254, once over the
bound).

Accuracy in realtime needs a machine that keeps the rate: a measurement or an estimate a
process cannot take in time is dropped for it alone, so on a loaded machine agents skip
rounds and their errors grow (load average 60 on two cores: 0.19 at t = 10, agent 1 at
0.81; see ``KEPT_UP`` for a machine with two busy processes). The realtime cases therefore run at the rate this machine
keeps: the ``rate`` fixture calibrates it first (tests/realtime.py: a short probe of the
team from 100 Hz down, not below ``RATE_FLOOR``); scenario time stays ``DT`` per round, so a
lower rate only stretches the run in wall time. Each case measures the share of rounds
every agent reported before the fault and over the window; when the load changed since the
calibration and that share is below ``KEPT_UP``, the case runs again at a lower rate (twice at
most), and asserts its accuracy bounds on the last run (the fault-tolerance checks, and
``BOUND_LOADED`` for every agent over the window, hold on each run).

Needs root (skipped otherwise, or when ``ip netns add`` fails). Each case is bounded
(``CASE_S``, only a hang reaches it) and kills every process it started and deletes its
namespaces on every path.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import pytest

from agents.api import load_experiment
from agents.simulate import simulate
from tests.conftest import ROOT, SCENARIOS
from tests.deploy.conftest import child_env, rse_cmd
from tests.deploy.netns import Net, close_all, reap_stale, unavailable

pytestmark = pytest.mark.multiprocess

LKS = SCENARIOS / "lee_kim_shim.toml"
HOSTS = {1: (1, 2), 2: (3,), 3: (4, 5)}  # agent hosts -> their agents; host 0: router, plant, monitor
PORT = 7447
CASE_S = 240.0  # wall-time budget of one case (a 24 s realtime run takes 30 to 45 s on a loaded machine)
DT = 0.01
RATE = 100.0  # realtime: scenario time = wall time (the rate tried first; see the rate fixture)
RATE_FLOOR = 40.0  # the lowest rate a case runs at (a 24 s scenario: 60 s of wall time)
# realtime cases: 24 s of scenario; the attack starts at t = 10 and its transient is over by
# t = 13 (the simulator's worst error from t = 13 on is 0.2165 <= 0.25); the fault starts
# at t = 13 and lasts 3 s of wall time; the bounds are checked 6 s after it, over [22, 24]
RT = ("run.dt=0.01", "run.duration=24", "output.window=[22.0, 24.0]")
FAULT_AT, FAULT_S, WINDOW = 13.0, 3.0, (22.0, 24.0)
BOUND_T10, BOUND_ATTACK = 0.01, 0.25  # the scenario's [[expect]] bounds
# per agent over [22, 24]: about ten times what a realtime run reaches, the scenario's bound
# where that is looser. rse simulate gives 0.216, 5.7e-6, 4.8e-9, 0.0721, 0.144; realtime
# runs with a fault measured 0.217 to 0.224 (agent 1), 0.0016 to 0.0084, 0.0029 to 0.021,
# 0.078 to 0.092 and 0.153 to 0.173 (agents 2 to 5, on a loaded machine); with the gap
# stepped open loop, 12 runs on a quiet machine: agent 1 at 0.216 to 0.219
BOUND_END = {1: BOUND_ATTACK, 2: 0.05, 3: 0.1, 4: BOUND_ATTACK, 5: BOUND_ATTACK}
# the share of the rounds every agent should report before the fault and over the window: below
# it the case runs again at a lower rate. The attacked agent 1 leans on its neighbours'
# estimates: while the steps of skipped rounds coupled in only estimates stamped up to them,
# its error over [22, 24] grew with the share skipped (86 to 94% kept: 0.250 to 0.253, at the
# scenario's bound; 79 to 80%: 0.272 to 0.281). Each step of a gap now couples in the estimate
# stamped nearest to it (estimation.base.held): a CI run beside 2 busy processes kept 87.5%,
# 91.0% and 96.7% of the rounds at 100, 70 and 51 Hz and agent 1 stayed at 0.217 each time.
# The accuracy bounds are asserted on the last run, whatever share it kept
KEPT_UP = 0.97
# the bound over [22, 24] asserted also when the machine did not keep up (see _fault_case)
BOUND_LOADED = 1.5

WATCH = """
import os, sys, time
from transport.codec import Schema, decode
from transport.keys import Keys
from transport.zenoh_session import SessionOptions, close_session, open_session
ep, run, path = sys.argv[1:4]
schema, last = Schema({"truth": {"x": (None,)}}), [-1]
def on(sample):
    try:
        last[0] = max(last[0], decode(sample.payload.to_bytes(), schema=schema).stamp)
    except Exception:
        pass
s = open_session(SessionOptions.client([ep]))
try:
    s.declare_subscriber(Keys(run).plant_truth(), on)
    while True:
        with open(path + ".tmp", "w") as f:
            f.write(str(last[0]))
        os.replace(path + ".tmp", path)
        time.sleep(0.02)
finally:
    close_session(s)
"""


@pytest.fixture(scope="module", autouse=True)
def _close_networks_at_the_end():
    yield
    close_all()  # whatever a failed case left open (netns.py also does it at exit)


@pytest.fixture
def net():
    why = unavailable()
    if why:
        pytest.skip(f"network namespaces unavailable: {why}")
    reap_stale()
    n = Net(1 + len(HOSTS))
    try:
        n.up()
        yield n
    finally:
        n.close()
        assert not n.exists(), "namespaces left behind"


class Team:
    """Router, plant and monitor on host 0, the agents on their hosts; every process a
    client of the router. Logs in ``out/../logs``; ``self.end`` bounds every wait."""

    def __init__(self, net: Net, out: Path, overrides: tuple[str, ...], run_args: tuple[str, ...], run_id: str,
                 save_estimates: bool = False, watch: bool = False) -> None:
        self.net, self.out, self.run_id = net, out, run_id
        self.end = time.monotonic() + CASE_S
        self.logs = out.parent / "logs"
        self.logs.mkdir(parents=True, exist_ok=True)
        self.ep = f"tcp/{net.addr(0)}:{PORT}"
        self.round_file = self.logs / "round"
        self.procs: dict[str, object] = {}
        sets = [a for ov in overrides for a in ("--set", ov)]
        common = [*sets, "--run-id", run_id, "--client", "--connect", self.ep, *run_args]
        self.t0 = time.monotonic()
        self._start(0, "router", rse_cmd("router", "--listen", self.ep))
        self.router_up_s = net.wait_tcp(1, net.addr(0), PORT, self.left())  # also: host 1 reaches host 0
        if watch:
            self._start(0, "watch", [sys.executable, "-c", WATCH, self.ep, run_id, str(self.round_file)])
        self._start(0, "monitor", rse_cmd("monitor", str(LKS), *common, "--out", str(out),
                                          *(["--save-estimates"] if save_estimates else [])))
        self._start(0, "plant", rse_cmd("plant", str(LKS), *common))
        for h, ids in HOSTS.items():
            for a in ids:
                self._start(h, f"agent {a}", rse_cmd("agent", "--id", str(a), str(LKS), *common))

    def left(self) -> float:
        return max(0.5, self.end - time.monotonic())

    def _start(self, host: int, name: str, args: list[str]) -> None:
        f = open(self.logs / f"{name.replace(' ', '-')}.log", "w")
        try:
            self.procs[name] = self.net.start(host, args, cwd=ROOT, env=child_env(), stdout=f, stderr=f)
        finally:
            f.close()  # the child holds its own descriptor

    def log(self, name: str) -> str:
        return (self.logs / f"{name.replace(' ', '-')}.log").read_text(errors="replace")

    def round(self) -> int:
        try:
            return int(self.round_file.read_text())
        except (OSError, ValueError):
            return -1

    def wait_round(self, k: int) -> float:
        """Wait until the plant published round ``k``; returns time.monotonic()."""
        while time.monotonic() < self.end:
            if self.round() >= k:
                return time.monotonic()
            for name in ("plant", "monitor"):
                assert self.procs[name].poll() is None, f"{name} exited early: {self.log(name)}"
            time.sleep(0.01)
        raise AssertionError(f"round {k} not reached within the case's {CASE_S:g} s (at {self.round()})")

    def finish(self) -> dict[str, int]:
        """Wait for plant, monitor and agents to exit; their exit statuses."""
        codes = {}
        for name, p in self.procs.items():
            if name in ("router", "watch"):
                continue
            try:
                codes[name] = p.wait(timeout=self.left())
            except subprocess.TimeoutExpired:
                raise AssertionError(f"{name} did not exit within the case's {CASE_S:g} s: {self.log(name)[-2000:]}") from None
        for name, code in codes.items():
            assert code == 0, f"{name}: exit status {code}: {self.log(name)[-2000:]}"
            assert "Traceback" not in self.log(name), self.log(name)
        self.wall_s = time.monotonic() - self.t0
        for name in ("watch", "router"):  # the host's port is free for another team
            p = self.procs.get(name)
            if p is not None and p.poll() is None:
                p.terminate()
                p.wait(timeout=5)
        return codes


def _errors(out: Path) -> tuple[np.ndarray, np.ndarray]:
    """Rounds x agents (ids 1..5) infinity-norm errors of the state from metrics.parquet
    (NaN where the monitor got no estimate), and the times."""
    m = pq.read_table(out / "metrics.parquet").to_pydict()
    k, agent, e = np.array(m["k"]), np.array(m["agent"]), np.array(m["error_inf"], dtype=float)
    x = np.array(m["block"]) == "x"
    K = int(k.max()) + 1
    E = np.full((K, 5), np.nan)
    E[k[x], agent[x] - 1] = e[x]
    return E, np.arange(K) * DT


def _check_run(team: Team, faulty: tuple[int, ...], k_down: int, k_up: int) -> dict:
    """The checks both fault cases share; returns the measured figures.

    Every process exited 0 (:meth:`Team.finish`); everyone within the scenario's first
    bound (0.01) at t = 10, before the fault; the agents that kept their links reporting
    during the fault (the team does not stall: when measurements and estimates were
    published with congestion control BLOCK, the router held everyone up while the cut
    agent could not take its messages, every agent missed about 3 s of rounds and the
    errors reached 0.88 after the cut, 0.2504 over [22, 24]); the faulty agents silent
    while cut off, back after it, and no leave (a 3 s outage is shorter than Zenoh's 10 s
    lease). Accuracy (checked by :func:`_fault_case` when the machine kept up): everyone
    within 0.01 at t = 10, each agent within ``BOUND_END`` over [22, 24], 6 s after healing,
    and the monitor's [[expect]] results all ok.
    """
    E, t = _errors(team.out)
    summary = json.loads((team.out / "summary.json").read_text())
    fa = [a - 1 for a in faulty]
    oi = [a - 1 for a in range(1, 6) if a not in faulty]
    i10, i_win = int(round(10.0 / DT)), int(round(WINDOW[0] / DT))
    # how well the machine kept the rate: the share of rounds each agent reported before the
    # fault and over the window (an agent that falls behind misses measurements and skips
    # those rounds)
    win = t >= WINDOW[0] - 1e-9
    kept_up = float(min(np.isfinite(E[:k_down]).mean(axis=0).min(), np.isfinite(E[win]).mean(axis=0).min()))
    during = E[k_down:k_up + 1][:, oi]
    present = float(np.isfinite(during).mean())
    # the team does not stall: the fault costs the others at most 10 points of their rounds
    assert present >= kept_up - 0.1, f"the others reported only {present:.0%} of their rounds during the fault"
    others_peak = np.nanmax(E[k_down:i_win][:, oi], axis=0)  # reported, not bounded (see the module docstring)
    cut = E[k_down + 50:k_up][:, fa]  # 0.5 s for the messages already in flight
    # silent while cut off: only what the links held when they were cut can come through,
    # late (at load average 32, agent 5 reported one round of 300 inside the outage: a
    # measurement queued before the cut, taken after the healing while the loaded monitor was
    # still that far behind); a team the cut did not cut reports nearly every round
    through = np.isfinite(cut).mean(axis=0)
    assert (through <= 0.05).all(), f"agents {faulty} reported {np.round(through, 3)} of the rounds while cut off"
    back = {}
    for a in faulty:
        rows = np.flatnonzero(np.isfinite(E[k_up:, a - 1]))
        assert rows.size, f"agent {a} never came back"
        back[a] = round(float(t[k_up + rows[0]]), 2)
    worst_end = np.nanmax(E[win], axis=0)
    # the team runs after healing: a stalled team reports next to nothing over the window. The
    # share reported follows the machine's load (quiet: 98 to 100%; load average 27: 33 to 40%,
    # before the fault as after), so it is compared with the share before the fault
    before = float(np.isfinite(E[:k_down]).mean())
    end_share = float(np.isfinite(E[win]).mean())
    assert end_share >= 0.25 * before, f"only {end_share:.0%} of the rows over the window (before the fault {before:.0%})"
    # a 3 s outage is shorter than Zenoh's 10 s lease: the sessions survive, nobody leaves
    # before the end of the run (the monitor can still be collecting the final counters when
    # an agent that is done exits: that leave comes after the plant's stop)
    members = [(m["id"], m["event"]) for m in summary["membership"]
               if m["role"] == "agent" and m["id"] in faulty and not m["after_stop"]]
    assert sorted(members) == [(a, "join") for a in faulty], members
    fig = {"back_at": back, "others_peak_fault_to_window": dict(zip([a + 1 for a in oi], np.round(others_peak, 4).tolist())),
           "at_10": [float(f"{v:.3g}") for v in E[i10]], "worst_end": [float(f"{v:.3g}") for v in worst_end],
           "present_during": round(present, 4), "present_before_and_end": round(kept_up, 4)}
    fig["expectations_ok"] = all(e["ok"] for e in summary["expectations"])
    return fig


@pytest.fixture(scope="module")
def rate() -> float:
    """The realtime rate this machine keeps for the team: a probe of lee_kim_shim.toml's
    team (a router, clients on loopback) from 100 Hz down until every agent ran KEPT_UP of its
    rounds (tests/realtime.py)."""
    from tests.realtime import calibrate

    r, probes = calibrate(LKS, start=RATE, floor=RATE_FLOOR, share=KEPT_UP, extra=("--router", "--set", "run.duration=4"))
    print(f"\nrealtime rate: {r:g} Hz (probes: rate, share of rounds the slowest agent ran: {probes})")
    return r


def _fault_case(net: Net, tmp_path: Path, name: str, cut: Any, heal: Any, faulty: tuple[int, ...], rate: float) -> dict:
    """The fault case at ``rate``; again at a lower rate (twice at most, not below
    ``RATE_FLOOR``) while the machine did not keep it (its load changed since the
    calibration), and the accuracy asserted then."""
    fig = _fault_run(net, tmp_path / "first", name, cut, heal, faulty, rate)
    for again in ("again", "again-2"):
        if fig["present_before_and_end"] >= KEPT_UP or rate <= RATE_FLOOR:
            break
        lower = max(RATE_FLOOR, round(rate * fig["present_before_and_end"] * 0.8, 1))
        print(f"{name}: the machine did not keep {rate:g} Hz ({fig['present_before_and_end']:.1%} of the rounds); "
              f"again at {lower:g} Hz")
        fig = _fault_run(net, tmp_path / again, name, cut, heal, faulty, lower)
        rate = lower
    kept = f"at {rate:g} Hz, {fig['present_before_and_end']:.1%} of the rounds kept"
    assert np.nanmax(fig["at_10"]) <= BOUND_T10, (fig["at_10"], kept)
    assert all(fig["worst_end"][a - 1] <= BOUND_END[a] for a in range(1, 6)), (fig["worst_end"], BOUND_END, kept)
    assert fig["expectations_ok"]
    return fig


def _fault_run(net: Net, tmp_path: Path, name: str, cut: Any, heal: Any, faulty: tuple[int, ...], rate: float) -> dict:
    team = Team(net, tmp_path / "run", RT, ("--mode", "realtime", "--rate", f"{rate:g}"), run_id=f"netns-{name}",
                watch=True)
    k_down = int(round(FAULT_AT / DT))
    team.wait_round(k_down)
    k_down = team.round()
    t_down = cut()
    time.sleep(FAULT_S)
    t_up = heal()
    k_up = team.round()
    team.finish()
    fig = _check_run(team, faulty, k_down, k_up)
    fig.update(rate=rate, outage_s=round(t_up - t_down, 2), k_down=k_down, k_up=k_up, wall_s=round(team.wall_s, 1),
               back_after_s={a: round(v - k_up * DT, 2) for a, v in fig["back_at"].items()})
    print(f"\n{name}: {fig}")
    # the faulty agents back by themselves soon after the healing. TCP resends what the cut
    # lost with a doubling timeout (about 0.2, 0.6, 1.4, 3.0, 6.2 s after the loss), so a
    # link healed just after a resend waits for the next one: up to about the outage plus one
    # timeout (measured: 0.3 to 0.5 s on a quiet machine, 4.15 s after a 3.13 s outage at load
    # average 27); the bound adds 3 s to the outage for a loaded machine's longer timeouts
    assert max(fig["back_after_s"].values()) <= fig["outage_s"] + 3.0, fig["back_after_s"]
    # whatever the load: no agent far off (an overloaded machine's worst was 0.81, agent 1 at
    # load 60; an unattacked agent 1,000 times less accurate than today is at 1.6 or more)
    assert max(fig["worst_end"]) <= BOUND_LOADED, (fig["worst_end"], BOUND_LOADED)
    return fig


def test_lockstep_across_hosts_equals_the_simulator(net, tmp_path):
    """Lockstep across the four hosts: every estimate equals rse simulate's within 1e-12
    (relative to the size of the state), the true state and the link counters too."""
    overrides = ("run.dt=0.01", "run.duration=12", "output.window=[8.0, 12.0]", "expect.1.max=1.0")
    team = Team(net, tmp_path / "run", overrides, ("--deadline", "30"), run_id="netns-lockstep", save_estimates=True)
    team.finish()
    exp, _ = load_experiment(LKS, overrides, None)
    ref = simulate(exp, keep_trajectories=True)
    est = np.load(team.out / "estimates.npy")
    assert est.shape == ref.estimates.shape == (1201, 5, 6)
    scale = np.maximum(1.0, np.abs(ref.truth).max(axis=1))[:, None, None]
    diff = float(np.max(np.abs(est - ref.estimates) / scale))
    assert diff <= 1e-12, diff
    np.testing.assert_array_equal(np.load(team.out / "truth.npy"), ref.truth)
    # the monitor's error of every agent in every round: the simulator's (the monitor role is
    # checked too, not only the estimates it receives)
    E, _ = _errors(team.out)
    x = ref.monitor.block_names.index("x")
    np.testing.assert_allclose(E, ref.monitor.metric("error_inf")[:E.shape[0], :, x], rtol=1e-9, atol=1e-12)
    summary = json.loads((team.out / "summary.json").read_text())
    for key, c in ref.links.items():
        got = summary["links"][key]
        assert {k: got[k] for k in ("sent", "delivered", "dropped", "late")} == \
            {k: c[k] for k in ("sent", "delivered", "dropped", "late")}, key
    assert summary["performance"]["deadline_misses"] == 0
    print(f"\nlockstep across hosts: max relative difference {diff:.3g}, {summary['performance']['rounds_per_s']:.0f} "
          f"rounds/s, wall {team.wall_s:.1f} s (router up in {team.router_up_s:.2f} s)")


def test_a_pulled_cable_for_3_s(net, tmp_path, rate):
    """Realtime at the calibrated rate; host 2 (agent 3) loses its link at t = 13 s for 3 s of wall
    time. The others keep running; agent 3 is silent while cut off and comes back by
    itself (its Zenoh session outlives the outage: no leave, no restart); everyone within
    0.01 at t = 10 and within 0.25 over [22, 24]."""

    def cut() -> float:
        t = net.link(2, up=False)
        assert not net.link_is_up(2)
        return t

    _fault_case(net, tmp_path, "cable", cut, lambda: net.link(2, up=True), (3,), rate)


def test_a_partition_of_two_agents_for_3_s(net, tmp_path, rate):
    """Realtime at the calibrated rate; bridge port isolation cuts host 3 (agents 4 and 5) off the
    router's host 0 at t = 13 s for 3 s, every link staying up. The run survives (every
    process exits 0), agents 1 to 3 keep running, agents 4 and 5 come back by themselves,
    everyone within 0.01 at t = 10 and within 0.25 over [22, 24]."""
    _fault_case(net, tmp_path, "partition", lambda: net.isolate([0, 3], on=True),
                lambda: net.isolate([0, 3], on=False), (4, 5), rate)
