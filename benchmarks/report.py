"""Figures of a benchmark run: the machine, the commit, the table, the JSON file, comparisons.

A result file (``--json FILE``) is one JSON object::

    {"format": "rse-benchmarks/1", "created": ISO-8601 UTC, "quick": bool,
     "sections": [...], "command": [...], "machine": {...}, "git": {...},
     "figures": [{"key", "section", "size", "name", "label", "value", "unit",
                  "higher_is_better", "detail"}, ...],
     "errors": ["section: message", ...]}

``key`` (``section/size/name``, e.g. ``simulate/1024 agents/fused_values_per_s``) is
what :func:`compare_rows` matches between two files; it names neither the rounds nor the
repeats, which are in ``detail``.
"""

from __future__ import annotations

import json
import math
import os
import platform
import subprocess
import sys
from collections.abc import Iterable
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

FORMAT = "rse-benchmarks/1"
ROOT = Path(__file__).resolve().parents[1]


class BenchmarkError(Exception):
    """A benchmark could not be run or a result file could not be read (one-line message)."""


@dataclass
class Figure:
    """One measured figure.

    Parameters
    ----------
    section : "simulate", "memory", "run" or "sweep"
    size : the team (or grid) it was measured at, e.g. ``"1024 agents"``, ``"8 procs"``
    name : machine name of the figure (part of :attr:`key`)
    label : what the table prints
    value : the figure
    unit : its unit ("1/s", "s", "ns", "MB", "x", ...)
    higher_is_better : the direction of an improvement (colours of ``--compare``)
    detail : how it was measured (rounds, repeats, ...), not part of the key
    """

    section: str
    size: str
    name: str
    label: str
    value: float
    unit: str
    higher_is_better: bool
    detail: str = ""

    @property
    def key(self) -> str:
        return f"{self.section}/{self.size}/{self.name}"

    def as_dict(self) -> dict[str, Any]:
        return {"key": self.key, **asdict(self)}


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.lower().startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info() -> dict[str, Any]:
    """The machine and software a run measured: CPU, cores, memory, Python, OS, libraries, load."""
    from importlib import metadata

    info: dict[str, Any] = {
        "cpu": _cpu_model(),
        "arch": platform.machine(),
        "cores_logical": os.cpu_count(),
        "python": f"{platform.python_implementation()} {platform.python_version()}",
        "os": platform.platform(),
    }
    try:
        import psutil

        info["cores_physical"] = psutil.cpu_count(logical=False)
        info["memory_gb"] = round(psutil.virtual_memory().total / 2**30, 1)
    except Exception:  # pragma: no cover - psutil is a dependency
        pass
    if hasattr(os, "sched_getaffinity"):
        info["cores_usable"] = len(os.sched_getaffinity(0))
    for dist in ("numpy", "scipy", "eclipse-zenoh"):
        try:
            info[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            info[dist] = None
    info["blas_threads"] = os.environ.get("OPENBLAS_NUM_THREADS")
    if hasattr(os, "getloadavg"):
        info["loadavg_start"] = [round(x, 2) for x in os.getloadavg()]
    return info


def git_info(root: Path = ROOT) -> dict[str, Any]:
    """The commit of the checkout (``commit``, ``branch``, ``dirty``: tracked files modified)."""

    def git(*args: str) -> str | None:
        try:
            r = subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, timeout=10)
        except (OSError, subprocess.TimeoutExpired):
            return None
        return r.stdout.strip() if r.returncode == 0 else None

    commit = git("rev-parse", "HEAD")
    status = git("status", "--porcelain", "--untracked-files=no")
    return {"commit": commit, "branch": git("rev-parse", "--abbrev-ref", "HEAD"),
            "dirty": None if status is None else bool(status)}


def result_document(figures: Iterable[Figure], *, machine: dict[str, Any], git: dict[str, Any], quick: bool,
                    sections: list[str], errors: list[str]) -> dict[str, Any]:
    """The JSON object of one run (see the module docstring)."""
    machine = dict(machine)
    if hasattr(os, "getloadavg"):
        machine["loadavg_end"] = [round(x, 2) for x in os.getloadavg()]
    return {
        "format": FORMAT,
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "quick": quick,
        "sections": sections,
        "command": [Path(sys.executable).name, "-m", "benchmarks", *sys.argv[1:]],
        "machine": machine,
        "git": git,
        "figures": [f.as_dict() for f in figures],
        "errors": errors,
    }


