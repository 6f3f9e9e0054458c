"""Throughput of ``rse sweep`` (section ``sweep``).

:func:`agents.sweep.run_sweep` (what ``rse sweep`` runs, without its figure) on
``scenarios/mitra_cells.toml`` (16 agents, its Byzantine agent, ``[expect]`` bounds
dropped) over a grid of drop probabilities and seeds, in a fresh sweep directory, with
``jobs`` worker processes. The wall time covers everything a sweep does: the validation
build of each grid point, the worker pool start, the runs, the files (with each run's
tagged ``run.rrd``) and ``sweep.parquet``.

Each size is measured twice in the same session, with the default executor (a ``spawn``
process pool) and with Dask (a ``LocalCluster`` of the same number of worker processes,
the path of ``rse sweep --cluster``), and the ratio of their throughputs is a figure: on
a loaded machine only the ratio measured in one session means much.

``python -m benchmarks.sweep_bench`` measures the 380-run sweep (``drop_p=0:0.9:0.05``,
20 seeds, 300 rounds, its ``[expect]`` bounds kept, 2 jobs: 380 runs) both ways.
"""

from __future__ import annotations

import importlib.util
import tempfile
import time
from pathlib import Path
from typing import Any

from .report import ROOT, BenchmarkError, Figure

SCENARIO = ROOT / "scenarios" / "mitra_cells.toml"


def measure_sweep(drop_ps: list[float], seeds: int, rounds: int | None, jobs: int, *, cluster: str | None = None,
                  keep_expect: bool = False) -> dict[str, Any]:
    """Run one sweep of ``len(drop_ps) * seeds`` points; returns ``runs``, ``elapsed_s``, ``N``, ``rounds``, ``jobs``.

    ``rounds`` None keeps the scenario's; ``cluster`` as ``rse sweep --cluster`` (``"local"``:
    a Dask ``LocalCluster``); ``keep_expect`` keeps the scenario's ``[expect]`` bounds.

    Raises
    ------
    BenchmarkError
        If a point of the sweep fails.
    """
    from agents.api import load_experiment
    from agents.sweep import run_sweep

    overrides = ([] if rounds is None else [f"run.rounds={rounds}"]) + ([] if keep_expect else ["expect=[]"])
    grid = "network.channel.drop_p=" + ",".join(f"{p:g}" for p in drop_ps)
    exp, _ = load_experiment(SCENARIO, tuple(overrides), None)  # the team size (outside the timing)
    with tempfile.TemporaryDirectory(prefix="rse-benchmarks-sweep-") as tmp:
        cpu0 = _cpu_s()
        t0 = time.perf_counter()
        rows = run_sweep(SCENARIO, [grid], seeds=seeds, jobs=jobs, out=Path(tmp) / "sweep", overrides=overrides,
                         cluster=cluster)
        elapsed = time.perf_counter() - t0
        cpu = _cpu_s() - cpu0
    bad = [r for r in rows if r.get("status") != "ok"]
    if bad:
        raise BenchmarkError(f"sweep: {len(bad)} of {len(rows)} runs failed, e.g. {bad[0].get('status')}")
    return {"runs": len(rows), "elapsed_s": elapsed, "N": exp.N, "rounds": exp.scenario.run.rounds + 1, "jobs": jobs,
            "grid": grid, "seeds": seeds, "executor": "dask" if cluster else "pool", "cpu_s": cpu}


def _cpu_s() -> float:
    """User + system CPU seconds of this process and of its finished child processes (the
    workers, once shut down): on a loaded machine the CPU a sweep costs varies far less
    than its wall time."""
    import resource

    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def sweep_figures(m: dict[str, Any], pool: dict[str, Any] | None = None) -> list[Figure]:
    """Figures of section ``sweep`` from one :func:`measure_sweep` result (and, for a Dask
    result, the throughput ratio to the ``pool`` result of the same size)."""
    dask = m.get("executor") == "dask"
    size = f"{m['runs']} runs" + (" dask" if dask else "")
    how = (f"{m['N']} agents x {m['rounds']} rounds per run, {m['jobs']} worker process(es)"
           + (" of a Dask LocalCluster" if dask else " (process pool)"))
    extra = []
    if dask and pool is not None:
        extra.append(Figure("sweep", size, "dask_vs_pool", "throughput, Dask / process pool",
                            pool["elapsed_s"] / m["elapsed_s"], "x", True, "same runs, same session"))
        extra.append(Figure("sweep", size, "cpu_dask_vs_pool", "CPU seconds, Dask / process pool",
                            m["cpu_s"] / pool["cpu_s"], "x", False, "this process and its workers"))
    return extra + [
        Figure("sweep", size, "elapsed_s", "sweep wall time", m["elapsed_s"], "s", False,
               f"{m['grid']}, {m['seeds']} seed(s)"),
        Figure("sweep", size, "runs_per_s", "runs/s", m["runs"] / m["elapsed_s"], "1/s", True, how),
        Figure("sweep", size, "agent_rounds_per_s", "agent-rounds/s", m["runs"] * m["N"] * m["rounds"] / m["elapsed_s"],
               "1/s", True, how),
    ]


def main() -> None:
    """The 380-run sweep, with the process pool and with Dask; prints both and the ratio."""
    import argparse

    from agents.api import pin_blas_threads

    pin_blas_threads()
    ap = argparse.ArgumentParser(prog="python -m benchmarks.sweep_bench", description=main.__doc__)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--step", type=float, default=0.05, help="drop_p step of the grid 0:0.9")
    ap.add_argument("--repeat", type=int, default=1, help="measure the pair this many times")
    a = ap.parse_args()
    drop_ps = [round(i * a.step, 12) for i in range(int(round(0.9 / a.step)) + 1)]
    dask = importlib.util.find_spec("distributed") is not None
    for _ in range(a.repeat):  # each figure printed as soon as it is measured
        pool = measure_sweep(drop_ps, a.seeds, None, a.jobs, keep_expect=True)
        print(f"pool: {pool['runs']} runs in {pool['elapsed_s']:.1f} s, {pool['cpu_s']:.1f} CPU s", flush=True)
        if dask:
            d = measure_sweep(drop_ps, a.seeds, None, a.jobs, cluster="local", keep_expect=True)
            print(f"dask LocalCluster: {d['runs']} runs in {d['elapsed_s']:.1f} s, {d['cpu_s']:.1f} CPU s; "
                  f"throughput dask/pool = {pool['elapsed_s'] / d['elapsed_s']:.2f}, "
                  f"CPU per run dask/pool = {d['cpu_s'] / pool['cpu_s']:.2f}", flush=True)


if __name__ == "__main__":
    main()
