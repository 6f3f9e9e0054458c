"""Lee-Kim-Shim estimator: design, discretisation against a finer step, missing data."""

import numpy as np
import pytest

from estimation.base import Received
from estimation.errors import DesignError
from estimation.graphs import in_neighbours, ring
from estimation.lee_kim_shim import LeeKimShim, design, shifted_poles
from estimation.lti import three_inertia, zoh
from estimation.signals import Signal


def test_shifted_poles_keep_frequencies():
    A_o = np.array([[0.0, 20.0], [-20.0, 0.0]])
    p = shifted_poles(A_o, real_part=-1.0)
    assert sorted(p.imag.tolist()) == pytest.approx([-20.0, 20.0])
    assert np.allclose(p.real, -1.0)
    with pytest.raises(DesignError):
        shifted_poles(A_o, real_part=0.5)


def test_partial_observer_gains_place_the_poles():
    p = three_inertia()
    des = design(p.A, p.B, p.banks)
    for i, ob in enumerate(des.observers):
        A_o = ob.W_i @ p.A @ ob.V_i
        ev = np.linalg.eigvals(A_o - ob.L @ ob.C @ ob.V_i)
        assert np.allclose(np.sort(ev.real), np.sort(np.real(ob.poles)), atol=1e-6)
        assert np.all(ev.real < 0)
        # Kalman decomposition: W_i A V~_i = 0 (unobservable part does not feed the observable one)
        hidden = np.flatnonzero(des.basis.S[i] == 0)
        if len(hidden):
            assert np.allclose(ob.W_i @ p.A @ des.basis.V[:, hidden], 0, atol=1e-9)
            assert np.allclose(ob.C @ des.basis.V[:, hidden], 0, atol=1e-9)


def run(dt, *, T=12.0, attack=True, variant="median", kappa=0.5, gamma=2.0, drop_agent=None, attack_at=5.0,
        cut=((), 0, 0), skips=(0.0, 0, 0)):
    """Infinity-norm errors (rounds x agents) of the paper's five agents on a ring. ``cut =
    (agents, k0, k1)``: those agents are cut off for rounds ``k0 <= k < k1`` (no step, no
    message; the others keep their last message until it ages out), and come back in round
    ``k1`` with one call over the rounds they missed (NaN rows while cut off). ``skips =
    (p, burst, k0)``: from round ``k0`` on, each agent in each round begins with probability
    ``p`` to skip the next 1 to ``burst`` rounds (a realtime agent descheduled on a busy
    machine), and runs the round after them with one call."""
    p = three_inertia()
    des = design(p.A, p.B, p.banks)
    rng = np.random.default_rng(7)
    x = rng.uniform(-1, 1, 6)
    u = Signal.sine(1, amplitude=0.01, omega=0.5)
    Adj = ring(5)
    ests = [LeeKimShim(des, agent=i, kappa=kappa, gamma=gamma, dt=dt, variant=variant, input_fn=u,
                       x0=rng.uniform(-1, 1, 6), max_degree=2) for i in range(5)]
    Ad, Bd = zoh(p.A, p.B, dt)
    K = int(round(T / dt))
    last: dict[int, Received] = {}  # the newest message of each agent
    errs = np.full((K + 1, 5), np.nan)
    skip_rng, skip_until = np.random.default_rng(11), np.zeros(5, dtype=int)
    for k in range(K + 1):
        y = p.C @ x
        if attack and k * dt >= attack_at:
            y[0] += np.pi / 3
        outs = {}
        for i, e in enumerate(ests):
            if i in cut[0] and cut[1] <= k < cut[2]:
                continue
            if skips[0] and k >= skips[2] and k >= skip_until[i] and skip_rng.random() < skips[0]:
                skip_until[i] = k + skip_rng.integers(1, skips[1] + 1)
            if k < skip_until[i]:
                continue
            inbox = {j: last[j] for j in in_neighbours(Adj, i) if j in last}
            outs[i] = e.step(k, None if (drop_agent == i and 200 <= k < 400) else y[i:i + 1], inbox)
            errs[k, i] = np.max(np.abs(outs[i] - x))
        last.update({j: Received(j, k, v) for j, v in outs.items()})
        x = Ad @ x + Bd @ u(k * dt)
    return errs


def test_discretisation_agrees_with_a_finer_step():
    """The same run at dt = 1e-2 and at a 10x finer step: the error trajectories agree
    (the sgn term is integrated implicitly, the linear part exactly)."""
    coarse = run(1e-2, T=20.0)
    fine = run(1e-3, T=20.0)[::10]
    late = slice(int(15 / 1e-2), None)  # after the attack transient
    assert np.max(np.abs(coarse[late] - fine[late])) < 1e-3
    assert np.max(fine[late]) > 0.1  # the attacked steady state is non-trivial, so agreement means something


def test_no_attack_converges_exactly():
    errs = run(1e-2, attack=False, T=30.0)
    assert np.max(errs[-100:]) < 1e-8


def test_missing_measurement_is_ordinary_input():
    errs = run(1e-2, attack=False, T=30.0, drop_agent=0)
    assert np.all(np.isfinite(errs))
    assert np.max(errs[-100:]) < 1e-8


def test_empty_inbox_and_stale_messages_are_ignored():
    p = three_inertia()
    des = design(p.A, p.B, p.banks)
    u = Signal.zero(1)
    est = LeeKimShim(des, agent=0, kappa=1, gamma=1, dt=0.01, input_fn=u, x0=np.zeros(6), max_degree=2, max_age=2)
    est.step(0, np.zeros(1), {})
    a = est.step(1, np.zeros(1), {})
    stale = {1: Received(1, -10, np.full(6, 1e6))}
    b = est.step(2, np.zeros(1), stale)
    assert np.allclose(a, 0) and np.allclose(b, 0)
    fresh = {1: Received(1, 2, np.full(6, 1.0))}
    c = est.step(3, np.zeros(1), fresh)
    assert np.all(np.abs(c) > 0)
    with pytest.raises(ValueError):
        c[0] = 1.0  # published estimates are read-only


