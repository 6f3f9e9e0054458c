"""Offline LMIs (34)/(40)/(49)/(52), footnote-3 fallback and graph selection (50)-(51)."""

from __future__ import annotations

import numpy as np
import pytest

from estimation.errors import DesignError, InfeasibleError
from estimation.hinf_lmi import (
    ResilientProblem,
    check_design,
    closed_form_design,
    coupling_matrices,
    design,
    select_graph,
)
from estimation.hinf_riccati import information_matrix, riccati_rhs
from estimation.ugrinovskii import first_order_attack_model
from estimation.ugrinovskii_example import PAPER_GAMMA2, PAPER_GAMMA2_BAR, example_problem

pytest.importorskip("cvxpy")


def small_problem(neighbours, *, C=None, H=0.0, Z=1.0, P_scale=1.0):
    """Two-state unstable plant, N nodes, node i measures coordinate i mod 2 (noise 0.1)."""
    N = len(neighbours)
    A = np.array([[0.2, 1.0], [-0.5, 0.1]])
    if C is None:
        C = [np.eye(2)[[i % 2]] for i in range(N)]
    edges = [(i, j) for i in range(N) for j in neighbours[i]]
    Om, Ga, Up = first_order_attack_model(gain=4.0, pole=4.0)
    Adj = np.zeros((N, N))
    for i, j in edges:
        Adj[i, j] = 1.0
    Lap = np.diag(Adj.sum(1)) - Adj
    LapT = np.diag(Adj.T.sum(1)) - Adj.T
    h = H * np.ones((2, 1))
    return ResilientProblem(
        A=A, B=0.1 * np.eye(2), C=tuple(C), D=tuple(0.1 * np.eye(c.shape[0]) for c in C),
        neighbours=tuple(tuple(v) for v in neighbours),
        W={e: np.eye(2) for e in edges}, H={e: h for e in edges}, Hc={e: h for e in edges},
        Z={e: Z * np.eye(2) for e in edges}, Zbar={e: Z * np.eye(2) for e in edges},
        F=tuple(np.ones((2, 1)) for _ in range(N)), Fc=tuple(np.zeros((4, 1)) for _ in range(N)),
        Omega=(Om,) * N, Gamma=(Ga,) * N, Upsilon=(Up,) * N,
        P=P_scale * np.kron(Lap + LapT, np.eye(2)),
    )


RING3 = [[2], [0], [1]]


@pytest.fixture(scope="module")
def example_design():
    pb = example_problem()
    return pb, design(pb, observer_channel="H_hat")


def test_example_reproduces_the_papers_gammas(example_design):
    _, d = example_design
    # Section IV: gamma^2 = 6.9113e-3, gamma_bar^2 = 3.4511e-2 (minima of the LMIs (49)/(52))
    assert abs(float(d["gamma2_opt"]) / PAPER_GAMMA2 - 1) < 0.01
    assert abs(float(d["gamma2_bar_opt"]) / PAPER_GAMMA2_BAR - 1) < 0.01
    # backed off by 5 % for the gains actually used
    assert float(d["backoff"]) == 0.05
    np.testing.assert_allclose(float(d["gamma2"]), 1.05 * float(d["gamma2_opt"]))
    np.testing.assert_allclose(float(d["gamma2_bar"]), 1.05 * float(d["gamma2_bar_opt"]))


def test_example_lmi_solution_makes_the_riccati_equations_decrease(example_design):
    # the LMI at Q_i means Ric(gamma^2 Q_i^-1) < 0: the Riccati solution started there decreases
    pb, d = example_design
    g = float(d["gamma2"])
    for i in range(pb.N):
        Ab, Bb, Cb, Wb = pb.detector_matrices(i)
        S = information_matrix(Cb, pb.D[i], Wb, [d[f"U_{i}_{j}"] for j in pb.neighbours[i]])
        Y0 = g * np.linalg.inv(d[f"Q_{i}"])
        assert np.linalg.eigvalsh(riccati_rhs(Y0, A=Ab, B=Bb, S=S, R=d[f"R_{i}"], gamma2=g))[-1] < 0


def test_design_result_round_trips_through_npz(example_design, tmp_path):
    pb, d = example_design
    np.savez(tmp_path / "design.npz", **d)
    loaded = dict(np.load(tmp_path / "design.npz"))  # no pickle needed
    again = design(pb, cached=loaded)  # checked, not re-solved
    assert set(again) == set(d)
    for k in d:
        np.testing.assert_array_equal(again[k], d[k])
    bad = dict(loaded)
    bad["R_3"] = bad["R_3"] * 1e6  # breaks node 3's Riccati LMI
    with pytest.raises(InfeasibleError, match="node 3"):
        check_design(pb, bad)
    with pytest.raises(DesignError, match="n = 2"):
        check_design(small_problem(RING3), d)


