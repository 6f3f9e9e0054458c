"""Sparse detectability w.r.t. D (Mao-Tabuada Definition 3, Lemmas 1-2, Corollary 1) on
small systems checked by hand, and the search for a compression matrix."""

import numpy as np
import pytest

from estimation.errors import DesignError
from estimation.mao_tabuada import example
from estimation.sparse_detectability import design_compression, sparse_detectability, sparse_detectability_index


def test_scalar_plant_three_identical_sensors():
    # x[k+1] = 2 x[k], three sensors y_i = x: removing any 2 leaves one -> index 2, not 3.
    A, C = np.array([[2.0]]), np.ones((3, 1))
    assert sparse_detectability(A, C, k=2).holds
    assert not sparse_detectability(A, C, k=3).holds
    assert sparse_detectability_index(A, C) == 2
    # D = [1 1 1]: D e_i = 1 spans R^1, so L_V = 0 for any single sensor -> index 0.
    assert sparse_detectability_index(A, C, D=np.ones((1, 3))) == 0


def test_compression_rows_by_hand():
    A, C = np.array([[2.0]]), np.ones((3, 1))
    # D = [[1,1,0],[0,1,1]]: DC = (2, 2); removing sensor 1 leaves L ~ (1,-1), L D C = 0.
    rep = sparse_detectability(A, C, k=1, D=np.array([[1.0, 1, 0], [0, 1, 1]]))
    assert not rep.holds and rep.worst_support == (1,)
    # D = [[1,2,0],[0,1,1]]: DC = (3, 2); L for sensors 0, 1, 2 gives 2, -1, 3 (all non-zero).
    D = np.array([[1.0, 2, 0], [0, 1, 1]])
    assert sparse_detectability(A, C, k=1, D=D).holds
    # v = 2 <= k = 2: range(D_V) = R^2 for some V, nothing survives.
    assert not sparse_detectability(A, C, k=2, D=D).holds
    assert sparse_detectability_index(A, C, D=D) == 1


def test_detectable_but_not_observable():
    # mode 2 (unstable) seen by sensors 0, 1, 2; mode 0.5 (stable) only by sensor 3.
    C = np.array([[1.0, 0], [1, 0], [1, 0], [0, 1]])
    assert sparse_detectability_index(np.diag([2.0, 0.5]), C) == 2
    # the same sensors with the second mode unstable: losing sensor 3 already hides it.
    assert sparse_detectability_index(np.diag([2.0, 1.5]), C) == 0
    # |mu| = 1 counts as not stable in discrete time
    assert sparse_detectability_index(np.diag([2.0, -1.0]), C) == 0


def test_schur_plant_is_always_detectable():
    A = np.diag([0.5, -0.3])
    C = np.array([[1.0, 0.0], [0.0, 0.0]])
    assert sparse_detectability_index(A, C) == 2


def test_not_2s_sparse_detectable_gives_design_error():
    # only sensors 0 and 1 see the unstable mode: s = 1 attacker plus 1 ambiguity hides it.
    A = np.diag([2.0, 0.5])
    C = np.array([[1.0, 0], [1, 0], [0, 1]])
    assert sparse_detectability_index(A, C) == 1
    with pytest.raises(DesignError, match=r"not 2-sparse detectable.*no compression matrix D exists"):
        design_compression(A, C, s=1)
    # Lemma 1: no D of any size works either
    rng = np.random.default_rng(0)
    for v in (1, 2, 3, 5):
        assert not sparse_detectability(A, C, k=2, D=rng.standard_normal((v, 3))).holds


def test_search_on_the_example_finds_minimal_rows():
    ex = example()
    p, s = ex.C.shape[0], ex.s
    ident = sparse_detectability(ex.A, ex.C, k=2 * s)
    assert ident.holds and ident.v == p  # identity always works (Corollary 1)
    rep = design_compression(ex.A, ex.C, s=s)
    assert rep.holds and rep.v == 2 * s + 1 < p
    assert rep.margin > 1e-3 and rep.cond_D == pytest.approx(1.0)
    assert sparse_detectability(ex.A, ex.C, k=2 * s, D=rep.D).holds
    assert rep.supports_checked == 70  # C(8, 4)
    # the example's written-out D is this search result, rounded
    np.testing.assert_allclose(ex.D, rep.D, atol=5e-5)
    assert sparse_detectability(ex.A, ex.C, k=2 * s, D=ex.D).holds
    # v <= 2s is never enough (A is not Schur)
    rng = np.random.default_rng(1)
    for v in range(1, 2 * s + 1):
        for _ in range(5):
            assert not sparse_detectability(ex.A, ex.C, k=2 * s, D=rng.standard_normal((v, p))).holds


def test_search_falls_back_to_identity():
    # p = 3, s = 1: v = 2s+1 = 3 = p, so only the identity is left
    A = np.array([[2.0]])
    rep = design_compression(A, np.ones((3, 1)), s=1)
    assert rep.holds and np.array_equal(rep.D, np.eye(3))


@pytest.mark.parametrize(
    "A, C, kw, msg",
    [
        (np.ones((2, 3)), np.ones((3, 3)), {"k": 1}, "square"),
        (np.eye(2), np.ones((3, 3)), {"k": 1}, r"shape \(p, 2\)"),
        (np.eye(2), np.ones((3, 2)), {"k": -1}, "non-negative"),
        (np.eye(2), np.ones((3, 2)), {"k": 1, "D": np.ones((2, 4))}, r"shape \(v, 3\)"),
    ],
)
def test_input_errors(A, C, kw, msg):
    with pytest.raises(DesignError, match=msg):
        sparse_detectability(A, C, **kw)
