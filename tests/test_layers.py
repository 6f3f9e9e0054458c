"""The dependency direction of DESIGN.md: ``estimation`` imports none of the other layers
and nothing of asyncio, zenoh, rerun or msgpack."""

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FORBIDDEN = {"agents", "transport", "scenarios", "asyncio", "zenoh", "rerun", "msgpack"}


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


def test_estimation_sources_import_no_other_layer():
    offenders = {}
    for path in sorted((ROOT / "estimation").rglob("*.py")):
        bad = _imports(path) & FORBIDDEN
        if bad:
            offenders[str(path.relative_to(ROOT))] = sorted(bad)
    assert offenders == {}


def test_importing_every_estimation_module_loads_no_other_layer():
    modules = [p.stem for p in (ROOT / "estimation").glob("*.py") if p.stem != "__init__"]
    code = (
        "import importlib, sys\n"
        f"for m in {modules!r}: importlib.import_module('estimation.' + m)\n"
        f"bad = sorted(m for m in sys.modules if m.split('.')[0] in {sorted(FORBIDDEN)!r})\n"
        "print(','.join(bad))\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == ""


def test_the_check_catches_a_forbidden_import(tmp_path):
    p = tmp_path / "m.py"
    p.write_text("import numpy\nfrom transport.channel import Channel\nimport zenoh\n")
    assert _imports(p) & FORBIDDEN == {"transport", "zenoh"}
