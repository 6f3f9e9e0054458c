"""``rse chaos``: a seeded schedule of faults against a realtime team (docs/chaos.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from .common import EXIT_INTERRUPTED, handle_errors


@click.command()
@click.argument("scenario", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--duration", type=click.FloatRange(min=1.0), required=True, metavar="S",
              help="Wall-clock seconds of the soak (split into teams in turn where the plant outgrows float64).")
@click.option("--faults", default=None, metavar="LIST",
              help="Fault kinds, comma-separated: kill-agent, kill-monitor, freeze-agent, cut-link, cpu-hog (default: all).")
@click.option("--seed", type=click.IntRange(min=0), default=1, show_default=True, help="Seed of the schedule.")
@click.option("--rate", type=click.FloatRange(min=0.001), default=None, metavar="HZ",
              help="The plant's tick rate (default: 1 / run.dt).")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Run directory (default: runs/chaos-NAME-TIMESTAMP).")
@click.option("--set", "overrides", multiple=True, metavar="KEY.PATH=VALUE", help="Override a scenario key.")
@click.option("--spacing", type=click.FloatRange(min=1.0), default=None, metavar="S",
              help="Seconds between two faults (default: the largest in [6, 10] with every kind 5 times).")
@click.option("--settle", type=click.FloatRange(min=0.0), default=None, metavar="S",
              help="Seconds after round 0 before the first fault (default: 1.5 x the simulated team's time "
                   "to get inside the bound for good, at least 5).")
@click.option("--budget", "budgets", multiple=True, metavar="KIND=S",
              help="Seconds after a fault's end within which it must be recovered (repeatable; defaults in docs/chaos.md).")
@click.option("--hogs", type=click.IntRange(1, 64), default=2, show_default=True, help="CPU hog processes per burst.")
@click.option("--threshold", type=click.FloatRange(min=0.0, min_open=True), default=None, metavar="T",
              help="The error bound of a recovered agent (default: the scenario's steady-state [[expect]] bound).")
@click.option("--metric", type=click.Choice(["error_2", "error_inf", "relative_error_2"]), default=None,
              help="The metric --threshold bounds (default error_inf).")
@click.option("--warmup", type=click.FloatRange(min=0.0), default=3.0, show_default=True,
              help="Scenario seconds a restarted agent listens before it publishes.")
@click.option("--no-rerun", is_flag=True, help="No Rerun recording.")
@handle_errors
def chaos(scenario: Path, duration: float, faults: str | None, seed: int, rate: float | None, out: Path | None,
          overrides: tuple[str, ...], spacing: float | None, settle: float | None, budgets: tuple[str, ...], hogs: int,
          threshold: float | None, metric: str | None, warmup: float, no_rerun: bool) -> None:
    """Run SCENARIO as a realtime team for --duration seconds under a seeded schedule of faults.

    Kills and restarts agents and the monitor, freezes agents (SIGSTOP, SIGCONT), cuts links
    between two agents, runs CPU hogs; writes OUT/chaos.json (schedule and seed),
    OUT/chaos.parquet (per fault: when, noticed, recovered, rounds unrecorded) and chaos.rrd
    (the faults on the dashboard's timeline), and prints the table. Exit 1 when a fault is
    not recovered within its budget, 130 when interrupted.
    """
    import sys

    from ..api import chaos as run
    from ..console import err

    def say(line: str) -> None:
        err.print(line, soft_wrap=True, markup=False, highlight=False)

    res = run(scenario, duration=duration, faults=faults, seed=seed, rate=rate, out=out, set=overrides,
              spacing=spacing, settle=settle, budgets=budgets, hogs=hogs, threshold=threshold, metric=metric,
              warmup=warmup, rerun=not no_rerun, say=say)
    _print(res)
    if res.status == EXIT_INTERRUPTED:
        raise KeyboardInterrupt
    sys.exit(res.status)


HEAD = f"{'#':>3}  {'fault':<12}  {'target':<12}  {'at s':>7}  {'lasts s':>7}  {'noticed s':>9}  " \
       f"{'rejoined s':>10}  {'recovered s':>11}  {'budget s':>8}  {'unrecorded':>10}"


def table_lines(res: Any) -> list[str]:
    """The printed table: one line per fault (times in seconds after round 0 of its team)."""
    from ..chaos.measure import fmt_s

    lines = [f"chaos: {len(res.rows)} fault(s); recovered: {res.bound.metric} <= {res.bound.limit:g} "
             f"({res.bound.source})" + ("; at: TEAM/SECONDS" if len(res.episodes) > 1 else ""), HEAD]
    for r in res.rows:
        at = f"{r['at_s']:.1f}" if len(res.episodes) < 2 else f"{r['episode'] + 1}/{r['at_s']:05.1f}"
        lines.append(f"{r['fault']:>3}  {r['kind']:<12}  {r['target']:<12}  {at:>7}  {r['lasts_s']:>7.1f}  "
                     f"{fmt_s(r['noticed_s']):>9}  {fmt_s(r.get('rejoined_s')):>10}  {fmt_s(r['recovered_s']):>11}  {r['budget_s']:>8g}  "
                     f"{r['rounds_unrecorded']:>10}  {'ok' if r['recovered'] else 'FAIL'}")
    lines.append(f"{sum(r['recovered'] for r in res.rows)} of {len(res.rows)} fault(s) recovered within budget; "
                 f"{res.undeclared} round(s) with a missing report outside the faults; {res.out / 'chaos.parquet'}")
    return lines


def _print(res: Any) -> None:
    from ..console import error
    from ..console import out as console

    for line in table_lines(res):
        console.print(line, soft_wrap=True, markup=False, highlight=False)
    for f in res.failures:
        error(f)
