"""The networked roles over the in-memory bus: the same protocol as ``rse run`` without
processes. Lockstep equals the simulator; addressed payloads; bad bytes are counted."""

import asyncio
import json
from dataclasses import replace

import msgpack
import numpy as np
import pytest

from agents.api import load_experiment
from agents.net.roles import RunConfig, run_team_in_memory
from agents.simulate import simulate
from scenarios.common import ByzantineSpec
from tests.conftest import SCENARIOS
from transport.keys import Keys
from transport.zenoh_bus import InMemoryHub, key_matches

LKS = ("run.dt=0.01", "run.duration=12", "output.window=[8.0, 12.0]")


def _both(path, overrides, tweak=None):
    exp, _ = load_experiment(path, overrides, None)
    if tweak:
        exp = tweak(exp)
    ref = simulate(exp, keep_trajectories=True)
    exp, _ = load_experiment(path, overrides, None)
    if tweak:
        exp = tweak(exp)
    res = asyncio.run(asyncio.wait_for(run_team_in_memory(exp, RunConfig(save_estimates=True, deadline=30.0)), 600))
    return ref, res


def _rel(a, b, truth):
    scale = np.maximum(1.0, np.abs(truth).max(axis=1))[:, None, None]
    return float(np.max(np.abs(a - b) / scale))


def test_key_matching():
    assert key_matches("rse/r/agent/*/est", "rse/r/agent/3/est")
    assert not key_matches("rse/r/agent/*/est", "rse/r/agent/3/est/4")
    assert key_matches("rse/r/ctl/done/**", "rse/r/ctl/done/3")
    assert key_matches("rse/r/**", "rse/r/a/b/c")
    assert not key_matches("rse/r/**", "rse/q/a")


def test_lockstep_in_memory_equals_the_simulator():
    ref, res = _both(SCENARIOS / "lee_kim_shim.toml", LKS)
    assert not np.isnan(res.estimates).any()
    assert _rel(res.estimates, ref.estimates, ref.truth) <= 1e-12
    assert res.summary["links"] == ref.links
    assert res.summary["rejected"] == {}


def test_mobile_agents_and_drops_in_memory_equal_the_simulator():
    ov = ("attacks=[]", "expect=[]", "run.rounds=40")
    ref, res = _both(SCENARIOS / "mitra_cells.toml", ov)
    assert _rel(res.estimates, ref.estimates, ref.truth) <= 1e-12
    assert res.summary["links"] == ref.links
    assert any(c["dropped"] for c in ref.links.values())


def test_omniscient_cancellation_adversary_in_memory_equals_the_simulator():
    """mitra_cells.toml as it is: 300 rounds, drops with p = 0.32, agent 5 cancelling with
    the omniscient view (NetworkView) in a second phase of each round."""
    ref, res = _both(SCENARIOS / "mitra_cells.toml", ())
    assert not np.isnan(res.estimates).any()
    assert _rel(res.estimates, ref.estimates, ref.truth) <= 1e-12
    assert res.summary["links"] == ref.links
    assert res.summary["agents"]["5"]["regular"] is False


def test_addressed_payloads_of_a_byzantine_agent():
    def tweak(exp):
        return replace(exp, byzantine_specs={**exp.byzantine_specs, 1: ByzantineSpec(kind="equivocation", start=200, scale=0.3)},
                       byzantine=exp.byzantine | {1})

    ref, res = _both(SCENARIOS / "lee_kim_shim.toml", LKS, tweak)
    assert _rel(res.estimates, ref.estimates, ref.truth) <= 1e-12
    assert res.summary["agents"]["2"]["regular"] is False


