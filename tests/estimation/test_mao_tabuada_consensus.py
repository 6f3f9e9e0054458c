"""Discrete-time dynamic average consensus (Mao-Tabuada (6)-(10)): gain design by the
spectral radius of the disagreement dynamics, tracking of known signals, lost messages."""

import networkx as nx
import numpy as np
import pytest

from estimation.dynamic_consensus import (
    ConsensusNode,
    design_consensus_gains,
    disagreement_spectral_radius,
    mode_matrix,
    rotating_frame_matrix,
)
from estimation.errors import DesignError
from estimation.mao_tabuada import companion, example


def _adj(G):
    return nx.to_numpy_array(G)


def test_modes_are_the_spectrum_of_the_whole_system():
    Adj = example().Adj
    g = design_consensus_gains(Adj)
    kw = dict(k_phi=g.k_phi, k_I=g.k_I, k_P=g.k_P)
    full = np.sort_complex(np.linalg.eigvals(rotating_frame_matrix(Adj, **kw)))
    lams = np.linalg.eigvalsh(np.diag(Adj.sum(1)) - Adj)
    modes = np.sort_complex(np.concatenate([np.linalg.eigvals(mode_matrix(l, **kw)) for l in lams]))
    np.testing.assert_allclose(full, modes, atol=1e-9)
    # disagreement radius = everything but the invariant average of b (eigenvalue 1)
    mags = np.sort(np.abs(full))
    assert mags[-1] == pytest.approx(1.0) and mags[-2] < 1.0
    assert g.spectral_radius == pytest.approx(max(mags[-2], abs(1 - g.k_phi)))
    assert g.spectral_radius < 0.8


def test_stable_gains_form_a_bounded_window():
    g = design_consensus_gains(example().Adj)
    lams = np.array([g.lambda_2, g.lambda_max])
    rho = lambda kI: disagreement_spectral_radius(lams, k_phi=g.k_phi, k_I=kI, k_P=g.k_P)
    assert rho(g.k_I) < 1
    assert rho(g.k_I * 1e-3) < 1  # small gains stay stable ...
    assert rho(g.k_I * 1e-3) > rho(g.k_I)  # ... but slow
    assert rho(g.k_I * 10) > 1  # large gains leave the unit disc (no "any gain above k_I0")
    assert disagreement_spectral_radius(lams, k_phi=2.5, k_I=g.k_I, k_P=g.k_P) > 1


def test_disconnected_graph_admits_no_stable_gains():
    Adj = _adj(nx.disjoint_union(nx.cycle_graph(4), nx.cycle_graph(4)))
    with pytest.raises(DesignError, match=r"not connected .*2 zero eigenvalues.*no gains"):
        design_consensus_gains(Adj)


def test_demanded_rate_on_a_long_path_names_the_connectivity():
    Adj = _adj(nx.path_graph(40))
    g = design_consensus_gains(Adj)  # stable, but barely
    assert 0.99 < g.spectral_radius < 1
    with pytest.raises(DesignError, match=r"poorly connected, lambda_2 / lambda_max = 0.00154"):
        design_consensus_gains(Adj, max_spectral_radius=0.99)


def test_directed_or_malformed_graphs_are_rejected():
    Adj = _adj(nx.cycle_graph(5))
    Adj[0, 1] = 0
    with pytest.raises(DesignError, match="undirected"):
        design_consensus_gains(Adj)
    with pytest.raises(DesignError, match="zero diagonal"):
        design_consensus_gains(np.ones((3, 3)))


def _run(Adj, Ahat, c, rounds, *, drop_p=0.0, seed=0, change=None):
    """Nodes with phi_i[k] = c_i Ahat^{kT}; returns the relative error of every node per round."""
    p, (v, m) = Adj.shape[0], c.shape[1:]
    gains = design_consensus_gains(Adj)
    nodes = [ConsensusNode(node=i, weights=dict(enumerate(Adj[i])), Ahat=Ahat, gains=gains, shape=(v, m)) for i in range(p)]
    rng = np.random.default_rng(seed)
    err = np.zeros((rounds, p))
    phi = c.copy()
    out = None
    for k in range(rounds):
        if change is not None and k == change[0]:
            phi = phi + change[1]
        if out is not None:
            for i in range(p):
                for j in np.flatnonzero(Adj[i]):
                    if rng.random() >= drop_p:
                        nodes[i].receive(int(j), k - 1, out[j])
        out = [nodes[i].step(k, phi[i]) for i in range(p)]
        avg = phi.mean(axis=0)
        for i in range(p):
            err[k, i] = np.linalg.norm(nodes[i].average - avg) / np.linalg.norm(avg)
        phi = phi @ Ahat.T
    return err, gains


def test_tracks_the_average_of_growing_signals():
    ex = example()
    Ahat, _ = companion(ex.A)
    c = np.random.default_rng(3).standard_normal((8, 5, 4))
    err, gains = _run(ex.Adj, Ahat, c, 300)
    assert err[299].max() <= 1e-12
    # the decay follows the designed spectral radius
    rate = (err[120].max() / err[60].max()) ** (1 / 60)
    assert rate == pytest.approx(gains.spectral_radius, abs=0.03)


def test_tracks_constants_and_a_change_of_inputs():
    Adj = _adj(nx.hypercube_graph(3))
    c = np.random.default_rng(4).standard_normal((8, 2, 3))
    step = np.zeros_like(c)
    step[3] = 5.0
    err, _ = _run(Adj, np.eye(3), c, 400, change=(200, step))
    assert err[199].max() <= 1e-12
    assert err[200].max() > 1e-2  # the change is seen ...
    assert err[399].max() <= 1e-12  # ... and tracked again


@pytest.mark.parametrize("drop_p", [0.1, 0.3])
def test_lost_messages_keep_exact_tracking(drop_p):
    ex = example()
    Ahat, _ = companion(ex.A)
    c = np.random.default_rng(5).standard_normal((8, 5, 4))
    err, _ = _run(ex.Adj, Ahat, c, 500, drop_p=drop_p, seed=11)
    assert err[499].max() <= 1e-12


def test_without_propagation_stale_values_break_tracking():
    # the same lossy run with Ahat-propagation disabled (identity powers) does not converge
    ex = example()
    Ahat, _ = companion(ex.A)
    c = np.random.default_rng(5).standard_normal((8, 5, 4))
    orig = ConsensusNode._power_T
    try:
        ConsensusNode._power_T = lambda self, tau: np.eye(4)
        err, _ = _run(ex.Adj, Ahat, c, 500, drop_p=0.1, seed=11)
    finally:
        ConsensusNode._power_T = orig
    assert err[499].max() > 1e-6


def test_node_rejects_bad_messages_and_keeps_the_newest():
    g = design_consensus_gains(_adj(nx.cycle_graph(3)))
    node = ConsensusNode(node=0, weights={1: 1.0, 2: 1.0}, Ahat=np.eye(2), gains=g, shape=(1, 2))
    node.receive(1, 3, np.ones(4))
    node.receive(1, 2, np.zeros(4))  # older: ignored
    node.receive(7, 3, np.ones(4))  # not a neighbour
    node.receive(2, 3, np.ones(3))  # wrong size
    node.receive(2, 3, np.array([1.0, np.nan, 0, 0]))
    assert node.rejected == 3
    assert node._last[1][0] == 3
    with pytest.raises(DesignError, match="shape"):
        node.step(4, np.zeros((2, 2)))
