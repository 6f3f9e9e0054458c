"""The distributed median solver (4) and Theorem 1 on adversarial inputs."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimation.graphs import algebraic_connectivity, complete, ring
from estimation.median_solver import median_set, run_scalar_median_solver, sgn_median_term, theorem1_bound


def distance_to(interval, x):
    lo, hi = interval
    return np.maximum(0.0, np.maximum(lo - x, x - hi))


def test_sgn_median_term_matches_paper_signum():
    z = np.array([1.0, -2.0, 0.5, 3.0])
    x = np.array([0.0, 0.0, 0.5, 4.0])
    s = np.array([1, 1, 1, 0])
    assert sgn_median_term(z, x, s).tolist() == [1.0, -1.0, 0.0, 0.0]


def test_median_set_odd_and_even():
    assert median_set(np.array([5.0, 1, 3]), np.array([1, 1, 1])) == (3.0, 3.0)
    assert median_set(np.array([5.0, 1, 3, 100]), np.array([1, 1, 1, 1])) == (3.0, 5.0)
    assert median_set(np.array([5.0, 1, 3, 100]), np.array([1, 1, 1, 0])) == (3.0, 3.0)


def test_ring_lambda2_matches_remark2():
    for N in (3, 5, 8):
        assert algebraic_connectivity(ring(N)) == pytest.approx(2 * (1 - np.cos(2 * np.pi / N)))
    assert algebraic_connectivity(complete(6)) == pytest.approx(6.0)


@settings(max_examples=25, deadline=None)
@given(
    N=st.integers(min_value=3, max_value=9),
    honest=st.lists(st.floats(-5, 5), min_size=9, max_size=9),
    attack=st.lists(st.floats(-1e6, 1e6), min_size=4, max_size=4),
    gamma=st.sampled_from([2.0, 5.0, 20.0]),
    topology=st.sampled_from(["ring", "complete"]),
    seed=st.integers(0, 2**16),
)
def test_theorem1_bound_under_adversarial_values(N, honest, attack, gamma, topology, seed):
    """At most q < S/2 of the indicated values are arbitrary (huge); every agent ends
    within 2 sqrt(N) / (gamma lambda_2) of the median set of the indicated values, which
    itself lies within the range of the honest values."""
    rng = np.random.default_rng(seed)
    z = np.array(honest[:N], dtype=float)
    s = np.ones(N, dtype=int)
    s[rng.choice(N, size=rng.integers(0, (N - 1) // 3 + 1), replace=False)] = 0  # some agents see nothing
    indicated = np.flatnonzero(s)
    q = (len(indicated) - 1) // 2
    attacked = rng.choice(indicated, size=min(q, len(attack)), replace=False)
    z[attacked] = np.array(attack[: len(attacked)])
    Adj = ring(N) if topology == "ring" else complete(N)
    bound = theorem1_bound(Adj, gamma)
    # Away from the median the blended dynamics move towards it at speed >= 1/N whatever
    # the attack values, so from x0 in [-10, 10] and honest values in [-5, 5] the
    # approach takes at most about 15 N seconds.
    dt = 2e-3
    T = 20.0 * N + 20.0
    traj = run_scalar_median_solver(z, s, Adj, gamma=gamma, dt=dt, steps=int(T / dt), x0=rng.uniform(-10, 10, N))
    final = traj[-1]
    med = median_set(z, s)
    assert np.all(distance_to(med, final) <= bound + 1e-6)
    honest_vals = np.delete(z, attacked)[np.delete(s, attacked) == 1]
    assert honest_vals.min() <= med[0] and med[1] <= honest_vals.max()


def test_theorem1_scalar_example_converges_within_bound():
    z = np.array([1.0, 2.0, 3.0, 1e3, -1e3])  # two adversarial values among five
    s = np.ones(5, dtype=int)
    Adj = ring(5)
    gamma = 5.0
    traj = run_scalar_median_solver(z, s, Adj, gamma=gamma, dt=1e-3, steps=60000, x0=np.zeros(5))
    bound = theorem1_bound(Adj, gamma)
    assert bound == pytest.approx(2 * np.sqrt(5) / (gamma * 2 * (1 - np.cos(2 * np.pi / 5))))
    # the median of {1, 2, 3, 1e3, -1e3} is 2
    assert np.all(np.abs(traj[-1] - 2.0) <= bound)
    assert np.all(np.abs(traj[-5000:] - 2.0) <= bound)
