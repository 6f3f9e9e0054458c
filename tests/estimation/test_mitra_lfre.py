"""LFRE / SW-LFRE end to end on a small team, written as a plain loop (no simulator).

One cell of the ``cells`` plant (20 states, 6 unstable modes up to 1.2). Agents 0-3
patrol locations 0-4, agents 4-7 locations 5-9 (the unstable modes), agents 8-10 only
location 0. Graph: 0-3 <-> 4-7 all-to-all, 8-10 <-> 0-3. For the unstable modes the
MEDAG has levels {4..7}, {0..3}, {8..10}. Agent 5, a source of the unstable modes, is
Byzantine and sends huge values.
"""

import numpy as np
import pytest

from estimation.base import Estimator, Received
from estimation.cells import cells
from estimation.errors import DesignError
from estimation.lfre import LFRE, SWLFRE, design, make_estimator
from estimation.patrols import Patrol

ADV = 5
ROUNDS = 300


def team(*, f=1, r=None):
    m = cells(1, np.random.default_rng(0))
    patrols = [Patrol((0, 1, 2, 3, 4), tuple((q + 2 * a) % 7 for q in range(5)), (7,) * 5, agent=a) for a in range(4)]
    patrols += [Patrol((5, 6, 7, 8, 9), tuple((q + 2 * a) % 7 for q in range(5)), (7,) * 5, agent=4 + a) for a in range(4)]
    patrols += [Patrol((0,), (a,), (3,), agent=8 + a) for a in range(3)]
    adj = np.zeros((11, 11), dtype=int)
    adj[0:4, 4:8] = adj[4:8, 0:4] = 1
    adj[8:11, 0:4] = adj[0:4, 8:11] = 1
    des = design(m.A, m.loc_C, patrols, adj, f=f, r=r, blocks=m.blocks, block_names=m.block_names)
    return m, des, adj


def huge(rng, n, k):
    return rng.choice([-1.0, 1.0], n) * 10.0 ** rng.uniform(6, 100, n)


def run(rule, *, attack=huge, drop=0.0, rounds=ROUNDS, delay=0, stamp=None, seed=3):
    """The in-test loop. ``delay``: messages arrive 1..delay+1 rounds after publication
    (newest delivered one kept per link); ``stamp(k)``: the adversary's forged stamp."""
    m, des, adj = team()
    N = adj.shape[0]
    ests = [make_estimator(des, agent=i, rule=rule) for i in range(N)]
    rng = np.random.default_rng(seed)
    x = m.x0.copy()
    pending = []  # (arrival round, receiver, Received)
    inboxes = [dict() for _ in range(N)]
    for k in range(rounds):
        if delay == 0:
            inboxes = [dict() for _ in range(N)]  # only this round's deliveries
        for _arrival, i, rec in [p for p in pending if p[0] == k]:
            old = inboxes[i].get(rec.sender)
            if old is None or rec.stamp >= old.stamp or rec.sender == ADV:
                inboxes[i][rec.sender] = rec
        pending = [p for p in pending if p[0] > k]
        for i in range(N):
            loc = des.schedules[i].location(k)
            y = None if loc is None else m.loc_C[loc] @ x
            out = ests[i].step(k, y, inboxes[i])
            for j in np.flatnonzero(adj[:, i]):  # i -> j
                if rng.random() < drop:
                    continue
                val, st = out, k
                if i == ADV and attack is not None:
                    val = attack(rng, m.n, k)
                    st = k if stamp is None else stamp(k)
                lag = 1 + (int(rng.integers(0, delay + 1)) if delay else 0)
                pending.append((k + lag, int(j), Received(i, st, val)))
        if k < rounds - 1:
            x = m.A @ x
    rel = [np.linalg.norm(ests[i].estimate - x) / np.linalg.norm(x) for i in range(N) if i != ADV]
    return np.array(rel), ests, des


def test_design_of_the_small_team():
    m, des, adj = team()
    assert des.sources[19] == frozenset(range(4, 8))  # lambda = 1.2 seen at location 9
    assert des.medags[19].levels == ((4, 5, 6, 7), (0, 1, 2, 3), (8, 9, 10))
    assert des.medags[19].neighbours[9] == (0, 1, 2, 3)
    assert des.sources[0] == frozenset(range(4)) | frozenset(range(8, 11))
    assert 19 in des.fused[9] and 0 not in des.fused[9]


@pytest.mark.parametrize("rule", ["lfre", "sw_lfre", "median"])
def test_resilient_rules_converge_despite_a_huge_value_adversary(rule):
    rel, ests, _ = run(rule)
    assert rel.max() < 1e-9
    # level-2 agents get the unstable modes only through fusion, and they did converge
    assert 19 in ests[9]._F


def test_non_resilient_average_is_ruined_by_the_same_adversary():
    rel, _, _ = run("average")
    assert rel.max() >= 0.5


def test_average_converges_without_adversary():
    rel, _, _ = run("average", attack=None)
    assert rel.max() < 1e-9


def test_lfre_with_random_erasures_below_the_mss_bound():
    # level-1 agents have 3f+1 = 4 MEDAG neighbours (m = 3): p* = 0.3265 for rho = 1.2
    rel, _, _ = run("lfre", drop=0.2, rounds=400)
    assert rel.max() < 1e-9


