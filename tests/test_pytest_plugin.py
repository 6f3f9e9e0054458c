"""The pytest plugin (``rse.pytest_plugin``, ``pytest --rse``): a scenario file is a test
file whose items are its ``[[expect]]`` bounds, each passing or failing with its measured
value (also in ``--junitxml``), a failure showing the file's table and the kept run
directory; shortened runs skip the bounds they cannot judge; bad input is one line.

The suite's own scenario checks are the plugin's items (``--rse`` in the project's
addopts, ``scenarios`` in its testpaths); these tests run it in pytester sessions on
copies of two scenario files, shortened where the bound allows it. ``--rse-driver run`` is
tested on the example plugin package's scenarios (tests/test_example_plugins.py)."""

from __future__ import annotations

import json
import re
import tomllib
import xml.etree.ElementTree as ET

import pytest

import rse
from tests.conftest import ROOT, SCENARIOS

pytest_plugins = ["pytester"]

LKS = (SCENARIOS / "lee_kim_shim.toml").read_text()
MITRA = (SCENARIOS / "mitra_cells.toml").read_text()
FAST = ("--rse-set", "run.dt=0.02")  # Lee-Kim-Shim at 2000 rounds: both bounds hold there too


@pytest.fixture(scope="module", autouse=True)
def _imported(tmp_path_factory):
    """What the in-process sessions import, imported once out here first: pytester drops
    the modules a session imported when it ends, and numpy's extensions cannot be loaded
    twice in a process."""
    for name, ov in (("lee_kim_shim", ["run.duration=0.1"]), ("mitra_cells", ["run.rounds=2"])):
        rse.simulate(rse.load(SCENARIOS / f"{name}.toml", set=ov), out=tmp_path_factory.mktemp(name))


def _session(pytester, *args):
    return pytester.runpytest_inprocess("--rse", "-p", "no:cacheprovider", *args)


def _cases(xml_path):
    return {c.get("name"): (c, {p.get("name"): p.get("value") for p in c.iter("property")})
            for c in ET.parse(xml_path).getroot().iter("testcase")}


def test_each_bound_is_a_test_with_its_measured_value_and_a_failure_shows_the_table(pytester):
    pytester.makefile(".toml", lks=LKS)
    xml = pytester.path / "out.xml"
    res = _session(pytester, *FAST, "--rse-set", "expect.1.max=0.1", f"--junitxml={xml}")
    res.assert_outcomes(passed=1, failed=1)
    cases = _cases(xml)  # in the file's order (pytest 9.2 appends a "]" to a name holding "[")
    assert len(cases) == 2
    names, (before, under) = list(cases), list(cases.values())
    assert names[0] == "worst agent, infinity-norm error at t = 10 (before the attack)"
    assert names[1].startswith("worst agent, max infinity-norm error over [30, 40] under attack")
    run_dir = before[1]["run_dir"]
    assert under[1]["run_dir"] == run_dir  # one run for the file's two bounds
    summary = json.loads((pytester.path / run_dir / "summary.json").read_text())
    measured = [e["value"] for e in summary["expectations"]]
    assert [float(before[1]["measured"]), float(under[1]["measured"])] == measured
    assert before[1]["bound"] == "<= 0.01" and under[1]["bound"] == "<= 0.1"
    assert measured[0] <= 0.01 and 0.1 < measured[1] <= 0.25  # the file's own bound 0.25 holds
    assert under[0].find("failure") is not None and before[0].find("failure") is None
    out = res.stdout.str()
    assert f"measured {measured[1]:.4g}, bound <= 0.1" in out
    assert re.search(rf"FAIL +worst agent, max infinity-norm error over \[30, 40\] under attack +{measured[1]:.4g} +<= 0.1", out)
    assert re.search(rf"ok +worst agent, infinity-norm error at t = 10 \(before the attack\) +{measured[0]:.4g} +<= 0.01", out)
    assert f"run directory: {run_dir}" in out
    assert "Traceback" not in out
    # the per-bound report lists both, with their values
    assert re.search(rf"PASS +{measured[0]:.4g} <= 0.01 +lks.toml::worst agent, infinity-norm", out)


