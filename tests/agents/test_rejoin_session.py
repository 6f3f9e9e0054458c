"""A process that rejoined a running team and does not hear a peer opens a new session
(Bus.reconnect): an agent that gets nothing from the plant, a monitor that gets no report
from a live agent. A process of a team that assembles does not."""

import asyncio
import types

import numpy as np

import agents.net.monitor as monitor_mod
import agents.net.rejoin as rejoin_mod
import agents.net.schedule as schedule_mod
from agents.api import load_experiment
from agents.net.agent import AgentProcess, run_agent_slice
from agents.net.monitor import MonitorProcess
from agents.net.roles import RunConfig
from agents.net.slices import agent_slice
from tests.conftest import SCENARIOS
from transport.keys import Keys
from transport.zenoh_bus import InMemoryBus, InMemoryHub


class CountingBus(InMemoryBus):
    def __init__(self, hub):
        super().__init__(hub)
        self.reconnected = 0

    async def _reconnect(self) -> bool:
        self.reconnected += 1
        await asyncio.sleep(0.01)  # a session opens on a worker thread
        return True


async def _agent_among_tokens(rejoin: bool, seconds: float, hosted: int = 1) -> int:
    """The first ``hosted`` agents of lee_kim_shim, on one bus, for ``seconds``, every
    other process's token present and nothing published on their measurement keys;
    returns how often the bus reconnected."""
    exp, _ = load_experiment(SCENARIOS / "lee_kim_shim.toml", ("run.dt=0.01",), None)
    hub, keys = InMemoryHub(), Keys("r")
    others = hub.bus()
    others.announce(keys.alive("plant", 0))
    others.announce(keys.alive("monitor", 0))
    for aid in exp.agent_ids[hosted:]:
        others.announce(keys.alive("agent", aid))
    bus = CountingBus(hub)
    cfg = RunConfig(startup_timeout=60.0)
    try:
        await asyncio.wait_for(asyncio.gather(*(run_agent_slice(agent_slice(exp, aid), bus, keys, cfg, rejoin=rejoin)
                                                for aid in exp.agent_ids[:hosted])), seconds)
    except TimeoutError:
        pass
    return bus.reconnected


def test_a_rejoining_agent_that_hears_no_plant_reconnects(monkeypatch):
    monkeypatch.setattr(schedule_mod, "UNHEARD_S", 0.3)
    monkeypatch.setattr(rejoin_mod, "UNHEARD_S", 0.3)
    n = asyncio.run(_agent_among_tokens(rejoin=True, seconds=2.5))
    assert 2 <= n <= rejoin_mod.RECONNECTS  # every 0.3 s after asking to join, at most RECONNECTS times


def test_agents_that_share_a_process_share_its_reconnects(monkeypatch):
    """Three rejoining agents on one session: a reconnect asked for by one while another
    runs opens no second session, and each waits UNHEARD_S after the last one, so the
    process reconnects as often as a process of one agent (not three times as often)."""
    monkeypatch.setattr(schedule_mod, "UNHEARD_S", 0.3)
    monkeypatch.setattr(rejoin_mod, "UNHEARD_S", 0.3)
    n = asyncio.run(_agent_among_tokens(rejoin=True, seconds=1.2, hosted=3))
    assert 2 <= n <= 4  # at 0.3 s after asking to join, then every 0.3 s or so: not 3 per period


def test_an_agent_waits_after_its_process_reconnected():
    """Another agent of the process reconnected 1 s ago: this one, which asked to join 10 s
    ago, waits UNHEARD_S from that reconnect, not from its own request."""
    now = rejoin_mod.time.monotonic()
    a = types.SimpleNamespace(rejoin=True, running_team=False, stop=None, _first_ready=now - 10.0, reconnects=0,
                              alive={("plant", 0)}, bus=types.SimpleNamespace(reconnected_at=now - 1.0))
    assert not AgentProcess._plant_unheard(a)
    a.bus.reconnected_at = now - rejoin_mod.UNHEARD_S - 1.0
    assert AgentProcess._plant_unheard(a)


def test_an_agent_of_an_assembling_team_waits(monkeypatch):
    monkeypatch.setattr(schedule_mod, "UNHEARD_S", 0.3)
    monkeypatch.setattr(rejoin_mod, "UNHEARD_S", 0.3)
    assert asyncio.run(_agent_among_tokens(rejoin=False, seconds=1.5)) == 0


async def _member_whose_measurements_stop(mode: str, rounds: int, seconds: float) -> int:
    """Agent 1 of lee_kim_shim, a member of a running team: a stand-in plant publishes its
    measurement every 10 ms for ``rounds`` rounds, then nothing more (its token stays);
    returns how often agent 1's bus reconnected within ``seconds``."""
    from agents.net.wire import _msg
    from transport.codec import PLANT_ID

    exp, _ = load_experiment(SCENARIOS / "lee_kim_shim.toml", ("run.dt=0.01",), None)
    hub, keys = InMemoryHub(), Keys("r")
    plant = hub.bus()
    plant.announce(keys.alive("plant", 0))
    plant.announce(keys.alive("monitor", 0))
    for aid in exp.agent_ids[1:]:
        plant.announce(keys.alive("agent", aid))
    bus = CountingBus(hub)
    task = asyncio.ensure_future(run_agent_slice(agent_slice(exp, 1), bus, keys, RunConfig(mode=mode, rate=100.0 if mode == "realtime" else None,
                                                                                      startup_timeout=60.0)))
    try:
        for k in range(rounds):
            plant.publish(keys.plant_loc(1), _msg("meas", PLANT_ID, k, {"y": np.zeros(0), "wait": np.zeros((0, 2))},
                                                  meta={"member": True, "nomeas": True}))
            await asyncio.sleep(0.01)
        await asyncio.sleep(seconds)
        assert not task.done() or task.exception() is None
    finally:
        task.cancel()
    return bus.reconnected