@pytest.mark.parametrize("forge", [lambda k: k + 1000, lambda k: max(k - 40, 0), lambda k: -5])
def test_sw_lfre_with_delays_and_forged_stamps(forge):
    """Section 5-6: delays of up to T = 4 rounds and an adversary forging its stamps."""
    rel, _, _ = run("sw_lfre", delay=3, stamp=forge, rounds=400)
    assert rel.max() < 1e-9


def test_sw_lfre_compensates_delays_with_lambda_tau():
    """Every packet 1-3 rounds late; without the lambda^tau factor of step 1 the stale
    values would bias the level-1 and level-2 agents by ~(1 - 1.2^-tau)."""
    rel, _, _ = run("sw_lfre", delay=2, rounds=400)
    assert rel.max() < 1e-9


def test_missing_measurement_and_empty_inbox_are_ordinary_input():
    m, des, adj = team()
    est = LFRE(des, agent=9)
    assert isinstance(est, Estimator)
    z0 = est.step(0, None, {})
    assert np.all(z0 == 0)
    est2 = SWLFRE(des, agent=9, z0=np.ones(20))
    est2.step(0, None, {})
    z1 = est2.step(1, None, {})
    # SW-LFRE without any message: every neighbour counts as 0 (footnote 9)
    assert np.all(z1[des.fused[9]] == 0)
    est3 = LFRE(des, agent=9, z0=np.ones(20))
    est3.step(0, None, {})
    z1 = est3.step(1, None, {})
    # LFRE with an empty inbox runs open loop, eq. (22)
    np.testing.assert_allclose(z1[des.fused[9]], des.modal.lam[des.fused[9]])
    out = est3.step(2, None, {})
    with pytest.raises(ValueError, match="read-only"):  # the payload is read-only ...
        out[:] = 123.0
    kept = out.copy()
    est3.step(3, None, {})
    np.testing.assert_array_equal(out, kept)  # ... and never modified by later rounds


def test_step_input_errors():
    m, des, adj = team()
    est = LFRE(des, agent=8)  # agent 8 visits location 0 at rounds 0, 3, 6, ...
    est.step(0, np.array([1.0]), {})
    with pytest.raises(ValueError, match="patrol is commuting"):
        est.step(1, np.array([1.0]), {})
    with pytest.raises(ValueError, match="rounds must increase"):
        est.step(1, None, {})
    est2 = LFRE(des, agent=8)
    with pytest.raises(ValueError, match=r"location 0 gives 1 value\(s\)"):
        est2.step(0, np.array([1.0, 2.0]), {})
    # a message of the wrong shape is skipped and counted
    est3 = LFRE(des, agent=9)
    est3.step(0, None, {})
    est3.step(1, None, {0: Received(0, 0, np.zeros(3))})
    assert est3.rejected == 1
    with pytest.raises(DesignError, match="unknown rule"):
        make_estimator(des, agent=0, rule="mean")


def test_design_errors_name_the_mode_and_agents():
    m = cells(1, np.random.default_rng(0))
    patrols = [Patrol((0, 1, 2, 3, 4), (0, 1, 2, 3, 4), (7,) * 5, agent=a) for a in range(4)]
    patrols += [Patrol((5, 6, 7, 8, 9), (0, 1, 2, 3, 4), (7,) * 5, agent=4 + a) for a in range(4)]
    adj = np.zeros((8, 8), dtype=int)
    adj[0:4, 4:8] = adj[4:8, 0:4] = 1
    adj[0, 7] = 0  # agent 0 hears only 3 of the 4 sources of the unstable modes
    design(m.A, m.loc_C, patrols, adj, f=1, blocks=m.blocks)  # 3 = 2f+1 suffice
    with pytest.raises(DesignError, match=r"mode 14 \(cell1, lambda=1.01579\): no MEDAG, .*strongly 4-robust.* agents \[0\]"):
        design(m.A, m.loc_C, patrols, adj, f=1, r=4, blocks=m.blocks, block_names=m.block_names)
    blind = [Patrol((0, 1, 2, 3, 4), (0, 1, 2, 3, 4), (7,) * 5, agent=a) for a in range(8)]
    with pytest.raises(DesignError, match=r"mode 14 .*no agent's patrol observes this mode"):
        design(m.A, m.loc_C, blind, adj, f=1, blocks=m.blocks, block_names=m.block_names)


@pytest.mark.parametrize("rule", ["lfre", "sw_lfre"])
def test_the_payload_is_the_estimate_when_the_modal_transform_is_the_identity(rule):
    """cells() is a diagonal process: z_hat is x_hat, so the payload may stand for the
    estimate (a lockstep done report carries it instead of a second message)."""
    from estimation.base import EstimatePayload

    _, des, _ = team()
    assert des.modal.is_identity
    est = make_estimator(des, agent=0, rule=rule)
    assert isinstance(est, EstimatePayload) and est.payload_is_estimate
    rng = np.random.default_rng(1)
    for k in range(6):
        inbox = {j: Received(j, k - 1, rng.normal(size=des.n)) for j in (4, 5, 8)} if k else {}
        out = est.step(k, None, inbox)
        np.testing.assert_array_equal(out, est.estimate)
