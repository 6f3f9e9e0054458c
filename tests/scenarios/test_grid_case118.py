"""The IEEE 118-bus scenarios (scenarios/case118*.toml): rse check's conditions, the area
graph drawn from the network's tie lines, and rse run (agents packed per process) equal to
rse simulate. Their [[expect]] bounds run as tests of their own (rse.pytest_plugin)."""

import tomllib
from pathlib import Path

import numpy as np
import pytest

from estimation.grid import tie_line_graph
from scenarios.build import build, conditions
from scenarios.loader import load

pytest.importorskip("pandapower", reason="the grid plant needs pandapower (the grid extra)")

from scenarios.plugins.grid import _builtin_model

SCENARIOS = Path(__file__).resolve().parents[2] / "scenarios"
CASE118 = SCENARIOS / "case118.toml"


def test_the_scenarios_graph_is_the_tie_line_graph_of_the_six_areas():
    model, dc = _builtin_model("case118", 5.0, 2.0)
    numbers = dc.pd_bus[model.gen_bus] + 1
    areas = np.array_split(numbers, 6)
    assert [(int(a[0]), int(a[-1])) for a in areas] == [(1, 19), (24, 40), (42, 62), (65, 77), (80, 100), (103, 116)]
    edges = tie_line_graph(areas, dc.pd_bus + 1, dc.f, dc.t)
    for name in ("case118.toml", "case118_linear.toml"):
        graph = tomllib.loads((SCENARIOS / name).read_text())["network"]["graph"]
        assert [tuple(e) for e in graph["edges"]] == edges, name


def test_case118_conditions_rse_check_reports():
    """Six areas, each observing all 108 states: 4-redundant observability (q = 2), Lemma 1
    with 6 >= 5 banks per direction, lambda_2 of the tie-line graph and Theorem 1's bound."""
    sc, _ = load(str(CASE118), ())
    exp = build(sc, source=str(CASE118))
    assert exp.n == 108 and exp.N == 6
    found = {c.name: c for c in conditions(exp)}
    assert found["network connected (Assumption 3)"].holds
    assert float(found["lambda_2(L)"].detail) == pytest.approx(1.69722, abs=1e-5)
    assert found["4-redundant observability, q = 2 (Assumption 2)"].holds
    assert found["common basis (Assumption 4)"].detail == "modal basis; each of the 108 basis directions observed by 6 to 6 banks"
    assert found["each direction observed by >= 2q+1 = 5 agents (Lemma 1)"].holds
    per_agent = found["observability per agent (directions w_l^T x each bank observes)"].detail
    assert per_agent == ", ".join(f"{i}: 108 of 108" for i in range(1, 7))
    robust = next(c for name, c in found.items() if name.startswith("graph r-robustness"))
    assert robust.detail == "2-robust"  # area 1 (or 3, or 5) has two neighbours
    bound = next(c for name, c in found.items() if name.startswith("Theorem 1 bound"))
    lam2 = float(found["lambda_2(L)"].detail)
    assert float(bound.detail) == pytest.approx(2 * np.sqrt(6) / (5.0 * lam2), rel=1e-5)
    assert float(bound.detail) == pytest.approx(0.577293, abs=1e-6)  # the scenario files' bound
    for ob in exp.design.observers:  # the sampled Kalman gains: every partial observer converges
        assert ob.Ld is not None and np.all(ob.poles.real < 0)


@pytest.mark.slow
@pytest.mark.multiprocess
def test_rse_run_packed_equals_rse_simulate_on_case118(procs, tmp_path):
    """Lockstep, three agents per process (two agent processes, plant, monitor), 250 rounds
    (the attack starts at round 200): every estimate and the truth equal the simulator's,
    max difference 0.0."""
    from agents.api import load_experiment
    from agents.simulate import simulate
    from tests.procs import rse_cmd

    ov = ("run.duration=2.5", "output.window=[2.0, 2.5]", "expect=[]")
    out = tmp_path / "run"
    p = procs.start(rse_cmd("run", str(CASE118), *[x for o in ov for x in ("--set", o)], "--agents-per-process", "3",
                            "--out", str(out), "--save-estimates", "--no-progress", "--no-rerun", "--deadline", "60"))
    so, se = p.communicate(timeout=600)  # only a hang reaches it
    assert p.returncode == 0, se
    exp, _ = load_experiment(CASE118, ov, None)
    ref = simulate(exp, keep_trajectories=True)
    est, truth = np.load(out / "estimates.npy"), np.load(out / "truth.npy")
    assert est.shape == ref.estimates.shape == (251, 6, 108)
    assert float(np.max(np.abs(truth - ref.truth))) == 0.0
    assert float(np.max(np.abs(est - ref.estimates))) == 0.0
