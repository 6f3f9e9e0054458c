"""The sign-based distributed median of time-varying values (one agent's step) and the
exact median by flooding (estimation.distributed_median)."""

from __future__ import annotations

import numpy as np
import pytest

from estimation import graphs
from estimation.base import Received
from estimation.distributed_median import FloodingMedian, SignMedianAgent, consensus_step, sign_median_update
from estimation.median_solver import median_set, run_scalar_median_solver, theorem1_bound


def _line(N):
    return graphs.from_edges(N, [(i, i + 1) for i in range(N - 1)])


def _team(Adj, targets, *, steps, dt=0.01, **kw):
    """Lockstep loop: agent i gets its own value targets(k)[i] and its neighbours' xi[k-1].
    Returns the trajectory (steps + 1, N, n)."""
    N = Adj.shape[0]
    z0 = np.asarray(targets(0), dtype=float)
    agents = [SignMedianAgent(n=z0.shape[1], dt=dt, **kw) for _ in range(N)]
    prev = [None] * N
    out = []
    for k in range(steps + 1):
        z = np.asarray(targets(k), dtype=float)
        inbox = [{j: Received(j, k - 1, prev[j]) for j in graphs.in_neighbours(Adj, i)} if k else {} for i in range(N)]
        prev = [a.step(k, z[i], inbox[i]) for i, a in enumerate(agents)]
        out.append(np.stack(prev))
    return np.array(out)


def test_consensus_step_is_the_exact_decay():
    stay, move = consensus_step(3.0, 0.1)
    assert stay == pytest.approx(np.exp(-0.3)) and move == pytest.approx((1 - np.exp(-0.3)) / 3.0)
    assert consensus_step(0.0, 0.1) == (1.0, 0.1)
    with pytest.raises(ValueError):
        consensus_step(-1.0, 0.1)


def test_held_sign_without_drift_is_the_scalar_solver_of_lee_kim_shim():
    """f = 0, kappa = 1, sign = 'held': the step of median_solver.run_scalar_median_solver."""
    rng = np.random.default_rng(3)
    Adj = graphs.ring(6)
    z = rng.normal(size=6) * 3
    x0 = rng.normal(size=6)
    ref = run_scalar_median_solver(z, np.ones(6), Adj, gamma=2.0, dt=0.05, steps=200, x0=x0)
    agents = [SignMedianAgent(n=1, kappa=1.0, gamma=2.0, dt=0.05, sign="held", x0=[x0[i]]) for i in range(6)]
    prev = [None] * 6
    got = []
    for k in range(201):
        inbox = [{j: Received(j, k - 1, prev[j]) for j in graphs.in_neighbours(Adj, i)} if k else {} for i in range(6)]
        prev = [a.step(k, z[i:i + 1], inbox[i]) for i, a in enumerate(agents)]
        got.append(np.concatenate(prev))
    np.testing.assert_allclose(np.array(got), ref, rtol=0, atol=1e-12)


@pytest.mark.parametrize("graph", ["ring", "line"])
@pytest.mark.parametrize("gamma", [1.0, 5.0])
def test_constant_values_end_within_theorem1_of_the_median(graph, gamma):
    rng = np.random.default_rng(7)
    N, n = 5, 3
    Adj = graphs.ring(N) if graph == "ring" else _line(N)
    z = rng.normal(size=(N, n)) * 10
    traj = _team(Adj, lambda k: z, steps=3000, kappa=5.0, gamma=gamma)
    bound = theorem1_bound(Adj, gamma)
    final = traj[-1]
    for c in range(n):
        lo, hi = median_set(z[:, c], np.ones(N))
        dist = np.maximum(0.0, np.maximum(lo - final[:, c], final[:, c] - hi))
        assert np.all(dist <= bound)
    # implicit sgn: no chattering at the end
    assert np.max(np.abs(traj[-1] - traj[-2])) <= 1e-9


def test_larger_gamma_agrees_more_tightly():
    rng = np.random.default_rng(11)
    Adj = _line(5)
    z = rng.normal(size=(5, 2)) * 10
    med = np.median(z, axis=0)
    errs = [np.max(np.abs(_team(Adj, lambda k: z, steps=2000, kappa=20.0, gamma=g)[-1] - med)) for g in (0.5, 2.0, 8.0)]
    assert errs[0] > errs[1] > errs[2]


def test_an_outlier_does_not_move_the_agreement():
    """Two of five values huge: the team stays near the median of the other three."""
    z = np.array([[1e6], [1.0], [2.0], [-1e6], [3.0]])
    traj = _team(graphs.ring(5), lambda k: z, steps=4000, kappa=20.0, gamma=5.0)
    assert np.all(np.abs(traj[-1] - 2.0) <= theorem1_bound(graphs.ring(5), 5.0))


def test_drift_tracks_moving_values():
    """Values moving with a common known motion f plus fixed offsets: with f as drift a
    small kappa suffices; without it the same kappa lags far behind."""
    a = -0.5
    offsets = np.array([[-3.0], [0.0], [1.0], [50.0], [-40.0]])  # median offset 0
    dt = 0.01

    def truth(k):
        return 100.0 * np.exp(a * k * dt) + 80.0 * np.sin(3 * k * dt)

    def f(t, x):  # the common motion: x' = a x + 80 (3 cos 3t - a sin 3t)
        return a * x + 80.0 * (3 * np.cos(3 * t) - a * np.sin(3 * t))

    Adj = _line(5)
    targets = lambda k: truth(k) + offsets
    with_f = _team(Adj, targets, steps=1500, dt=dt, kappa=2.0, gamma=20.0, drift=f)
    # a common reference with the same motion (any offset): xi moves with it
    with_r = _team(Adj, targets, steps=1500, dt=dt, kappa=2.0, gamma=20.0, reference=lambda k: np.array([truth(k) + 7.0]))
    without = _team(Adj, targets, steps=1500, dt=dt, kappa=2.0, gamma=20.0)
    ks = np.arange(1000, 1501)
    ref = np.array([truth(k) for k in ks])[:, None]
    err_f = np.max(np.abs(with_f[ks, :, 0] - ref))
    err_r = np.max(np.abs(with_r[ks, :, 0] - ref))
    err_0 = np.max(np.abs(without[ks, :, 0] - ref))
    assert err_f <= theorem1_bound(Adj, 20.0)
    assert err_r <= theorem1_bound(Adj, 20.0)
    assert err_0 >= 10 * max(err_f, err_r)


