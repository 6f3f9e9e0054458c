"""Riccati equations (35)/(41), gains (36)/(42)/(44) and the escape check."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.linalg import solve_continuous_are

from estimation.errors import NumericalError
from estimation.hinf_riccati import (
    RiccatiFlow,
    check_riccati_solution,
    difference_gains,
    filter_gains,
    information_matrix,
    riccati_rhs,
    split_detector_gains,
    stabilizing_solution,
)


def test_information_matrix_hand_checked():
    C = np.array([[1.0, 0.0]])
    D = np.array([[0.5]])  # (DD')^-1 = 4
    W = [np.eye(2)]
    U = [np.diag([2.0, 4.0])]
    S = information_matrix(C, D, W, U)
    np.testing.assert_allclose(S, [[4.0 + 0.5, 0.0], [0.0, 0.25]])


def test_riccati_rhs_scalar_hand_checked():
    # y' = 2 a y + b^2 - y (s - r / g2) y with a = -1, b = 2, s = 3, r = 1, g2 = 0.5 at y = 2:
    # -4 + 4 - 4 * (3 - 2) = -4
    out = riccati_rhs(np.array([[2.0]]), A=np.array([[-1.0]]), B=np.array([[2.0]]),
                      S=np.array([[3.0]]), R=np.array([[1.0]]), gamma2=0.5)
    np.testing.assert_allclose(out, [[-4.0]])


def test_riccati_rhs_matrix_hand_checked():
    A = np.array([[0.0, 1.0], [0.0, 0.0]])
    B = np.array([[0.0], [1.0]])
    S = np.eye(2)
    R = np.zeros((2, 2))
    Y = np.eye(2)
    # A + A' + BB' - I = [[0,1],[1,0]] + [[0,0],[0,1]] - I
    np.testing.assert_allclose(riccati_rhs(Y, A=A, B=B, S=S, R=R, gamma2=1.0), [[-1.0, 1.0], [1.0, 0.0]])


def test_filter_gains_hand_checked_and_split():
    Y = np.array([[2.0, 1.0, 0.5], [1.0, 3.0, 0.0], [0.5, 0.0, 4.0]])
    C = np.array([[1.0, 0.0, 0.0]])
    D = np.array([[0.5]])
    W = [np.array([[0.0, 1.0, 0.0]])]
    U = [np.array([[2.0]])]
    L, K = filter_gains(Y, C=C, D=D, W=W, U=U)  # (36): Y C' (DD')^-1, Y W' U^-1
    np.testing.assert_allclose(L, 4.0 * Y[:, [0]])
    np.testing.assert_allclose(K[0], 0.5 * Y[:, [1]])
    Lh, Lc, Kh, Kc = split_detector_gains(L, K, n=2)  # (31)
    np.testing.assert_allclose(Lh, L[:2])
    np.testing.assert_allclose(Lc, L[2:])
    np.testing.assert_allclose(Kh[0], K[0][:2])
    np.testing.assert_allclose(Kc[0], K[0][2:])
    Lb, Kb = difference_gains(Lh, Kh, np.ones((2, 1)), [np.ones((2, 1))])  # (44)
    np.testing.assert_allclose(Lb, Lh - 1.0)
    np.testing.assert_allclose(Kb[0], Kh[0] - 1.0)


def test_stabilizing_solution_matches_scipy_in_the_definite_case():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(3, 3))
    B = rng.normal(size=(3, 2))
    C = rng.normal(size=(2, 3))
    S = C.T @ C
    Ys = stabilizing_solution(A=A, B=B, S=S, R=np.zeros((3, 3)), gamma2=1.0)
    # filter ARE A Y + Y A' + BB' - Y C'C Y = 0  <=>  control ARE with A'
    ref = solve_continuous_are(A.T, C.T, B @ B.T, np.eye(2))
    np.testing.assert_allclose(Ys, ref, rtol=1e-8, atol=1e-10)
    assert np.linalg.eigvals(A - Ys @ S).real.max() < 0


def test_flow_matches_an_accurate_ode_solution():
    # stiff-ish 2x2 H-infinity case with an indefinite S - R/g2
    A = np.array([[0.5, 1.0], [-0.3, -2.0]])
    B = np.array([[1.0, 0.0], [0.2, 3.0]])
    S = np.diag([50.0, 2.0])
    R = np.diag([0.5, 0.5])
    g2 = 0.8
    Y0 = np.array([[2.0, 0.3], [0.3, 1.0]])
    dt = 0.01
    flow = RiccatiFlow(A=A, B=B, S=S, R=R, gamma2=g2, Y0=Y0, dt=dt)
    f = lambda t, y: riccati_rhs(y.reshape(2, 2), A=A, B=B, S=S, R=R, gamma2=g2).ravel()
    sol = solve_ivp(f, (0.0, 2.0), Y0.ravel(), method="Radau", rtol=1e-11, atol=1e-13,
                    t_eval=np.arange(1, 201) * dt)
    got = np.array([flow.step() for _ in range(200)])
    err = np.abs(got.reshape(200, 4) - sol.y.T).max()
    assert err < 1e-7 * np.abs(sol.y).max()
    # converges to the stationary solution
    assert np.abs(riccati_rhs(flow.Y_stationary, A=A, B=B, S=S, R=R, gamma2=g2)).max() < 1e-9


def test_escape_check_raises_numerical_error():
    # y' = -2y + 0.25 + y^2 (a = -1, b = 0.5, S - R/g2 = -1): stabilising y_s = 1 - sqrt(.75),
    # and y(0) = 2 > 1 + sqrt(.75) escapes to +inf at t = ln(1 + ...) ~ 1.52 s.
    r = 1 + np.sqrt(0.75)
    s = 1 - np.sqrt(0.75)
    t_escape = np.log((2.0 - s) / (2.0 - r)) / (r - s)
    flow = RiccatiFlow(A=np.array([[-1.0]]), B=np.array([[0.5]]), S=np.array([[0.0]]),
                       R=np.array([[1.0]]), gamma2=1.0, Y0=np.array([[2.0]]), dt=1e-3,
                       name="detector Riccati (35) of node 4")
    with pytest.raises(NumericalError, match="node 4.*(escape|bound)"):
        for _ in range(5000):
            flow.step()
    assert 0.9 * t_escape < flow.t <= t_escape


def test_escape_check_names_loss_of_positive_definiteness():
    with pytest.raises(NumericalError, match="positive definite"):
        check_riccati_solution(np.diag([1.0, -1e-3]), bound=10.0, name="Y")
    with pytest.raises(NumericalError, match="bound"):
        check_riccati_solution(np.diag([1.0, 20.0]), bound=10.0, name="Y")
    with pytest.raises(NumericalError, match="finite"):
        check_riccati_solution(np.array([[np.inf]]), bound=10.0, name="Y")
    check_riccati_solution(np.diag([1.0, 2.0]), bound=10.0)  # passes


def test_no_stabilising_solution_is_an_error():
    # A = 1 unobservable (S = 0), R = 0: Hamiltonian eigenvalues +-1, stable subspace is
    # [A', 0; -BB', -A] -> exists; make it truly singular with B = 0 and a = 0.
    with pytest.raises(NumericalError, match="stabilising"):
        stabilizing_solution(A=np.zeros((1, 1)), B=np.zeros((1, 1)), S=np.zeros((1, 1)),
                             R=np.zeros((1, 1)), gamma2=1.0)
