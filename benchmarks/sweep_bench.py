"""Throughput of ``rse sweep`` (section ``sweep``).

:func:`agents.sweep.run_sweep` (what ``rse sweep`` runs, without its figure) on
``scenarios/mitra_cells.toml`` (16 agents, its Byzantine agent, ``[expect]`` bounds
dropped) over a grid of drop probabilities and seeds, in a fresh sweep directory, with
``jobs`` worker processes. The wall time covers everything a sweep does: the validation
build of each grid point, the worker pool start, the runs, the files and
``sweep.parquet``.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

from .report import ROOT, BenchmarkError, Figure

SCENARIO = ROOT / "scenarios" / "mitra_cells.toml"


def measure_sweep(drop_ps: list[float], seeds: int, rounds: int, jobs: int) -> dict[str, Any]:
    """Run one sweep of ``len(drop_ps) * seeds`` points; returns ``runs``, ``elapsed_s``, ``N``, ``rounds``, ``jobs``.

    Raises
    ------
    BenchmarkError
        If a point of the sweep fails.
    """
    from agents.api import load_experiment
    from agents.sweep import run_sweep

    overrides = [f"run.rounds={rounds}", "expect=[]"]
    grid = "network.channel.drop_p=" + ",".join(f"{p:g}" for p in drop_ps)
    exp, _ = load_experiment(SCENARIO, tuple(overrides), None)  # the team size (outside the timing)
    with tempfile.TemporaryDirectory(prefix="rse-benchmarks-sweep-") as tmp:
        t0 = time.perf_counter()
        rows = run_sweep(SCENARIO, [grid], seeds=seeds, jobs=jobs, out=Path(tmp) / "sweep", overrides=overrides)
        elapsed = time.perf_counter() - t0
    bad = [r for r in rows if r.get("status") != "ok"]
    if bad:
        raise BenchmarkError(f"sweep: {len(bad)} of {len(rows)} runs failed, e.g. {bad[0].get('status')}")
    return {"runs": len(rows), "elapsed_s": elapsed, "N": exp.N, "rounds": rounds + 1, "jobs": jobs, "grid": grid,
            "seeds": seeds}


def sweep_figures(m: dict[str, Any]) -> list[Figure]:
    """Figures of section ``sweep`` from one :func:`measure_sweep` result."""
    size = f"{m['runs']} runs"
    how = f"{m['N']} agents x {m['rounds']} rounds per run, {m['jobs']} worker process(es)"
    return [
        Figure("sweep", size, "elapsed_s", "sweep wall time", m["elapsed_s"], "s", False,
               f"{m['grid']}, {m['seeds']} seed(s)"),
        Figure("sweep", size, "runs_per_s", "runs/s", m["runs"] / m["elapsed_s"], "1/s", True, how),
        Figure("sweep", size, "agent_rounds_per_s", "agent-rounds/s", m["runs"] * m["N"] * m["rounds"] / m["elapsed_s"],
               "1/s", True, how),
    ]