def test_implicit_sign_lands_on_the_own_value_or_moves_by_g():
    # alone (no neighbours): g = kappa dt
    x = sign_median_update(np.array([0.0, 0.0]), [], np.array([0.05, 10.0]), kappa=2.0, gamma=1.0, dt=0.1)
    np.testing.assert_allclose(x, [0.05, 0.2])
    with pytest.raises(ValueError):
        sign_median_update(np.zeros(1), [], np.zeros(1), kappa=0.0, gamma=1.0, dt=0.1)
    with pytest.raises(ValueError):
        sign_median_update(np.zeros(1), [], np.zeros(1), kappa=1.0, gamma=1.0, dt=0.1, sign="soft")


def test_agent_interface_stale_and_skipped_rounds():
    ag = SignMedianAgent(n=2, kappa=1.0, gamma=1.0, dt=0.1, max_age=1)
    out = ag.step(0, np.array([1.0, 2.0]), {})
    np.testing.assert_array_equal(out, [1.0, 2.0])  # starts on its own value
    assert not out.flags.writeable
    with pytest.raises(ValueError):
        out[0] = 3.0
    # a neighbour stamped too old is ignored: same as no neighbour
    solo = SignMedianAgent(n=2, kappa=1.0, gamma=1.0, dt=0.1, max_age=1)
    solo.step(0, np.array([1.0, 2.0]), {})
    old = {3: Received(3, -5, np.array([100.0, 100.0]))}
    np.testing.assert_array_equal(ag.step(1, np.array([1.0, 2.0]), old), solo.step(1, np.array([1.0, 2.0]), {}))
    # a skipped round is two steps
    two = ag.step(3, np.array([5.0, 5.0]), {})
    np.testing.assert_allclose(two, [1.2, 2.2])
    with pytest.raises(ValueError):
        ag.step(3, np.zeros(2), {})


# --------------------------------------------------------------------------- flooding
def _flood_team(Adj, values, *, steps, predict=False, drift=None, dt=0.1):
    N = Adj.shape[0]
    n = np.asarray(values(0)).shape[1]
    ags = [FloodingMedian(agent=i, N=N, n=n, dt=dt, drift=drift, predict=predict) for i in range(N)]
    prev = [None] * N
    est = []
    for k in range(steps + 1):
        v = np.asarray(values(k), dtype=float)
        inbox = [{j: Received(j, k - 1, prev[j]) for j in graphs.in_neighbours(Adj, i)} if k else {} for i in range(N)]
        prev = [a.step(k, v[i], inbox[i]) for i, a in enumerate(ags)]
        est.append(np.stack([a.estimate for a in ags]))
    return ags, np.array(est)


def test_flooding_knows_every_row_after_the_diameter_and_takes_the_exact_median():
    Adj = _line(5)
    vals = lambda k: np.arange(5.0)[:, None] * np.array([[1.0, -2.0]]) + k
    ags, est = _flood_team(Adj, vals, steps=6)
    for a in ags:
        assert np.all(a.stamps >= 0)
    # agent 0 (an end of the line) at round 6 knows agent j's value of round 6 - j
    stale = np.stack([vals(6 - j)[j] for j in range(5)])
    np.testing.assert_allclose(est[6, 0], np.median(stale, axis=0))
    # before the diameter the end agents know only part of the line
    assert FloodingMedian(agent=0, N=5, n=2, dt=0.1).stamps.tolist() == [-1] * 5


def test_flooding_prediction_removes_the_staleness_of_a_known_motion():
    a = -0.3
    drift = lambda t, X: a * X  # batched: (m, n) -> (m, n)
    dt = 0.1
    base = np.array([[1.0], [4.0], [2.0], [8.0], [-3.0]])
    vals = lambda k: base * np.exp(a * k * dt)
    _, est = _flood_team(_line(5), vals, steps=10, predict=True, drift=drift, dt=dt)
    _, stale = _flood_team(_line(5), vals, steps=10)
    exact = np.median(vals(10), axis=0)
    assert np.max(np.abs(est[10] - exact)) <= 1e-6  # RK4 of a linear drift at dt = 0.1
    assert np.max(np.abs(stale[10] - exact)) >= 1e-2


def test_flooding_ignores_malformed_tables_and_round_trips():
    f = FloodingMedian(agent=1, N=3, n=2, dt=0.1)
    f.step(0, np.array([1.0, 2.0]), {})
    payload = f.pack()
    stamps, rows = f.unpack(payload)
    assert stamps.tolist() == [-1, 0, -1] and rows[1].tolist() == [1.0, 2.0]
    bad = {0: Received(0, 0, np.full(9, np.nan)), 2: Received(2, 0, np.ones(4))}
    f.step(1, np.array([1.0, 2.0]), bad)
    assert f.stamps.tolist() == [-1, 1, -1]
    with pytest.raises(ValueError):
        f.unpack(np.concatenate([[0.5, 0, 0], np.zeros(6)]))
    with pytest.raises(ValueError):
        FloodingMedian(agent=0, N=3, n=2, dt=0.1, predict=True)
