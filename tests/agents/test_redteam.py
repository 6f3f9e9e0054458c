"""``rse redteam``: the search space and its threat model, candidates as overrides,
shrinking, and the worst attack replayed exactly from worst.toml."""

import json
import math
from pathlib import Path

import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner

from agents import api
from agents.cli import cli
from agents.redteam import active_components, derive, redteam
from agents.redteam.search import metric_value
from agents.redteam.shrink import proposals, round_sig, shrink
from agents.redteam.warm import warm_start
from estimation.errors import ScenarioError

SC = Path(__file__).resolve().parents[2] / "scenarios"
LKS, LKS_NR = SC / "lee_kim_shim.toml", SC / "lee_kim_shim_nonresilient.toml"
MITRA = SC / "mitra_cells.toml"
#: a short Lee-Kim-Shim run: 8 s at dt = 0.02, window [6, 8]
SHORT = ["run.dt=0.02", "run.duration=8.0", "output.window=[6.0, 8.0]", "expect=[]"]


def test_space_derived_from_lee_kim_shim():
    sp, spec = derive(api.load(LKS))
    assert (sp.q, sp.f, sp.sensors, sp.agents) == (1, None, 1, 0)
    assert sp.banks == [1, 2, 3, 4, 5] and sp.kinds == ["constant", "ramp", "sine", "random", "trajectory"]
    assert sp.amplitude == pytest.approx(math.pi / 3)  # the scenario's own attack sets the bound
    assert sp.omega[0] == 0 and sp.omega[1] == pytest.approx(2 * 20.27, abs=0.1)  # twice the top modal frequency
    assert sp.start == (0.0, 30.0)  # up to the start of the window
    assert (spec.metric, spec.over, spec.block) == ("error_inf", "window", "x")
    sp2, _ = derive(api.load(LKS), beyond=True)
    assert sp2.sensors == 2 and sp2.agents == 0


def test_space_derived_from_mitra_cells():
    sp, spec = derive(api.load(MITRA))
    assert (sp.q, sp.f, sp.sensors, sp.agents) == (None, 1, 0, 1)
    assert sp.candidates == list(range(1, 17)) and len(sp.strategies) == 8
    assert sp.drop_p == 0.32 and sp.seed
    assert (spec.metric, spec.over, spec.block) == ("relative_error_2", "final", "all")
    assert derive(api.load(MITRA), beyond=True)[0].agents == 2


@pytest.mark.parametrize("path,sets,beyond,match", [
    (LKS, ["redteam.sensors=2"], False, "outside the threat model.*estimator.q = 1"),
    (LKS, ["redteam.agents=1"], False, "Byzantine agents are outside lee_kim_shim's threat model"),
    (MITRA, ["redteam.agents=2"], False, "at most estimator.f = 1"),
    (MITRA, ["redteam.drop_p=0.5"], False, "network.channel.drop_p = 0.32"),
    (MITRA, ["redteam.sensors=1"], False, "sensors are trusted"),
    (MITRA, ["redteam.agents=0", "network.channel.drop_p=0.0"], True, "empty search space"),
    (LKS, ["redteam.banks=[7]"], False, "no sensor bank 7"),
])
def test_threat_model_is_enforced(path, sets, beyond, match):
    with pytest.raises(ScenarioError, match=match):
        derive(api.load(path, set=sets), beyond=beyond)


def test_the_strategy_names_agree_across_the_layers():
    """A ThreatModel names strategies from scenarios.common.STRATEGIES (the scenario layer
    does not import the transport): the same as the runtime's and the schema's."""
    from typing import get_args

    from scenarios.common import STRATEGIES
    from scenarios.schema import AgentKind
    from transport.byzantine import KINDS

    assert STRATEGIES == KINDS == get_args(AgentKind)