def write_document(doc: dict[str, Any], path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=2, allow_nan=True) + "\n")


def read_document(path: Path) -> dict[str, Any]:
    """Read a result file written by ``--json``; :class:`BenchmarkError` if it is not one."""
    try:
        doc = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise BenchmarkError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise BenchmarkError(f"{path}: cannot read: {exc}") from None
    except json.JSONDecodeError as exc:
        raise BenchmarkError(f"{path}: not JSON ({exc.msg} at line {exc.lineno})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT or not isinstance(doc.get("figures"), list):
        raise BenchmarkError(f"{path}: not a benchmark result file (expected format {FORMAT!r})")
    return doc


def figures_of(doc: dict[str, Any]) -> list[Figure]:
    fields = Figure.__dataclass_fields__
    return [Figure(**{k: v for k, v in f.items() if k in fields}) for f in doc["figures"]]


def fmt_value(v: float | None) -> str:
    if v is None:
        return "-"
    if isinstance(v, float) and not math.isfinite(v):
        return str(v)
    if abs(v) >= 1000:
        return f"{v:,.0f}"
    if float(v).is_integer():
        return f"{int(v)}"
    return f"{v:.4g}"


def describe_machine(doc: dict[str, Any]) -> str:
    m, g = doc.get("machine", {}), doc.get("git", {})
    commit = (g.get("commit") or "?")[:10] + (" (modified)" if g.get("dirty") else "")
    load = m.get("loadavg_start")
    return (f"{m.get('cpu', '?')}, {m.get('cores_logical', '?')} cores, {m.get('python', '?')}, {m.get('os', '?')}; "
            f"commit {commit}" + (f"; load average at start {load[0]:g}" if load else ""))


def table(doc: dict[str, Any], old: dict[str, Any] | None = None) -> Any:
    """One rich table of every figure of ``doc``; with ``old``, its value and new / old."""
    from rich.table import Table

    figs = figures_of(doc)
    title = "rse benchmarks" + (" (--quick)" if doc.get("quick") else "")
    t = Table(title=title, title_justify="left", caption=describe_machine(doc), caption_justify="left")
    t.add_column("benchmark")
    t.add_column("size", justify="right")
    t.add_column("figure")
    t.add_column("value", justify="right")
    t.add_column("unit")
    prev = {f["key"]: f for f in (old or {}).get("figures", [])}
    if old is not None:
        t.add_column("old", justify="right")
        t.add_column("new / old", justify="right")
    t.add_column("detail", style="dim")
    for idx, f in enumerate(figs):
        row = [f.section, f.size, f.label, fmt_value(f.value), f.unit]
        if old is not None:
            o = prev.get(f.key)
            ratio = ratio_of(f.value, o["value"]) if o is not None else None
            row += [fmt_value(o["value"]) if o is not None else "-", _ratio_cell(ratio, f.higher_is_better)]
        row.append(f.detail)
        last = idx + 1 == len(figs) or figs[idx + 1].section != f.section
        t.add_row(*row, end_section=last)
    if old is not None:
        t.caption += "\ncompared with " + describe_machine(old)
    return t


def ratio_of(new: float | None, old: float | None) -> float | None:
    if new is None or old is None or not (isinstance(new, (int, float)) and isinstance(old, (int, float))):
        return None
    if old == 0 or not (math.isfinite(new) and math.isfinite(old)):
        return None
    return new / old


def _ratio_cell(ratio: float | None, higher_is_better: bool) -> str:
    if ratio is None:
        return "-"
    better = ratio > 1.05 if higher_is_better else ratio < 1 / 1.05
    worse = ratio < 1 / 1.05 if higher_is_better else ratio > 1.05
    text = f"{ratio:.2f}"
    return f"[green]{text}" if better else f"[red]{text}" if worse else text


def compare_rows(new: dict[str, Any], old: dict[str, Any]) -> list[tuple[str, float | None]]:
    """``(key, new / old)`` for every figure of ``new`` (None when ``old`` lacks it)."""
    prev = {f["key"]: f["value"] for f in old["figures"]}
    return [(f["key"], ratio_of(f["value"], prev.get(f["key"]))) for f in new["figures"]]
