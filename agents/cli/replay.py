"""``rse replay``: a recorded ``rse run`` re-executed in-process from its delivery record."""

from __future__ import annotations

from pathlib import Path

import click

from .. import api
from .common import dashboard_options, handle_errors, rerun_options, sigterm_interrupts, wait_while_serving


@click.command()
@click.argument("run_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Run directory of the replay (default: RUN_DIR-replay).")
@click.option("--set", "overrides", multiple=True, metavar="KEY.PATH=VALUE",
              help="Override a key of the run's scenario (a counterfactual), e.g. --set estimator.variant=linear. "
                   "Repeatable.")
@click.option("--progress/--no-progress", default=True, show_default=True, help="Show a progress bar.")
@rerun_options
@handle_errors
def replay(run_dir: Path, out: Path | None, overrides: tuple[str, ...], progress: bool, rrd: Path | None,
           no_rerun: bool, viewer: bool, serve_web: bool, web_port: int | None, grpc_port: int | None) -> None:
    """Re-execute the run in RUN_DIR (written by `rse run`) in-process from its delivery
    record, and write a run directory (manifest.json, metrics.parquet, summary.json,
    estimates.npy, truth.npy, recording.rrd).

    Every agent steps at the rounds it stepped in the run, on the measurement and the
    inbox stamps it held; with the run's scenario the estimates equal the run's
    (--save-estimates) bit for bit. With --set (another estimator) the same deliveries
    feed the new estimators; compare with `rse report RUN_DIR REPLAY_DIR`. A run whose
    writer was killed replays up to its last complete round.
    """
    from ..console import expectations_table, round_progress, summary_table
    from ..console import out as console
    from ..replay_dir import check_run_dir, default_out

    sigterm_interrupts()
    check_run_dir(run_dir)  # bad input is one line, before the progress bar
    dest = out or default_out(run_dir)
    dopts = dashboard_options(dest, rrd, no_rerun, viewer, serve_web, web_port, grpc_port)
    if dopts is not None:
        for what, url in dopts.urls.items():
            console.print(f"rerun {what}: {url}")
    with round_progress(None, f"replay of {run_dir.name}", enabled=progress) as update:
        res = api.replay(run_dir, out=dest, set=list(overrides), rerun=dopts if dopts is not None else False,
                         progress=update)
    summary = res.summary()
    rep = summary["replay"]
    state = "complete" if rep["complete"] else f"incomplete: {summary.get('reason')}"
    console.print(summary_table(summary, title=f"replay of {run_dir}: rounds 0 to {rep['last_round']} ({state})"))
    if res.expectations():
        console.print(expectations_table(res.expectations()))
    console.print(f"run directory: {dest}")
    if dopts is not None and dopts.serve_web:
        wait_while_serving(dopts.urls.get("web", ""))
