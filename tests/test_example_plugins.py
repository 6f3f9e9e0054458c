"""Algorithms from other packages: every example plugin package under ``examples/`` (a
``pyproject.toml`` with an ``rse.algorithms`` entry point) is installed outside the source
tree (``pip install --no-deps --target``) and found through its entry point alone. Each
scenario of its ``scenarios/`` passes ``rse check``, ``rse simulate`` and ``rse run``
(lockstep, equal to the simulator); each of its ``comparisons/`` (a non-resilient
counterpart) fails its bounds (exit 3). A broken entry point is a one-line error naming
the package."""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
import textwrap
import tomllib
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from tests.conftest import ROOT, SCENARIOS, rse

GROUP = "rse.algorithms"


def _example_packages() -> list[Path]:
    out = []
    for pp in sorted((ROOT / "examples").glob("*/pyproject.toml")):
        meta = tomllib.loads(pp.read_text()).get("project", {})
        if meta.get("entry-points", {}).get(GROUP):
            out.append(pp.parent)
    return out


PACKAGES = _example_packages()


def test_there_is_an_example_plugin_package():
    assert PACKAGES, "examples/ should hold at least one plugin package"
    for pkg in PACKAGES:
        assert list((pkg / "scenarios").glob("*.toml")), pkg
        assert list((pkg / "comparisons").glob("*.toml")), pkg


def _env(site: Path) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(site), str(ROOT), *filter(None, [env.get("PYTHONPATH")])])
    return env


@pytest.fixture(scope="module", params=PACKAGES, ids=lambda p: p.name)
def installed(request, tmp_path_factory):
    """The package built from a copy (the source tree stays clean) and installed into a
    temporary directory; ``(package dir, environment with it on PYTHONPATH)``."""
    pkg = request.param
    tmp = tmp_path_factory.mktemp(pkg.name)
    src = tmp / "src"
    shutil.copytree(pkg, src, ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__"))
    site = tmp / "site"
    cmd = [sys.executable, "-m", "pip", "install", "--no-deps", "--quiet", "--target", str(site), str(src)]
    if importlib.util.find_spec("wheel") is not None and importlib.util.find_spec("setuptools") is not None:
        cmd.insert(4, "--no-build-isolation")  # build offline with what is installed
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr
    assert not (pkg / "build").exists()
    return pkg, _env(site)


def _scenarios(pkg: Path, sub: str) -> list[Path]:
    return sorted((pkg / sub).glob("*.toml"))


def test_the_plugin_is_found_through_its_entry_point_only(installed):
    """Nothing in the project's packages names the plugin: the schema accepts its
    algorithm only when the package is on the path."""
    pkg, env = installed
    scenario = _scenarios(pkg, "scenarios")[0]
    res = rse("check", str(scenario), env=env)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "FAILS" not in res.stdout
    bare = dict(os.environ)
    res = rse("check", str(scenario), env=bare)
    assert res.returncode == 2
    assert "estimator: unknown algorithm" in " ".join(res.stderr.split())


@pytest.mark.multiprocess
def test_the_package_own_tests_and_scenario_bounds_pass_against_the_installed_copy(installed, tmp_path):
    """The package's ``pytest`` (its pyproject's testpaths, with ``--rse``): its unit tests
    and one test per bound of each of its scenarios, through rse's pytest plugin, here with
    ``--rse-driver run``: plant, monitor and agent processes over Zenoh, each finding the
    algorithm through its entry point (the simulator's bounds: the lockstep test below)."""
    pkg, env = installed
    if not (pkg / "tests").is_dir():
        pytest.skip(f"{pkg.name} has no tests/")
    xml = tmp_path / "junit.xml"
    res = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "rse.pytest_plugin",
                          "--rse-driver", "run", f"--junitxml={xml}"], capture_output=True, text=True, env=env,
                         timeout=600, cwd=pkg)
    assert res.returncode == 0, res.stdout + res.stderr
    bounds = [c for c in ET.parse(xml).getroot().iter("testcase") if c.get("classname", "").startswith("scenarios.")]
    n = sum(len(tomllib.loads(sc.read_text())["expect"]) for sc in _scenarios(pkg, "scenarios"))
    assert n and len(bounds) == n
    for case in bounds:
        props = {p.get("name"): p.get("value") for p in case.iter("property")}
        assert case.find("failure") is None and case.find("skipped") is None and float(props["measured"]) >= 0
        run_dir = Path(props["run_dir"])
        assert json.loads((run_dir / "manifest.json").read_text())["driver"] == "run"
        assert float(props["measured"]) in [e["value"] for e in json.loads((run_dir / "summary.json").read_text())["expectations"]]


