"""Several agents per process (``rse run --agents-per-process N``, ``rse agent --id 1-8``):
one Zenoh session per process, one asyncio task and node per agent, the same keys and
messages; lockstep results equal ``rse simulate``'s."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from agents.cli.net import parse_ids
from agents.net.child import group_label
from agents.net.slices import agent_slices, find_slices, read_slice, read_slices, write_slices
from agents.net.startup import agent_groups, peer_links
from estimation.errors import ScenarioError
from tests.agents.test_run_processes import LKS, MITRA, _cmd, _compare


def test_ids_groups_and_labels():
    assert parse_ids("3") == [3]
    assert parse_ids("1,2,3") == [1, 2, 3]
    assert parse_ids("1-4,9,2") == [1, 2, 3, 4, 9]
    for bad in ("", "a", "4-2", "1,,2", "-1"):
        with pytest.raises(ScenarioError):
            parse_ids(bad)
    assert agent_groups([1, 2, 3, 4, 5], 2) == [(1, 2), (3, 4), (5,)]
    assert agent_groups([1, 2, 3], 1) == [(1,), (2,), (3,)]
    assert group_label((1, 2, 3)) == "agents 1-3" and group_label((2, 5)) == "agents 2,5"
    assert group_label((7,)) == "agent 7"


@pytest.mark.skipif(not os.path.exists("/proc/self/comm"), reason="needs Linux's /proc/self/comm")
def test_a_role_process_is_named_after_its_role():
    """`ps` and `top` show the role: the main thread's name, at most 15 bytes."""
    code = ("from agents.net.child import _name_process, group_label; "
            "_name_process('rse ' + group_label([1, 2, 3, 4, 5, 6, 7, 8, 9, 10])); "
            "print(open('/proc/self/comm').read().strip())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == ("rse " + group_label(list(range(1, 11))))[:15], out


def test_links_follow_the_graph_and_the_packing(tmp_path):
    """Each process is linked to the processes its agents talk to, not to the whole team;
    a slice written to a file reads back the same."""
    from agents.api import load_experiment

    exp, _ = load_experiment(MITRA, ("run.rounds=5", "expect=[]"), None)
    slices = agent_slices(exp)
    links = peer_links(slices)
    assert links["plant"] == {"monitor", *(f"agent {a}" for a in exp.agent_ids)}
    near: dict[int, set[int]] = {}
    for s in slices:
        near[s.agent_id] = set(s.in_ids) | set(s.out_ids)
        if s.view is not None:  # the omniscient adversary also hears its receivers' in-neighbours
            assert set(s.view.needed) - near[s.agent_id]
            near[s.agent_id] |= set(s.view.needed) | {j for v in s.view.before.values() for j in v}
    for a in exp.agent_ids:  # a link goes both ways
        want = near[a] | {b for b in exp.agent_ids if a in near[b]}
        assert links[f"agent {a}"] == {"plant", "monitor"} | {f"agent {j}" for j in want}, a
    # not a full mesh: a regular agent of this graph hears 4 of its cell and 4 of another
    assert max(len(links[f"agent {s.agent_id}"]) for s in slices if s.view is None) <= 2 + 12 < exp.N + 1
    host = {a: group_label(g) for g in agent_groups(exp.agent_ids, 4) for a in g}
    packed = peer_links(slices, host)
    assert set(packed) == {"plant", "monitor", *host.values()}
    assert all(nm not in packed[nm] for nm in packed)
    paths = write_slices(tmp_path, slices)
    back = read_slice(paths[5])
    assert back.agent_id == 5 and back.in_ids == slices[4].in_ids and back.view.needed == slices[4].view.needed
    assert back.view.masks.keys() == slices[4].view.masks.keys()
    # one file per agent process: its agents share their design (one copy in the file)
    grouped = write_slices(tmp_path / "g", slices, agent_groups(exp.agent_ids, 8))
    assert grouped[1].name == "agents-1-8.pkl" and grouped[16].name == "agents-9-16.pkl"
    assert grouped[1].stat().st_size < 3 * paths[1].stat().st_size
    assert [p.agent_id for p in read_slices(grouped[9])] == list(range(9, 17))
    picked = read_slices(find_slices(tmp_path / "g", [3, 12]))
    assert [p.agent_id for p in picked] == [3, 12]
    assert find_slices(tmp_path / "g", [99]) is None
    (tmp_path / "bad.pkl").write_bytes(b"not a slice")
    with pytest.raises(ScenarioError, match="bad.pkl"):
        read_slice(tmp_path / "bad.pkl")


@pytest.mark.multiprocess
def test_packed_teams_equal_the_simulator(procs, tmp_path):
    """lee_kim_shim.toml with drops and delays, two agents per process (3 agent processes),
    and mitra_cells.toml with its omniscient adversary, four per process: both equal
    rse simulate."""
    lossy = ("run.dt=0.01", "run.duration=3", "output.window=[2.0, 3.0]", "expect=[]", "network.channel.drop_p=0.2",
             "network.channel.delay_max=2")
    mitra = ("run.rounds=120", "expect=[]")
    a, b = tmp_path / "a", tmp_path / "b"
    pa = procs.start(_cmd("run", str(LKS), *[x for ov in lossy for x in ("--set", ov)], "--agents-per-process", "2",
                          "--out", str(a), "--save-estimates", "--no-progress", "--deadline", "30"))
    pb = procs.start(_cmd("run", str(MITRA), *[x for ov in mitra for x in ("--set", ov)], "--agents-per-process", "4",
                          "--out", str(b), "--save-estimates", "--no-progress", "--deadline", "30"))
    for p in (pa, pb):
        so, se = p.communicate(timeout=600)  # only a hang reaches it
        assert p.returncode == 0, se
    _compare(a, LKS, lossy, tmp_path / "sim-a")
    _compare(b, MITRA, mitra, tmp_path / "sim-b")
    team = json.loads((b / "team.json").read_text())
    assert set(team["endpoints"]) == {"plant", "monitor", "agents 1-4", "agents 5-8", "agents 9-12", "agents 13-16"}
    assert len(json.loads((b / "summary.json").read_text())["processes"]) == 18  # every agent reports


@pytest.mark.slow
@pytest.mark.multiprocess
def test_a_64_agent_team_packed_equals_the_simulator(procs, tmp_path):
    """mitra_cells.toml with K = 16 cells (64 agents), 100 lockstep rounds, 8 agents per process."""
    ov = ("plant.params.K=16", "run.rounds=100", "expect=[]")
    out = tmp_path / "r"
    p = procs.start(_cmd("run", str(MITRA), *[x for o in ov for x in ("--set", o)], "--agents-per-process", "8",
                         "--out", str(out), "--save-estimates", "--no-progress", "--no-rerun", "--deadline", "30"))
    so, se = p.communicate(timeout=600)
    assert p.returncode == 0, se
    _compare_estimates(out, ov)


def _compare_estimates(out, ov):
    import numpy as np

    from agents.api import load_experiment
    from agents.simulate import simulate

    exp, _ = load_experiment(MITRA, ov, None)
    ref = simulate(exp, keep_trajectories=True)
    est = np.load(out / "estimates.npy")
    assert est.shape == ref.estimates.shape
    scale = np.maximum(1.0, np.abs(ref.truth).max(axis=1))[:, None, None]
    assert float(np.max(np.abs(est - ref.estimates) / scale)) <= 1e-12
