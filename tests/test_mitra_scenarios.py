"""Mitra et al. (2019) reproduced through scenario files: the acceptance figures."""

from pathlib import Path

import numpy as np
import pytest

from agents.simulate import simulate
from scenarios.build import build, conditions
from scenarios.loader import load

SC = Path(__file__).resolve().parents[1] / "scenarios"


def run(name, *overrides):
    sc, _ = load(SC / name, overrides)
    exp = build(sc, source=name)
    return exp, simulate(exp)


def metric(exp, res, name, rounds=None, agents=None):
    """(rounds, agents, blocks) slice of a metric, regular agents by default, cell blocks only."""
    m = res.monitor.metric(name)[: res.monitor.last_round + 1]
    cols = np.flatnonzero(res.regular) if agents is None else [exp.agent_ids.index(a) for a in agents]
    blocks = [b for b, nm in enumerate(res.monitor.block_names) if nm.startswith("cell")]
    m = m[:, cols][:, :, blocks]
    return m if rounds is None else m[rounds]


@pytest.mark.parametrize("kind", ["cancellation", "huge", "equivocation"])
def test_mitra_cells_converges_despite_the_adversary(kind):
    exp, res = run("mitra_cells.toml", f"attacks.0.kind={kind}")
    assert 4 in exp.byzantine and not res.regular[4]
    final = metric(exp, res, "relative_error_2", rounds=-1)
    assert final.shape == (15, 4)  # every regular agent, every cell block
    assert np.max(final) <= 1e-9
    assert np.max(metric(exp, res, "error_2", rounds=slice(0, 151))) <= 1e2


def test_high_erasure_probability_blows_up_and_mss_reports_it():
    exp, res = run("mitra_cells_p08.toml")
    assert np.max(metric(exp, res, "error_2", rounds=slice(0, 151))) >= 1e3
    mss = {c.name.split(":")[0]: c for c in conditions(exp) if c.name.startswith("MSS")}
    assert list(mss.values())[0].holds is False
    exp2, _ = run("mitra_cells.toml", "run.rounds=1", "expect=[]")
    c2 = [c for c in conditions(exp2) if c.name.startswith("MSS")][0]
    assert c2.holds is True
    pmax = [c for c in conditions(exp2) if c.name.startswith("largest tolerable")][0]
    assert float(pmax.detail) == pytest.approx(0.3265, abs=5e-5)


def test_omission_needs_3f_plus_1_robustness():
    exp, res = run("mitra_omission.toml")
    cell3 = [9, 10, 11, 12]
    assert np.max(metric(exp, res, "relative_error_2", rounds=-1, agents=cell3)) >= 1e-3
    rob = [c for c in conditions(exp) if c.name.startswith("cell1: strongly")][0]
    assert rob.detail == "strong robustness 3"  # only (2f+1)-robust w.r.t. cell 1's agents
    exp, res = run("mitra_omission.toml", "network.graph.remove=[]")
    assert np.max(metric(exp, res, "relative_error_2", rounds=-1)) <= 1e-9


def test_diffusion_converges_at_p08():
    exp, res = run("mitra_diffusion.toml")
    ratio = res.monitor.metric("error_ratio")[res.monitor.last_round, res.regular, 0]
    assert np.max(ratio) <= 1e-3
    mss = [c for c in conditions(exp) if c.name.startswith("MSS")][0]
    assert mss.holds is True


def test_nonresilient_averaging_is_frozen_by_cancellation():
    exp, res = run("mitra_nonresilient.toml")
    assert np.max(metric(exp, res, "relative_error_2", rounds=-1)) >= 0.5
    exp, res = run("mitra_nonresilient.toml", "estimator.rule=lfre")
    assert np.max(metric(exp, res, "relative_error_2", rounds=-1)) <= 1e-3


@pytest.mark.parametrize("shift", [50, -40])
def test_sw_lfre_survives_delays_losses_and_forged_stamps(shift):
    exp, res = run("mitra_sw_lfre.toml", f"attacks.0.shift={shift}")
    late = sum(c["late"] for c in res.links.values())
    assert late > 1000  # the delays are real
    assert np.max(metric(exp, res, "relative_error_2", rounds=-1)) <= 1e-6
    exp, res = run("mitra_sw_lfre.toml", "estimator.rule=lfre")  # memoryless LFRE does not cope
    assert np.max(metric(exp, res, "relative_error_2", rounds=-1)) >= 1e-3


def test_median_variant_remark7():
    exp, res = run("mitra_cells.toml", "estimator.rule=median")
    assert np.max(metric(exp, res, "relative_error_2", rounds=-1)) <= 1e-9


def test_mobile_agents_read_only_where_they_are():
    exp, _ = run("mitra_cells.toml", "run.rounds=1", "expect=[]")
    assert not exp.static
    # agent 1 patrols cell 1 with period 13: ten visits then three commuting rounds
    seen = [exp.rows_at(0, k) for k in range(13)]
    assert sum(r is None for r in seen) == 3
    assert all(exp.cell_of_location[int(r[0])] == 0 for r in seen if r is not None)


def test_patrol_validation_errors_name_the_agent():
    import tomllib

    from estimation.errors import ScenarioError
    from scenarios.loader import validate

    raw = tomllib.loads((SC / "mitra_cells.toml").read_text())
    raw["agents"] = [{"patrol": {"locations": [1, 2], "offsets": [0, 0], "periods": [2, 2]}}]
    raw["network"]["graph"] = {"kind": "complete"}
    raw["attacks"] = []
    with pytest.raises(ScenarioError, match=r"agents\[0\]\.patrol: .*infeasible"):
        sc, _ = validate(raw, source="x.toml")
        build(sc, source="x.toml")
    raw["agents"] = {"kind": "cell_patrols", "per_cell": 4, "periods": [13, 14, 9, 14]}
    with pytest.raises(ScenarioError, match="cell 3: period 9 is shorter than its 10 locations"):
        sc, _ = validate(raw, source="x.toml")
        build(sc, source="x.toml")


def test_generated_teams_of_any_size():
    """cells with K cells and 4 agents per cell from one file with --set (Section 8 layout)."""
    exp, res = run("mitra_cells.toml", "plant.params.K=8", "agents.periods=[13, 14]", "run.rounds=150",
                   "expect=[]", "network.channel.drop_p=0.0")
    assert exp.N == 32 and exp.n == 160
    assert np.max(metric(exp, res, "relative_error_2", rounds=-1)) <= 1e-9
    from estimation.errors import ScenarioError
    with pytest.raises(ScenarioError, match="3 periods do not repeat evenly over 8 cells"):
        run("mitra_cells.toml", "plant.params.K=8", "agents.periods=[13, 14, 14]")


def test_a_sparse_cells_plant_runs_the_team_bit_for_bit_as_the_dense_one(monkeypatch):
    """Large teams keep the diagonal ``A`` sparse (``estimation.cells.SPARSE_FROM``): a
    4-cell team built with the sparse ``A`` (design, horizon check, plant step) gives the
    dense one's errors bit for bit."""
    from scipy import sparse

    import estimation.cells

    ov = ("run.rounds=60", "expect=[]")
    exp_d, dense = run("mitra_cells.toml", *ov)
    monkeypatch.setattr(estimation.cells, "SPARSE_FROM", 0)
    exp_s, sp = run("mitra_cells.toml", *ov)
    assert not sparse.issparse(exp_d.plant.A) and sparse.issparse(exp_s.plant.A)
    for name in ("error_2", "error_inf"):
        np.testing.assert_array_equal(sp.monitor.metric(name), dense.monitor.metric(name))