def test_a_declared_strategy_list_limits_the_search(monkeypatch):
    """A plugin's ``THREAT_MODEL.strategies`` is the default strategy list; naming another
    strategy in ``[redteam]`` is outside the threat model unless ``--beyond``."""
    from scenarios import plugins
    from scenarios.helpers import ThreatModel

    monkeypatch.setattr(plugins.algorithm("lfre"), "THREAT_MODEL", ThreatModel(agents="f", strategies=("constant", "huge")))
    sp, _ = derive(api.load(MITRA))
    assert (sp.agents, sp.strategies) == (1, ["constant", "huge"])
    with pytest.raises(ScenarioError, match="'cancellation' is outside lfre's threat model"):
        derive(api.load(MITRA, set=['redteam.strategies=["constant", "cancellation"]']))
    assert derive(api.load(MITRA, set=['redteam.strategies=["cancellation"]']), beyond=True)[0].strategies == ["cancellation"]


def test_beyond_allows_one_step_outside():
    sp, _ = derive(api.load(LKS, set=["redteam.sensors=2", "redteam.amplitude=10"]), beyond=True)
    assert sp.sensors == 2 and sp.amplitude == 10


def test_unknown_metric_and_block():
    with pytest.raises(ScenarioError, match="unknown metric 'rmse'"):
        derive(api.load(LKS), metric="rmse")
    with pytest.raises(ScenarioError, match="unknown block 'cell9'"):
        derive(api.load(MITRA), block="cell9")


@pytest.mark.parametrize("args,match", [
    ([str(LKS), "--set", "redteam.sensors=2"], "pass --beyond"),
    ([str(LKS), "--metric", "rmse"], "unknown metric"),
    ([str(SC / "ugrinovskii_biasing.toml")], "empty search space"),
])
def test_cli_bad_input_is_one_line_exit_2(args, match, tmp_path):
    res = CliRunner().invoke(cli, ["redteam", *args, "--out", str(tmp_path / "o"), "--no-progress"])
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and match in lines[0]


def test_candidate_overrides_build_the_attacks():
    exp = api.load(LKS, set=SHORT)
    sp, _ = derive(exp)
    cand = {"sensor": [{"bank": 2, "kind": "ramp", "size": 0.5, "start": 4.0},
                       {"bank": 3, "kind": "sine", "size": -0.25, "start": 1.0, "omega": 11.7, "phase": 0.5}],
            "agent": [], "channel": {}}
    e = api.load(LKS, set=SHORT + sp.overrides(cand))
    ramp, sine = e.scenario.attacks
    assert ramp.sensors == [2] and ramp.slope * (8.0 - 4.0) == pytest.approx(0.5)  # |a| <= size up to the horizon
    assert (sine.kind, sine.amplitude, sine.omega, sine.phase, sine.start) == ("sine", -0.25, 11.7, 0.5, 1.0)
    assert active_components(cand) == 2
    m = derive(api.load(MITRA))[0]
    cand = {"sensor": [], "agent": [{"agent": 7, "kind": "false_stamp", "start": 3.0, "shift": -4, "payload": "estimate"}],
            "channel": {"drop_p": 0.125, "seed": 99}}
    e = api.load(MITRA, set=m.overrides(cand))
    (byz,) = e.scenario.attacks
    assert (byz.agents, byz.kind, byz.shift, byz.payload) == ([7], "false_stamp", -4, "estimate")
    assert e.scenario.network.channel.drop_p == 0.125 and e.seed == 99
    assert active_components(cand) == 2


def test_trajectory_candidate_is_dynamics_consistent_and_bounded():
    import numpy as np

    exp = api.load(LKS, set=SHORT)
    sp, _ = derive(exp)
    u = [0.5, -0.3, 0.2, 0.1, -0.9, 0.4]
    cand = {"sensor": [{"bank": 4, "kind": "trajectory", "size": -0.75, "start": 2.0, "direction": u}],
            "agent": [], "channel": {}}
    (at,) = api.load(LKS, set=SHORT + sp.overrides(cand)).scenario.attacks
    d = np.asarray(at.x0_attack) - exp.x0
    assert np.allclose(d / np.linalg.norm(d), np.asarray(u) / np.linalg.norm(u))  # along the sampled direction
    C, v, peak = exp.plant.C[exp.bank_rows[3]], d.copy(), 0.0
    for _ in range(exp.n_rounds + 1):  # a_4[k] = C_4 Ad^k (x0_attack - x0) peaks at |size|
        peak, v = max(peak, float(np.max(np.abs(C @ v)))), exp.Ad @ v
    assert peak == pytest.approx(0.75, rel=1e-12)