def test_bad_bytes_are_dropped_and_counted_per_sender():
    exp, _ = load_experiment(SCENARIOS / "lee_kim_shim.toml", LKS, None)
    ref = simulate(exp, keep_trajectories=True)
    exp, _ = load_experiment(SCENARIOS / "lee_kim_shim.toml", LKS, None)
    hub = InMemoryHub()
    keys = Keys("mem")
    good = msgpack.packb({"v": 1, "kind": "est", "from": 2, "k": 3, "arr": {"x": [[6], b"\0" * 48]}})
    bad = [
        b"\xc1garbage",
        msgpack.packb({"v": 1, "kind": "est", "from": "2", "k": 3, "arr": {}}),
        msgpack.packb({"v": 1, "kind": "est", "from": 2, "k": 3, "arr": {"x": [[6], np.full(6, np.nan).tobytes()]}}),
        msgpack.packb({"v": 1, "kind": "est", "from": 2, "k": 3, "arr": {"x": [[7], b"\0" * 56]}}),
        b"\0" * (2 << 20),
    ]
    forged = good.replace(b"\xa4from\x02", b"\xa4from\x04")  # claims agent 4 on agent 2's key
    bad.append(forged)

    async def main():
        from agents.net import roles

        buses = [hub.bus() for _ in range(exp.N + 3)]
        cfg = RunConfig(save_estimates=True, deadline=30.0)
        mon = asyncio.ensure_future(roles.run_monitor(exp, buses[0], keys, cfg))
        agents = [asyncio.ensure_future(roles.run_agent(exp, a, buses[2 + i], keys, cfg)) for i, a in enumerate(exp.agent_ids)]
        plant = asyncio.ensure_future(roles.run_plant(exp, buses[1], keys, cfg))
        evil = buses[-1]
        for _ in range(20):
            await asyncio.sleep(0.02)
            for payload in bad:
                for key in (keys.est(2), keys.est(2, 1), keys.plant_loc(3), keys.plant_truth(), keys.ctl("done", 4),
                            keys.ctl("stats", 5), keys.ctl("ready", 1)):
                    if payload is forged and key == keys.ctl("done", 4):
                        # well formed there: agent 4's estimate on its own done key (a
                        # broadcast report); only access control keeps others off a key
                        continue
                    evil.publish(key, payload)
        await asyncio.gather(plant, *agents)
        out = await mon
        for b in buses:
            b.close()
        return out

    res = asyncio.run(asyncio.wait_for(main(), 600))
    rej = res.summary["rejected"]
    assert {"2", "plant", "4", "5", "1"} <= set(rej), rej
    assert rej["2"]["total"] > 0 and rej["2"].get("sender", 0) > 0 and rej["2"].get("size", 0) > 0
    assert _rel(res.estimates, ref.estimates, ref.truth) <= 1e-12
    assert res.summary["links"]["2->1"]["rejected"] > 0


def test_run_config_validation():
    with pytest.raises(ValueError, match="rate"):
        RunConfig(mode="realtime")
    with pytest.raises(ValueError, match="mode"):
        RunConfig(mode="fast")


def test_omniscient_adversary_among_agents_whose_done_report_carries_the_estimate():
    """lee_kim_shim.toml (the payload is the estimate: an honest agent's done report carries
    it, no separate estimate message) with agent 2 cancelling with the omniscient view: the
    view reads its receivers' other inputs from those done reports; equal to the simulator."""
    def tweak(exp):
        return replace(exp, byzantine_specs={**exp.byzantine_specs, 1: ByzantineSpec(kind="cancellation", start=100, seed=3, agent=2)},
                       byzantine=exp.byzantine | {1})

    ref, res = _both(SCENARIOS / "lee_kim_shim.toml", LKS, tweak)
    assert _rel(res.estimates, ref.estimates, ref.truth) <= 1e-12
    assert res.summary["links"] == ref.links
    assert res.summary["agents"]["2"]["regular"] is False


