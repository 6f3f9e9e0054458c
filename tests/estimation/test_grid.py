"""The grid maths (estimation.grid): DC Laplacian, Kron reduction, swing model, PMU rows,
on a four-bus network small enough to check by hand."""

import numpy as np
import pytest

from estimation.errors import DesignError
from estimation.grid import damping, inertia, kron_reduce, susceptance_matrix, swing_model
from estimation.lti import zoh

# buses 0-1-2-3 in a line plus 0-3, generators at 0 and 3, loads at 1 and 2
F, T, B_BR = np.array([0, 1, 2, 0]), np.array([1, 2, 3, 3]), np.array([10.0, 5.0, 8.0, 4.0])


def test_susceptance_matrix_is_the_weighted_laplacian():
    B = susceptance_matrix(4, F, T, B_BR)
    assert np.allclose(B, B.T)
    assert np.allclose(B.sum(axis=1), 0.0)
    assert B[0, 0] == 14.0 and B[0, 1] == -10.0 and B[0, 3] == -4.0 and B[1, 3] == 0.0


def test_kron_reduction_by_hand():
    B = susceptance_matrix(4, F, T, B_BR)
    B_red, K, T_ = kron_reduce(B, np.array([0, 3]))
    # buses 1, 2 in series: 10 and 5 and 8 in series = 1 / (1/10 + 1/5 + 1/8), parallel to 4
    b_eq = 4.0 + 1.0 / (1 / 10 + 1 / 5 + 1 / 8)
    assert np.allclose(B_red, [[b_eq, -b_eq], [-b_eq, b_eq]], rtol=1e-12)
    # the reduced network carries the same flows: random injections, angles from the full network
    rng = np.random.default_rng(0)
    p = rng.normal(size=4)
    p -= p.mean()
    theta = np.linalg.lstsq(B, p, rcond=None)[0]
    assert np.allclose(B_red @ theta[[0, 3]], K @ p, atol=1e-12)
    assert np.allclose(T_ @ np.concatenate([theta[[0, 3]], p]), theta, atol=1e-12)


def test_swing_model_structure_and_equilibrium():
    B = susceptance_matrix(4, F, T, B_BR)
    M, D = np.array([0.2, 0.1]), np.array([0.02, 0.01])
    m = swing_model(B, np.array([0, 3]), M=M, D=D, input_bus=np.array([1, 2]))
    A = m.A
    assert np.array_equal(A[:2, 2:], np.eye(2)) and np.allclose(A[2:, 2:], -np.diag(D / M))
    ev = np.linalg.eigvals(A)
    assert np.sum(np.abs(ev) < 1e-12) == 1 and np.max(ev.real) < 1e-12  # one rotation mode, the rest decays
    p = np.array([1.0, -0.3, -0.5, -0.2])
    x = m.equilibrium(p, ref=0, angle=0.25)
    assert x[0] == 0.25 and np.array_equal(x[2:], [0.0, 0.0])
    Bp = np.zeros((4, 4))
    Bp[2:] = m.K / M[:, None]
    assert np.allclose(A @ x + Bp @ p, 0.0, atol=1e-12)
    Ad, Bd = zoh(A, Bp, 0.01)
    assert np.allclose(Ad @ x + Bd @ p, x, atol=1e-12)  # the exact discretisation keeps the rest state
    # a load increase at bus 1 (the model's input) decelerates both machines
    assert np.all(m.B[2:, 0] < 0) and np.array_equal(m.B[:2], np.zeros((2, 2)))


def test_pmu_rows_and_errors():
    B = susceptance_matrix(4, F, T, B_BR)
    m = swing_model(B, np.array([0, 3]), M=np.ones(2), D=np.ones(2), input_bus=np.array([1]))
    assert np.array_equal(m.pmu_rows(3), [[0, 1, 0, 0], [0, 0, 0, 1]])
    with pytest.raises(DesignError, match="bus 1 has no generator"):
        m.pmu_rows(1)
    with pytest.raises(DesignError, match="B_ll is singular"):
        kron_reduce(susceptance_matrix(4, F[:1], T[:1], B_BR[:1]), np.array([0, 1]))  # buses 2, 3 islanded
    with pytest.raises(DesignError, match="inertias must be > 0"):
        swing_model(B, np.array([0, 3]), M=np.array([1.0, 0.0]), D=np.ones(2), input_bus=np.array([1]))


def test_inertia_and_damping_per_unit():
    # H = 5 s on 100 MVA at 60 Hz, system base 100 MVA: M = 2 H / omega_s
    assert inertia(5.0, 100.0, base_mva=100.0, f_hz=60.0) == pytest.approx(10 / (2 * np.pi * 60))
    assert damping(2.0, 200.0, base_mva=100.0, f_hz=50.0) == pytest.approx(4 / (2 * np.pi * 50))
