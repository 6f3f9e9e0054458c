"""The public Python API (agents.api, re-exported by ``import rse``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import rse
from agents import api
from estimation.errors import ScenarioError

ROOT = Path(__file__).resolve().parents[2]
LKS = ROOT / "scenarios" / "lee_kim_shim.toml"


def test_the_facade_is_the_api():
    assert set(rse.__all__) <= set(api.__all__)
    assert rse.simulate is api.simulate and rse.load is api.load


def test_load_takes_a_mapping_or_strings_and_a_seed():
    a = rse.load(LKS, set={"run.dt": 0.01, "run.duration": 1.0, "expect": []}, seed=7)
    b = rse.load(LKS, set=["run.dt=0.01", "run.duration=1.0", "expect=[]"], seed=7)
    assert a.dt == b.dt == 0.01 and a.seed == b.seed == 7
    assert a.overrides == b.overrides == ("run.dt=0.01", "run.duration=1.0", "expect=[]", "run.seed=7")
    assert a.frozen["run"]["dt"] == 0.01


def test_a_bad_override_names_the_key():
    with pytest.raises(ScenarioError, match="run.dt"):
        rse.load(LKS, set={"run.dt": -1})


def test_simulate_metrics_summary_save_and_reopen(tmp_path):
    exp = rse.load(LKS, set={"run.dt": 0.01})
    run = rse.simulate(exp)
    m = run.metrics()
    assert isinstance(m, pd.DataFrame)
    assert list(m.columns) == ["k", "t", "agent", "regular", "block", "error_2", "error_inf", "relative_error_2"]
    assert len(m) == (exp.n_rounds + 1) * exp.N * len(set(m["block"]))
    s = run.summary()
    assert s["worst_regular"]["x"]["window_max_error_inf"] == pytest.approx(
        m[(m.t >= exp.window[0] - 1e-9) & m.regular & (m.block == "x")]["error_inf"].max())
    assert run.ok and [r.label for r in run.expectations()] == [e["label"] for e in s["expectations"]]
    d = run.save(tmp_path / "run")
    assert {p.name for p in d.iterdir()} >= {"manifest.json", "design.json", "metrics.parquet", "summary.json"}
    back = rse.open_run(d)
    pd.testing.assert_frame_equal(back.metrics(), m, check_dtype=False, check_categorical=False)
    assert back.summary()["worst_regular"] == s["worst_regular"]


def test_simulate_does_not_consume_the_experiment():
    exp = rse.load(LKS, set={"run.dt": 0.01, "run.duration": 2.0, "expect": []})
    a = rse.simulate(exp, keep_trajectories=True).sim.estimates
    b = rse.simulate(exp, keep_trajectories=True).sim.estimates
    assert np.array_equal(a, b)


def test_check_returns_the_conditions_as_data():
    conds = rse.check(rse.load(LKS, check_conditions=False))
    assert conds and all(hasattr(c, "name") and c.holds in (True, False, None) for c in conds)
    assert all(c.holds is not False for c in conds)