def test_shrinking_removes_components_and_rounds_values():
    sp, _ = derive(api.load(MITRA, set=["redteam.losses=1"]), beyond=True)
    cand = {"sensor": [], "agent": [{"agent": 3, "kind": "constant", "start": 17.3456, "value": 123.456},
                                    {"agent": 9, "kind": "huge", "start": 40.123, "scale": 5.5}],
            "channel": {"drop_p": 0.2345, "seed": 12345, "losses": [{"link": [1, 5], "start": 10, "length": 8}]}}

    def fake(cands):  # violates while agent 3 sends more than 10 from before round 200
        out = []
        for c in cands:
            a = [x for x in c["agent"] if x["agent"] == 3 and x["kind"] == "constant"]
            out.append({"metric": a[0]["value"] / (1 + a[0]["start"] / 200) if a else 0.0, "elapsed_s": 0.0, "status": "ok"})
        return out

    assert all(active_components(p) <= active_components(cand) for p in proposals(cand, sp))
    small, value, n = shrink(cand, fake([cand])[0]["metric"], sp, fake, lambda v: v > 10, batch=3, max_evals=400)
    # start moved to the latest start of the space (225: the window), the value rounded (0 no longer
    # violates; division stops at 1e-3 of the space's bound 1e6), the seed 0
    assert small == {"sensor": [], "agent": [{"agent": 3, "kind": "constant", "start": 225.0, "value": 100.0}],
                     "channel": {"drop_p": 0.0, "seed": 0, "losses": []}}
    assert value == pytest.approx(100 / 2.125) and active_components(small) == 1
    # with a smaller bound the value is divided further: 100 -> 50 -> 25 (12.5 / 2.125 < 10)
    sp.value = 1e3
    small, value, _ = shrink(cand, fake([cand])[0]["metric"], sp, fake, lambda v: v > 10, batch=3, max_evals=400)
    assert small["agent"][0]["value"] == 25.0 and value == pytest.approx(25 / 2.125)
    assert n <= 400


def test_round_sig():
    assert round_sig(123.456, 1) == 100.0 and round_sig(0.0123456, 2) == 0.012 and round_sig(0.0, 3) == 0.0
    assert round_sig(123.456, 1, up=True) == 200.0 and round_sig(17.3456, 2, up=True) == 18.0
    assert round_sig(-0.0123456, 2, up=True) == -0.012 and round_sig(300.0, 1, up=True) == 300.0


