"""Median fusion (5) with fewer than N/2 corrupted observers (van der Horst et al., Theorem 1)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimation.median_bank import median_fuse


@settings(max_examples=300, deadline=None)
@given(
    N=st.integers(1, 9),
    n=st.integers(1, 4),
    seed=st.integers(0, 2**31 - 1),
    huge=st.floats(-1e12, 1e12, allow_nan=False),
)
def test_median_stays_within_the_honest_range(N, n, seed, huge):
    rng = np.random.default_rng(seed)
    M = (N - 1) // 2  # the largest budget with N > 2M
    honest = rng.normal(size=(N - M, n))
    bad = np.full((M, n), huge) + rng.normal(size=(M, n)) * abs(huge) * rng.integers(0, 2)
    rows = np.concatenate([bad, honest])[rng.permutation(N)]
    med = median_fuse(rows, n_attacked=M)
    assert med.shape == (n,)
    assert np.all(med >= honest.min(axis=0) - 1e-12)
    assert np.all(med <= honest.max(axis=0) + 1e-12)


def test_median_removes_two_of_five_exactly():
    truth = np.array([1.0, -2.0, 3.0])
    rows = np.stack([truth, truth + 1e6, truth, -1e9 * np.ones(3), truth])
    np.testing.assert_array_equal(median_fuse(rows, n_attacked=2), truth)


def test_median_even_N_averages_the_middle_pair():
    np.testing.assert_allclose(median_fuse(np.array([[0.0], [1.0], [3.0], [100.0]])), [2.0])


def test_median_rejects_a_budget_without_honest_majority():
    with pytest.raises(ValueError, match="N > 2M"):
        median_fuse(np.zeros((4, 2)), n_attacked=2)
    with pytest.raises(ValueError):
        median_fuse(np.zeros((0, 2)))
