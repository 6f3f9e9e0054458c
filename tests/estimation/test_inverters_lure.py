"""Lur'e plant (7) and its fixed-step integration; the observer's discretisation."""

from __future__ import annotations

import numpy as np
import pytest

from estimation.inverters import InverterNetwork, reference_signals
from estimation.lure import LurePlant, integrate, rk4_step
from estimation.median_bank import LureObserver

DT = 0.01  # the inverter scenario's round length


def test_rk4_is_fourth_order_on_a_smooth_system():
    f = lambda t, x: np.array([x[1], -x[0] + np.cos(t)])
    exact = lambda t: np.array([0.5 * t * np.sin(t), 0.5 * (np.sin(t) + t * np.cos(t))])
    errs = []
    for h in (0.1, 0.05):
        x = np.zeros(2)
        for k in range(int(round(2.0 / h))):
            x = rk4_step(f, k * h, x, h)
        errs.append(np.abs(x - exact(2.0)).max())
    assert 14.0 < errs[0] / errs[1] < 18.0  # 2^4 = 16


def test_plant_at_scenario_dt_matches_a_10x_finer_step():
    net = InverterNetwork()
    _, dist = reference_signals(net, disturbance_seed=5)
    plant = net.plant
    x1 = x20 = np.zeros(5)
    worst = 0.0
    for k in range(1200):  # 12 s, the acceptance window starts here
        t = k * DT
        d = dist(t)
        x1 = plant.step(t, x1, DT, d=d)
        x20 = plant.step(t, x20, DT, d=d, substeps=10)
        worst = max(worst, float(np.abs(plant.H @ (x1 - x20)).max()))
    assert np.abs(x20).max() > 100.0  # a non-trivial trajectory (VAr)
    assert worst < 1e-6  # V^2: far below every acceptance tolerance


def test_integrate_validates_substeps():
    with pytest.raises(ValueError):
        integrate(lambda t, x: -x, 0.0, np.ones(1), 0.1, substeps=0)


def test_plant_build_validates_shapes():
    w = lambda t: np.zeros(2)
    with pytest.raises(ValueError, match="square"):
        LurePlant.build(A=np.zeros((2, 3)), H=np.eye(2), phi=np.tanh, slope_upper=1.0, w=w)
    with pytest.raises(ValueError, match="H must be"):
        LurePlant.build(A=np.eye(2), H=np.eye(3), phi=np.tanh, slope_upper=1.0, w=w)
    with pytest.raises(ValueError, match="w"):
        LurePlant.build(A=np.eye(2), H=np.eye(2), phi=np.tanh, slope_upper=1.0, w=lambda t: np.zeros(3))
    pl = LurePlant.build(A=-np.eye(2), H=np.eye(2), phi=np.tanh, slope_upper=1.0, w=w)
    with pytest.raises(ValueError):
        pl.A[0, 0] = 1.0  # read-only


def test_observer_started_on_the_truth_reproduces_the_plant():
    net = InverterNetwork()
    plant = net.plant
    L = np.full((5, 1), -3.0)
    K = np.full((5, 1), 0.5)
    x = np.array([10.0, 20.0, -30.0, 40.0, 0.0])
    obs = LureObserver(plant, sensors=[2], L=L, K=K, dt=DT, x0=x)
    for k in range(300):
        y = plant.output(k * DT, x)
        np.testing.assert_allclose(obs.step(k, y[2:3], {}), x, atol=1e-9)
        x = plant.step(k * DT, x, DT)


def test_observer_missing_measurement_and_round_order():
    net = InverterNetwork()
    obs = LureObserver(net.plant, sensors=[0], L=np.zeros((5, 1)), K=np.zeros((5, 1)), dt=DT, x0=np.zeros(5))
    e0 = obs.step(0, None, {})
    e1 = obs.step(1, None, {})
    assert not np.array_equal(e0, e1)  # open-loop prediction
    e1[0] = 1e9
    assert obs.estimate[0] != 1e9  # hands out copies
    with pytest.raises(ValueError, match="rounds"):
        obs.step(1, None, {})


def test_volt_measurements_through_measurement_map():
    net = InverterNetwork()
    x = np.zeros(5)
    a = LureObserver(net.plant, sensors=[1], L=np.ones((5, 1)), K=np.zeros((5, 1)), dt=DT, x0=np.ones(5),
                     measurement_map=net.lure_output)
    b = LureObserver(net.plant, sensors=[1], L=np.ones((5, 1)), K=np.zeros((5, 1)), dt=DT, x0=np.ones(5))
    for k in range(5):
        t = k * DT
        np.testing.assert_allclose(a.step(k, net.voltages(t, x)[1:2], {}), b.step(k, net.plant.z(t, x)[1:2], {}))
        x = net.plant.step(t, x, DT)
