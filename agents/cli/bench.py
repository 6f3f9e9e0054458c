"""``rse bench``: benchmarks that print throughput figures (not timed tests)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import click

from estimation.errors import RSEError

from .. import api
from .common import handle_errors, load_experiment, scenario_options


@click.group()
def bench() -> None:
    """Benchmarks that print throughput figures (not timed tests)."""


@bench.command("simulate")
@scenario_options
@click.option("--repeat", type=click.IntRange(1, 100), default=3, show_default=True, help="Timed runs (best and median are printed).")
@click.option("--rerun-overhead", is_flag=True, help="Also time the same runs streaming to a Rerun recording and print the overhead.")
@handle_errors
def bench_simulate(scenario: Path, overrides: tuple[str, ...], seed: int | None, repeat: int, rerun_overhead: bool) -> None:
    """Agent-rounds per second of the in-process simulator on SCENARIO (monitor included, no files written).

    With --rerun-overhead the runs alternate with and without the dashboard (writing a
    temporary .rrd) and the relative cost of the logging in the rounds is printed.
    """
    import platform
    import statistics
    import tempfile

    from ..console import out as console
    
    def once(with_rerun: bool) -> float:
        exp, _ = load_experiment(scenario, overrides, seed)  # fresh state every run
        if not with_rerun:
            return api.simulate(exp).sim.elapsed
        from ..dashboard import Dashboard, DashboardOptions

        with tempfile.TemporaryDirectory() as tmp:
            dash = Dashboard(exp, run_id="bench", options=DashboardOptions(rrd=Path(tmp) / "bench.rrd"))
            try:
                return api.simulate(exp, dashboard=dash).sim.elapsed
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


@bench.command("run")
@scenario_options
@click.option("--deadline", type=click.FloatRange(min=0.001), default=2.0, show_default=True, help="Lockstep deadline.")
@click.option("--skeleton/--no-skeleton", default=True, show_default=True,
              help="Also time the bare Zenoh lockstep skeleton (same processes and message sizes, no estimation).")
@handle_errors
def bench_run(scenario: Path, overrides: tuple[str, ...], seed: int | None, deadline: float, skeleton: bool) -> None:
    """Lockstep rounds/s of `rse run` on SCENARIO, next to the bare Zenoh skeleton's, and peak RSS per agent."""
    import os
    import platform
    import statistics
    import tempfile

    from ..console import out as console
    from ..net.launcher import launch
    from ..net.protocol import RunConfig

    exp, frozen = load_experiment(scenario, overrides, seed)
    with tempfile.TemporaryDirectory(prefix="rse-bench-") as tmp:
        res = launch(scenario, overrides, seed, Path(tmp) / "run", RunConfig(deadline=deadline), progress=False,
                     exp=exp, frozen=frozen, say=lambda m: None)
    if res.status != 0 or res.summary is None:
        raise RSEError("; ".join(res.failures) or "the benchmark run failed")
    perf = res.summary["performance"]
    rss = [rec.get("maxrss_mb", float("nan")) for who, rec in res.summary["processes"].items() if who.startswith("agent")]
    rate = perf["rounds_per_s"]
    console.print(f"scenario {exp.scenario.run.name}: {exp.N} agents, {perf['rounds']} rounds, n = {exp.n}, "
                  f"{exp.N + 2} processes")
    console.print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
                  f"Python {platform.python_version()}, {platform.system()} {platform.release()}")
    line = f"rse run lockstep:      {rate:10,.0f} rounds/s  ({rate * exp.N:,.0f} agent-rounds/s)"
    console.print(line)
    if skeleton:
        root = str(Path(__file__).resolve().parents[2])  # benchmarks/ lives next to agents/
        if root not in sys.path:
            sys.path.insert(0, root)
        try:
            from benchmarks.zenoh_skeleton import run_skeleton, sizes_for
        except ImportError:
            raise RSEError("the skeleton benchmark (benchmarks/zenoh_skeleton.py) is not available in this "
                           "installation; run from a source checkout or use --no-skeleton") from None

        sk = run_skeleton(sizes_for(exp), rounds=perf["rounds"])
        console.print(f"bare Zenoh skeleton:   {sk['rounds_per_s']:10,.0f} rounds/s  (same processes and message sizes)")
        console.print(f"runtime / skeleton:    {rate / sk['rounds_per_s']:10.0%}  (target >= 50%)")
    console.print(f"peak RSS per agent process: max {max(rss):.0f} MB, median {statistics.median(rss):.0f} MB "
                  f"(target <= 150 MB); plant {res.summary['processes'].get('plant', {}).get('maxrss_mb', float('nan')):.0f} MB, "
                  f"monitor {res.summary['processes']['monitor']['maxrss_mb']:.0f} MB")
