"""Inverter line (van der Horst et al., Sections V-VI): droop (12), DistFlow, coordinates (7), (13), (14)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimation.inverters import (
    InverterNetwork,
    InverterParams,
    distflow_paths,
    droop,
    droop_slope_bound,
    random_voltage_disturbance,
    reference_signals,
    voltage_attack,
)
from estimation.lure import check_slope

BREAKS = dict(w_min=-17320.5, w_m=0.0, w_n=0.0, w_max=17320.5)


def test_droop_values_of_eq_12():
    Q = 2000.0
    kw = dict(Q_bar=Q, w_min=-1000.0, w_m=-200.0, w_n=100.0, w_max=500.0)
    w = np.array([-5000.0, -1000.0, -600.0, -200.0, 0.0, 100.0, 300.0, 500.0, 9000.0])
    expect = np.array([-Q, -Q, -(1 - 400 / 800) * Q, 0.0, 0.0, 0.0, (200 / 400) * Q, Q, Q])
    np.testing.assert_allclose(droop(w, **kw), expect)


def test_droop_slope_bounds_and_e_bar():
    p = InverterParams()
    slopes = droop_slope_bound(Q_bar=p.Q_bar, **BREAKS)
    np.testing.assert_allclose(slopes, p.Q_bar / 17320.5)
    assert slopes.max() == pytest.approx(0.2, abs=1e-5)  # e_bar = 0.2 is the common bound
    net = InverterNetwork()
    grid = np.linspace(-30000.0, 30000.0, 2401)
    smin, smax = check_slope(net.plant.phi, lower=net.plant.slope_lower, upper=net.plant.slope_upper, points=grid)
    assert np.all(smin >= -1e-12)
    assert np.all(smax <= net.plant.slope_upper + 1e-12)
    np.testing.assert_allclose(smax, p.Q_bar / 17320.5, rtol=1e-9)  # the bound is reached


@settings(max_examples=200, deadline=None)
@given(a=st.floats(-5e4, 5e4), b=st.floats(-5e4, 5e4), Q=st.floats(1.0, 5000.0))
def test_droop_secant_slopes_in_0_ebar(a, b, Q):
    if abs(a - b) < 1e-3:
        return
    kw = dict(Q_bar=Q, w_min=-1000.0, w_m=-100.0, w_n=50.0, w_max=800.0)
    s = (droop(a, **kw) - droop(b, **kw)) / (a - b)
    bound = droop_slope_bound(Q_bar=Q, w_min=-1000.0, w_m=-100.0, w_n=50.0, w_max=800.0)
    assert -1e-9 <= s <= bound * (1 + 1e-9)


def test_e_bar_below_droop_slope_is_rejected():
    with pytest.raises(ValueError, match="e_bar"):
        InverterParams(e_bar=0.1)


def _two_customers():
    return InverterParams(
        R=np.array([0.01, 0.02]), X=np.array([0.1, 0.2]), R_cable=np.array([0.03, 0.04]),
        X_cable=np.array([0.3, 0.4]), tau=np.array([1.0, 2.0]), rho_g=np.array([1000.0, 0.0]),
        rho_c=np.array([400.0, 500.0]), q_c=np.array([100.0, 200.0]), Q_bar=np.array([1000.0, 1000.0]),
        e_bar=0.1, w_min=-10000.0, w_m=0.0, w_n=0.0, w_max=10000.0)


def test_distflow_two_bus_hand_computed():
    # head v0' --(0.01 + j0.1)-- v1' --(0.02 + j0.2)-- v2'; cables (0.03 + j0.3) to v1, (0.04 + j0.4) to v2.
    # v1^2 = v0^2 + 2*0.01*(r1 + r2) + 2*0.1*(q1 + q2) + 2*0.03*r1 + 2*0.3*q1
    # v2^2 = v0^2 + 2*0.01*(r1 + r2) + 2*0.1*(q1 + q2) + 2*0.02*r2 + 2*0.2*q2 + 2*0.04*r2 + 2*0.4*q2
    p = _two_customers()
    Rp, Xp = distflow_paths(R=p.R, X=p.X, R_cable=p.R_cable, X_cable=p.X_cable)
    np.testing.assert_allclose(Rp, [[0.04, 0.01], [0.01, 0.07]])
    np.testing.assert_allclose(Xp, [[0.4, 0.1], [0.1, 0.7]])
    net = InverterNetwork(p)
    np.testing.assert_allclose(net.plant.H, [[-0.8, -0.2], [-0.2, -1.4]])
    np.testing.assert_allclose(net.plant.A, np.diag([-1.0, -0.5]))
    qg = np.array([150.0, -50.0])
    r1, r2 = 600.0, -500.0  # rho_g - rho_c
    q1, q2 = 150.0 - 100.0, -50.0 - 200.0
    t = 0.3
    v0 = 230 + 5 * np.sin(t)
    v1sq = v0**2 + 2 * 0.01 * (r1 + r2) + 2 * 0.1 * (q1 + q2) + 2 * 0.03 * r1 + 2 * 0.3 * q1
    v2sq = v0**2 + 2 * 0.01 * (r1 + r2) + 2 * 0.1 * (q1 + q2) + 2 * 0.02 * r2 + 2 * 0.2 * q2 + 2 * 0.04 * r2 + 2 * 0.4 * q2
    np.testing.assert_allclose(net.voltages(t, qg) ** 2, [v1sq, v2sq], rtol=1e-12)
    # z = v_bar^2 - v^2 = H x + w
    np.testing.assert_allclose(net.plant.z(t, qg), 230.0**2 - np.array([v1sq, v2sq]), rtol=1e-12)
    # voltage estimate (14), sign corrected, is exact at x_hat = x
    np.testing.assert_allclose(net.squared_voltage_estimate(t, qg), [v1sq, v2sq], rtol=1e-12)


def test_cigre_H_is_the_printed_matrix():
    p = InverterParams()
    c = np.cumsum(p.X)
    expect = -2 * np.array([[c[min(i, k)] for k in range(5)] for i in range(5)]) - 2 * np.diag(p.X_cable)
    np.testing.assert_allclose(InverterNetwork().plant.H, expect)
    np.testing.assert_allclose(InverterNetwork().plant.H[0, 0], -2 * (0.04711 + 0.02157))


def test_known_input_sign_of_cable_reactance():
    # raising q_c,i by 1 VAr lowers v_i^2 by 2 Xp[i, i], i.e. raises w_i by 2 Xp[i, i]
    base = InverterParams()
    more = InverterParams(q_c=base.q_c + np.array([0.0, 1.0, 0.0, 0.0, 0.0]))
    dw = InverterNetwork(more).w(0.7) - InverterNetwork(base).w(0.7)
    np.testing.assert_allclose(dw, 2 * InverterNetwork(base).Xp[:, 1], rtol=1e-9)
    assert dw[1] == pytest.approx(2 * (0.04711 + 0.02356 + 0.09707), rel=1e-9)


def test_squared_attack_and_disturbance_are_exact():
    net = InverterNetwork()
    x = np.array([100.0, -50.0, 200.0, 0.0, 30.0])
    t = 1.3
    z = net.plant.z(t, x)
    v = net.voltages(t, x)
    alpha = np.array([30.0, 0.0, -7.0, 30.0, 0.0])
    y_volts = v + alpha  # (13)
    np.testing.assert_allclose(net.lure_output(y_volts), z + net.squared_attack(z, alpha), rtol=1e-12)
    assert np.all(net.squared_attack(z, alpha)[[0, 3]] < -13000)  # +30 V lowers v_bar^2 - y^2
    d = net.squared_disturbance(np.array([6.0, -6.0, 0.0, 1.0, -1.0]))
    np.testing.assert_allclose(d, 230.0**2 - (230.0 + np.array([6.0, -6.0, 0.0, 1.0, -1.0])) ** 2)


def test_attack_schedule_and_disturbance_generator():
    alpha = voltage_attack(N=5, sensors=(0, 3), magnitude=30.0, start=10.5)
    np.testing.assert_array_equal(alpha(10.49), np.zeros(5))
    np.testing.assert_array_equal(alpha(1050 * 0.01), [30.0, 0, 0, 30.0, 0])
    with pytest.raises(ValueError):
        voltage_attack(N=5, sensors=(5,), magnitude=1.0, start=0.0)
    delta = random_voltage_disturbance(N=5, seed=7)
    a, b = delta(0.0), delta(0.0999)
    np.testing.assert_array_equal(a, b)  # held over 0.1 s
    assert not np.array_equal(a, delta(0.1))
    vals = np.stack([delta(0.1 * m) for m in range(400)])
    assert np.abs(vals).max() <= 6.0 and np.abs(vals).max() > 5.5
    np.testing.assert_array_equal(random_voltage_disturbance(N=5, seed=7)(3.05), delta(3.05))
    attack, dist = reference_signals(InverterNetwork(), disturbance_seed=3)
    assert np.abs(dist(2.0)).max() <= 2 * 230 * 6 + 36


def test_operating_point_in_linear_droop_region():
    net = InverterNetwork()
    x = np.zeros(5)
    for k in range(2000):
        x = net.plant.step(0.01 * k, x, 0.01)
    z = net.plant.z(20.0, x)
    assert np.all(np.abs(z) < 17320.5)  # the droop is not saturated at this operating point
    assert np.all(np.abs(net.voltages(20.0, x) - 230.0) < 12.0)
