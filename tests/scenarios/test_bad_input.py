"""Bad input gives one line naming the key and exit status 2: non-finite numbers, absurd
sizes (size budgets, :mod:`scenarios.budget`), and the validator's jargon said in the
scenario format's words (:mod:`scenarios.messages`)."""

from __future__ import annotations

import math
import time
import tomllib
from pathlib import Path
from types import SimpleNamespace

import pytest
from click.testing import CliRunner

from agents.cli import cli
from agents.net.exits import EXIT_BAD_INPUT
from estimation.errors import ScenarioError
from scenarios import budget
from scenarios.build import build
from scenarios.helpers import finite, integer, plant_params
from scenarios.loader import validate

ROOT = Path(__file__).resolve().parents[2]
SC = ROOT / "scenarios"


def raw(name: str) -> dict:
    return tomllib.loads((SC / name).read_text())


def message(data: dict, overrides=()) -> str:
    with pytest.raises(ScenarioError) as ei:
        sc, _ = validate(data, source="x.toml", overrides=overrides)
        build(sc, source="x.toml")
    return str(ei.value)


# the five inputs of the issue: internal errors and hangs before; each one line, exit 2
ISSUE_INPUTS = [
    (["check", "mitra_omission.toml", "--set", "plant.params.K=nan"], "plant.params.K: expected a finite number, got nan"),
    (["check", "inverters_median.toml", "--set", "plant.params.substeps=inf"],
     "plant.params.substeps: expected a finite number, got inf"),
    (["check", "ugrinovskii_biasing.toml", "--set", "run.dt=inf"], "run.dt: expected a finite number, got inf"),
    (["check", "ugrinovskii_baseline.toml", "--set", "run.duration=1e18"],
     "run: duration / dt: 2e+20 rounds exceed the limit of 10,000,000 rounds; set run.force = true"),
    (["simulate", "mitra_nonresilient.toml", "--set", "agents.per_cell=1000000"],
     "agents.per_cell x cells: 4,000,000 agents exceed the limit of 100,000 agents"),
    (["check", "inverters_median.toml", "--set", "plant.params.substeps=1e300"],
     "plant.params.substeps: 1e+300 substeps exceed the limit of 10,000 substeps"),
]


@pytest.mark.parametrize("args, expected", ISSUE_INPUTS, ids=[" ".join(a[1:]) for a, _ in ISSUE_INPUTS])
def test_issue_inputs_exit_2_with_one_line(args, expected, tmp_path):
    args = [args[0], str(SC / args[1]), *args[2:]]
    if args[0] == "simulate":
        args += ["--out", str(tmp_path / "run")]
    t0 = time.perf_counter()
    res = CliRunner().invoke(cli, args)
    elapsed = time.perf_counter() - t0
    print(f"rse {' '.join(args)}: exit {res.exit_code} in {elapsed:.2f} s")
    assert res.exit_code == EXIT_BAD_INPUT, res.output
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and expected in lines[0], res.output
    assert elapsed < 30  # refused before any per-round work (about 0.1 s here; a hang before)


def test_graph_as_a_word_says_the_table():
    d = raw("lee_kim_shim.toml")
    d["network"]["graph"] = "ring"
    assert message(d) == 'x.toml: network.graph: expected a table, e.g. network.graph = { kind = "ring" }, got \'ring\''


def test_vector_for_a_matrix_is_one_line_with_the_rows():
    d = raw("ugrinovskii_baseline.toml")
    d["plant"]["model"], d["plant"]["A"] = "hinf", [[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, -1.0, -1.0]]
    d["sensors"] = [{"C": [1, 0, 0]}]
    assert message(d) == "x.toml: sensors[0].C is a list of rows: [[1, 0, 0]]"


def test_union_alternatives_in_one_line():
    d = raw("lee_kim_shim.toml")
    d["agents"] = 5
    assert message(d) == "x.toml: agents: expected a list or a table, got 5"
    d = raw("mitra_nonresilient.toml")
    d["agents"]["periods"][0] = math.nan  # a table: the "should be a list" alternative is noise
    assert message(d) == "x.toml: agents.periods[0]: expected a finite number, got nan"


def test_missing_keys_and_items_in_one_line():
    d = raw("mitra_diffusion.toml")
    d["run"] = {}
    assert message(d) == "x.toml: run: missing required key(s) 'name', 'dt'"
    d = raw("mitra_diffusion.toml")
    d["output"] = {"window": []}
    assert message(d) == "x.toml: output.window: expected 2 items, got []"


@pytest.mark.parametrize("key, value", [
    ("run.dt", math.inf), ("estimator.kappa", math.nan), ("network.channel.drop_p", math.nan),
    ("output.window", [0.0, math.inf]), ("plant.x0", {"kind": "uniform", "low": -math.inf}),
])
def test_every_float_of_the_schema_is_finite(key, value):
    """NaN and infinity in the file itself (not only through --set): the schema's tables and
    a plugin's [estimator] section (estimator.kappa) alike."""
    d = raw("lee_kim_shim.toml")
    node = d
    *parents, last = key.split(".")
    for p in parents:
        node = node.setdefault(p, {})
    node[last] = value
    msg = message(d)
    assert "\n" not in msg and "expected a finite number" in msg and key.split(".")[0] in msg


