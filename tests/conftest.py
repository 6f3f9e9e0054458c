import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):  # as the rse command does
    os.environ.setdefault(_var, "1")

import shutil  # noqa: E402
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ROOT / "scenarios"


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
