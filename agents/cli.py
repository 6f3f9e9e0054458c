"""The ``rse`` command line.

Exit status: 0 success; 1 a condition (``rse check``) or the run itself failed;
2 bad input (usage, scenario file, ``--set``); 3 the run finished but an ``[expect]``
bound of the scenario failed; 130 interrupted.
"""

from __future__ import annotations

import functools
import os
import sys
import uuid
from pathlib import Path
from typing import Any, Callable

# The runtime's linear algebra is many small products: a multi-threaded BLAS only adds
# contention (5-10x slower on a loaded 2-core machine). Users can still override it.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import click  # noqa: E402

from estimation.errors import ExpectationFailed, RSEError, ScenarioError  # noqa: E402

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT, EXIT_EXPECTATION, EXIT_INTERRUPTED = 0, 1, 2, 3, 130


def _handle_errors(fn: Callable) -> Callable:
    """Turn the runtime's own errors into a one-line message and an exit status."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        from .console import error

        try:
            return fn(*args, **kwargs)
        except ScenarioError as exc:
            error(str(exc))
            sys.exit(EXIT_BAD_INPUT)
        except ExpectationFailed as exc:
            error(str(exc))
            sys.exit(EXIT_EXPECTATION)
        except RSEError as exc:
            error(str(exc))
            sys.exit(EXIT_FAILED)
        except KeyboardInterrupt:
            error("interrupted")
            sys.exit(EXIT_INTERRUPTED)
        except OSError as exc:
            error(f"{exc.strerror or exc}: {exc.filename}" if getattr(exc, "filename", None) else str(exc))
            sys.exit(EXIT_FAILED)
        except Exception as exc:  # a bug: say so plainly, traceback only on request
            if os.environ.get("RSE_DEBUG"):
                raise
            error(f"internal error: {type(exc).__name__}: {exc} (set RSE_DEBUG=1 for the traceback)")
            sys.exit(EXIT_FAILED)

    return wrapper


def scenario_options(fn: Callable) -> Callable:
    """The flags every scenario-taking sub-command shares."""
    fn = click.option("--set", "overrides", multiple=True, metavar="KEY.PATH=VALUE",
                      help="Override any scenario key (TOML value), e.g. --set estimator.kappa=5. Repeatable.")(fn)
    fn = click.option("--seed", type=click.IntRange(min=0), default=None, help="Override run.seed.")(fn)
    fn = click.argument("scenario", type=click.Path(dir_okay=False, path_type=Path))(fn)
    return fn


def load_experiment(scenario: Path, overrides: tuple[str, ...], seed: int | None, *, check_conditions: bool = True):
    from scenarios.build import build
    from scenarios.loader import load

    ov = list(overrides) + ([f"run.seed={seed}"] if seed is not None else [])
    sc, frozen = load(scenario, ov)
    return build(sc, source=str(scenario), check_conditions=check_conditions), frozen


@click.group(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(package_name="resilient-state-estimation", prog_name="rse")
def cli() -> None:
    """Resilient distributed state estimation: simulate, run and check scenarios."""


def rerun_options(fn: Callable) -> Callable:
    """The Rerun sink flags every run command shares."""
    fn = click.option("--grpc-port", type=click.IntRange(1, 65535), default=None,
                      help="Port of the gRPC server the web viewer reads from (default 9876).")(fn)
    fn = click.option("--web-port", type=click.IntRange(1, 65535), default=None,
                      help="Port of the web viewer (default 9090).")(fn)
    fn = click.option("--serve-web", is_flag=True, help="Serve the web viewer so a browser (also on another machine) can watch live; the URL is printed.")(fn)
    fn = click.option("--viewer", is_flag=True, help="Spawn the native Rerun viewer (needs a display).")(fn)
    fn = click.option("--no-rerun", is_flag=True, help="No Rerun output at all (benchmarks).")(fn)
    fn = click.option("--rrd", type=click.Path(dir_okay=False, path_type=Path), default=None,
                      help="Recording file (default: recording.rrd in the run directory).")(fn)
    return fn


def dashboard_options(run_dir: Path, rrd: Path | None, no_rerun: bool, viewer: bool, serve_web: bool,
                      web_port: int | None, grpc_port: int | None):
    from .dashboard import DashboardOptions

    if no_rerun:
        if viewer or serve_web or rrd:
            raise ScenarioError("--no-rerun cannot be combined with --rrd, --viewer or --serve-web", source="command line")
        return None
    return DashboardOptions(rrd=rrd or run_dir / "recording.rrd", viewer=viewer, serve_web=serve_web,
                            web_port=web_port, grpc_port=grpc_port)


def wait_while_serving(url: str) -> None:
    """After a run with --serve-web: keep the viewer up until Ctrl-C / SIGTERM."""
    import signal
    import threading

    from .console import out as console

    done = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: done.set())
    console.print(f"the run is finished; still serving the recording at {url} (Ctrl-C to stop)")
    done.wait()


@cli.command()
@scenario_options
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Run directory (default: runs/NAME-TIMESTAMP).")
@click.option("--progress/--no-progress", default=True, show_default=True, help="Show a progress bar.")
@rerun_options
@_handle_errors
def simulate(scenario: Path, overrides: tuple[str, ...], seed: int | None, out: Path | None, progress: bool,
             rrd: Path | None, no_rerun: bool, viewer: bool, serve_web: bool, web_port: int | None,
             grpc_port: int | None) -> None:
    """Run SCENARIO in the in-process lockstep simulator and write a run directory.

    Writes manifest.json, design.json, metrics.parquet, summary.json and the Rerun
    recording recording.rrd, prints the summary table and each [expect] bound with its
    measured value.
    """
    from .console import expectations_table, out as console, round_progress, summary_table
    from .rundir import default_run_dir, write_design, write_json, write_manifest, write_metrics
    from .simulate import simulate as run_sim
    from .summary import evaluate, summarise

    exp, frozen = load_experiment(scenario, overrides, seed)
    run_dir = out or default_run_dir(exp.scenario.run.name)
    run_dir.mkdir(parents=True, exist_ok=True)
    run_id = uuid.uuid4().hex[:12]
    write_manifest(run_dir, exp, frozen, driver="simulate", run_id=run_id)
    write_design(run_dir, exp)
    dopts = dashboard_options(run_dir, rrd, no_rerun, viewer, serve_web, web_port, grpc_port)
    dash = None
    if dopts is not None:
        from .dashboard import Dashboard

        dash = Dashboard(exp, run_id=run_id, options=dopts)
        for what, url in dopts.urls.items():
            console.print(f"rerun {what}: {url}")
    try:
        with round_progress(exp.n_rounds + 1, exp.scenario.run.name, enabled=progress) as update:
            res = run_sim(exp, progress=update, dashboard=dash)
    except BaseException:
        if dash is not None:
            dash.close()
        raise
    if dash is not None:
        dash.flush()  # the recording file is complete; a served viewer stays up below
    results = evaluate(exp, res.monitor, res.regular)
    summary = summarise(exp, res.monitor, res.regular, res.links)
    summary["expectations"] = [r.as_dict() for r in results]
    summary["performance"] = {"elapsed_s": res.elapsed, "agent_rounds_per_s": res.agent_rounds_per_s}
    write_metrics(run_dir, exp, res.monitor, res.regular)
    write_json(run_dir / "summary.json", summary)
    console.print(summary_table(summary, title=f"{exp.scenario.run.name}: {res.rounds} rounds, window t in [{exp.window[0]:g}, {exp.window[1]:g}]"))
    if results:
        console.print(expectations_table(results))
    console.print(f"run directory: {run_dir}")
    failed = [r for r in results if not r.ok]
    if dash is not None:
        try:
            if dopts.serve_web:
                wait_while_serving(dopts.urls.get("web", ""))
        finally:
            dash.close()
    if failed:
        raise ExpectationFailed(f"{len(failed)} of {len(results)} expectation(s) failed: " + "; ".join(r.label for r in failed))


@cli.command()
@scenario_options
@_handle_errors
def check(scenario: Path, overrides: tuple[str, ...], seed: int | None) -> None:
    """Print the paper conditions for SCENARIO and whether they hold (exit 1 if one fails)."""
    from rich.table import Table

    from scenarios.build import conditions

    from .console import out as console

    exp, _ = load_experiment(scenario, overrides, seed, check_conditions=False)
    table = Table(title=f"{exp.scenario.run.name}: conditions", title_justify="left")
    table.add_column("")
    table.add_column("condition")
    table.add_column("value / detail")
    ok = True
    for c in conditions(exp):
        mark = "" if c.holds is None else ("[green]holds" if c.holds else "[red]FAILS")
        ok = ok and c.holds is not False
        table.add_row(mark, c.name, c.detail)
    console.print(table)
    sys.exit(EXIT_OK if ok else EXIT_FAILED)


@cli.group()
def bench() -> None:
    """Benchmarks that print throughput figures (not timed tests)."""


@bench.command("simulate")
@scenario_options
@click.option("--repeat", type=click.IntRange(1, 100), default=3, show_default=True, help="Timed runs (best and median are printed).")
@click.option("--rerun-overhead", is_flag=True, help="Also time the same runs streaming to a Rerun recording and print the overhead.")
@_handle_errors
def bench_simulate(scenario: Path, overrides: tuple[str, ...], seed: int | None, repeat: int, rerun_overhead: bool) -> None:
    """Agent-rounds per second of the in-process simulator on SCENARIO (monitor included, no files written).

    With --rerun-overhead the runs alternate with and without the dashboard (writing a
    temporary .rrd) and the relative cost of the logging in the rounds is printed.
    """
    import platform
    import statistics
    import tempfile

    from .console import out as console
    from .simulate import simulate as run_sim

    def once(with_rerun: bool) -> float:
        exp, _ = load_experiment(scenario, overrides, seed)  # fresh state every run
        if not with_rerun:
            return run_sim(exp).elapsed
        from .dashboard import Dashboard, DashboardOptions

        with tempfile.TemporaryDirectory() as tmp:
            dash = Dashboard(exp, run_id="bench", options=DashboardOptions(rrd=Path(tmp) / "bench.rrd"))
            try:
                return run_sim(exp, dashboard=dash).elapsed
            finally:
                dash.close()

    once(False)  # warm-up (imports, caches)
    if rerun_overhead:
        once(True)
    plain, logged = [], []
    for _ in range(repeat):
        plain.append(once(False))
        if rerun_overhead:
            logged.append(once(True))
    exp, _ = load_experiment(scenario, overrides, seed)
    work = exp.N * (exp.n_rounds + 1)
    rates = [work / t for t in plain]
    console.print(f"scenario {exp.scenario.run.name}: {exp.N} agents, {exp.n_rounds + 1} rounds, n = {exp.n}")
    console.print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}")
    console.print(f"simulator agent-rounds/s: median {statistics.median(rates):,.0f}, best {max(rates):,.0f} over {repeat} runs")
    if rerun_overhead:
        ratio = [l / p for l, p in zip(logged, plain)]
        console.print(f"with the Rerun dashboard: median {statistics.median([work / t for t in logged]):,.0f} agent-rounds/s; "
                      f"logging overhead in the rounds: median {100 * (statistics.median(ratio) - 1):.1f}% "
                      f"(min {100 * (min(ratio) - 1):.1f}%, max {100 * (max(ratio) - 1):.1f}%)")


def main() -> None:
    cli(prog_name="rse")


if __name__ == "__main__":
    main()

from . import cli_net  # noqa: E402,F401
from . import cli_report  # noqa: E402,F401
from . import cli_sweep  # noqa: E402,F401
from . import cli_deploy  # noqa: E402,F401
from . import cli_compose  # noqa: E402,F401
