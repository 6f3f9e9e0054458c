"""``rse simulate`` and ``rse check``: the in-process simulator and the paper's conditions."""

from __future__ import annotations

import contextlib
import sys
import uuid
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from agents.net.exits import EXIT_FAILED, EXIT_OK
from estimation.errors import ExpectationFailed, ScenarioError

from .. import api
from .common import (
    dashboard_options,
    handle_errors,
    load_experiment,
    rerun_options,
    scenario_options,
    sigterm_interrupts,
    wait_while_serving,
    warn_threat_model,
)

if TYPE_CHECKING:
    from scenarios.build import Experiment


@click.command()
@scenario_options
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Run directory (default: runs/NAME-TIMESTAMP).")
@click.option("--progress/--no-progress", default=True, show_default=True, help="Show a progress bar.")
@click.option("--sign", type=click.Path(file_okay=False, path_type=Path), default=None, metavar="DIR",
              help="Sign every message with the agents' keys of `rse certs DIR`, compare digests one round later "
                   "and write the proof of each equivocation to evidence.jsonl.")
@click.option("--ignore-convicted", is_flag=True, help="With --sign: receivers drop a convicted sender's messages.")
@rerun_options
@handle_errors
def simulate(scenario: Path, overrides: tuple[str, ...], seed: int | None, out: Path | None, progress: bool,
             sign: Path | None, ignore_convicted: bool, rrd: Path | None, no_rerun: bool, viewer: bool,
             serve_web: bool, web_port: int | None, grpc_port: int | None) -> None:
    """Run SCENARIO in the in-process lockstep simulator and write a run directory.

    Writes manifest.json, design.json, metrics.parquet, summary.json and the Rerun
    recording recording.rrd, prints the summary table and each [expect] bound with its
    measured value.
    """
    from ..console import expectations_table, round_progress, summary_table
    from ..console import out as console
    from ..rundir import default_run_dir

    sigterm_interrupts()
    exp, _ = load_experiment(scenario, overrides, seed)
    warn_threat_model(exp)
    run_dir = out or default_run_dir(exp.scenario.run.name)
    run_id = uuid.uuid4().hex[:12]
    watch = _watch(exp, sign, run_id, ignore_convicted)
    dopts = dashboard_options(run_dir, rrd, no_rerun, viewer, serve_web, web_port, grpc_port)

    bar = contextlib.ExitStack()

    def report(res: api.RunResult) -> None:
        """The console's part, once the run directory is written (a served viewer still up)."""
        bar.close()  # the progress bar ends before the tables
        title = f"{exp.scenario.run.name}: {res.sim.rounds} rounds, window t in [{exp.window[0]:g}, {exp.window[1]:g}]"
        console.print(summary_table(res.summary(), title=title))
        if res.expectations():
            console.print(expectations_table(res.expectations()))
        if watch is not None:
            console.print(convicted_line(res.summary().get("evidence", {}), run_dir))
        console.print(f"run directory: {run_dir}")
        if dopts is not None and dopts.serve_web:
            wait_while_serving(dopts.urls.get("web", ""))

    with bar:
        bar_update = bar.enter_context(round_progress(exp.n_rounds + 1, exp.scenario.run.name, enabled=progress))
        urls_shown = False

        def update(k: int, worst: float) -> None:
            nonlocal urls_shown
            if not urls_shown and dopts is not None:  # round 0: the dashboard is open, its servers known
                urls_shown = True
                for what, url in dopts.urls.items():
                    console.print(f"rerun {what}: {url}", soft_wrap=True)
            bar_update(k, worst)

        res = api.simulate(exp, progress=update, dashboard=dopts, out=run_dir, on_done=report, run_id=run_id,
                           evidence=watch)
    failed = [r for r in res.expectations() if r.failed]
    if failed:
        raise ExpectationFailed(f"{len(failed)} of {len(res.expectations())} expectation(s) failed: "
                                + "; ".join(r.label for r in failed))


def _watch(exp: Experiment, sign: Path | None, run_id: str, ignore_convicted: bool) -> Any:
    if sign is None:
        if ignore_convicted:
            raise ScenarioError("--ignore-convicted needs --sign DIR")
        return None
    from ..evidence import watch_for

    try:
        return watch_for(exp, sign, run_id, ignore_convicted=ignore_convicted)
    except ValueError as exc:
        raise ScenarioError(f"--sign: {exc}") from None


def convicted_line(evidence: dict[str, Any], run_dir: Path) -> str:
    """``convicted: agent 5 (round 21); evidence in RUN_DIR/evidence.jsonl`` (or nobody)."""
    conv = evidence.get("convicted") or {}
    if not conv:
        return "convicted: nobody (no two receivers were told different signed values)"
    who = ", ".join(f"agent {a} (round {k})" for a, k in conv.items())
    return f"convicted: {who}; evidence in {run_dir / 'evidence.jsonl'}"


@click.command()
@scenario_options
@handle_errors
def check(scenario: Path, overrides: tuple[str, ...], seed: int | None) -> None:
    """Print the paper conditions for SCENARIO and whether they hold (exit 1 if one fails)."""
    from rich.table import Table

    from ..console import out as console

    exp = api.load(scenario, set=list(overrides), seed=seed, check_conditions=False)
    table = Table(title=f"{exp.scenario.run.name}: conditions", title_justify="left")
    table.add_column("")
    table.add_column("condition")
    table.add_column("value / detail")
    ok = True
    for c in api.check(exp):
        mark = "" if c.holds is None else ("[green]holds" if c.holds else "[red]FAILS")
        ok = ok and c.holds is not False
        table.add_row(mark, c.name, c.detail)
    console.print(table)
    warn_threat_model(exp)
    sys.exit(EXIT_OK if ok else EXIT_FAILED)
