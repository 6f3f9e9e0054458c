"""The documentation as a newcomer reads it: a README read in minutes, an index of every
page, links that resolve, no dated measurement diaries, an API page that names every
function of `rse`, and a format page with a complete scenario that runs and every algorithm."""

from __future__ import annotations

import inspect
import re
import tomllib
from pathlib import Path

import pytest

import rse
from tests.conftest import ROOT

DOCS = ROOT / "docs"
README = ROOT / "README.md"
#: generated from the benchmark suite's JSON, which carries the date of the measurement
GENERATED = {DOCS / "benchmarks.md"}
MONTHS = "January|February|March|April|May|June|July|August|September|October|November|December"
DATE_OR_TIME = re.compile(
    rf"\b\d{{4}}-\d{{2}}-\d{{2}}\b"  # 2026-12-03
    rf"|\b\d{{1,2}} ({MONTHS})\b|\b({MONTHS}) \d{{1,2}}\b"  # 3 December, December 3
    r"|\b([01]?\d|2[0-3]):[0-5]\d( ?UTC)?\b(?![:.\d])"  # 14:30, 08:09 UTC
)


def _pages() -> list[Path]:
    return sorted(DOCS.rglob("*.md"))


def test_the_readme_is_at_most_200_lines():
    assert len(README.read_text().splitlines()) <= 200


@pytest.mark.parametrize("path", [README, *_pages()], ids=lambda p: str(p.relative_to(ROOT)))
def test_no_calendar_date_or_time_of_day(path):
    if path in GENERATED:
        pytest.skip("generated from the benchmark JSON: it names the date of its measurement")
    hits = [f"{path.name}:{i}: {m.group(0)!r}" for i, line in enumerate(path.read_text().splitlines(), 1)
            for m in [DATE_OR_TIME.search(line)] if m]
    assert not hits, hits


def test_the_date_pattern_catches_what_it_must_and_spares_ports_and_grids():
    for bad in ("3 December, 08:09-08:24 UTC", "on 2026-12-05", "at 14:30", "December 4"):
        assert DATE_OR_TIME.search(bad), bad
    for ok in ("tcp/127.0.0.1:7447", "--grid network.channel.drop_p=0:0.9:0.05", "ports 9090:9090", "eq. (23)"):
        assert not DATE_OR_TIME.search(ok), ok


def test_every_docs_page_is_linked_from_the_index():
    index = (DOCS / "README.md").read_text()
    linked = {(DOCS / m).resolve() for m in re.findall(r"\]\(([^)#\s]+\.md)(?:#[^)]*)?\)", index)}
    missing = [str(p.relative_to(DOCS)) for p in _pages() if p.name != "README.md" and p.resolve() not in linked]
    assert not missing, f"docs/README.md does not link: {missing}"


@pytest.mark.parametrize("path", [README, *_pages()], ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(path):
    text = re.sub(r"```.*?```", "", path.read_text(), flags=re.S)
    bad = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"[a-z]+:", target) or target.startswith("#"):
            continue
        if not (path.parent / target.split("#")[0]).exists():
            bad.append(target)
    assert not bad, bad


def test_the_tutorial_exists_and_the_readme_links_it():
    assert (DOCS / "tutorial.md").is_file() and "docs/tutorial.md" in README.read_text()


def test_the_api_page_names_every_function_of_rse_with_its_parameters():
    """Every public name is on the page; a function's signature line names only parameters
    the function has (a renamed or removed one fails here) and every required one. A new
    keyword with a default is reported by the last assertion's message as well, so the
    page follows the code; it is not asked of other changes' authors at once."""
    page = (DOCS / "api.md").read_text()
    undocumented = []
    for name in rse.__all__:
        obj = getattr(rse, name)
        assert f"rse.{name}" in page or f"`{name}`" in page, name
        if not inspect.isfunction(obj):
            continue
        sig = inspect.signature(obj)
        line = next((x for x in page.splitlines() if x.startswith(f"`rse.{name}(")), "")
        assert line, f"docs/api.md: no signature line `rse.{name}(...)`"
        documented = re.findall(r"[(,*]\s*(\w+)(?==|,|\))", line.split("->")[0])
        stale = [p for p in documented if p not in sig.parameters]
        assert not stale, f"docs/api.md: `rse.{name}` has no parameter(s) {stale}"
        required = [p.name for p in sig.parameters.values() if p.default is inspect.Parameter.empty]
        assert all(p in documented for p in required), (name, required, documented)
        undocumented += [f"{name}({p})" for p in sig.parameters if p not in documented]
    assert 'set={"estimator.variant": "linear"}' in page  # how to switch a variant
    assert len(undocumented) <= 3, f"docs/api.md: document {undocumented}"


