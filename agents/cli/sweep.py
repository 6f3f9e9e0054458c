"""``rse sweep``: a scenario over a grid of overrides and seeds."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import click

from .common import handle_errors, sigterm_interrupts


@click.command()
@click.argument("scenario", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--grid", "grid", multiple=True, metavar="KEY=V1,V2|START:STOP:STEP", required=True,
              help="A scenario key and its values (repeatable: the grid is the product).")
@click.option("--seeds", type=click.IntRange(1, 10_000), default=1, show_default=True,
              help="Seeds per grid point: run.seed, run.seed + 1, ...")
@click.option("--jobs", "-j", type=click.IntRange(1, 256), default=os.cpu_count() or 1, show_default=True,
              help="Worker processes.")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Sweep directory (default: runs/sweep-NAME). Re-running with the same directory resumes.")
@click.option("--set", "overrides", multiple=True, metavar="KEY.PATH=VALUE", help="Override a key for every point.")
@click.option("--cluster", default=None, metavar="tcp://HOST:8786",
              help="Run on the Dask cluster whose scheduler is at this address (needs the cluster extra); "
                   "'local': a Dask LocalCluster of --jobs processes. Default: a process pool of --jobs.")
@click.option("--rrd/--no-rrd", "record", default=True, show_default=True,
              help="Write each run's Rerun recording (points/ID/run.rrd), tagged with its grid values and seed.")
@click.option("--png/--no-png", default=True, show_default=True, help="Write sweep.png (needs the plot extra).")
@click.option("--metric", default=None, metavar="M",
              help="What sweep.png draws, the worst regular agent's: final_relative_error_2, final_error_2, "
                   "final_error_inf, window_max_relative_error_2, window_max_error_2 or window_max_error_inf "
                   "(default: final_relative_error_2 for lfre, window_max_error_inf otherwise).")
@click.option("--threshold", type=float, default=None, metavar="T",
              help="Draw T and where the median first exceeds it (default: the scenario's [[expect]] bound "
                   "on the metric, if any).")
@handle_errors
def sweep(scenario: Path, grid: tuple[str, ...], seeds: int, jobs: int, out: Path | None,
          overrides: tuple[str, ...], cluster: str | None, record: bool, png: bool, metric: str | None,
          threshold: float | None) -> None:
    """Run SCENARIO over a grid of overrides and seeds in parallel; resumable.

    Writes one row per run to sweep.parquet (grid values, seed, the worst regular agent's
    final and window errors, whether the [expect] bounds held) and sweep.png: the median
    over seeds of --metric against the first grid key with --threshold (with Theorem 2's
    MSS bound when that key is network.channel.drop_p of an lfre scenario). Each run's Rerun
    recording, tagged with its grid values and seed, is points/ID/run.rrd: `rerun
    OUT/points/*/run.rrd` opens them together. `rse report OUT` prints the table.
    """
    from rich.markup import escape
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    from scenarios.loader import load

    from ..console import err
    from ..console import out as console
    from ..sweep import figure, figure_choice, run_sweep

    sigterm_interrupts()
    sc, _ = load(scenario, list(overrides))
    metric, threshold, origin = figure_choice(sc, metric, threshold)  # a bad --metric fails before any run
    out = out or Path("runs") / f"sweep-{sc.run.name}"
    bar = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TextColumn("runs"),
                   TimeElapsedColumn(), TimeRemainingColumn(), console=err)
    with contextlib.ExitStack() as stack:
        task = None

        def progress(done: int, total: int) -> None:  # the bar appears once the sweep is valid and connected
            nonlocal task
            if task is None:
                stack.enter_context(bar)
                task = bar.add_task(f"sweep {sc.run.name}", total=None)
            bar.update(task, completed=done, total=total)

        rows = run_sweep(scenario, list(grid), seeds=seeds, jobs=jobs, out=out, overrides=list(overrides),
                         progress=progress, cluster=cluster, record=record)
    failed = [r for r in rows if r.get("status") != "ok"]
    console.print(f"{len(rows)} runs in {out} ({len(failed)} failed); table: {out / 'sweep.parquet'}")
    for r in failed[:5]:
        console.print(f"  point {r['point']} seed {r['seed']}: {r['status']}")
    if png:
        drawn = figure(out, rows, list(grid), scenario, list(overrides), metric, threshold)
        if drawn is not None:
            path, c = drawn
            limit = "no threshold" if threshold is None else f"threshold {threshold:g} ({origin})"
            where = "" if threshold is None else (
                f", median above it from {c['crossing']:g}" if c["crossing"] is not None else ", median never above it")
            console.print(escape(f"figure: {path} (median of the worst regular agent's {metric}; {limit}{where})"),
                          soft_wrap=True)
