"""The dependency direction of DESIGN.md, for every layer:

    estimation <- transport <- scenarios <- agents <- benchmarks, the CLI (agents.cli) on top

A module imports only from its own layer or the layers below (imports inside functions
count; ``if TYPE_CHECKING:`` blocks do not), nothing outside ``agents.cli`` imports the
CLI, no import cycle exists among the project's modules, and ``estimation`` imports none
of asyncio, zenoh, rerun or msgpack.
"""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import networkx as nx
import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("estimation", "transport", "scenarios", "agents", "benchmarks", "rse")
RANK = {"estimation": 0, "transport": 1, "scenarios": 2, "agents": 3, "benchmarks": 4, "rse": 4, "agents.cli": 5}
FORBIDDEN_IN_ESTIMATION = {"agents", "transport", "scenarios", "asyncio", "zenoh", "rerun", "msgpack"}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _is_type_checking(node: ast.If) -> bool:
    t = node.test
    return (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or (
        isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING")


def imports_of(path: Path, modules: set[str] | None = None) -> set[str]:
    """Absolute names of the modules ``path`` imports (relative imports resolved; ``from
    pkg import name`` counts as ``pkg.name`` when that is a module of ``modules``)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    me = module_name(path) if path.is_relative_to(ROOT) else path.stem
    package = me if path.name == "__init__.py" else me.rpartition(".")[0]
    found: set[str] = set()

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and _is_type_checking(node):
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)] if node.level > 1 else base
                mod = ".".join([*base, node.module] if node.module else base)
            else:
                mod = node.module or ""
            found.add(mod)
            for a in node.names:
                sub = f"{mod}.{a.name}"
                if modules is not None and sub in modules:
                    found.add(sub)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return found


def project_modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            out[module_name(path)] = path
    return out


def layer_of(module: str) -> str:
    return "agents.cli" if module == "agents.cli" or module.startswith("agents.cli.") else module.split(".")[0]


def import_graph() -> nx.DiGraph:
    mods = project_modules()
    names = set(mods)
    g = nx.DiGraph()
    g.add_nodes_from(names)
    for name, path in mods.items():
        for imp in imports_of(path, names):
            # the module itself, or the nearest enclosing package that is a project module
            target = imp
            while target and target not in names:
                target = target.rpartition(".")[0]
            if target and target != name and not name.startswith(target + "."):
                g.add_edge(name, target)
    return g


def test_every_layer_imports_only_downwards():
    g = import_graph()
    upward = sorted(f"{a} -> {b}" for a, b in g.edges if RANK[layer_of(b)] > RANK[layer_of(a)])
    assert upward == []


def test_nothing_outside_the_cli_imports_it():
    g = import_graph()
    users = sorted(f"{a} -> {b}" for a, b in g.edges if layer_of(b) == "agents.cli" and layer_of(a) != "agents.cli")
    assert users == []


def test_the_product_imports_no_benchmark_and_edits_no_sys_path():
    """The installed package does not need the benchmarks (architecture: CLI and runtime never
    import them), and no module of the project edits ``sys.path`` (only tests may)."""
    g = import_graph()
    users = sorted(f"{a} -> {b}" for a, b in g.edges if layer_of(b) == "benchmarks" and layer_of(a) != "benchmarks")
    assert users == []
    edits = sorted(name for name, path in project_modules().items()
                   if re.search(r"sys\.path\.(insert|append|extend)|sys\.path\s*=", path.read_text()))
    assert edits == []


def test_no_import_cycle_among_the_project_modules():
    g = import_graph()
    cycles = [c for c in nx.simple_cycles(g)]
    assert cycles == []


def test_the_graph_sees_relative_lazy_and_package_imports(tmp_path):
    g = import_graph()
    assert g.has_edge("agents.cli", "agents.cli.sim")  # from .sim import simulate
    assert g.has_edge("agents.cli.sim", "agents.api")  # from .. import api
    assert g.has_edge("agents.runs", "scenarios.build")  # a lazy import inside a function
    assert g.has_edge("rse", "agents.api")


@pytest.mark.parametrize("layer", ["estimation", "transport", "scenarios"])
def test_a_planted_upward_import_is_caught(layer, monkeypatch):
    g = import_graph()
    g.add_edge(f"{layer}.x", "agents.api")
    upward = [f"{a} -> {b}" for a, b in g.edges if RANK[layer_of(b)] > RANK[layer_of(a)]]
    assert upward == [f"{layer}.x -> agents.api"]


def test_estimation_sources_import_no_other_layer():
    offenders = {}
    for path in sorted((ROOT / "estimation").rglob("*.py")):
        bad = {m.split(".")[0] for m in imports_of(path)} & FORBIDDEN_IN_ESTIMATION
        if bad:
            offenders[str(path.relative_to(ROOT))] = sorted(bad)
    assert offenders == {}


def test_importing_every_estimation_module_loads_no_other_layer():
    modules = [p.stem for p in (ROOT / "estimation").glob("*.py") if p.stem != "__init__"]
    code = (
        "import importlib, sys\n"
        f"for m in {modules!r}: importlib.import_module('estimation.' + m)\n"
        f"bad = sorted(m for m in sys.modules if m.split('.')[0] in {sorted(FORBIDDEN_IN_ESTIMATION)!r})\n"
        "print(','.join(bad))\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == ""


def test_the_check_catches_a_forbidden_import(tmp_path):
    p = tmp_path / "m.py"
    p.write_text("import numpy\nfrom transport.channel import Channel\nimport zenoh\n"
                 "def f():\n    from agents import api\n")
    assert {m.split(".")[0] for m in imports_of(p)} & FORBIDDEN_IN_ESTIMATION == {"transport", "zenoh", "agents"}


def test_importing_the_cli_loads_no_numerics():
    """The CLI pins BLAS threads in main(): importing it must not have imported numpy yet."""
    code = "import sys, agents.cli, rse; print(','.join(m for m in ('numpy', 'scipy', 'scenarios.build') if m in sys.modules))"
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == ""


MAX_LINES = 500  # STYLE.md / the developers' guide: modules stay small (about 400 lines, 500 at most)


def test_no_module_of_the_project_is_over_500_lines():
    sizes = {name: len(path.read_text().splitlines()) for name, path in project_modules().items()}
    assert len(sizes) > 100, sorted(sizes)  # the walk found the project
    over = {name: n for name, n in sizes.items() if n > MAX_LINES}
    assert not over, f"modules over {MAX_LINES} lines: {over}"
