"""Secure decoding of compressed windows against random supports and attack values, and
the plain least-squares baseline (Mao-Tabuada, Sections III-D and VI)."""

from itertools import combinations

import numpy as np
import pytest

from estimation.errors import DesignError
from estimation.mao_tabuada import example, window_observability
from estimation.secure_decoder import SecureDecoder, compressed_observability, least_squares_decode
from estimation.sparse_detectability import design_compression


@pytest.fixture(scope="module")
def setup():
    ex = example()
    D = design_compression(ex.A, ex.C, s=ex.s).D
    O = window_observability(ex.A, ex.C)
    return ex, D, O, SecureDecoder(O, D, s=ex.s)


def _compress(D, O, x, E):
    return np.einsum("ri,im->rm", D, O @ x + E)


def test_random_supports_and_attack_values(setup):
    ex, D, O, dec = setup
    p, n = O.shape[0], O.shape[2]
    rng = np.random.default_rng(2024)
    for trial in range(200):
        x = rng.standard_normal(n) * 10 ** rng.uniform(-3, 6)
        size = rng.integers(0, ex.s + 1)
        V = sorted(rng.choice(p, size=size, replace=False))
        E = np.zeros((p, n))
        for i in V:  # arbitrary windows, magnitudes from tiny to huge relative to the signal
            E[i] = rng.standard_normal(n) * np.linalg.norm(x) * 10 ** rng.uniform(-4, 4)
        res = dec.decode(_compress(D, O, x, E))
        assert np.linalg.norm(res.x - x) <= 1e-8 * np.linalg.norm(x), (trial, V)
        assert set(V) <= set(res.support) and len(res.support) == ex.s
        assert res.residual <= 1e-10


def test_least_squares_is_fooled_by_the_same_attacks(setup):
    ex, D, O, dec = setup
    rng = np.random.default_rng(7)
    x = rng.standard_normal(4)
    E = np.zeros((8, 4))
    E[list(ex.attacked)] = rng.standard_normal((2, 4))
    Z = _compress(D, O, x, E)
    assert np.linalg.norm(least_squares_decode(Z, O, D).x - x) > 1e-2 * np.linalg.norm(x)
    assert np.allclose(dec.decode(Z).x, x, rtol=0, atol=1e-10)
    # without attacks least squares is exact
    assert np.allclose(least_squares_decode(_compress(D, O, x, 0 * E), O, D).x, x, atol=1e-12)


def test_every_support_pair_with_a_dynamics_consistent_attack(setup):
    # attacks that are outputs of another initial state, on every pair of nodes
    ex, D, O, dec = setup
    x, xa = np.array(ex.x0), np.array(ex.x0_attack)
    for V in combinations(range(8), 2):
        E = np.zeros((8, 4))
        E[list(V)] = O[list(V)] @ (xa - x)
        res = dec.decode(_compress(D, O, x, E))
        assert res.support == V
        np.testing.assert_allclose(res.x, x, atol=1e-11)


def test_random_systems_with_identity_compression():
    rng = np.random.default_rng(3)
    for _ in range(10):
        n, p, s = 3, 6, 1
        A = rng.standard_normal((n, n))
        C = rng.standard_normal((p, n))
        O = window_observability(A, C)
        dec = SecureDecoder(O, np.eye(p), s=s)
        assert dec.n_supports == 6
        x = rng.standard_normal(n)
        E = np.zeros((p, n))
        E[rng.integers(p)] = rng.standard_normal(n) * 100
        np.testing.assert_allclose(dec.decode(O @ x + E).x, x, atol=1e-8)


def test_shapes_and_errors(setup):
    ex, D, O, dec = setup
    assert compressed_observability(O, D).shape == (D.shape[0] * 4, 4)
    with pytest.raises(DesignError, match="shape"):
        dec.decode(np.zeros((3, 3)))
    with pytest.raises(DesignError, match=r"s must be"):
        SecureDecoder(O, D, s=8)
    with pytest.raises(DesignError, match=r"D must have shape"):
        SecureDecoder(O, D[:, :5], s=1)
    assert dec.decode(np.zeros((D.shape[0], 4))).residual == 0.0
