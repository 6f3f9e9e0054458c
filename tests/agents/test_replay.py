"""The delivery record and its replay, in-process (agents.deliveries, agents.replay): the
simulator writes the record as `rse run` does, and the replay reproduces its estimates bit
for bit; a counterfactual estimator on the same deliveries equals the simulator's run of
that estimator; a torn record replays up to its last complete round; bad input is one line."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

import rse
from agents.deliveries import DIR, read_record, record_bytes
from agents.replay import replay
from agents.runs import load
from agents.simulate import simulate
from estimation.errors import RSEError, ScenarioError
from tests.conftest import SCENARIOS

LKS = SCENARIOS / "lee_kim_shim.toml"
MITRA = SCENARIOS / "mitra_cells.toml"
LKS_SHORT = {"run.duration": 3.0, "output.window": [2.0, 3.0], "expect": []}


def _recorded(scenario, tmp_path, **set_):
    exp = load(scenario, set=set_)
    res = simulate(exp, keep_trajectories=True, deliveries=tmp_path)
    return exp, res


def test_mitra_cells_replay_equals_the_simulator_bit_for_bit(tmp_path):
    """mitra_cells.toml: erasures p = 0.32 and agent 5 the omniscient cancelling adversary,
    whose sends (computed from the others' messages) are recorded and replayed as recorded.
    Every agent's every estimate equal, max difference 0.0."""
    exp, res = _recorded(MITRA, tmp_path, **{"run.rounds": 120, "expect": []})
    rec = read_record(tmp_path)
    assert sorted(rec) == exp.agent_ids and all(len(v) == 1 and len(v[0].k) == 121 for v in rec.values())
    byz_id = exp.agent_ids[next(iter(exp.byzantine))]
    assert len(rec[byz_id][0].sends) > 100  # what it addressed to each receiver
    # the erasures: some in-neighbour stamps are older than k - 1
    st = np.concatenate([inc.stamps[1:] - inc.k[1:, None] for v in rec.values() for inc in v])
    assert (st < -1).mean() > 0.1
    rep = replay(exp, rec)
    assert rep.complete and rep.last_round == 120
    assert np.array_equal(rep.estimates, res.estimates) and np.abs(rep.estimates - res.estimates).max() == 0.0


def test_lee_kim_shim_counterfactual_equals_the_simulated_linear_baseline(tmp_path):
    """The median solver recorded, the linear baseline replayed on its deliveries: equal, bit
    for bit, to the simulator's run of the linear baseline (the channel's fates do not depend
    on the estimator), and different from the median solver's estimates."""
    exp, res = _recorded(LKS, tmp_path, **LKS_SHORT)
    lin = load(LKS, set={**LKS_SHORT, "estimator.variant": "linear"})
    rep = replay(lin, read_record(tmp_path))
    want = simulate(lin, keep_trajectories=True, batched=False).estimates
    assert np.array_equal(rep.estimates, want)
    assert np.abs(rep.estimates - res.estimates).max() > 1e-3
    same = replay(exp, read_record(tmp_path))
    assert np.array_equal(same.estimates, res.estimates)


def test_bytes_per_agent_round(tmp_path):
    """LKS (one sensor and two in-neighbours per agent): 34 bytes of block per agent-round
    plus its 4-byte length (k, the measurement, two stamps)."""
    _recorded(LKS, tmp_path, **LKS_SHORT)
    total, rounds = record_bytes(tmp_path)
    assert rounds == 5 * 301
    print(f"\nbytes per agent-round: {total / rounds:.1f}")
    assert 30 <= total / rounds <= 48


def test_a_torn_record_replays_up_to_its_last_complete_round(tmp_path):
    """The writer of agent 2 killed in the middle of its round-200 block (the file cut
    there): the replay stops at round 199, the last every agent's record reached, and
    equals the simulator up to it."""
    exp, res = _recorded(LKS, tmp_path, **LKS_SHORT)
    path = tmp_path / DIR / "agent-0002-000.rec"
    data = path.read_bytes()
    inc = read_record(tmp_path)[2][0]
    # block offsets: walk the length prefixes to the start of round 200's block (header + 200 rounds)
    pos = 0
    for _ in range(1 + 200):
        pos += 4 + int.from_bytes(data[pos:pos + 4], "little")
    path.write_bytes(data[:pos + 9])  # its length and five bytes of its body
    torn = read_record(tmp_path)[2][0]
    assert torn.torn and len(torn.k) == 200 and len(inc.k) == 301
    rep = replay(exp, read_record(tmp_path), completed=False)
    assert not rep.complete and rep.last_round == 199 and "did not complete" in rep.reason
    assert np.array_equal(rep.estimates, res.estimates[:200])


def test_a_missing_payload_ends_the_replay_there(tmp_path):
    """A receiver's inbox names a message its sender's record lacks (the sender's file
    removed after round 50): the replay ends before the first round that needs it."""
    exp, _ = _recorded(LKS, tmp_path, **LKS_SHORT)
    rec = read_record(tmp_path)
    inc = rec[3][0]
    keep = inc.k <= 50
    inc.k, inc.stamps, inc.y = inc.k[keep], inc.stamps[keep], [y for y, m in zip(inc.y, keep) if m]
    rep = replay(exp, rec)  # a "completed" run whose agent 3 record stops at 50
    assert not rep.complete and rep.last_round == 51
    assert "holds agent 3's message stamped 51, which the record lacks" in rep.reason


def test_bad_input_is_one_line(tmp_path):
    with pytest.raises(RSEError, match="no delivery record"):
        read_record(tmp_path)
    (tmp_path / DIR).mkdir()
    body = msgpack.packb({"v": 99, "agent": 1, "in": []})
    (tmp_path / DIR / "agent-0001-000.rec").write_bytes(len(body).to_bytes(4, "little") + body)
    with pytest.raises(RSEError, match="not a delivery record of this version"):
        read_record(tmp_path)
    # a step block whose stamps do not match the header's in-neighbours
    head, step = msgpack.packb({"v": 1, "agent": 1, "in": [2, 5]}), msgpack.packb({"k": 0, "y": None, "s": b"\0" * 8})
    (tmp_path / DIR / "agent-0001-000.rec").write_bytes(b"".join(len(b).to_bytes(4, "little") + b for b in (head, step)))
    with pytest.raises(RSEError, match="agent-0001-000.rec: a malformed block"):
        read_record(tmp_path)
    with pytest.raises(ScenarioError, match="not a run directory"):
        rse.replay(tmp_path, out=tmp_path / "rep")


def test_rse_replay_of_a_directory_without_a_record_is_one_line_exit_2(tmp_path):
    import subprocess

    from tests.procs import child_env, rse_cmd

    exp = load(LKS, set=LKS_SHORT)
    rse.simulate(exp, out=tmp_path / "sim")  # a run directory, but no delivery record
    r = subprocess.run(rse_cmd("replay", str(tmp_path / "sim"), "--no-rerun"), capture_output=True, text=True,
                       timeout=120, env=child_env())
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [f"error: {tmp_path / 'sim'}: no delivery record (deliveries/ is missing "
                                             "or empty; was it written by `rse run`?)"]