def test_comparisons_fail_their_bounds(installed, tmp_path):
    pkg, env = installed
    for sc in _scenarios(pkg, "comparisons"):
        res = rse("simulate", str(sc), "--out", str(tmp_path / sc.stem), "--no-progress", "--no-rerun", env=env)
        assert res.returncode == 3, res.stdout + res.stderr
        exps = json.loads((tmp_path / sc.stem / "summary.json").read_text())["expectations"]
        assert any(e["ok"] is False for e in exps)


@pytest.mark.needs("optuna", "rse redteam")
def test_redteam_searches_the_plugin_within_its_declared_threat_model(installed, tmp_path):
    """The plugin declares its threat model (``THREAT_MODEL``): ``rse redteam`` searches a
    third-party algorithm within it without ``--beyond``, and the worst attack found stays
    inside the bound the scenario's own ``[[expect]]`` names (the W-MSR example: F = 1)."""
    pkg, env = installed
    sc = _scenarios(pkg, "scenarios")[0]
    out = tmp_path / "redteam"
    res = rse("redteam", str(sc), "--budget", "30", "--jobs", "1", "--out", str(out), env=env, timeout=600)
    assert res.returncode == 0, res.stdout + res.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["evaluations"] == 30 and summary["failed_evaluations"] == 0
    assert summary["space"]["beyond"] is False
    est = tomllib.loads(sc.read_text())["estimator"]
    assert summary["space"]["threat_model"]["f"] == est["f"] == summary["space"]["agents"]["count"]
    bound = min(e["max"] for e in tomllib.loads(sc.read_text())["expect"] if "max" in e)
    assert 0.0 <= summary["worst"]["value"] <= bound, summary["worst"]
    assert summary["worst"]["reproduced"] is True


TRAJECTORIES = textwrap.dedent("""
    import sys
    import numpy as np
    import rse
    run = rse.simulate(rse.load(sys.argv[1]), keep_trajectories=True)
    np.save(sys.argv[2], run.sim.estimates)
    np.save(sys.argv[3], run.sim.truth)
""")


@pytest.mark.slow
@pytest.mark.multiprocess
def test_rse_run_lockstep_equals_the_simulator(installed, tmp_path):
    """`rse run` spawns plant, monitor and agent processes: each finds the plugin (the
    entry point resolves in the children) and the lockstep result equals `rse simulate`'s."""
    pkg, env = installed
    for sc in _scenarios(pkg, "scenarios"):
        out, sim = tmp_path / f"run-{sc.stem}", tmp_path / f"sim-{sc.stem}"
        res = rse("run", str(sc), "--out", str(out), "--save-estimates", "--no-progress", "--no-rerun",
                  "--deadline", "30", env=env, timeout=600)
        assert res.returncode == 0, res.stdout + res.stderr
        assert "expectations" in res.stdout
        res = rse("simulate", str(sc), "--out", str(sim), "--no-progress", "--no-rerun", env=env)
        assert res.returncode == 0, res.stderr
        ref_est, ref_truth = tmp_path / "est.npy", tmp_path / "truth.npy"
        res = subprocess.run([sys.executable, "-c", TRAJECTORIES, str(sc), str(ref_est), str(ref_truth)],
                             capture_output=True, text=True, env=env, timeout=300, cwd=ROOT)
        assert res.returncode == 0, res.stderr
        est, ref = np.load(out / "estimates.npy"), np.load(ref_est)
        assert est.shape == ref.shape
        scale = np.maximum(1.0, np.abs(np.load(ref_truth)).max(axis=1))[:, None, None]
        assert float(np.max(np.abs(est - ref) / scale)) <= 1e-12
        np.testing.assert_array_equal(np.load(out / "truth.npy"), np.load(ref_truth))
        a, b = pq.read_table(out / "metrics.parquet"), pq.read_table(sim / "metrics.parquet")
        assert a.num_rows == b.num_rows
        for col in ("k", "agent", "block"):
            assert a.column(col).to_pylist() == b.column(col).to_pylist()
        for col in ("error_inf", "relative_error_2"):
            ra, rb = (np.array(t.column(col).to_pylist(), float) for t in (a, b))
            assert np.allclose(ra, rb, rtol=1e-9, atol=1e-14, equal_nan=True), col
        ja, jb = (json.loads((d / "summary.json").read_text()) for d in (out, sim))
        assert [e["ok"] for e in ja["expectations"]] == [e["ok"] for e in jb["expectations"]] == [True, True]
        for key, c in jb["links"].items():
            assert {k: ja["links"][key][k] for k in ("sent", "delivered", "dropped")} == \
                {k: c[k] for k in ("sent", "delivered", "dropped")}, key


