import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):  # as the rse command does
    os.environ.setdefault(_var, "1")

import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from hypothesis import settings

# the property tests draw the same examples in every run (a run is reproducible and a red CI
# is not a new random draw); HYPOTHESIS_PROFILE=explore draws new ones
settings.register_profile("repeatable", derandomize=True)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "repeatable"))

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ROOT / "scenarios"

# algorithms whose offline design solves a convex program with cvxpy (an optional extra:
# `pip install '.[lmi]'`); their scenarios skip without it
CVXPY_ALGORITHMS = {"median_bank": "the median bank's observer gains (LMI)", "ugrinovskii": "the H-infinity LMIs"}


def pytest_addoption(parser):
    parser.addoption("--without", action="append", default=[], metavar="MODULE",
                     help="run as if MODULE were not installed (for the tests that must skip without an optional "
                          "dependency), e.g. --without cvxpy")


def pytest_configure(config):
    config.addinivalue_line("markers", "needs(module, why): skip (with the reason) where the optional module is absent")
    for name in config.getoption("--without"):
        sys.modules[name] = None  # `import name` raises ModuleNotFoundError


def pytest_runtest_setup(item):
    for mark in item.iter_markers("needs"):
        name, why = mark.args[0], mark.args[1] if len(mark.args) > 1 else ""
        pytest.importorskip(name, reason=f"needs {name}" + (f" for {why}" if why else "") + " (not installed)")


def pytest_collection_modifyitems(config, items):
    """The scenario files' bounds (collected by ``rse.pytest_plugin`` under ``--rse``, the
    suite's addopts) skip, as the suite's own tests do, where they need cvxpy or pandapower and
    it is absent (or hidden by ``--without MODULE``)."""
    for item in items:
        if item.path.suffix == ".toml":
            for mark in needs_cvxpy(item.path) + needs_pandapower(item.path):
                name, why = mark.args
                if _absent(name):
                    item.add_marker(pytest.mark.skip(reason=f"needs {name} for {why} (not installed)"))


def _absent(name: str) -> bool:
    if name in sys.modules:
        return sys.modules[name] is None
    import importlib.util

    return importlib.util.find_spec(name) is None


def needs_cvxpy(path: Path) -> list:
    """The ``needs("cvxpy")`` mark for a scenario file whose algorithm's design uses cvxpy."""
    algorithm = tomllib.loads(Path(path).read_text()).get("estimator", {}).get("algorithm")
    why = CVXPY_ALGORITHMS.get(algorithm)
    return [pytest.mark.needs("cvxpy", f"{Path(path).name}: {why}")] if why else []


def needs_pandapower(path: Path) -> list:
    """The ``needs("pandapower")`` mark for a scenario file whose plant is ``model = "grid"``."""
    model = tomllib.loads(Path(path).read_text()).get("plant", {}).get("model")
    return [pytest.mark.needs("pandapower", f"{Path(path).name}: the grid plant")] if model == "grid" else []


def scenario_params(paths) -> list:
    """One ``pytest.param`` per scenario file, id its stem, marked where it needs cvxpy or pandapower."""
    return [pytest.param(p, id=Path(p).stem, marks=needs_cvxpy(p) + needs_pandapower(p)) for p in paths]


def rse(*args: str, timeout: float = 300, cwd: Path | None = None, env: dict | None = None) -> subprocess.CompletedProcess:
    """Run the ``rse`` command line as a user would (a fresh interpreter)."""
    e = dict(os.environ)
    e.pop("RSE_DEBUG", None)
    e.setdefault("COLUMNS", "200")  # rich wraps tables at the terminal width
    e.update(env or {})
    exe = shutil.which("rse")
    cmd = [exe, *args] if exe else [sys.executable, "-m", "agents.cli", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=cwd or ROOT, env=e)


@pytest.fixture
def run_rse():
    return rse


@pytest.fixture
def procs():
    """Real ``rse`` processes started by a test (:class:`tests.procs.Procs`), all killed at
    its end whatever happened."""
    from tests.procs import Procs

    ps = Procs()
    try:
        yield ps
    finally:
        ps.kill_all()