def test_a_realtime_member_whose_measurements_stop_reconnects(monkeypatch):
    """A member of a realtime team that gets no measurement for twice UNHEARD_S though the
    plant's token is there opens a new session (a link that dropped every measurement
    stays that way); while measurements come, it does not."""
    monkeypatch.setattr(schedule_mod, "UNHEARD_S", 0.3)
    monkeypatch.setattr(rejoin_mod, "UNHEARD_S", 0.3)
    assert asyncio.run(_member_whose_measurements_stop("realtime", 100, 0.0)) == 0  # 1 s of rounds: none
    n = asyncio.run(_member_whose_measurements_stop("realtime", 20, 2.0))
    assert 2 <= n <= rejoin_mod.RECONNECTS  # 0.6 s (twice UNHEARD_S) after the last one, then every 0.6 s or so


def test_a_member_of_a_slow_realtime_team_waits_ten_rounds():
    """At 0.2 rounds/s a measurement comes every 5 s: no reconnect before 10 rounds (50 s)."""
    now = rejoin_mod.time.monotonic()
    a = types.SimpleNamespace(member=True, cfg=RunConfig(mode="realtime", rate=0.2), stop=None, reconnects=0,
                              alive={("plant", 0)}, _last_loc=now - 20.0, bus=types.SimpleNamespace(reconnected_at=0.0))
    assert not AgentProcess._measurements_stopped(a)
    a.cfg = RunConfig(mode="realtime", rate=100.0)
    assert AgentProcess._measurements_stopped(a)  # at 100 rounds/s, 20 s is a stopped link
    a.cfg, a._last_loc = RunConfig(mode="realtime", rate=0.2), now - 51.0
    assert AgentProcess._measurements_stopped(a)


def test_a_lockstep_member_waits_for_its_measurements(monkeypatch):
    """Lockstep: the plant sends the next measurement once the round is done by everyone,
    so a long wait is no broken link."""
    monkeypatch.setattr(schedule_mod, "UNHEARD_S", 0.3)
    monkeypatch.setattr(rejoin_mod, "UNHEARD_S", 0.3)
    assert asyncio.run(_member_whose_measurements_stop("lockstep", 20, 1.0)) == 0


def _monitor(present, *, synced=False, listening_for=10.0, reconnects=0):
    rounds = {k: types.SimpleNamespace(x=np.zeros(2), present=np.array(present)) for k in range(25)}
    m = types.SimpleNamespace(synced=synced, reconnects=reconnects, rounds=rounds,
                              _listening_since=monitor_mod.time.monotonic() - listening_for,
                              alive={("agent", 1), ("agent", 2), ("agent", 3), ("plant", 0)}, index={1: 0, 2: 1, 3: 2})
    m._reports_held = lambda: MonitorProcess._reports_held(m)
    return m


def test_a_rejoining_monitor_names_the_agents_it_does_not_hear():
    m = _monitor([1, 0, 1])
    assert MonitorProcess._reports_unheard(m) == [2]
    m = _monitor([1, 1, 1])
    assert MonitorProcess._reports_unheard(m) == []
    for kw in ({"synced": True}, {"listening_for": 1.0}, {"reconnects": monitor_mod.RECONNECTS}):
        m = _monitor([1, 0, 1], **kw)
        assert MonitorProcess._reports_unheard(m) == [], kw


def test_a_monitor_joining_a_running_team_listens_on_a_port_of_its_own():
    """Not on its endpoint in team.json (a restarted monitor there missed some agents'
    reports in at least 6 of 51 scripted rejoins, 2 of 80 on a port of its own); an agent keeps its
    endpoint (on a port of its own 5 of 20 restarted agents never heard the plant)."""
    from agents.net.launcher import session_for
    from transport.zenoh_session import any_port

    team = {"endpoints": {"plant": "tcp/127.0.0.1:7001", "monitor": "tcp/10.0.0.2:7002", "agent 1": "tcp/[::1]:7003"}}
    mon = session_for(team, "monitor")
    assert mon.listen == ("tcp/10.0.0.2:0",) and set(mon.connect) == {"tcp/127.0.0.1:7001", "tcp/[::1]:7003"}
    assert session_for(team, "agent 1").listen == ("tcp/[::1]:7003",)
    assert session_for(team, "agent 9").listen == ("tcp/127.0.0.1:0",)  # not in the file
    assert any_port("tcp/host.example:7447") == "tcp/host.example:0"
    assert any_port("tcp/[::1]:7447") == "tcp/[::1]:0"
