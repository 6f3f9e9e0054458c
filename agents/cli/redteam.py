"""``rse redteam``: search a scenario's threat model for the attack that breaks its estimator."""

from __future__ import annotations

import math
import os
import signal
from pathlib import Path
from typing import Any

import click

from .common import handle_errors


def _over(text: str | None):
    if text is None or text in ("window", "final"):
        return text
    try:
        t0, t1 = (float(x) for x in text.split(","))
    except ValueError:
        from estimation.errors import ScenarioError

        raise ScenarioError(f"--over: expected window, final or T0,T1, got {text!r}", source="command line") from None
    return (t0, t1)


@click.command()
@click.argument("scenario", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--budget", type=click.IntRange(1, 1_000_000), default=200, show_default=True,
              help="Evaluations of the search (a resumed search counts the ones it holds).")
@click.option("--jobs", "-j", type=click.IntRange(1, 256), default=os.cpu_count() or 1, show_default=True,
              help="Worker processes (one batch of this many candidates at a time).")
@click.option("--cluster", default=None, metavar="tcp://HOST:8786", help="Evaluate on this Dask cluster instead.")
@click.option("--metric", default=None, metavar="NAME",
              help="error_inf, error_2, relative_error_2 or error_ratio (default: error_inf over the window; "
                   "relative_error_2 at the final round for lfre).")
@click.option("--over", "over", default=None, metavar="window|final|T0,T1", help="Rounds of the metric.")
@click.option("--block", default=None, help="State block of the metric (or 'all').")
@click.option("--threshold", type=float, default=None,
              help="A metric above this violates (default: the paper's bound that rse check prints).")
@click.option("--beyond", is_flag=True, help="Also search one step outside the threat model (q + 1 banks, f + 1 agents).")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Output directory (default: runs/redteam-NAME). Re-running with it resumes the search.")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True, help="Seed of the optimiser.")
@click.option("--set", "overrides", multiple=True, metavar="KEY.PATH=VALUE",
              help="Override a scenario key first (e.g. --set redteam.amplitude=10). Repeatable.")
@click.option("--shrink-budget", type=click.IntRange(0, 100_000), default=100, show_default=True,
              help="Evaluations spent on shrinking a violating attack.")
@click.option("--no-rerun", is_flag=True, help="No Rerun recordings (search and worst run).")
@click.option("--png/--no-png", default=True, show_default=True, help="Write redteam.png (needs the plot extra).")
@click.option("--progress/--no-progress", default=True, show_default=True, help="Show a progress bar.")
@handle_errors
def redteam(scenario: Path, budget: int, jobs: int, cluster: str | None, metric: str | None, over: str | None,
            block: str | None, threshold: float | None, beyond: bool, out: Path | None, seed: int,
            overrides: tuple[str, ...], shrink_budget: int, no_rerun: bool, png: bool, progress: bool) -> None:
    """Search the attacks SCENARIO's threat model allows for the one that maximises an
    error metric; shrink it when it breaks the paper's bound; write it as a scenario file.

    Writes redteam.parquet (every evaluation), worst.toml (rse simulate reproduces it) and
    its run directory worst/, shrunk.toml when the bound (or --threshold) is exceeded,
    redteam.png, summary.json and recording.rrd (the search, live). See docs/redteam.md.
    """

    def _terminate(*_: object) -> None:  # SIGTERM as Ctrl-C: the workers are cancelled, the files closed
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        res = _search(scenario, budget, jobs, cluster, metric, over, block, threshold, beyond, out, seed, overrides,
                      shrink_budget, no_rerun, png, progress)
    finally:
        signal.signal(signal.SIGTERM, previous)
    _report(res, jobs, png, no_rerun)


def _search(scenario: Path, budget: int, jobs: int, cluster: str | None, metric: str | None, over: str | None,
            block: str | None, threshold: float | None, beyond: bool, out: Path | None, seed: int,
            overrides: tuple[str, ...], shrink_budget: int, no_rerun: bool, png: bool, progress: bool) -> Any:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    from ..console import err
    from ..redteam import redteam as run_redteam

    bar = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[best]}"),
                   TimeElapsedColumn(), TimeRemainingColumn(), console=err, disable=not progress)
    with bar:
        task = bar.add_task(f"redteam {scenario.stem}", total=budget, best="")

        def on_eval(row: dict) -> None:
            if row["phase"] == "search":
                bar.update(task, completed=row["evaluation"] + 1, best=f"worst {row['best']:.4g}")
            else:
                bar.update(task, description=f"shrinking {scenario.stem}", best=f"{row['metric']:.4g}")

        res = run_redteam(scenario, budget=budget, jobs=jobs, cluster=cluster, beyond=beyond, metric=metric,
                          over=_over(over), block=block, threshold=threshold, out=out, seed=seed, overrides=overrides,
                          rerun=not no_rerun, png=png, shrink_budget=shrink_budget, on_eval=on_eval,
                          say=lambda m: bar.console.print(m))
    return res


def _report(res: Any, jobs: int, png: bool, no_rerun: bool) -> None:
    from ..console import out as console

    s = res.summary
    w = s["worst"]
    console.print(f"{s['evaluations']} evaluations of {s['metric']}")
    rate = s["evaluations_per_s"]
    if rate:
        console.print(f"throughput: {rate:.2f} evaluations/s with {jobs} job(s) ({s['search_s']:.1f} s)"
                      + (f", load average {os.getloadavg()[0]:.2f}" if hasattr(os, "getloadavg") else ""))
    console.print(f"worst: {w['value']!r} ({w['components']} active component(s)); "
                  f"rse simulate worst.toml gives {w['replayed']!r}: {'reproduced exactly' if w['reproduced'] else 'NOT REPRODUCED'}")
    b = s["bound"]
    if b is not None:
        console.print(f"paper bound ({b['name']}): {b['value']:.6g}" + ("" if b["applies"] else
                      " (the estimator is outside the theorem's assumptions: shown for comparison)"))
    if s["threshold"] is not None:
        verdict = "held" if s["held"] else "VIOLATED"
        console.print(f"threshold {s['threshold']:.6g}: {verdict} (worst {w['value']:.6g})")
    if s["shrunk"] is not None:
        sh = s["shrunk"]
        console.print(f"shrunk: {sh['value']:.6g} with {sh['components']} active component(s) "
                      f"({sh['evaluations']} evaluations): {res.out / 'shrunk.toml'}")
        if sh["components"] == 0:
            console.print("the scenario exceeds the threshold without any attack: the violation is not the attack's")
    console.print(f"output: {res.out} (worst.toml, worst/, redteam.parquet, summary.json"
                  + (", redteam.png" if png else "") + ("" if no_rerun else ", recording.rrd") + ")")
    if not math.isfinite(w["value"]):
        console.print("the worst run diverged (the metric is not finite)")