def test_resilient_vs_linear_baseline_under_attack():
    res = run(1e-2, T=30.0)
    lin = run(1e-2, T=30.0, variant="linear")
    last = slice(int(25 / 1e-2), None)
    assert np.max(res[last]) <= 0.25
    assert np.max(lin[last]) >= 0.3


def test_lyapunov_variant_equals_median_in_the_modal_basis():
    """With the modal basis P_bar = I, so eq. (11) reduces to eq. (6)."""
    a = run(1e-2, T=6.0, variant="median")
    b = run(1e-2, T=6.0, variant="lyapunov")
    assert np.allclose(a, b, atol=1e-9)


def test_agents_cut_off_for_3_s_come_back_near_where_they_were():
    """Agents 4 and 5 cut off for 3.35 s under attack (rounds 1301 to 1635, the network
    partition of tests/deploy/test_netns.py) come back with one call over the rounds they
    missed, in which the fresh estimates of agents 1 and 3 (stamped 1634) are already in
    their inboxes. The gap predicts: the measurement of round 1300 holds over one step
    only, and an estimate holds only over the steps from its own round on. Back within 1.3
    times their error when cut (measured 1.21 and 1.13; holding the stale measurement and
    coupling in the estimates of t = 16.34 over the whole gap brought them back 0.33 and
    0.61 off, 7.7 and 6.2 times); attacked agent 1 over [22, 24] within 0.1% of the run
    without the cut (measured 0.2165 both; it was 0.2289, the deploy test's 0.25 bound
    failed once at 0.254)."""
    k0, k1 = 1301, 1635
    cut = run(1e-2, T=24.0, attack_at=10.0, cut=((3, 4), k0, k1))
    ref = run(1e-2, T=24.0, attack_at=10.0)
    assert np.isnan(cut[k0:k1, 3:]).all() and np.isfinite(cut[k1:]).all()
    back = cut[k1, 3:] / cut[k0 - 1, 3:]
    assert np.all(back <= 1.3), back
    window = slice(2200, None)
    assert np.max(cut[window, 0]) <= 1.001 * np.max(ref[window, 0]) <= 0.25, (np.max(cut[window, 0]), np.max(ref[window, 0]))


def test_one_call_over_skipped_rounds_equals_a_step_per_round():
    """``step(k)`` after ``step(k0)`` with ``k > k0 + 1`` integrates each skipped round as a
    round with no measurement, each step coupling in the estimates stamped within
    ``max_age`` rounds of it: bit for bit what a call per round with ``measurement=None``
    computes. The inbox holds a message stamped inside the gap (62), which holds over the
    steps from 59 to 65, and one from before it (48), which holds over the gap's first two
    steps (``max_age`` 3) and then ages out."""
    p = three_inertia()
    des = design(p.A, p.B, p.banks)
    u = Signal.sine(1, amplitude=0.01, omega=0.5)
    x0 = np.linspace(-0.5, 0.5, 6)
    a, b = (LeeKimShim(des, agent=1, kappa=0.5, gamma=2.0, dt=0.01, input_fn=u, x0=x0, max_degree=2, max_age=3)
            for _ in range(2))
    rng = np.random.default_rng(3)
    for k in range(51):
        y, inbox = rng.normal(size=1), {0: Received(0, k - 1, rng.normal(size=6)), 2: Received(2, k - 1, rng.normal(size=6))}
        np.testing.assert_array_equal(a.step(k, y, inbox), b.step(k, y, inbox))
    inbox = {0: Received(0, 62, np.full(6, 0.3)), 2: Received(2, 48, np.full(6, -0.2))}
    y = np.array([0.7])
    got = a.step(80, y, inbox)
    for k in range(51, 80):
        b.step(k, None, inbox)
    np.testing.assert_array_equal(got, b.step(80, y, inbox))
    assert np.abs(got - x0).max() > 1e-3  # it moved


def test_agents_that_skip_rounds_in_bursts_stay_near_their_lockstep_error():
    """Every agent skips bursts of 1 to 5 rounds (about 6% of its rounds) from t = 10 s, as
    realtime agents on a busy machine do; each comes back with one call over the rounds it
    missed, in which its neighbours' estimates stamped in the gap are already in its inbox.
    Each step of the gap couples in the estimate stamped within ``max_age`` rounds of it
    (also one stamped just after the step): the attacked agent 1 stays near its error
    without skips (measured over [14, 24]: 90th percentile 1.034 times, largest 1.046
    times). Coupling in only the estimates stamped up to each step cut the coupling for
    most of every burst: 1.121 and 1.193 times (largest 0.258, over the scenario's bound
    of 0.25)."""
    ref = run(1e-2, T=24.0, attack_at=10.0)
    got = run(1e-2, T=24.0, attack_at=10.0, skips=(0.02, 5, 1000))
    window = slice(1400, None)
    level = np.max(ref[window, 0])
    assert np.isnan(got[window]).mean() > 0.04  # the agents did skip
    assert np.nanpercentile(got[window, 0], 90) <= 1.05 * level, (np.nanpercentile(got[window, 0], 90), level)
    assert np.nanmax(got[window, 0]) <= 1.1 * level, (np.nanmax(got[window, 0]), level)
