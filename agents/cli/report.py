"""``rse report``: summary table, figures and comparisons of run directories."""

from __future__ import annotations

from pathlib import Path

import click

from .common import handle_errors


@click.command()
@click.argument("run_dir", type=click.Path(path_type=Path))
@click.argument("other", type=click.Path(path_type=Path), required=False)
@click.option("--png", "png_dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Write static figures (errors.png, state_NAME.png, compare.png) into this directory (needs the plot extra).")
@handle_errors
def report(run_dir: Path, other: Path | None, png_dir: Path | None) -> None:
    """Print the summary table of RUN_DIR (and compare it with OTHER when given).

    The table lists, per agent and state block, the final error, the worst error in the
    output window, the convergence round, detected attacks and the in-link counters, then
    the scenario's [expect] bounds (ok, FAIL, or not evaluated with the reason). It is
    read from the run directory only, so runs of `rse simulate` and `rse run` report alike.

    RUN_DIR may also be a sweep directory (`rse sweep`) or a boundary search directory
    (`rse boundary`): then the sweep's table is printed, one row per grid point (runs, the
    median and maximum over seeds of the worst regular agent's errors).
    """
    from ..console import expectations_table, health_table, out
    from ..health import rate_line
    from ..report import boundary_lines, compare_table, figure_compare, figure_errors, figure_states, is_sweep_dir, load_run, report_table, sweep_table
    from ..summary import ExpectationResult

    def show(run) -> None:
        out.print(report_table(run))
        results = [ExpectationResult.from_dict(e) for e in run.summary.get("expectations", [])]
        if results:
            out.print(expectations_table(results))
        health = health_table(run.summary) if (run.summary.get("health") or {}).get("mode") == "realtime" else None
        if health is not None:
            out.print(health)
        line = rate_line(run.summary)
        if line:
            out.print(line)

    if is_sweep_dir(run_dir):
        if other is not None or png_dir is not None:
            raise click.UsageError("a sweep directory takes no OTHER run and no --png (see sweep.png)")
        out.print(sweep_table(run_dir))
        for line in boundary_lines(run_dir):
            out.print(line)
        return
    a = load_run(run_dir)
    show(a)
    b = load_run(other) if other is not None else None
    if b is not None:
        show(b)
        out.print(compare_table(a, b))
    if png_dir is not None:
        png_dir.mkdir(parents=True, exist_ok=True)
        paths = [figure_errors(a, png_dir), *figure_states(a, png_dir)]
        if b is not None:
            paths.append(figure_compare(a, b, png_dir))
        for p in paths:
            out.print(f"figure: {p}")
