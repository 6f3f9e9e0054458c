"""The partial observers' Kalman gain (estimation.kalman_gain) and the one-decomposition
unobservable subspaces (estimation.observability.unobservable_subspaces)."""

import numpy as np
import pytest
from scipy.linalg import expm

from estimation.errors import DesignError
from estimation.kalman_gain import sampled_kalman_gain
from estimation.lee_kim_shim import LeeKimShim, design
from estimation.observability import unobservable_subspace, unobservable_subspaces
from estimation.subspaces import same


def _oscillators(G: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``2G`` states: ``G`` lightly damped masses on a random weighted path (a swing-like plant)."""
    rng = np.random.default_rng(seed)
    w = rng.uniform(1.0, 50.0, G - 1)
    L = np.zeros((G, G))
    for i, wi in enumerate(w):
        L[np.ix_([i, i + 1], [i, i + 1])] += wi * np.array([[1, -1], [-1, 1]])
    M = rng.uniform(0.02, 0.2, G)
    A = np.block([[np.zeros((G, G)), np.eye(G)], [-L / M[:, None], -0.2 * np.eye(G)]])
    return A, M


def test_scalar_gain_is_the_riccati_closed_form():
    a, dt = -0.5, 0.1
    phi = np.exp(a * dt)
    # the DARE with Q = R = 1: P = phi^2 P / (P + 1) + 1, i.e. P^2 - phi^2 P - 1 = 0
    P = (phi**2 + np.sqrt(phi**4 + 4.0)) / 2.0
    Ld, poles = sampled_kalman_gain(np.array([[a]]), np.array([[1.0]]), dt)
    assert Ld[0, 0] == pytest.approx(phi * P / (P + 1.0), rel=1e-12)
    assert poles[0].real == pytest.approx(np.log(phi - Ld[0, 0]) / dt, rel=1e-12)
    assert poles[0].real < a  # the observer converges faster than the plant decays


def test_gain_on_a_hundred_state_oscillator_chain_seen_at_one_end_is_moderate_and_stable():
    """Where pole placement needs huge gains (every mode to one real part through one PMU),
    the Kalman gain is O(1) and its sampled error dynamics are Schur stable."""
    A, _ = _oscillators(50)
    C = np.zeros((2, 100))
    C[0, 0], C[1, 50] = 1.0, 1.0  # angle and frequency of mass 1
    dt = 0.01
    Ld, poles = sampled_kalman_gain(A, C, dt)
    F = expm(A * dt) - Ld @ C
    assert np.max(np.abs(np.linalg.eigvals(F))) < 1.0
    assert np.all(poles.real < 0)
    assert np.max(np.abs(Ld)) < 10.0
    np.testing.assert_allclose(np.sort_complex(np.exp(poles * dt)), np.sort_complex(np.linalg.eigvals(F)), atol=1e-9)


def test_design_with_kalman_gains_and_the_agent_refuses_another_step():
    A, _ = _oscillators(6, seed=1)
    B = np.zeros((12, 1))
    Cs = [np.eye(12)[[0, 6]], np.eye(12)[[3, 9]], np.eye(12)[[5, 11]]]
    des = design(A, B, Cs, gains="kalman", dt=0.01)
    for ob in des.observers:
        assert ob.Ld is not None and ob.dt == 0.01 and np.all(ob.poles.real < 0)
    kw = dict(kappa=1.0, gamma=1.0, input_fn=lambda t: np.zeros(1), x0=np.zeros(12), max_degree=2)
    LeeKimShim(des, agent=0, dt=0.01, **kw)
    with pytest.raises(DesignError, match="designed for dt = 0.01, the agent steps 0.02"):
        LeeKimShim(des, agent=0, dt=0.02, **kw)
    with pytest.raises(DesignError, match="unknown observer gain design 'lqr'"):
        design(A, B, Cs, gains="lqr", dt=0.01)


def test_one_decomposition_equals_the_recursion_with_hidden_modes():
    rng = np.random.default_rng(1)
    blocks = np.zeros((12, 12))
    blocks[:6, :6], blocks[6:, 6:] = rng.normal(size=(6, 6)), rng.normal(size=(6, 6))
    T = rng.normal(size=(12, 12))
    A = T @ blocks @ np.linalg.inv(T)
    Ti = np.linalg.inv(T)
    C1 = np.hstack([rng.normal(size=(1, 6)), np.zeros((1, 6))]) @ Ti  # sees the first block only
    C2 = np.hstack([np.zeros((1, 6)), rng.normal(size=(1, 6))]) @ Ti
    fast = unobservable_subspaces(A, [C1, C2, C1 + C2])
    slow = [unobservable_subspace(C, A) for C in (C1, C2, C1 + C2)]
    assert [U.shape[1] for U in fast] == [6, 6, 0]
    assert all(same(a, b) for a, b in zip(fast, slow))


def test_repeated_eigenvalues_fall_back_to_the_recursion():
    A = np.kron(np.eye(3), np.diag([-1.0, -2.0, -3.0]))  # three identical decoupled cells
    C = np.zeros((1, 9))
    C[0, 0] = 1.0
    (U,) = unobservable_subspaces(A, [C])
    assert same(U, unobservable_subspace(C, A)) and U.shape[1] == 8


def test_neighbour_values_come_in_the_senders_order_whatever_the_arrival():
    """A sum over them rounds alike in the simulator and in processes, where messages
    arrive in any order."""
    from estimation.base import Received, held

    a, b, c = np.array([0.1]), np.array([0.2]), np.array([0.3])
    arrived = {5: Received(5, 3, c), 1: Received(1, 3, a), 2: Received(2, 1, b)}
    assert [v[0] for v in held(arrived, 3, max_age=3)] == [0.1, 0.2, 0.3]
    assert [v[0] for v in held(arrived, 3, max_age=1)] == [0.1, 0.3]  # stamped 1: too old


def test_large_agents_step_on_their_own():
    """Above BATCH_MAX_N states the simulator does not stack Lee-Kim-Shim agents."""
    from estimation.lee_kim_shim import BATCH_MAX_N

    for G, batched in ((6, True), (BATCH_MAX_N // 2 + 1, False)):
        A, _ = _oscillators(G, seed=2)
        n = 2 * G
        Cs = [np.eye(n)[[0, G]], np.eye(n)[[G - 1, n - 1]]]
        des = design(A, np.zeros((n, 1)), Cs, gains="kalman", dt=0.01)
        est = LeeKimShim(des, agent=0, kappa=1.0, gamma=1.0, dt=0.01, input_fn=lambda t: np.zeros(1),
                         x0=np.zeros(n), max_degree=1)
        assert (est.batch_key() is not None) is batched, n
