"""The grid plant model against pandapower (the independent reference): the model's rest
state under constant injections equals pandapower's DC power flow (rundcpp) on the same
network, for the IEEE 14-, 30- and 118-bus systems; and its input errors."""

import sys

import numpy as np
import pytest

from estimation.errors import ScenarioError
from estimation.lti import zoh
from scenarios.build import build
from scenarios.loader import load

pytest.importorskip("pandapower", reason="the grid plant needs pandapower (the grid extra)")

from scenarios.plugins.grid import _grid_plant, grid_model, pandapower_net


@pytest.mark.parametrize("case", ["case14", "case30", "case118"])
def test_rest_state_equals_pandapower_dc_power_flow(case):
    model, dc = grid_model(pandapower_net(case))
    # the reference generator: pandapower's slack (its angle is the case's va_degree)
    net = pandapower_net(case)
    slack = int(np.flatnonzero(dc.pd_bus == int(net.ext_grid.bus.iloc[0]))[0])
    x = model.equilibrium(dc.p, ref=slack, angle=dc.theta[slack])
    # the rest state of the dynamics discretised exactly (run.dt = 0.01): x = Ad x + Bd p
    Bp = np.zeros((2 * model.G, dc.p.size))
    Bp[model.G:] = model.K / model.M[:, None]
    Ad, Bd = zoh(model.A, Bp, 0.01)
    assert np.max(np.abs(Ad @ x + Bd @ dc.p - x)) <= 1e-9 * np.max(np.abs(x))
    theta = model.bus_angles(x, dc.p)
    rel = np.max(np.abs(theta - dc.theta)) / np.max(np.abs(dc.theta))
    print(f"{case}: {model.G} generator buses, max relative difference to rundcpp {rel:.3g}")
    assert rel <= 1e-9


def test_case_sizes_and_generator_buses():
    model, dc = grid_model(pandapower_net("case14"))
    assert [int(dc.pd_bus[g]) + 1 for g in model.gen_bus] == [1, 2, 3, 6, 8]
    assert model.A.shape == (10, 10) and model.B.shape == (10, 11)  # 11 load buses
    model, _ = grid_model(pandapower_net("case118"))
    assert model.G == 54


def _scenario(tmp_path, plant: str) -> str:
    p = tmp_path / "g.toml"
    p.write_text(f"""
[run]
name = "g"
dt = 0.01
rounds = 5
[plant]
model = "grid"
{plant}
[network]
graph = {{ kind = "ring" }}
[estimator]
algorithm = "lee_kim_shim"
kappa = 0.5
gamma = 2.0
q = 1
""")
    return str(p)


def _build(path):
    sc, _ = load(path, ())
    return build(sc, source=path)


def test_pmus_areas_and_discrete_time(tmp_path):
    exp = _build(_scenario(tmp_path, 'case = "case14"\npmus = [1, [2, 3], 6]'))
    assert exp.N == 3 and [len(r) for r in exp.agent_rows] == [2, 4, 2]
    assert np.array_equal(exp.plant.C[exp.agent_rows[1]][:, [1, 2, 6, 7]], [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    sc, _ = load(_scenario(tmp_path, 'case = "case14"\nparams = { areas = 2, frequency = 0 }\ntime = "discrete"'), ())
    plant = _grid_plant(sc, "x")
    assert [C.shape[0] for C in plant.lti.banks] == [3, 2]  # angle rows of buses 1, 2, 3 | 6, 8
    model, _ = grid_model(pandapower_net("case14"))
    Ad, Bd = zoh(model.A, model.B, 0.01)  # the plant's matrices are the exact discretisation
    assert plant.discrete and np.array_equal(plant.lti.A, Ad) and np.array_equal(plant.lti.B, Bd)


@pytest.mark.parametrize(("plant", "message"), [
    ('case = "case9999"', "plant.case: pandapower has no network 'case9999'"),
    ('case = "nope.json"', "plant.case: no pandapower network file"),
    ("", "plant.case: model 'grid' needs a network"),
    ('case = "case14"\npmus = [4]', r"plant.pmus\[0\]: bus\(es\) \[4\] carry no generator"),
    ('case = "case14"\nparams = { H = -1 }', "expected H > 0"),
    ('case = "case14"\nparams = { areas = 9 }', "9 areas for 5 generator buses"),
    ('case = "case14"\nparams = { inertia = 1 }', "unknown parameter"),
])
def test_errors_name_the_key(tmp_path, plant, message):
    with pytest.raises(ScenarioError, match=message) as exc:
        _build(_scenario(tmp_path, plant))
    assert "\n" not in str(exc.value)


def test_without_pandapower_one_line_naming_the_extra(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "pandapower", None)
    monkeypatch.setitem(sys.modules, "pandapower.networks", None)
    with pytest.raises(ScenarioError, match=r"needs pandapower, which is not installed; pip install .*\[grid\]") as exc:
        _build(_scenario(tmp_path, 'case = "case14"'))
    assert "\n" not in str(exc.value)


def test_case14_conditions_rse_check_reports():
    """The redundancy that sets the case14 scenario's attack budget, and Theorem 1's bound."""
    from pathlib import Path

    from scenarios.build import conditions

    path = Path(__file__).resolve().parents[2] / "scenarios" / "case14.toml"
    exp = _build(str(path))
    found = {c.name: c for c in conditions(exp)}
    assert found["4-redundant observability, q = 2 (Assumption 2)"].holds
    assert found["each direction observed by >= 2q+1 = 5 agents (Lemma 1)"].holds
    bound = next(c for name, c in found.items() if name.startswith("Theorem 1 bound"))
    assert float(bound.detail) == pytest.approx(1.61803, abs=1e-5)
    sc, _ = load(str(path), ("estimator.q=3",))  # one more falsified PMU than the redundancy allows
    with pytest.raises(ScenarioError, match="not 6-redundantly observable"):
        build(sc, source=str(path))
