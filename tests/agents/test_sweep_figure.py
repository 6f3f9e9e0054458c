"""sweep.png draws the metric and threshold the user chose, else the algorithm's metric and
the scenario's own bound on it (not one paper's squared relative error and 1e-6)."""

from __future__ import annotations

import pytest

from agents.sweep import FIGURE_METRICS, figure_choice, figure_curve
from estimation.errors import ScenarioError
from scenarios.loader import load
from tests.conftest import SCENARIOS


def _sc(name: str, *overrides: str):
    return load(SCENARIOS / name, list(overrides))[0]


def test_the_default_metric_is_the_algorithms_and_the_threshold_the_scenarios_bound():
    # mitra_cells.toml: [[expect]] relative_error_2, over "final", max 1e-9
    assert figure_choice(_sc("mitra_cells.toml"), None, None) == (
        "final_relative_error_2", 1e-9, "the scenario's [[expect]] bound")
    # lee_kim_shim.toml: [[expect]] error_inf over the window, max 0.25
    assert figure_choice(_sc("lee_kim_shim.toml"), None, None) == (
        "window_max_error_inf", 0.25, "the scenario's [[expect]] bound")


def test_without_a_bound_on_the_metric_there_is_no_threshold():
    assert figure_choice(_sc("lee_kim_shim.toml"), "final_error_2", None) == ("final_error_2", None, "none")
    assert figure_choice(_sc("lee_kim_shim.toml", "expect=[]"), None, None)[1] is None


def test_the_users_metric_and_threshold_win():
    assert figure_choice(_sc("mitra_cells.toml"), "worst_window_max_error_2", 3.5) == (
        "window_max_error_2", 3.5, "--threshold")


def test_an_unknown_metric_names_the_choices():
    with pytest.raises(ScenarioError, match="unknown metric 'mse'.*final_relative_error_2"):
        figure_choice(_sc("mitra_cells.toml"), "mse", None)
    assert len(FIGURE_METRICS) == 6


def test_the_curve_is_the_median_over_seeds_and_crosses_the_threshold_where_it_first_exceeds_it():
    rows = [{"status": "ok", "p": p, "worst_final_error_inf": v}
            for p, vs in ((0.1, (0.01, 0.02, 0.5)), (0.5, (0.2, 0.3, 0.4)), (0.9, (1.0, 2.0, 3.0))) for v in vs]
    rows.append({"status": "error: x", "p": 0.1, "worst_final_error_inf": None})
    c = figure_curve(rows, "p", "final_error_inf", 0.25)
    assert c["x"] == [0.1, 0.5, 0.9] and c["median"] == [0.02, 0.3, 2.0] and c["runs"] == 9
    assert c["low"] == [0.01, 0.2, 1.0] and c["high"] == [0.5, 0.4, 3.0]
    assert c["crossing"] == 0.5
    assert figure_curve(rows, "p", "final_error_inf", 5.0)["crossing"] is None
    assert figure_curve(rows, "p", "final_error_inf", None)["crossing"] is None


@pytest.mark.needs("matplotlib", "sweep.png")
def test_the_figure_draws_the_chosen_metric_and_threshold(tmp_path):
    import json

    from agents.sweep import figure

    (tmp_path / "sweep.json").write_text(json.dumps({"scenario": "scenarios/lee_kim_shim.toml"}))
    rows = [{"status": "ok", "point": f"p{g}", "seed": s, "estimator.gamma": g, "worst_final_error_inf": v / s}
            for g, v in ((0.5, 1e-4), (2.0, 1e-2), (4.0, 1.0)) for s in (1, 2)]
    drawn = figure(tmp_path, rows, ["estimator.gamma=0.5,2,4"], SCENARIOS / "lee_kim_shim.toml", [],
                   "final_error_inf", 1e-3)
    assert drawn is not None
    path, c = drawn
    assert path == tmp_path / "sweep.png" and path.stat().st_size > 10_000
    assert c["crossing"] == 2.0 and c["median"] == pytest.approx([7.5e-5, 7.5e-3, 0.75])


def test_an_unknown_metric_fails_rse_sweep_before_any_run(tmp_path):
    from click.testing import CliRunner

    from agents.cli import cli

    bad = CliRunner().invoke(cli, ["sweep", str(SCENARIOS / "lee_kim_shim.toml"), "--grid", "estimator.gamma=2",
                                   "--out", str(tmp_path / "b"), "--metric", "mse"])
    assert bad.exit_code == 2 and "unknown metric 'mse'" in bad.output and not (tmp_path / "b").exists()
