"""Measurement windows, companion dynamics, the latched local sanity check (Section V),
the signal limit for long runs and the estimator interface."""

import numpy as np
import pytest

from estimation.base import Estimator, Received
from estimation.errors import DesignError, NumericalError
from estimation.mao_tabuada import (
    SIGNAL_LIMIT,
    MaoTabuadaEstimator,
    MeasurementWindow,
    companion,
    design_mao_tabuada,
    example,
    safe_horizon,
    window_observability,
)


@pytest.fixture(scope="module")
def ex():
    return example()


@pytest.fixture(scope="module")
def design(ex):
    return design_mao_tabuada(ex.A, ex.C, ex.Adj, s=ex.s)


def _outputs(A, C, x0, rounds):
    x, ys = np.array(x0, dtype=float), []
    for _ in range(rounds):
        ys.append(C @ x)
        x = A @ x
    return np.array(ys)


def test_companion_and_window_observability(ex):
    Ahat, alpha = companion(ex.A)
    np.testing.assert_allclose(np.sort_complex(np.linalg.eigvals(Ahat)), np.sort_complex(np.linalg.eigvals(ex.A)), atol=1e-12)
    np.testing.assert_allclose(np.poly(ex.A)[1:], alpha[::-1], atol=1e-14)
    O = window_observability(ex.A, ex.C)
    ys = _outputs(ex.A, ex.C, ex.x0, 12)
    x = np.array(ex.x0)
    for k in range(3, 12):
        Yk, Yprev = ys[k - 3 : k + 1].T, ys[k - 4 : k].T if k >= 4 else None
        np.testing.assert_allclose(Yk, O @ (np.linalg.matrix_power(ex.A, k - 3) @ x), atol=1e-12)
        if Yprev is not None:
            np.testing.assert_allclose(Yk, Yprev @ Ahat.T, atol=1e-12)  # eq. (5), discrete


def test_honest_window_never_flags_over_a_long_growing_run(ex):
    Ahat, alpha = companion(ex.A)
    ys = _outputs(ex.A, ex.C, ex.x0, 3000)  # |y| grows to ~1e50
    assert np.abs(ys).max() > 1e45
    for i in range(8):
        w = MeasurementWindow(alpha)
        for k, y in enumerate(ys[:, i]):
            w.push(k, y)
        assert not w.flagged
        np.testing.assert_allclose(w.values, ys[-4:, i], rtol=1e-15)


def test_bias_is_flagged_in_the_round_it_starts_and_latched(ex):
    _, alpha = companion(ex.A)
    ys = _outputs(ex.A, ex.C, ex.x0_attack, 300)[:, 5]  # a dynamics-consistent attack
    w = MeasurementWindow(alpha)
    for k in range(300):
        w.push(k, ys[k] + (1.0 if 150 <= k < 152 else 0.0))  # bias on for two rounds only
        assert w.flagged == (k >= 150)
    assert w.flag_round == 150
    # after the flag the window follows the last sane window's prediction
    np.testing.assert_allclose(w.values, ys[-4:], rtol=1e-10)


def test_small_relative_violation_is_seen_at_any_magnitude(ex):
    _, alpha = companion(ex.A)
    ys = _outputs(ex.A, ex.C, ex.x0, 2000)[:, 0]
    w = MeasurementWindow(alpha, rtol=1e-9)
    for k in range(1999):
        w.push(k, ys[k])
    w.push(1999, ys[1999] * (1 + 1e-6))
    assert w.flagged and w.flag_round == 1999


def test_missing_samples(ex):
    _, alpha = companion(ex.A)
    ys = _outputs(ex.A, ex.C, ex.x0, 20)[:, 1]
    w = MeasurementWindow(alpha)
    w.push(0, ys[0])
    w.push(1, None)  # before the window is full: start again
    assert not w.full
    for k in range(2, 10):
        w.push(k, ys[k])
    w.push(10, None)  # full: predicted
    w.push(11, ys[11])
    assert not w.flagged
    np.testing.assert_allclose(w.values, ys[8:12], rtol=1e-12)


def test_safe_horizon():
    assert safe_horizon(np.array([[2.0]]), x0_norm=1.0, limit=1e3) == 9  # 2^9 <= 1e3 < 2^10
    ex = example()
    h = safe_horizon(ex.A, x0_norm=np.linalg.norm(ex.x0))
    assert ex.rounds < h < 20000
    assert np.linalg.norm(np.linalg.matrix_power(ex.A, h)) * np.linalg.norm(ex.x0) < 2 * SIGNAL_LIMIT


def test_estimator_interface(design):
    est = MaoTabuadaEstimator(design, node=0)
    assert isinstance(est, Estimator)
    out = est.step(0, np.array([0.5]), {})
    assert out.shape == (2 * design.v * design.n,)
    out2 = est.step(1, None, {1: Received(1, 0, out)})  # missing measurement, one message
    assert np.all(np.isfinite(out2))
    e = est.estimate
    e[:] = 1e9
    assert not np.allclose(est.estimate, 1e9)
    est.step(4, np.array([0.1]), {})  # rounds 2, 3 skipped: predicted
    with pytest.raises(DesignError, match="rounds must increase"):
        est.step(4, np.array([0.1]), {})
    with pytest.raises(DesignError, match="one scalar"):
        est.step(5, np.array([0.1, 0.2]), {})
    with pytest.raises(NumericalError, match="signal limit"):
        est.step(6, np.array([1e200]), {})
    with pytest.raises(DesignError, match="node must be"):
        MaoTabuadaEstimator(design, node=8)
    with pytest.raises(DesignError, match="decoder"):
        MaoTabuadaEstimator(design, node=1, decoder="median")


def test_design_arrays_are_read_only(design):
    with pytest.raises(ValueError):
        design.A[0, 0] = 3.0
    with pytest.raises(ValueError):
        design.D[0, 0] = 3.0


def test_given_D_is_checked(ex):
    with pytest.raises(DesignError, match=r"not 4-sparse detectable w.r.t. the given D \(v = 4\)"):
        design_mao_tabuada(ex.A, ex.C, ex.Adj, s=2, D=np.random.default_rng(0).standard_normal((4, 8)))
