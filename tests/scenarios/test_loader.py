"""Scenario validation: every error names the file, the key path, what was expected and
what was found; unknown keys are errors; --set is validated the same way."""

import tomllib
from pathlib import Path

import pytest

from estimation.errors import ScenarioError
from scenarios.build import build
from scenarios.loader import apply_override, load, parse_value, validate

ROOT = Path(__file__).resolve().parents[2]
LKS = ROOT / "scenarios" / "lee_kim_shim.toml"


def raw():
    return tomllib.loads(LKS.read_text())


def err(data, overrides=(), *, build_it=True):
    with pytest.raises(ScenarioError) as ei:
        sc, _ = validate(data, source="x.toml", overrides=overrides)
        if build_it:
            build(sc, source="x.toml")
    return str(ei.value)


def test_paper_scenario_loads():
    sc, frozen = load(LKS)
    assert sc.estimator.kappa == 0.5 and sc.network.graph.kind == "ring"
    assert sc.run.n_rounds == 4000


def test_missing_file(tmp_path):
    with pytest.raises(ScenarioError, match="nope.toml: no such file"):
        load(tmp_path / "nope.toml")


def test_toml_syntax_error(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text("[run\nname = 1\n")
    with pytest.raises(ScenarioError, match=r"bad.toml: TOML syntax error"):
        load(p)


def test_unknown_graph_kind_message():
    d = raw()
    d["network"]["graph"] = {"kind": "rnig"}
    assert err(d) == "x.toml: network.graph: unknown kind 'rnig'; expected one of ring, complete, edges, cells, attachment"


def test_unknown_keys_are_errors():
    d = raw()
    d["estimator"]["kapa"] = 3
    d["extra_table"] = {}
    msg = err(d)
    assert "estimator.kapa: unknown key" in msg and "extra_table: unknown key" in msg


def test_wrong_value_names_key_and_value():
    d = raw()
    d["estimator"]["kappa"] = -1
    assert err(d) == "x.toml: estimator.kappa: input should be greater than 0, got -1"


def test_wrong_matrix_shapes():
    d = raw()
    d["plant"] = {"model": "lti", "A": [[0, 1], [0, 0]], "B": [[0], [1]]}
    d["sensors"] = [{"C": [[1, 0, 0]]}]
    assert err(d) == "x.toml: sensors[0].C: expected rows of length 2, got 3"
    d["sensors"] = [{"C": [[1, 0]]}]
    d["plant"]["A"] = [[0, 1, 2], [0, 0]]
    assert err(d) == "x.toml: plant.A: rows have different lengths"
    d["plant"]["A"] = [[0, 1, 2], [0, 0, 1]]
    assert "plant.A: expected a square matrix, got shape (2, 3)" in err(d)


def test_disconnected_graph():
    d = raw()
    d["network"]["graph"] = {"kind": "edges", "edges": [[1, 2], [2, 3], [4, 5]]}
    assert err(d) == "x.toml: network.graph: the graph is disconnected: agents {1, 2, 3} and {4, 5}"


def test_edge_to_unknown_agent():
    d = raw()
    d["network"]["graph"] = {"kind": "edges", "edges": [[1, 9]]}
    assert "network.graph.edges[0]: no agent 9" in err(d)


def test_unobservable_sensor_set_for_q():
    d = raw()
    d["estimator"]["q"] = 2
    msg = err(d)
    assert msg.startswith("x.toml: estimator.q: the sensor set is not 4-redundantly observable (Assumption 2)")
    assert "agents 2 alone" in msg


def test_assumption4_failure_is_a_scenario_error():
    d = raw()
    d["plant"] = {"model": "lti", "A": [[2, 0, 0], [0, 2, 1], [0, 0, 2]], "B": [[0], [0], [1]]}
    d["sensors"] = [{"C": [[1, 1, 0.3]]}, {"C": [[1, -1, 0.3]]}, {"C": [[1, 2, 0.3]]}]
    d["estimator"]["q"] = 0
    d["attacks"] = []
    d["expect"] = []
    d["network"]["graph"] = {"kind": "complete"}
    assert "estimator: Assumption 4 fails" in err(d)


def test_attack_on_unknown_sensor():
    d = raw()
    d["attacks"][0]["sensors"] = [7]
    assert err(d) == "x.toml: attacks[0].sensors: no sensor bank 7; banks are 1..5"


def test_horizon_needs_exactly_one_of_duration_or_rounds():
    d = raw()
    d["run"]["rounds"] = 10
    assert "run: give exactly one of 'duration' (seconds) or 'rounds'" in err(d)


def test_set_overrides_are_validated_and_named():
    d = raw()
    msg = err(d, ["estimator.gamma=-3"])
    assert msg == "x.toml (with --set estimator.gamma=-3): estimator.gamma: input should be greater than 0, got -3"
    msg = err(d, ["estimator.gama=3"])
    assert "estimator.gama: unknown key" in msg
    with pytest.raises(ScenarioError, match=r"--set attacks.3.value=1: attacks.3: index 3 out of range"):
        validate(d, source="x.toml", overrides=["attacks.3.value=1"])
    with pytest.raises(ScenarioError, match="expected KEY.PATH=VALUE"):
        validate(d, source="x.toml", overrides=["estimator.gamma"])


def test_set_parses_toml_values():
    assert parse_value("5") == 5 and parse_value("1e-3") == 1e-3 and parse_value("[]") == []
    assert parse_value("ring") == "ring" and parse_value('{kind = "complete"}') == {"kind": "complete"}
    d = raw()
    apply_override(d, "attacks=[]")
    apply_override(d, "network.graph={kind = \"complete\"}")
    sc, frozen = validate(d, source="x.toml")
    assert sc.attacks == [] and sc.network.graph.kind == "complete"
    sc, frozen = validate(raw(), source="x.toml", overrides=["attacks.0.value=2.5", "run.dt=0.01"])
    assert sc.attacks[0].value == 2.5 and sc.run.dt == 0.01 and frozen["run"]["dt"] == 0.01
