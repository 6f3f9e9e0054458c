"""A sweep's size within the budget (scenarios.budget): its grid is counted before it is
expanded, and the sum of its runs' estimated times is checked before any run."""

from pathlib import Path

import pytest

from agents.sweep import parse_grid, points, validate_points
from estimation.errors import ScenarioError

SCENARIO = Path(__file__).resolve().parents[2] / "scenarios" / "mitra_nonresilient.toml"


@pytest.mark.parametrize("spec, said", [
    ("run.dt=0:1e18:1e-9", r"--grid: run.dt: 1e\+27 values exceed the limit of 100,000 points"),
    ("run.dt=0:nan:1", r"--grid: run.dt: need finite numbers, STEP > 0 and STOP >= START, got '0:nan:1'"),
    ("run.dt=0:inf:1", r"--grid: run.dt: need finite numbers"),
])
def test_a_grid_range_is_counted_before_it_is_expanded(spec, said):
    with pytest.raises(ScenarioError, match=said):
        parse_grid(spec)


def test_values_times_seeds_within_the_limit():
    grid = [("a", list(range(1000))), ("b", list(range(1000)))]
    with pytest.raises(ScenarioError, match=r"--grid: 1,000,000 points \(values x seeds\) exceed the limit of 100,000"):
        points(grid, [0])


def test_the_sweep_s_total_time_is_refused_beyond_the_limit_without_force():
    key = [("output.convergence_threshold", [0.01])]
    base = ["run.rounds=3000000"]  # one run: about 0.51 h (16 agents)
    validate_points(SCENARIO, base, points(key, list(range(10))))
    with pytest.raises(ScenarioError, match=r"mitra_nonresilient.toml: --grid: the sweep \(100 runs\) needs about "
                                            r".* and 50.8 h, beyond the limit of 24 h; set run.force = true"):
        validate_points(SCENARIO, base, points(key, list(range(100))))
    validate_points(SCENARIO, [*base, "run.force=true"], points(key, list(range(100))))
