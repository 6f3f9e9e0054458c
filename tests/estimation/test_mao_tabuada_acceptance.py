"""Acceptance numbers of the Mao-Tabuada experiment, on a self-contained reference loop:
all nodes in one process, synchronous rounds, a seeded RNG for the Bernoulli link losses.

Round ``k``: the plant's ``x[k]`` gives ``y[k]`` (attacked nodes report the outputs of
another initial state, optionally plus a bias); every node receives the newest message
of each neighbour delivered so far (those of round ``k-1`` unless dropped), steps its
estimator and publishes its payload stamped ``k``.
"""

import numpy as np
import pytest

from estimation.base import Received
from estimation.mao_tabuada import MaoTabuadaEstimator, check_report, design_mao_tabuada, example


@pytest.fixture(scope="module")
def ex():
    return example()


@pytest.fixture(scope="module")
def design(ex):
    return design_mao_tabuada(ex.A, ex.C, ex.Adj, s=ex.s, D=ex.D)


def reference_run(ex, design, *, rounds, drop_p=0.0, bias=False, decoder="secure", seed=0):
    """Returns ``(err, ests, dropped)``: relative errors ``(rounds, p)``, the estimators, drops."""
    rng = np.random.default_rng(seed)
    p = design.p
    ests = [MaoTabuadaEstimator(design, node=i, decoder=decoder) for i in range(p)]
    nbrs = [np.flatnonzero(ex.Adj[i]) for i in range(p)]
    x, xa = np.array(ex.x0), np.array(ex.x0_attack)
    delivered: dict[tuple[int, int], Received] = {}
    err = np.zeros((rounds, p))
    out, dropped = None, 0
    for k in range(rounds):
        y, ya = ex.C @ x, ex.C @ xa
        y[list(ex.attacked)] = ya[list(ex.attacked)]
        if bias and k >= ex.bias_round:
            y[ex.bias_node] += ex.bias_value
        if out is not None:
            for i in range(p):
                for j in nbrs[i]:
                    if rng.random() < drop_p:
                        dropped += 1
                    else:
                        delivered[i, j] = Received(int(j), k - 1, out[j])
        out = []
        for i in range(p):
            inbox = {int(j): delivered[i, j] for j in nbrs[i] if (i, j) in delivered}
            out.append(ests[i].step(k, y[i : i + 1], inbox))
            err[k, i] = np.linalg.norm(ests[i].estimate - x) / np.linalg.norm(x)
        x, xa = ex.A @ x, ex.A @ xa
    return err, ests, dropped


def _honest(ex):
    return [i for i in range(ex.C.shape[0]) if i not in ex.attacked]


def test_example_is_the_issue_setting(ex, design):
    p = ex.C.shape[0]
    assert p >= 8 and ex.s == 2 and len(ex.attacked) == 2
    assert np.all(np.abs(np.linalg.eigvals(ex.A)) > 1)
    assert np.array_equal(ex.Adj, ex.Adj.T)
    lam = np.sort(np.linalg.eigvalsh(np.diag(ex.Adj.sum(1)) - ex.Adj))
    assert lam[1] > 1e-9  # connected
    assert design.v < p
    assert np.array_equal(design.D, ex.D)


def test_check_report(ex, design):
    rep = check_report(design, x0_norm=float(np.linalg.norm(ex.x0)))
    sd = rep["sparse_detectability"]
    assert sd["holds"] is True and sd["k"] == 4 and sd["wrt"] == "D" and sd["margin"] > 0
    assert rep["v"] == 5 and 2 * rep["s"] + 1 <= rep["v"] < rep["p"] == 8
    c = rep["consensus"]
    assert 0 < c["spectral_radius"] < 1
    assert c["k_I"] > 0 and c["k_P"] > 0 and 0 < c["k_phi"] < 2
    assert rep["numerics"]["strategy"] == "limit" and rep["numerics"]["safe_horizon"] > ex.rounds


def test_dynamics_consistent_attacks(ex, design):
    err, ests, _ = reference_run(ex, design, rounds=401)
    assert err[200:].max() <= 1e-6
    assert err[300].max() <= 1e-10
    assert not any(e.flagged for e in ests)  # the attack passes the sanity check
    for i in range(design.p):
        assert ests[i].support == tuple(sorted(ex.attacked))


def test_least_squares_decoding_of_the_same_consensus_fails(ex, design):
    err, ests, _ = reference_run(ex, design, rounds=401, decoder="least_squares")
    assert err[400].min() >= 1e-3
    assert not any(e.flagged for e in ests)


def test_ten_percent_message_loss(ex, design):
    err, ests, dropped = reference_run(ex, design, rounds=400, drop_p=0.1, seed=7)
    links = int(ex.Adj.sum())
    assert 0.08 < dropped / (399 * links) < 0.12
    assert err[300:].max() <= 1e-6
    assert not any(ests[i].flagged for i in _honest(ex))


def test_bias_switched_on_at_an_attacked_node(ex, design):
    assert ex.bias_node in ex.attacked
    err, ests, _ = reference_run(ex, design, rounds=400, bias=True)
    b = ests[ex.bias_node]
    assert b.flagged and 0 <= b.flag_round - ex.bias_round <= 1
    assert [i for i, e in enumerate(ests) if e.flagged] == [ex.bias_node]
    assert err[300:].max() <= 1e-6


def test_long_run_stays_sound(ex, design):
    # |x| grows ~1.04^k to ~1e26: relative accuracy does not degrade with the magnitude
    err, ests, _ = reference_run(ex, design, rounds=1500, drop_p=0.1, seed=3)
    assert err[300:].max() <= 1e-10
    assert not any(ests[i].flagged for i in _honest(ex))
