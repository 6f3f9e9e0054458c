"""Monitor blocks over transformed coordinates: a 2-D block ``M`` gives the metrics of
``M (x_hat - x)`` (agents.monitor)."""

from dataclasses import replace

import numpy as np
import pytest

from agents.monitor import Monitor
from scenarios.build import build
from scenarios.loader import load
from tests.conftest import SCENARIOS


def _exp(blocks):
    """A real experiment (the Lee-Kim-Shim plant, n = 6, five agents) with these blocks."""
    sc, _ = load(SCENARIOS / "lee_kim_shim.toml", ["run.duration=0.004", "run.dt=0.001", "expect=[]", "output.window=[0.0, 0.004]"])
    return replace(build(sc, source="lee_kim_shim.toml"), blocks=dict(blocks))


def test_matrix_block_metrics_are_those_of_the_mapped_error():
    M = np.array([[1.0, -2.0, 0.0, 0.0, 0.0, 1.0], [0.5, 0.0, 3.0, 0.0, -1.0, 0.0]])
    mon = Monitor(_exp({"x": np.arange(6), "odd": np.array([1]), "Mx": M}))
    rng = np.random.default_rng(0)
    xs, ests = rng.normal(size=(5, 6)), rng.normal(size=(5, 5, 6))
    for k in range(5):
        mon.record(k, xs[k], ests[k])
    b = mon.block_names.index("Mx")
    E = (ests - xs[:, None, :]) @ M.T  # (rounds, agents, 2)
    np.testing.assert_allclose(mon.metric("error_inf")[:, :, b], np.abs(E).max(axis=2))
    np.testing.assert_allclose(mon.metric("error_2")[:, :, b], np.linalg.norm(E, axis=2))
    np.testing.assert_allclose(mon.truth_norm[:, b], np.linalg.norm(xs @ M.T, axis=1))
    np.testing.assert_allclose(mon.metric("relative_error_2")[:, :, b],
                               np.linalg.norm(E, axis=2) / np.linalg.norm(xs @ M.T, axis=1)[:, None])
    # index blocks unchanged
    np.testing.assert_allclose(mon.metric("error_inf")[:, :, 1], np.abs(ests[:, :, 1] - xs[:, None, 1]))
    np.testing.assert_allclose(mon.metric("error_2")[:, :, 0], np.linalg.norm(ests - xs[:, None, :], axis=2))


def test_identity_matrix_block_equals_the_whole_state_and_absent_agents_are_nan():
    mon = Monitor(_exp({"x": np.arange(6), "I": np.eye(6)}))
    x, est = np.ones(6), np.arange(30.0).reshape(5, 6)
    mon.record(0, x, est, present=np.array([True, False, True, True, True]))
    for m in ("error_2", "error_inf", "relative_error_2"):
        a = mon.metric(m)[0]
        np.testing.assert_array_equal(a[:, 0], a[:, 1])
        assert np.isnan(a[1, 1]) and not np.isnan(a[0, 1])


def test_matrix_block_needs_n_columns():
    with pytest.raises(ValueError, match="6 columns"):
        Monitor(_exp({"x": np.arange(6), "bad": np.ones((2, 4))}))


def test_unbuffered_rounds_and_agent_slices_give_the_buffered_metrics_bit_for_bit(monkeypatch):
    """A large team's monitor records a round at once (no chunk buffer) and forms the
    errors a few agents at a time; a small one buffers rounds and forms them all at once:
    the same numbers. relative_error_2 is error_2 / |x_b|, 0 where both are 0."""
    blocks = {"x": np.arange(6), "odd": np.array([1, 3]), "Mx": np.array([[1.0, -2.0, 0.0, 0.0, 0.0, 1.0]])}
    rng = np.random.default_rng(1)
    xs, ests = rng.normal(size=(5, 6)), rng.normal(size=(5, 5, 6))
    xs[2, [1, 3]] = 0.0
    ests[2, 4, [1, 3]] = 0.0  # agent 5 exact on a zero block in round 2: relative error 0
    present = np.array([True, True, False, True, True])
    whole = Monitor(_exp(blocks))
    monkeypatch.setattr(Monitor, "CHUNK_BYTES", 1)  # one round per chunk: not buffered
    monkeypatch.setattr(Monitor, "SLICE_BYTES", 1)  # one agent per slice
    sliced = Monitor(_exp(blocks))
    assert whole._est is not None and sliced._est is None
    for k in range(5):
        whole.record(k, xs[k], ests[k], present)
        sliced.record(k, xs[k], ests[k], present)
    for m in ("error_2", "error_inf", "relative_error_2"):
        np.testing.assert_array_equal(sliced.metric(m), whole.metric(m))
    np.testing.assert_array_equal(sliced.truth_norm, whole.truth_norm)
    b = whole.block_names.index("odd")
    assert whole.metric("relative_error_2")[2, 4, b] == 0.0 and np.isnan(whole.metric("relative_error_2")[2, 2, b])
    e2, xn = whole.metric("error_2")[[0, 1, 3, 4]], whole.truth_norm[[0, 1, 3, 4]]
    np.testing.assert_array_equal(whole.metric("relative_error_2")[[0, 1, 3, 4]], e2 / xn[:, None, :])
