"""Controlled observers (8), (17)-(19) on the Section IV example: the acceptance numbers.

All runs start from ``x0 = 0`` with no noise, so the plant stays at 0 and the estimation
error *is* the attack-induced error (the run minus the same run without the attack, which
is identically zero). Step ``DT = 5e-3`` (the exponential integrator is stable at any step;
the comparison with ``DT / 4`` below shows the error of this choice).
"""

from __future__ import annotations

import numpy as np
import pytest

from estimation.base import Received
from estimation.errors import DesignError
from estimation.hinf_lmi import design
from estimation.hinf_riccati import RiccatiFlow, information_matrix
from estimation.ugrinovskii import (
    UgrinovskiiBaseline,
    UgrinovskiiNode,
    first_order_attack_model,
    run_network,
)
from estimation.ugrinovskii_example import example_problem

pytest.importorskip("cvxpy")

DT = 5e-3
T_END = 10.0
AMP = 5.0
NODE2 = 1  # the paper's node 2, 0-based


def attack(t: float) -> float:
    """Amplitude 5 for 3 s from t = 4 (Section IV); held over each step from its start."""
    return AMP if 4.0 <= t < 7.0 else 0.0


def worst_error(run):
    return np.linalg.norm(run["xhat"] - run["x"][:, None, :], axis=2).max(axis=1)


def window(t, a, b, *, closed=True):
    return (t >= a - 1e-9) & ((t <= b + 1e-9) if closed else (t < b - 1e-9))


@pytest.fixture(scope="module")
def example():
    pb = example_problem()
    return pb, design(pb, observer_channel="H_hat")


@pytest.fixture(scope="module")
def runs(example):
    pb, d = example
    ctl = run_network(pb, d, dt=DT, t_end=T_END, observer_attacks={NODE2: attack}, gain_rtol=1e-2)
    base = run_network(pb, d, dt=DT, t_end=T_END, observer_attacks={NODE2: attack}, controlled=False,
                       gain_rtol=1e-2)
    return ctl, base


def test_realisation_13_is_minus_G_over_s():
    Om, Ga, Up = first_order_attack_model(gain=410.0, pole=40.0)
    for w in (0.1, 1.0, 10.0, 100.0):
        s = 1j * w
        h = (Up @ np.linalg.solve(s * np.eye(2) - Om, Ga))[0, 0]
        assert abs(h - (-410.0 / (s * (s + 40.0)))) <= 1e-12 * abs(h)
    with pytest.raises(DesignError, match="Lemma 1"):
        first_order_attack_model(gain=410.0, pole=-1.0)


def test_riccati_solutions_stay_positive_definite_and_bounded(example):
    pb, d = example
    g, gb = float(d["gamma2"]), float(d["gamma2_bar"])
    for i in range(pb.N):
        nb = pb.neighbours[i]
        Ab, Bb, Cb, Wb = pb.detector_matrices(i)
        S = information_matrix(Cb, pb.D[i], Wb, [d[f"U_{i}_{j}"] for j in nb])
        det = RiccatiFlow(A=Ab, B=Bb, S=S, R=d[f"R_{i}"], gamma2=g, Y0=g * np.linalg.inv(d[f"Q_{i}"]), dt=DT)
        Sb = information_matrix(pb.C[i], pb.D[i], [pb.W[(i, j)] for j in nb], [d[f"Ubar_{i}_{j}"] for j in nb])
        obs = RiccatiFlow(A=pb.A, B=pb.observer_input_matrix(i), S=Sb, R=d[f"Rbar_{i}"], gamma2=gb,
                          Y0=gb * np.linalg.inv(d[f"Qbar_{i}"]), dt=DT)
        for flow in (det, obs):
            top = np.linalg.eigvalsh(flow.Y)[-1]
            lo, hi = np.inf, 0.0
            for _ in range(int(T_END / DT)):
                lam = np.linalg.eigvalsh(flow.step())
                lo, hi = min(lo, lam[0]), max(hi, lam[-1])
            assert lo > 0.0 and np.isfinite(hi)
            assert hi <= top * (1 + 1e-9)  # decreasing from the LMI start, hence bounded


def test_controlled_error_is_a_tenth_of_the_baselines_during_the_attack(runs):
    ctl, base = runs
    t = ctl["t"]
    w = window(t, 5.0, 7.0)
    assert worst_error(ctl)[w].max() <= 0.1 * worst_error(base)[w].max()