def test_search_writes_a_worst_toml_that_replays_exactly_and_resumes(tmp_path):
    out = tmp_path / "rt"
    res = redteam(LKS_NR, budget=4, jobs=2, out=out, overrides=SHORT, threshold=1e-3, shrink_budget=6, seed=1)
    s = res.summary
    assert s["evaluations"] == 4 and len([r for r in res.rows if r["phase"] == "search"]) == 4
    table = pq.read_table(out / "redteam.parquet").to_pandas()
    assert {"metric", "elapsed_s", "p_s0_kind", "p_s0_bank", "candidate", "overrides"} <= set(table.columns)
    worst = s["worst"]
    assert worst["value"] == table[table.phase == "search"].metric.max() and worst["reproduced"]
    # rse simulate worst.toml: the same number, bit for bit, and the metric is an [[expect]] of the file
    exp = api.load(out / "worst.toml")
    run = api.simulate(exp)
    assert metric_value(exp, run, derive(exp)[1]) == worst["value"]
    assert run.expectations()[-1].value == worst["value"] and run.expectations()[-1].max == 1e-3
    cli_out = CliRunner().invoke(cli, ["simulate", str(out / "worst.toml"), "--out", str(tmp_path / "w"), "--no-rerun",
                                       "--no-progress"])
    assert cli_out.exit_code == 3  # the threshold is exceeded: the expectation fails
    assert json.loads((tmp_path / "w" / "summary.json").read_text())["expectations"][-1]["value"] == worst["value"]
    # above the threshold: shrunk, never more components, still violating
    assert s["held"] is False and s["shrunk"] is not None
    assert s["shrunk"]["components"] <= worst["components"] and s["shrunk"]["value"] > 1e-3
    assert (out / "shrunk.toml").is_file() and (out / "redteam.png").is_file() and (out / "recording.rrd").is_file()
    assert (out / "worst" / "metrics.parquet").is_file() and (out / "worst" / "recording.rrd").is_file()
    # resuming the same directory continues the study
    res2 = redteam(LKS_NR, budget=6, jobs=2, out=out, overrides=SHORT, threshold=1e-3, shrink_budget=0, seed=1,
                   rerun=False, png=False)
    assert res2.summary["evaluations"] == 6 and res2.summary["resumed"] == 4


def test_byzantine_search_on_mitra_cells_short(tmp_path):
    res = redteam(MITRA, budget=2, jobs=2, out=tmp_path / "m", overrides=["run.rounds=40", "expect=[]"], rerun=False,
                  png=False, seed=2)
    s = res.summary
    assert s["bound"]["value"] == 1e-6 and "MSS" in s["bound"]["condition"]
    assert s["worst"]["reproduced"] and all(r["status"] == "ok" for r in res.rows)
    assert all(len(json.loads(r["candidate"])["agent"]) == 1 for r in res.rows if r["phase"] == "search")


@pytest.mark.slow
def test_acceptance_mitra_nonresilient_one_byzantine_agent_freezes_a_regular_one(tmp_path):
    res = redteam(SC / "mitra_nonresilient.toml", budget=100, jobs=2, out=tmp_path / "m", rerun=False, png=False,
                  shrink_budget=0)
    assert res.summary["evaluations"] == 100 and res.summary["worst"]["value"] >= 0.5
    assert res.summary["worst"]["reproduced"] and res.summary["worst"]["components"] == 1


@pytest.mark.slow
def test_acceptance_lee_kim_shim_beyond_breaks_theorem_1_and_shrinks(tmp_path):
    res = redteam(LKS, budget=100, jobs=2, beyond=True, overrides=["redteam.amplitude=10"], out=tmp_path / "l",
                  rerun=False, png=False, shrink_budget=40)
    s = res.summary
    bound = s["bound"]["value"]
    assert s["bound"]["name"].startswith("Theorem 1") and bound == pytest.approx(1.61803, abs=1e-5)
    assert s["worst"]["value"] > bound and s["held"] is False and s["worst"]["reproduced"]
    assert s["shrunk"]["value"] > bound and s["shrunk"]["components"] <= s["worst"]["components"]
    exp = api.load(res.out / "shrunk.toml")
    assert metric_value(exp, api.simulate(exp), derive(exp)[1]) == s["shrunk"]["value"]


def test_warm_start_is_the_scenarios_attack_then_its_escalation():
    sp, _ = derive(api.load(LKS, set=["redteam.amplitude=10"]), beyond=True)
    own, escalated = warm_start(sp)
    assert own == {"s0_kind": "constant", "s0_bank": 1, "s0_size": math.pi / 3, "s0_start": 10.0}
    assert escalated == {**own, "s0_size": 10.0, "s1_kind": "constant", "s1_bank": 2, "s1_size": 10.0, "s1_start": 10.0}
    sp, _ = derive(api.load(MITRA))
    assert warm_start(sp) == [{"a0_agent": 5, "a0_kind": "cancellation", "a0_start": 0.0, "drop_p": 0.32, "seed": 3}]
