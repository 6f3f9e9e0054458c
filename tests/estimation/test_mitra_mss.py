"""Theorem 2's mean-square-stability condition (eqs. (23)-(24)) of Mitra et al."""

import math

import numpy as np
import pytest

from estimation.cells import cells
from estimation.errors import DesignError
from estimation.modal import modal_form
from estimation.mss import (
    effective_erasure_probability,
    is_mean_square_stable,
    max_erasure_probability,
    mss_margin,
    robustness_multiplier,
)
from estimation.robustness import cell_graph, strong_robustness


def test_largest_erasure_probability_for_the_paper_setup():
    p = max_erasure_probability(rho=1.2, m=3, f=1)
    assert round(p, 4) == 0.3265
    assert p == pytest.approx(1.0 - (1.0 - 1.0 / 1.44) ** (1.0 / 3.0), abs=1e-12)
    assert mss_margin(p, rho=1.2, m=3, f=1) == pytest.approx(1.0, abs=1e-12)
    # the paper runs at its (truncated) maximum 0.32; Fig. 9's p = 0.8 violates (23)
    assert is_mean_square_stable(0.32, rho=1.2, m=3, f=1)
    assert not is_mean_square_stable(0.33, rho=1.2, m=3, f=1)
    assert not is_mean_square_stable(0.8, rho=1.2, m=3, f=1)


def test_four_cell_setup_gives_m_3_and_0_32():
    """rho from the cells plant, m from the strong robustness of the Fig. 5 graph."""
    model = cells(4, np.random.default_rng(0))
    rho = modal_form(model.A, blocks=model.blocks).spectral_radius
    assert rho == pytest.approx(1.2)
    adj = cell_graph(4, 4)
    r = min(strong_robustness(adj, range(4 * c, 4 * c + 4)) for c in range(4))
    assert r == 4
    m = robustness_multiplier(r, f=1)
    assert m == 3
    p = max_erasure_probability(rho=rho, m=m, f=1)
    assert 0.32 <= p < 0.33
    assert round(p, 4) == 0.3265


def test_pbar_formula_and_remarks():
    p = np.linspace(0, 1, 11)
    # m = 3, f = 1: one term l = 3 of binom(3, 3)
    np.testing.assert_allclose(effective_erasure_probability(p, m=3, f=1), 1 - (1 - p) ** 3)
    # m = 4, f = 1: (m-1)f+1 = 4 regular neighbours, at least 3 must get through
    q = 1 - p
    ok = 4 * q**3 * p + q**4
    np.testing.assert_allclose(effective_erasure_probability(p, m=4, f=1), 1 - ok)
    # Remark 12: f = 0 gives pbar = p
    np.testing.assert_allclose(effective_erasure_probability(p, m=3, f=0), p)
    # Remark 13: m <= 2 certifies nothing
    assert effective_erasure_probability(0.0, m=2, f=1) == 1.0
    assert max_erasure_probability(rho=1.2, m=2, f=1) == 0.0
    # Remark 11: pbar increases in p and decreases in m
    assert np.all(np.diff(effective_erasure_probability(p, m=5, f=2)) >= 0)
    assert effective_erasure_probability(0.3, m=5, f=1) < effective_erasure_probability(0.3, m=3, f=1)
    assert max_erasure_probability(rho=1.2, m=5, f=1) > max_erasure_probability(rho=1.2, m=3, f=1)
    # Section 8.2: a marginally stable plant tolerates any p < 1
    assert max_erasure_probability(rho=1.0, m=3, f=1) == 1.0
    assert is_mean_square_stable(0.8, rho=1.0, m=3, f=1)


def test_multiplier_and_errors():
    assert robustness_multiplier(4, f=1) == 3
    assert robustness_multiplier(7, f=2) == 3
    assert robustness_multiplier(math.inf, f=1) == math.inf
    with pytest.raises(DesignError, match="erasure probability"):
        effective_erasure_probability(1.5, m=3, f=1)
    with pytest.raises(DesignError, match="m must be an integer"):
        effective_erasure_probability(0.1, m=0, f=1)