# ---------------------------------------------------------------- broken entry points
def _fake_distribution(site: Path, module: str, body: str | None) -> None:
    """A distribution ``broken-algo 0.3`` whose entry point ``algo = MODULE`` is in ``site``."""
    info = site / "broken_algo-0.3.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: broken-algo\nVersion: 0.3\n")
    (info / "entry_points.txt").write_text(f"[{GROUP}]\nalgo = {module}\n")
    if body is not None:
        (site / f"{module}.py").write_text(body)


@pytest.mark.parametrize("module, body, message", [
    ("no_such_module", None,
     "cannot be loaded: ModuleNotFoundError: No module named 'no_such_module'"),
    ("half_plugin", "ESTIMATOR = None\ndef design(exp, *, check=True): pass\n",
     "does not define make_estimator, conditions, design_json"),
    ("clashing_plugin", textwrap.dedent("""
        from typing import Literal
        from scenarios.helpers import Strict
        class E(Strict):
            algorithm: Literal["lfre"]
        ESTIMATOR = E
        design = make_estimator = conditions = design_json = lambda *a, **k: None
     """), "algorithm 'lfre' is already provided by scenarios.plugins.mitra"),
    ("bad_threat_model", textwrap.dedent("""
        from typing import Literal
        from scenarios.helpers import Strict, ThreatModel
        class E(Strict):
            algorithm: Literal["algo"]
            f: int = 1
        ESTIMATOR = E
        THREAT_MODEL = ThreatModel(agents="F")
        design = make_estimator = conditions = design_json = lambda *a, **k: None
     """), "THREAT_MODEL.agents = 'F' is not a field of its ESTIMATOR"),
    ("unknown_strategy", textwrap.dedent("""
        from typing import Literal
        from scenarios.helpers import Strict, ThreatModel
        class E(Strict):
            algorithm: Literal["algo"]
        ESTIMATOR = E
        THREAT_MODEL = ThreatModel(strategies=("constant", "bribery"))
        design = make_estimator = conditions = design_json = lambda *a, **k: None
     """), "THREAT_MODEL.strategies: unknown strategy 'bribery'"),
])
def test_a_broken_entry_point_is_one_line_naming_the_package(tmp_path, module, body, message):
    site = tmp_path / "site"
    _fake_distribution(site, module, body)
    res = rse("check", str(SCENARIOS / "lee_kim_shim.toml"), env=_env(site))
    assert res.returncode == 1, res.stdout + res.stderr
    assert "Traceback" not in res.stderr
    lines = [l for l in res.stderr.splitlines() if l.strip()]
    assert len(" ".join(lines)) <= 400 and " ".join(" ".join(lines).split()).startswith("error: algorithm plugin 'algo'")
    text = " ".join(res.stderr.split())
    assert f"(entry point {GROUP}: algo = {module}) of package broken-algo 0.3" in text
    assert message in text