def test_set_values_are_finite_anywhere_in_them():
    msg = message(raw("lee_kim_shim.toml"), ["plant.x0={kind='value', value=[1.0, nan]}"])
    assert msg == "--set plant.x0={kind='value', value=[1.0, nan]}: plant.x0.value[1]: expected a finite number, got nan"


def test_helpers_check_numbers_before_use():
    assert integer(3.0, "k", None) == 3 and finite(2, "k", None) == 2.0
    for bad, said in ((math.nan, "finite"), (math.inf, "finite"), (2.5, "integer"), (0, ">= 1"), ("3", "number"), (True, "number")):
        with pytest.raises(ScenarioError, match=f"x.toml: plant.params.K: expected .*{said}"):
            integer(bad, "plant.params.K", "x.toml")
    with pytest.raises(ScenarioError, match=r"plant.params.K: expected an integer <= 10, got 11"):
        integer(11, "plant.params.K", None, high=10)
    pl = SimpleNamespace(params={"K": 4.0})
    assert plant_params(pl, {"K": 1.0, "eps": 0.5}, None, integers={"K": (1, None)}) == {"K": 4, "eps": 0.5}
    with pytest.raises(ScenarioError, match=r"plant.params.eps: expected a finite number, got nan"):
        plant_params(pl, {"K": 1.0, "eps": math.nan}, None)  # a plugin's own defaults are checked too


def test_force_lifts_the_documented_limits_only():
    d = raw("mitra_nonresilient.toml")
    d["run"]["rounds"] = 20_000_000
    assert "20,000,000 rounds exceed the limit of 10,000,000 rounds" in message(d)
    d["run"]["force"] = True
    sc, _ = validate(d, source="x.toml")
    assert sc.run.n_rounds == 20_000_000
    cost = budget.estimate(rounds=10, agents=4, states=10**6, fused=0)  # a dense 1e6 x 1e6 plant: 24 TB
    assert cost.memory == pytest.approx(8.0 * (3e12 + 16 + 8e6 + 11 * 8 * 4))
    with pytest.raises(ScenarioError, match=r"k: this run needs about 2.24e\+04 GiB .*more than this machine's memory \(16 GiB\)"):
        budget.check_run(cost, "k", force=True, source=None, memory=16 * 2**30)


def test_time_estimate_is_refused_beyond_the_limit_without_force():
    cost = budget.estimate(rounds=10_000_000, agents=10_000, states=10, fused=0)
    assert cost.seconds == pytest.approx((10_000_001) * 10_000 * 30e-6 + 10_000_001 * 100e-9)
    with pytest.raises(ScenarioError, match=r"k: this run needs about .* and 833 h, beyond the limit of 24 h; set run.force"):
        budget.check_run(cost, "k", force=False, source=None, memory=2**50)
    budget.check_run(cost, "k", force=True, source=None, memory=2**50)


def test_patrol_tables_within_the_rounds_limit():
    """A patrol schedule tabulates its largest offset + hyper-period rounds (the lcm of its
    periods): a huge or coprime set of periods is refused before the table is built."""
    d = raw("mitra_nonresilient.toml")
    d["agents"]["periods"][3] = 10**30
    assert message(d) == ("x.toml: agents.periods (largest offset + hyper-period): 1e+30 rounds exceed the limit of "
                          "10,000,000 rounds; set run.force = true (--set run.force=true) for a deliberately large run")


def test_a_step_whose_transition_overflows_names_run_dt():
    msg = message(raw("lee_kim_shim.toml"), ["run.dt=1e300"])
    assert msg == "x.toml: run.dt: the plant's one-round transition expm(A dt) overflows float64 at dt = 1e+300; use a shorter step"


def test_one_alternative_s_finer_problem_is_the_message():
    """``remove`` pairs take an id or a list of ids: a NaN id is a bad number, not "should be a list"."""
    d = raw("mitra_omission.toml")
    d["network"]["graph"]["remove"][0][0] = math.nan
    assert message(d) == "x.toml: network.graph.remove[0][0]: expected a finite number, got nan"


def test_found_by_the_fuzz_an_id_or_a_list_and_an_empty_agent_list():
    d = raw("mitra_omission.toml")
    d["network"]["graph"]["remove"][1][0] = -0.5  # an id or a list of ids: not "a list of rows"
    assert message(d) == "x.toml: network.graph.remove[1][0]: expected an integer or a list, got -0.5"
    d = raw("mitra_omission.toml")
    d["expect"][0]["agents"] = []  # was an IndexError in the summary
    assert message(d) == "x.toml: expect[0].agents: list should have at least 1 item after validation, not 0, got []"


def test_found_by_the_fuzz_an_empty_team_and_a_table_with_missing_and_unknown_keys():
    d = raw("inverters_median.toml")
    d["agents"] = []  # was an IndexError in the monitor
    assert message(d) == "x.toml: agents: list should have at least 1 item after validation, not 0, got []"
    d = raw("inverters_median.toml")
    d["agents"] = {"bogus_key": 1}
    assert message(d) == "x.toml: agents: missing required key(s) 'kind', 'periods'; unknown key(s) 'bogus_key'"