@pytest.mark.parametrize("args, passed, skipped, horizon", [
    (("--rse-quick",), 1, 1, 10),  # a quarter of 40 s: t = 10 is judged, [30, 40] is not
    (("--rse-rounds", "250"), 0, 2, 5),
])
def test_a_shortened_run_skips_the_bounds_it_cannot_judge(pytester, args, passed, skipped, horizon):
    pytester.makefile(".toml", lks=LKS)
    res = _session(pytester, *FAST, *args, "-rs", "-vv")
    res.assert_outcomes(passed=passed, skipped=skipped)
    out = res.stdout.str()
    assert f"not judged: the output window t in [30, 40] ends after the run's horizon t = {horizon}" in out
    assert "lks.toml:54:" in out  # the skip is reported at the bound's [[expect]] line


def test_a_run_given_in_rounds_is_shortened_in_rounds(pytester):
    pytester.makefile(".toml", mitra=MITRA)
    xml = pytester.path / "out.xml"
    res = _session(pytester, "--rse-rounds", "150", "-rs", "-vv", f"--junitxml={xml}")  # -vv: summary lines not cut
    res.assert_outcomes(passed=1, skipped=1)
    out = res.stdout.str()
    assert "relative error at the final round: not judged: the run is shortened to t = 150" in out
    (_, props), = [c for c in _cases(xml).values() if "measured" in c[1]]
    summary = json.loads((pytester.path / props["run_dir"] / "summary.json").read_text())
    assert summary["last_round"] == 150 and float(props["measured"]) == summary["expectations"][1]["value"] <= 100


def test_only_scenario_files_with_bounds_are_collected_and_only_under_rse(pytester):
    pytester.makefile(".toml", lks=LKS, plain="[tool]\nx = 1\n", nobounds=LKS.split("[[expect]]")[0])
    res = pytester.runpytest_inprocess("-p", "no:cacheprovider", "--collect-only", "-q")
    assert "no tests collected" in res.stdout.str()
    res = _session(pytester, "--collect-only", "-q")
    ids = [line for line in res.stdout.lines if "::" in line]
    assert ids == ["lks.toml::worst agent, infinity-norm error at t = 10 (before the attack)",
                   "lks.toml::worst agent, max infinity-norm error over [30, 40] under attack"]


@pytest.mark.parametrize("args, files, message", [
    (("--rse-set", "run.dtt=0.02"), {"lks": LKS},
     "lks.toml (with --set run.dtt=0.02): run.dtt: unknown key (not part of the scenario format)"),
    ((), {"broken": "[[expect]]\nmetric = \n"}, "broken.toml: TOML syntax error"),
    (("--rse-set", "run.dt=-1"), {"lks": LKS}, "run.dt"),
])
def test_bad_input_is_one_line_naming_the_file(pytester, args, files, message):
    pytester.makefile(".toml", **files)
    res = _session(pytester, *args)
    out = res.stdout.str()
    assert res.ret == pytest.ExitCode.INTERRUPTED  # a collection error stops the session
    assert message in out and "Traceback" not in out and "pydantic" not in out


def test_bad_options_are_usage_errors(pytester):
    res = _session(pytester, "--rse-rounds", "0")
    assert res.ret == pytest.ExitCode.USAGE_ERROR
    assert "--rse-rounds: expected a positive number of rounds, got 0" in res.stderr.str()
    res = _session(pytester, "--rse-quick", "--rse-rounds", "5")
    assert "--rse-quick and --rse-rounds: give one of them" in res.stderr.str()


def test_the_suite_runs_every_built_in_scenario_file_through_the_plugin():
    """This project's CI runs the scenario files through the plugin (the scenarios' former
    per-file test): ``scenarios`` is a test path and ``--rse`` is on, and every file there
    declares bounds (so every one is collected)."""
    ini = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["pytest"]["ini_options"]
    assert "scenarios" in ini["testpaths"] and "--rse" in ini["addopts"].split()
    for path in SCENARIOS.glob("*.toml"):
        assert tomllib.loads(path.read_text()).get("expect"), f"{path.name} declares no [[expect]] bounds"
