"""The W-MSR update and the modal design on their own (run by rse's suite with the package
installed)."""

import numpy as np
import pytest
from rse_wmsr.wmsr import WmsrObserver, average, design, wmsr

from estimation.errors import DesignError


def test_wmsr_removes_f_values_on_each_side_of_its_own():
    # own 0: 100 (the largest above) and -1 (the smallest below) are removed
    assert wmsr(np.array([0.0]), np.array([[100.0], [1.0], [-1.0]]), 1) == pytest.approx([0.5])
    # fewer than f above its own: every value above is removed; f = 2 below: both removed
    assert wmsr(np.array([0.0]), np.array([[1.0], [-1.0], [-2.0]]), 2) == pytest.approx([0.0])
    # values equal to its own are kept
    assert wmsr(np.array([1.0]), np.array([[1.0], [1.0], [5.0]]), 1) == pytest.approx([1.0])
    # per component, no neighbour: its own value
    got = wmsr(np.array([0.0, 10.0]), np.array([[3.0, 10.0], [1.0, -50.0], [2.0, 11.0]]), 1)
    assert got == pytest.approx([(0 + 1 + 2) / 3, (10 + 10) / 2])  # 2nd: 11 and -50 removed
    assert wmsr(np.array([2.0]), np.zeros((0, 1)), 1) == pytest.approx([2.0])
    assert average(np.array([0.0]), np.array([[100.0], [1.0], [-1.0]])) == pytest.approx([25.0])


def test_wmsr_stays_within_the_regular_values_whatever_f_adversaries_send():
    """The property the convergence argument rests on (LeBlanc et al. 2013, Lemma 1 with
    an F-local adversary): with at most F adversarial values among the in-neighbours' and
    at least 2F + 1 values in all, the result lies between the smallest and the largest of
    the regular values and its own."""
    rng = np.random.default_rng(7)
    for _ in range(2000):
        f = int(rng.integers(0, 3))
        d = int(rng.integers(2 * f + 1, 2 * f + 6))
        own = rng.normal(size=3)
        regular = rng.normal(size=(d - f, 3))
        bad = rng.choice([-1e6, 1e6, 0.0, 3.0], size=(f, 3)) * rng.uniform(0.5, 2, size=(f, 3))
        vals = rng.permutation(np.vstack([regular, bad]))
        got = wmsr(own, vals, f)
        lo = np.minimum(own, regular.min(axis=0))
        hi = np.maximum(own, regular.max(axis=0))
        assert np.all(got >= lo - 1e-12) and np.all(got <= hi + 1e-12)


A = np.array([[1.0, 0.1, 0.0], [0.0, 0.95, 0.0], [0.0, 0.0, -1.0]])
C = [np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 0.0, 1.0]]), np.array([[0.0, 1.0, 0.0]])]


def test_design_places_each_local_observers_poles():
    des = design(A, C, pole=0.5)
    assert des.lam == pytest.approx([1.0, 0.95, -1.0])
    assert des.V @ np.diag(des.lam) @ des.W == pytest.approx(A)
    assert [ob.observed.tolist() for ob in des.observers] == [[0, 1], [2], [1]]
    for ob in des.observers:
        lam_o = np.diag(des.lam[ob.observed])
        poles = np.sort(np.linalg.eigvals(lam_o - ob.L @ ob.C).real)
        assert poles == pytest.approx(np.sort(0.5 * (1 - 0.1 * np.arange(ob.observed.size))))


def test_design_errors_name_the_problem():
    with pytest.raises(DesignError, match="complex eigenvalues"):
        design(np.array([[0.0, 1.0], [-1.0, 0.0]]), [np.eye(2)], pole=0.5)
    with pytest.raises(DesignError, match=r"mode 3 \(eigenvalue -1\) is observed by no agent"):
        design(A, C[:1], pole=0.5)


def test_an_observer_alone_converges_on_what_it_sees():
    des = design(A, C, pole=0.5)
    x = np.array([0.3, -0.2, 0.7])
    est = WmsrObserver(des, agent=0, x0=np.zeros(3), f=1)
    for k in range(60):
        est.step(k, C[0] @ x, {})  # no neighbours: mode 3 is never corrected
        if k < 59:
            x = A @ x
    err = des.W @ (est.estimate - x)
    assert np.abs(err[:2]).max() < 1e-12  # modes 1 and 2, seen through x1