def test_coupling_matrix_reduces_to_the_laplacian_form_of_47():
    pb = small_problem([[1, 2], [2], [1]], H=0.0, Z=1.0)  # W = I, H = 0, Z = I
    U, _ = pb.channel_weights()
    M = coupling_matrices(pb, U, pb.Z)
    Adj = np.array([[0, 1, 1], [0, 0, 1], [0, 1, 0]], float)
    Dg = np.diag(Adj.sum(1))
    Lap = Dg - Adj
    np.testing.assert_allclose(M, np.kron(Lap + Lap.T - Dg, np.eye(2)))


def test_small_problem_is_feasible_and_checked():
    pb = small_problem(RING3, H=0.05, Z=0.1)
    d = design(pb)
    assert 0 < float(d["gamma2_opt"]) < float(d["gamma2"])
    check_design(pb, d)


def test_infeasible_case_names_the_failing_block():
    # node 2 measures nothing useful (C = 0) and receives from nobody: the plant is unstable,
    # so its Riccati LMI block has no solution.
    C = [np.array([[1.0, 0.0]]), np.array([[0.0, 1.0]]), np.zeros((1, 2))]
    pb = small_problem([[2], [0], []], C=C)
    with pytest.raises(InfeasibleError, match=r"detector LMIs .*Riccati LMI block of node 2"):
        design(pb)


def test_closed_form_fallback_satisfies_34_and_40():
    # every node sees the whole state: then the footnote's weights leave (35), (41) stable
    pb = small_problem(RING3, C=[np.eye(2)] * 3, H=0.05, Z=0.1)
    d = closed_form_design(pb, gamma2=0.5, gamma2_bar=0.5)
    assert str(d["method"]) == "closed_form"
    check_design(pb, d)  # (34), (40), Rcheck > Ups'Ups, positivity
    U, _ = pb.channel_weights()
    for i in range(pb.N):  # Y(0) = gamma^2 Q^-1 is stationary for (35)
        Ab, Bb, Cb, Wb = pb.detector_matrices(i)
        S = information_matrix(Cb, pb.D[i], Wb, [U[(i, j)] for j in pb.neighbours[i]])
        Y0 = 0.5 * np.linalg.inv(d[f"Q_{i}"])
        assert np.abs(riccati_rhs(Y0, A=Ab, B=Bb, S=S, R=d[f"R_{i}"], gamma2=0.5)).max() < 1e-6 * np.abs(Y0).max()


def test_closed_form_fallback_is_not_enough_for_the_example():
    # footnote 3: "not every solution of (34) is suitable" -- for Section IV it is not
    with pytest.raises(DesignError, match="node 0"):
        closed_form_design(example_problem(), gamma2=2 * PAPER_GAMMA2, gamma2_bar=2 * PAPER_GAMMA2_BAR,
                           observer_channel="H_hat")


def test_graph_selection_recursion_50():
    C = [np.array([[1.0, 0.0]]), np.array([[0.0, 1.0]]), np.zeros((1, 2))]
    candidates = [
        small_problem([[2], [0], []], C=C),  # infeasible: node 2 blind and isolated
        small_problem([[2], [0], [1]], C=C),  # directed ring
        small_problem([[1, 2], [0, 2], [0, 1]], C=C),  # complete graph
    ]
    res = select_graph(candidates, criterion="gamma2")
    g = res["gamma_m"]
    assert np.isinf(g[0]) and np.all(np.isfinite(g[1:]))
    run = res["gamma_running"]
    np.testing.assert_allclose(run, np.minimum.accumulate(g))  # (50)
    assert int(res["best"]) == int(np.argmin(g))
    check_design(candidates[int(res["best"])], res)
    res_bar = select_graph(candidates, criterion="gamma2_bar")  # (51)
    assert int(res_bar["best"]) == int(np.argmin(res_bar["gamma_m"]))


def test_graph_selection_with_no_feasible_graph():
    C = [np.array([[1.0, 0.0]]), np.array([[0.0, 1.0]]), np.zeros((1, 2))]
    with pytest.raises(InfeasibleError, match="no candidate graph"):
        select_graph([small_problem([[2], [0], []], C=C)])


def test_problem_validation_messages():
    with pytest.raises(DesignError, match="neighbours"):
        small_problem([[0], [0], [1]])  # self-loop
    with pytest.raises(DesignError, match="backoff"):
        design(small_problem(RING3), backoff=-1.0)
