"""``rse boundary``: where a metric crosses a threshold, found by probabilistic bisection."""

from __future__ import annotations

import os
from pathlib import Path

import click

from .common import handle_errors


@click.command()
@click.argument("scenario", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--vary", "vary", multiple=True, required=True, metavar="KEY=LO:HI [--vary KEY2=V1,V2|START:STOP:STEP]",
              help="The parameter searched over [LO, HI]; a second --vary traces the boundary over KEY2's values.")
@click.option("--metric", default="relative_error_2", show_default=True,
              help="The worst regular agent's figure compared with the threshold (final_relative_error_2, "
                   "window_max_error_2, ...; relative_error_2 is the final relative error).")
@click.option("--threshold", type=float, required=True, help="The metric's value that separates success from failure.")
@click.option("--seeds", type=click.IntRange(1, 10_000), default=20, show_default=True,
              help="Seeds per query point (run.seed, run.seed + 1, ...): the boundary is where their median crosses.")
@click.option("--tol", type=click.FloatRange(min=0, min_open=True), default=0.005, show_default=True,
              help="Stop when the search's 95% interval is narrower than 2 x TOL.")
@click.option("--max-runs", type=click.IntRange(min=1), default=90, show_default=True,
              help="Stop after this many runs (per search).")
@click.option("--jobs", "-j", type=click.IntRange(1, 256), default=os.cpu_count() or 1, show_default=True,
              help="Worker processes.")
@click.option("--cluster", default=None, metavar="tcp://HOST:8786",
              help="Run on the Dask cluster whose scheduler is at this address (see rse sweep).")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Output directory (default: runs/boundary-NAME). Re-running with the same directory resumes.")
@click.option("--set", "overrides", multiple=True, metavar="KEY.PATH=VALUE", help="Override a key for every run.")
@click.option("--rrd/--no-rrd", "record", default=True, show_default=True,
              help="Write each run's Rerun recording (points/ID/run.rrd), tagged with its values and seed.")
@click.option("--png/--no-png", default=True, show_default=True, help="Write boundary.png (needs the plot extra).")
@handle_errors
def boundary(scenario: Path, vary: tuple[str, ...], metric: str, threshold: float, seeds: int, tol: float,
             max_runs: int, jobs: int, cluster: str | None, out: Path | None, overrides: tuple[str, ...],
             record: bool, png: bool) -> None:
    """Find the value of a parameter at which a metric crosses a threshold.

    Probabilistic bisection (Waeber, Frazier & Henderson 2013) with a sequential sign test
    over the seeds at each query point: far fewer runs than a grid. Example:

    \b
      rse boundary scenarios/mitra_cells.toml --vary network.channel.drop_p=0:0.95 \\
          --metric relative_error_2 --threshold 1e-6 --seeds 20

    Writes boundary.parquet (every run), boundary.json (the estimate, its 95% interval, the
    queries) and boundary.png (with Theorem 2's largest tolerable p for an lfre scenario).
    """
    from scenarios.loader import load

    from ..boundary import figure, run_boundary
    from ..console import err
    from ..console import out as console

    sc, _ = load(scenario, list(overrides))
    out = out or Path("runs") / f"boundary-{sc.run.name}"

    def progress(runs: int, state: str) -> None:
        err.print(f"{runs} runs: {state}", highlight=False)

    rows, results = run_boundary(scenario, list(vary), metric=metric, threshold=threshold, seeds=seeds, jobs=jobs,
                                 out=out, overrides=list(overrides), cluster=cluster, tol=tol, max_runs=max_runs,
                                 record=record, progress=progress)
    key = vary[0].split("=", 1)[0].strip()
    for r in results:
        where = ", ".join(f"{k}={v}" for k, v in r["at"].items())
        note = "" if r["inside"] else " (at an end of the range: no crossing inside it)"
        seeds_ci = (f"[{r['ci_low']:.4f}, {r['ci_high']:.4f}]" if r["ci_low"] is not None
                    else f"none ({seeds} seeds are too few)")
        console.print(f"{(where + ': ') if where else ''}{key} = {r['estimate']:.4f}{note}; "
                      f"search interval [{r['search_low']:.4f}, {r['search_high']:.4f}]; "
                      f"{int(r['level'] * 100)}% interval from the seeds {seeds_ci}; "
                      f"{r['runs']} runs in {r['queries']} queries", soft_wrap=True)
    console.print(f"{len(rows)} runs in {out}; table: {out / 'boundary.parquet'}")
    if png:
        path = figure(out, rows, results, scenario=scenario, vary=list(vary), metric=metric, threshold=threshold,
                      overrides=list(overrides))
        console.print(f"figure: {path}")
