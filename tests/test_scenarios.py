"""The acceptance figures of the reproductions, asserted here with their variants. Every
scenario file in scenarios/ runs end to end with its [[expect]] bounds as the suite's own
items: one per bound, through the pytest plugin (``--rse`` in the addopts; tests/test_pytest_plugin.py).
The variants below that the files' bounds already cover (dt = 1e-2, the files' own step)
are not run again."""

from pathlib import Path

import numpy as np
import pytest

from agents.simulate import simulate
from scenarios.build import build
from scenarios.loader import load

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"


def run(path, *overrides):
    sc, _ = load(path, overrides)
    exp = build(sc, source=str(path))
    return exp, simulate(exp)


def worst(exp, res, metric, t0, t1, block="x"):
    mon = res.monitor
    t = np.arange(mon.last_round + 1) * exp.dt
    rows = (t >= t0 - 1e-9) & (t <= t1 + 1e-9)
    b = mon.block_names.index(block)
    return float(np.nanmax(mon.metric(metric)[rows][:, res.regular, b]))


LKS = SCENARIOS / "lee_kim_shim.toml"
LKS_BASE = SCENARIOS / "lee_kim_shim_nonresilient.toml"


def test_lee_kim_shim_acceptance():
    """At dt = 1e-3; at the file's 1e-2 the two bounds are the file's own (its items)."""
    exp, res = run(LKS, "run.dt=0.001")
    assert worst(exp, res, "error_inf", 10.0, 10.0) <= 0.01
    assert worst(exp, res, "error_inf", 30.0, 40.0) <= 0.25
    # the attacked agents are not all exact: the bound is met with a non-trivial margin only
    assert worst(exp, res, "error_inf", 30.0, 40.0) >= 0.05


@pytest.mark.parametrize("dt", [1e-3, 1e-2])
def test_lee_kim_shim_high_gains(dt):
    exp, res = run(LKS, f"run.dt={dt}", "estimator.kappa=5", "estimator.gamma=20")
    assert worst(exp, res, "error_inf", 30.0, 40.0) <= 0.03


@pytest.mark.parametrize("dt", [1e-3, 1e-2])
def test_lee_kim_shim_without_attack(dt):
    exp, res = run(LKS, f"run.dt={dt}", "attacks=[]")
    assert worst(exp, res, "error_inf", 30.0, 40.0) <= 0.01


def test_nonresilient_baseline_is_biased():
    """At dt = 1e-3; at the file's 1e-2 the bound is the file's own (its item)."""
    exp, res = run(LKS_BASE, "run.dt=0.001")
    assert worst(exp, res, "error_inf", 30.0, 40.0) >= 0.3


# measured with the scenario's seed (the simulator is deterministic), the worst infinity-norm
# error of each agent over [30, 40]: agent 1 (its own sensor attacked), then agents 2 to 5
OTHER_ATTACKS = {
    "ramp": ("attacks.0.slope=0.5", [0.125, 0.00215, 2.49e-06, 0.0575, 0.105]),
    "sine": ("attacks.0.amplitude=3.0", [0.248, 0.0178, 1.12e-05, 0.0437, 0.105]),
    "random": ("attacks.0.scale=5.0", [0.396, 0.101, 5.87e-05, 0.0309, 0.0698]),
}


@pytest.mark.parametrize("kind", list(OTHER_ATTACKS))
def test_lee_kim_shim_other_attack_kinds(kind):
    """Unbounded ramp, sinusoid and random attacks on sensor 1: the agents whose own sensor
    is clean stay within the acceptance bound 0.25, each within 10 times what it reaches
    today (OTHER_ATTACKS); agent 1, whose own partial observer is corrupted, is pulled back
    by its neighbours and stays bounded. With a random attack its sign term random-walks
    its estimate: 0.396 with the scenario's seed, 0.40 to 0.48 over seeds 1 to 8, so it is
    held to 0.5 (twice the scenario's bound, which is for the sinusoid the paper uses);
    with the ramp and the sinusoid it stays within the scenario's 0.25."""
    extra, measured = OTHER_ATTACKS[kind]
    exp, res = run(LKS, "run.dt=0.01", f"attacks.0.kind={kind}", extra, "attacks.0.omega=1.0")
    t = np.arange(res.monitor.last_round + 1) * exp.dt
    worst_each = res.monitor.metric("error_inf")[t >= 30.0, :, 0].max(axis=0)
    bounds = [0.25 if kind != "random" else 0.5] + [min(0.25, 10 * m) for m in measured[1:]]
    assert np.all(worst_each <= bounds), (worst_each.tolist(), bounds)
