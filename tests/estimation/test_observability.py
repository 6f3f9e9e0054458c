"""Kalman decompositions, the common basis of Assumption 4 and 2q-redundancy
(Lee, Kim, Shim, Appendix B items 4 and 8, and the Section IV plant)."""

import numpy as np
import pytest

from estimation.errors import DesignError
from estimation.lti import three_inertia
from estimation.observability import common_basis, redundancy_violations, unobservable_subspace
from estimation.subspaces import contains


def rows(C):
    return [np.atleast_2d(np.asarray(r, dtype=float)) for r in C]


def spans(Q, vectors):
    V = np.column_stack(vectors)
    return Q.shape[1] == V.shape[1] and contains(Q, V)


@pytest.mark.parametrize("star", [0.0, 0.3, -2.0])
def test_item4_basis_exists(star):
    lam = 2.0
    A = np.array([[lam, 0, 0], [0, lam, 1], [0, 0, lam]])
    C = rows([[1, 1, star], [1, -1, star], [2, 2, star]])
    v1, v2, _v3 = np.array([1.0, 1, 0]), np.array([1.0, -1, 0]), np.array([0.0, 0, 1])
    U = [unobservable_subspace(c, A) for c in C]
    assert spans(U[0], [v2]) and spans(U[2], [v2]) and spans(U[1], [v1])
    b = common_basis(A, C)
    assert np.allclose(b.W @ b.V, np.eye(3))
    for i, Ui in enumerate(U):  # each U_i is the span of the basis vectors with s_i^l = 0
        hidden = b.V[:, b.S[i] == 0]
        assert spans(Ui, list(hidden.T))
    # the paper's counts: every direction observable from >= 1 bank, U_1 = U_3 one-dimensional
    assert b.S.sum(axis=1).tolist() == [2, 2, 2]


def test_item4_no_basis_when_c3_changes():
    A = np.array([[2.0, 0, 0], [0, 2, 1], [0, 0, 2]])
    C = rows([[1, 1, 0.3], [1, -1, 0.3], [1, 2, 0.3]])
    assert spans(unobservable_subspace(C[2], A), [np.array([2.0, -1, 0])])
    with pytest.raises(DesignError, match="Assumption 4"):
        common_basis(A, C)


ITEM8_A = np.array([[0, 1, 0, 0], [-1, 0, 0, 0], [0, 0, 0, 1], [0, 0, -1, 0.0]])
ITEM8_C = [[-1, 0, 0, 1], [1, 1, 0, 0], [0, 1, 1, 0], [1, -1, 0, 0], [-1, 1, 1, 1], [1, 0, 0, 0]]


def test_item8_basis_and_subspaces():
    C = rows(ITEM8_C)
    e3, e4 = np.eye(4)[2], np.eye(4)[3]
    v3, v4 = np.array([0.0, 1, -1, 0]), np.array([1.0, 0, 0, 1])
    U = [unobservable_subspace(c, ITEM8_A) for c in C]
    for i in (0, 2, 4):
        assert spans(U[i], [v3, v4])
    for i in (1, 3, 5):
        assert spans(U[i], [e3, e4])
    b = common_basis(ITEM8_A, C)
    assert b.method == "lattice"
    assert (b.S[[0, 2, 4]].sum(axis=1) == 2).all() and (b.S[[1, 3, 5]].sum(axis=1) == 2).all()
    for i, Ui in enumerate(U):
        assert spans(Ui, list(b.V[:, b.S[i] == 0].T))


def test_item8_no_basis_when_c1_changes():
    C = rows(ITEM8_C)
    C[0] = np.array([[2.0, 0, 0, 1]])
    assert spans(unobservable_subspace(C[0], ITEM8_A), [np.array([1.0, 0, 0, -2]), np.array([0.0, 1, 2, 0])])
    with pytest.raises(DesignError, match="Assumption 4"):
        common_basis(ITEM8_A, C)


def test_three_inertia_modal_basis_normalisation():
    p = three_inertia()
    b = common_basis(p.A, p.banks)
    assert b.method == "modal"
    lam = np.linalg.eigvals(p.A)
    n_complex_pairs = int(np.sum(lam.imag > 1e-9))
    assert n_complex_pairs == 2
    V = b.V
    # real vectors first (two real eigenvalues), then (Re, Im) pairs
    for l in range(2):
        assert np.linalg.norm(V[:, l]) == pytest.approx(1.0)
    for l in (2, 4):
        re, im = V[:, l], V[:, l + 1]
        assert re @ im == pytest.approx(0.0, abs=1e-12)
        assert re @ re + im @ im == pytest.approx(2.0)
    # theta1, theta3 observe everything; the relative sensors miss the rigid-body modes
    assert b.S[0].all() and b.S[2].all()
    assert b.S[3, :2].sum() == 0 and b.S[4, :2].sum() == 0
    # Lemma 1: every direction observable from >= 2q + 1 = 3 banks
    assert (b.S.sum(axis=0) >= 3).all()


def test_three_inertia_redundancy():
    p = three_inertia()
    assert redundancy_violations(p.A, p.banks, 1) == []  # 2-redundant observable
    bad = redundancy_violations(p.A, p.banks, 2)  # one bank alone is not enough
    assert {s for s, _ in bad} == {(1,), (3,), (4,)}