def test_the_api_pages_variant_switch_works():
    exp = rse.load(ROOT / "scenarios" / "lee_kim_shim.toml", set={"estimator.variant": "linear", "run.duration": 1})
    assert exp.scenario.estimator.variant == "linear"
    exp = rse.load(ROOT / "scenarios" / "lee_kim_shim.toml", set=["estimator.variant=linear", "run.duration=1"])
    assert exp.scenario.estimator.variant == "linear"


def _format_page_scenario() -> str:
    page = (DOCS / "scenario-format.md").read_text()
    return re.findall(r"^```toml\n(.*?)^```$", page, flags=re.S | re.M)[0]


def test_the_format_pages_complete_scenario_holds_its_bound_and_the_baseline_fails_it(tmp_path):
    path = tmp_path / "my_plant.toml"
    path.write_text(_format_page_scenario())
    assert tomllib.loads(path.read_text())["estimator"]["algorithm"] == "lee_kim_shim"
    assert all(c.holds is not False for c in rse.check(rse.load(path)))
    run = rse.simulate(rse.load(path, set={"run.duration": 22, "output.window": [20.0, 22.0]}))
    assert run.ok and run.expectations()[0].value <= 0.5
    base = rse.simulate(rse.load(path, set={"run.duration": 22, "output.window": [20.0, 22.0],
                                            "estimator.variant": "linear"}))
    assert not base.ok and base.expectations()[0].value > 0.5


def test_the_format_page_lists_every_built_in_algorithm():
    import importlib

    from scenarios.plugins import MODULES, algorithm_name

    page = (DOCS / "scenario-format.md").read_text()
    for mod in MODULES:
        name = algorithm_name(importlib.import_module(mod))
        assert f'### `algorithm = "{name}"`' in page, name


def _window_error(path, **overrides) -> float:
    run = rse.simulate(rse.load(path, set=overrides or None))
    return run.summary()["worst_regular"]["x"]["window_max_error_inf"]


def test_the_figures_of_reading_the_output_are_what_the_runs_give(tmp_path):
    """The tutorial's numbers (steps 2 and 5) are measured here, not copied: a change that
    moves them fails until the page says what the runs give."""
    page = (DOCS / "tutorial.md").read_text()
    lks = ROOT / "scenarios" / "lee_kim_shim.toml"
    assert "is 0.2165, below the scenario's bound 0.25" in page and f"{_window_error(lks):.4g}" == "0.2165"
    assert "(`--set estimator.kappa=5 --set estimator.gamma=20`: 0.0217)" in page
    assert f"{_window_error(lks, **{'estimator.kappa': 5, 'estimator.gamma': 20}):.3g}" == "0.0217"
    assert f"{_window_error(ROOT / 'scenarios' / 'lee_kim_shim_nonresilient.toml'):.3g}" == "0.495"
    mine = tmp_path / "my_plant.toml"
    mine.write_text(_format_page_scenario())
    assert "window error is 0.238 under an attack of 10" in page and f"{_window_error(mine):.3g}" == "0.238"
    assert f"{_window_error(mine, **{'attacks.0.value': 3.0}):.3g}" == "0.238"
    assert "ends 1.18 off" in page and f"{_window_error(mine, **{'estimator.variant': 'linear'}):.3g}" == "1.18"
    assert "error to 0.033" in page
    assert f"{_window_error(mine, **{'estimator.kappa': 5, 'estimator.gamma': 20}):.2g}" == "0.033"