def test_omniscient_adversary_does_not_hear_its_own_addressed_messages(monkeypatch):
    """The adversary subscribes to its receivers' addressed messages by sender: none of its
    subscriptions matches its own addressed keys (a pattern did: one local delivery per
    message sent), and it still equals the simulator."""
    from transport.zenoh_bus import InMemoryBus

    subs: list[tuple[object, str]] = []
    plain = InMemoryBus.subscribe

    def recording(self, pattern, queue):
        subs.append((self, pattern))
        plain(self, pattern, queue)

    monkeypatch.setattr(InMemoryBus, "subscribe", recording)
    ref, res = _both(SCENARIOS / "mitra_cells.toml", ("run.rounds=40", "expect=[]"))
    assert _rel(res.estimates, ref.estimates, ref.truth) <= 1e-12
    exp, _ = load_experiment(SCENARIOS / "mitra_cells.toml", ("run.rounds=40", "expect=[]"), None)
    (b,) = exp.byzantine
    me, keys = exp.agent_ids[b], Keys("mem")
    mine = [p for bus, p in subs if any(q == keys.plant_loc(me) for bus2, q in subs if bus2 is bus)]
    assert mine, "the adversary's subscriptions were not recorded"
    outs = [exp.agent_ids[j] for j in exp.out_neighbours(b)]
    assert not [p for p in mine for j in outs if key_matches(p, keys.est(me, j))]
    others = [exp.agent_ids[i] for i in exp.in_neighbours(exp.out_neighbours(b)[0]) if i != b]
    assert any(key_matches(p, keys.est(s, outs[0])) for p in mine for s in others)


@pytest.mark.parametrize("scenario, merged", [("mitra_cells.toml", True), ("mitra_diffusion.toml", False)])
def test_an_lfre_agent_sends_its_estimate_once_when_the_payload_is_the_estimate(monkeypatch, scenario, merged):
    """LFRE's payload is its modal estimate z_hat, the estimate itself when the modal
    transform is the identity (mitra_cells.toml, a diagonal process): an honest agent's
    done report then carries it and no estimate message goes out. mitra_diffusion.toml
    (x_hat = V z_hat, V not the identity) sends both. Both equal the simulator."""
    from transport.zenoh_bus import InMemoryBus

    sent: list[str] = []
    plain = InMemoryBus.publish

    def recording(self, key, payload, *, droppable=False):
        sent.append(key)
        plain(self, key, payload, droppable=droppable)

    monkeypatch.setattr(InMemoryBus, "publish", recording)
    ov = ("attacks=[]", "expect=[]", "run.rounds=20")
    ref, res = _both(SCENARIOS / scenario, ov)
    assert _rel(res.estimates, ref.estimates, ref.truth) <= 1e-12
    assert res.summary["links"] == ref.links
    exp, _ = load_experiment(SCENARIOS / scenario, ov, None)
    per_agent = {aid: sum(k.endswith(f"/agent/{aid}/est") for k in sent) for aid in exp.agent_ids}
    done = {aid: sum(k.endswith(f"/ctl/done/{aid}") for k in sent) for aid in exp.agent_ids}
    assert set(done.values()) == {21}  # one report per round, rounds 0..20
    assert set(per_agent.values()) == ({0} if merged else {21}), per_agent


def test_a_restarted_monitor_that_never_rejoins_says_its_record_is_incomplete(tmp_path):
    """A monitor restarted into a running team that stops before it had one whole round
    (no agent's report reached it) records nothing and says so: the summary is incomplete,
    with the reason, not a complete record of the rounds before it."""
    from agents.net.monitor import MonitorProcess
    from agents.net.wire import _msg
    from estimation.errors import TransportError
    from transport.codec import PLANT_ID

    exp, _ = load_experiment(SCENARIOS / "lee_kim_shim.toml", LKS, None)
    hub, keys = InMemoryHub(), Keys("r")

    async def main():
        plant = hub.bus()
        plant.announce(keys.alive("plant", 0))
        mon = MonitorProcess(exp, hub.bus(), keys, RunConfig(deadline=0.2, linger=0.2), out_dir=tmp_path / "run",
                             resume=True)
        task = asyncio.create_task(mon.run())
        await asyncio.sleep(0.2)
        for k in range(5):  # the truth of some rounds, no agent's report
            plant.publish(keys.plant_truth(), _msg("truth", PLANT_ID, k, {"x": np.zeros(exp.n)}))
        plant.publish(keys.ctl("stop", PLANT_ID), _msg("ctl", PLANT_ID, 4, {}))
        return await asyncio.wait_for(task, 30)

    with pytest.raises(TransportError, match="did not rejoin the team before its last round 4"):
        asyncio.run(main())
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["complete"] is False
    assert summary["reason"].endswith("this monitor did not rejoin the team before its last round 4")
