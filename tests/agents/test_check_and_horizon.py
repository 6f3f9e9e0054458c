"""`rse check` judges a scenario by its own variant's conditions; expectations outside a
shortened run's horizon are listed as not evaluated and do not fail the command."""

import json
import math

import pytest

from agents import api
from agents.cli.net import _print_outcome
from agents.console import out as console
from agents.summary import ExpectationResult
from estimation.errors import ExpectationFailed
from tests.conftest import SCENARIOS

# An unstable LTI plant (eigenvalues 0.2 and -0.5), five agents each measuring x1 (every
# set of 2q + 1 = 3 agents observes x: 2q-redundant for q = 1), on a ring.
UNSTABLE = """
[run]
name = "unstable_median"
dt = 0.01
duration = 5.0

[plant]
model = "lti"
A = [[0.2, 1.0], [0.0, -0.5]]

[[sensors]]
C = [[1.0, 0.0]]
[[sensors]]
C = [[1.0, 0.0]]
[[sensors]]
C = [[1.0, 0.0]]
[[sensors]]
C = [[1.0, 0.0]]
[[sensors]]
C = [[1.0, 0.0]]

[network]
graph = { kind = "ring" }

[estimator]
algorithm = "lee_kim_shim"
variant = "median"
kappa = 0.5
gamma = 2.0
q = 1
"""


def _flat(text: str) -> str:
    return " ".join(text.split())


def test_check_of_an_unstable_plant_with_the_median_variant_exits_0(run_rse, tmp_path):
    path = tmp_path / "unstable_median.toml"
    path.write_text(UNSTABLE)
    res = run_rse("check", str(path))
    assert res.returncode == 0, res.stdout + res.stderr
    out = _flat(res.stdout)
    assert "FAILS" not in out
    assert "plant Lyapunov stable (Theorem 3 / eq. 11; not needed by variant 'median')" in out
    assert "2-redundant observability, q = 1 (Assumption 2)" in out
    (cond,) = [c for c in api.check(api.load(path, check_conditions=False)) if c.name.startswith("plant Lyapunov")]
    assert cond.holds is None and cond.detail.startswith("no")  # shown as information
    # the variant that needs a stable plant (eq. 11) fails on it
    res = run_rse("check", str(path), "--set", 'estimator.variant="lyapunov"')
    assert res.returncode == 1, res.stdout + res.stderr
    assert "FAILS | plant Lyapunov stable (Theorem 3 / eq. 11)" in _flat(res.stdout).replace("│", "|")


def test_shortened_mitra_run_lists_both_expectations_as_not_evaluated(run_rse, tmp_path):
    out = tmp_path / "run"
    res = run_rse("simulate", str(SCENARIOS / "mitra_cells.toml"), "--set", "run.rounds=40", "--out", str(out),
                  "--no-progress", "--no-rerun")
    assert res.returncode == 0, res.stdout + res.stderr
    text = _flat(res.stdout)
    assert text.count("not evaluated") == 3  # two rows and the caption
    assert "the run is shortened to t = 40; the bound is for the final round of the scenario's horizon, t = 300" in text
    assert "its window t in [0, 150] ends after the run's horizon t = 40" in text
    exps = json.loads((out / "summary.json").read_text())["expectations"]
    assert [e["ok"] for e in exps] == [None, None]
    assert all(e["reason"] and e["value"] is None for e in exps)
    rep = run_rse("report", str(out))
    assert rep.returncode == 0, rep.stderr
    assert _flat(rep.stdout).count("not evaluated") == 3


def test_a_failed_bound_inside_the_horizon_still_fails_a_shortened_run(run_rse, tmp_path):
    """lee_kim_shim.toml cut at t = 20: the bound at t = 10 is evaluated (and made to
    fail), the one over the window [30, 40] is not evaluated."""
    res = run_rse("simulate", str(SCENARIOS / "lee_kim_shim.toml"), "--set", "run.dt=0.01", "--set",
                  "run.duration=20", "--set", "expect.0.max=1e-9", "--out", str(tmp_path / "r"), "--no-progress",
                  "--no-rerun")
    assert res.returncode == 3, res.stdout + res.stderr
    assert "1 of 2 expectation(s) failed" in res.stderr
    text = _flat(res.stdout)
    assert "FAIL" in text and "the output window t in [30, 40] ends after the run's horizon t = 20" in text


def test_api_result_of_a_shortened_run_is_ok_and_lists_the_reasons():
    exp = api.load(SCENARIOS / "lee_kim_shim.toml", set={"run.dt": 0.01, "run.duration": 5.0})
    assert exp.nominal_horizon == 40.0
    run = api.simulate(exp)
    assert run.ok
    got = run.expectations()
    assert [r.ok for r in got] == [None, None] and all(math.isnan(r.value) for r in got)
    assert got[0].reason == "its window t in [10, 10] ends after the run's horizon t = 5"
    # the same run at its full horizon evaluates both (and they hold)
    full = api.simulate(api.load(SCENARIOS / "lee_kim_shim.toml", set={"run.dt": 0.01}))
    assert [r.ok for r in full.expectations()] == [True, True]


def test_rse_run_outcome_prints_not_evaluated_and_passes(monkeypatch):
    """The outcome `rse run` prints from the team's summary: not-evaluated bounds do not
    raise ExpectationFailed; a failed one does."""
    summary = {"agents": {}, "worst_regular": {}, "expectations": [
        ExpectationResult("a", math.nan, 1.0, None, None, "its window t in [0, 150] ends after the run's horizon t = 40").as_dict(),
        ExpectationResult("b", 0.5, 1.0, None, True).as_dict(),
    ]}
    summary["expectations"][0]["value"] = None  # as JSON stores NaN
    monkeypatch.setattr(console, "width", 200)
    with console.capture() as cap:
        _print_outcome(summary, "t")
    text = _flat(cap.get())
    assert "not evaluated" in text and "ends after the run's horizon t = 40" in text
    summary["expectations"][1]["ok"] = False
    with pytest.raises(ExpectationFailed, match="1 of 2 expectation"), console.capture():
        _print_outcome(summary, "t")