def test_unbiased_at_t7_while_the_baseline_keeps_a_bias(runs):
    ctl, base = runs
    k7 = int(round(7.0 / DT))
    assert worst_error(ctl)[k7] <= 1e-3
    assert worst_error(base)[k7] >= 1e-2


def test_transient_after_the_attack_decays(runs):
    ctl, _ = runs
    t, e = ctl["t"], worst_error(ctl)
    assert e[window(t, 8.0, 10.0)].max() <= 0.1 * e[window(t, 7.0, 7.5)].max()


def test_u2_tracks_the_attack_and_only_node_2_is_flagged(runs):
    ctl, _ = runs
    t, u = ctl["t"], ctl["u"][:, :, 0]
    f = np.array([attack(tk) for tk in t])
    w = window(t, 4.5, 7.0, closed=False)  # the attack switches off at t = 7
    assert np.abs(f - u[:, NODE2])[w].max() <= 0.02 * AMP
    healthy = [i for i in range(6) if i != NODE2]
    assert np.abs(u[:, healthy])[t >= 2.0].max() <= 0.05 * AMP
    threshold = 0.5 * AMP  # a flag "|u_i| above threshold" raises on node 2 alone
    assert np.all(np.abs(u[:, NODE2])[w] > threshold)
    assert not np.any(np.abs(u[:, healthy]) > threshold)


def test_attack_on_the_detector_as_well_leaves_estimates_unbiased():
    pb = example_problem(detector_attack=True)  # F_c,i = [F_i; 0]
    d = design(pb, observer_channel="H_hat")
    run = run_network(pb, d, dt=DT, t_end=T_END, observer_attacks={NODE2: attack},
                      detector_attacks={NODE2: attack}, gain_rtol=1e-2)
    t, e = run["t"], worst_error(run)
    peak = e[window(t, 4.0, 4.5)].max()
    assert peak > 1e-2  # the attack does hit
    assert e[int(round(7.0 / DT))] <= 1e-3  # unbiased after the transient
    assert e[window(t, 6.0, 7.0)].max() <= 1e-3
    assert e[window(t, 9.0, 10.0)].max() <= 1e-3


def test_integrator_against_a_finer_step(example):
    # attack from t = 0.3 so that a short horizon covers its transient
    pb, d = example
    att = {NODE2: lambda t: AMP if t >= 0.3 else 0.0}
    runs = {m: run_network(pb, d, dt=DT / m, t_end=1.0, observer_attacks=att, gain_rtol=1e-2) for m in (1, 2, 4)}
    ref = runs[4]
    scale = np.abs(ref["xhat"]).max()
    assert scale > 1e-2
    err = {m: np.abs(runs[m]["xhat"] - ref["xhat"][:: 4 // m]).max() for m in (1, 2)}
    # first order in dt (explicit one-round-old coupling): halving dt at least halves the error
    assert err[2] <= 0.5 * err[1]
    assert err[1] <= 0.15 * scale
    # the detector output and the peak of the worst node error hardly depend on dt
    assert np.abs(runs[1]["u"] - ref["u"][::4]).max() <= 1e-3 * AMP
    peak = {m: worst_error(runs[m]).max() for m in (1, 4)}
    assert abs(peak[1] / peak[4] - 1) <= 0.02


def test_estimator_interface_and_missing_data(example):
    pb, d = example
    node = UgrinovskiiNode(pb, d, node=NODE2, dt=DT)
    y = np.zeros(2)
    out0 = node.step(0, y, {})
    assert out0.shape == (12,) and np.all(out0 == 0)
    out0[:] = 7.0  # handing out copies only
    assert np.all(node.estimate == 0)
    # empty inbox, then a missing measurement, then a bad payload: ordinary input
    node.step(1, y, {})
    node.step(2, None, {0: Received(0, 1, np.zeros(12))})
    node.step(3, y, {0: Received(0, 2, np.full(12, np.nan))})
    assert node.rejected == 1
    assert np.all(np.isfinite(node.estimate))
    with pytest.raises(DesignError, match="rounds must increase"):
        node.step(3, y, {})
    base = UgrinovskiiBaseline(pb, d, node=0, dt=DT, xi0=np.ones(6))
    assert base.step(0, y, {}).shape == (6,)
    np.testing.assert_array_equal(base.estimate, np.ones(6))
    with pytest.raises(DesignError, match="measurement"):
        base.step(1, np.zeros(3), {})
