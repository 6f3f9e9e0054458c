"""``rse bench``: benchmarks that print throughput figures (not timed tests)."""

from __future__ import annotations

import os
import platform
import statistics
import sys
import tempfile
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
              help="Also time the bare Zenoh lockstep skeletons (minimal, and the runtime's full pattern).")
@click.option("--agents-per-process", type=click.IntRange(min=1), default=1, show_default=True, metavar="N",
              help="Host N agents in each agent process (as rse run --agents-per-process).")
@click.option("--startup-timeout", type=click.FloatRange(min=0.1), default=60.0, show_default=True,
              help="Seconds to wait for the team to assemble.")
@handle_errors
def bench_run(scenario: Path, overrides: tuple[str, ...], seed: int | None, deadline: float, skeleton: bool,
              agents_per_process: int, startup_timeout: float) -> None:
    """Lockstep rounds/s of `rse run` on SCENARIO next to the bare Zenoh skeletons', the
    start-up time (this command to round 0), and peak RSS and USS per process."""
    from ..console import out as console
    from ..net.launcher import launch
    from ..net.protocol import RunConfig
    from ..net.startup import prestart

    t_cmd = _command_started()
    prestart()
    exp, frozen = load_experiment(scenario, overrides, seed)
    with tempfile.TemporaryDirectory(prefix="rse-bench-") as tmp:
        res = launch(scenario, overrides, seed, Path(tmp) / "run",
                     RunConfig(deadline=deadline, startup_timeout=startup_timeout), progress=False,
                     exp=exp, frozen=frozen, say=lambda m: None, agents_per_process=agents_per_process)
    if res.status != 0 or res.summary is None:
        raise RSEError("; ".join(res.failures) or "the benchmark run failed")
    perf = res.summary["performance"]
    procs = res.summary["processes"]
    rate = perf["rounds_per_s"]
    n_proc = -(-exp.N // agents_per_process) + 2
    console.print(f"scenario {exp.scenario.run.name}: {exp.N} agents, {perf['rounds']} rounds, n = {exp.n}, "
                  f"{n_proc} processes" + (f" ({agents_per_process} agents per process)" if agents_per_process > 1 else ""))
    console.print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
                  f"Python {platform.python_version()}, {platform.system()} {platform.release()}, "
                  f"load average {os.getloadavg()[0]:.1f}")
    if perf.get("round0_at"):
        console.print(f"start-up, this command to round 0: {perf['round0_at'] - t_cmd:6.2f} s  "
                      f"(targets: <= 4 s for mitra_cells.toml, 18 processes; <= 2 s for lee_kim_shim.toml, 7)")
    console.print(f"rse run lockstep:         {rate:8,.1f} rounds/s  ({rate * exp.N:,.0f} agent-rounds/s)")
    if skeleton:
        run_skeleton, sizes_for = _skeleton()
        sizes = sizes_for(exp)
        mini = run_skeleton(sizes, rounds=perf["rounds"], minimal=True)["rounds_per_s"]
        full = run_skeleton(sizes, rounds=perf["rounds"])["rounds_per_s"]
        console.print(f"minimal Zenoh skeleton:   {mini:8,.1f} rounds/s  (a clock tick, one estimate and one done "
                      f"per agent and round)")
        console.print(f"full-pattern skeleton:    {full:8,.1f} rounds/s  (the runtime's processes and messages)")
        console.print(f"runtime / minimal:        {rate / mini:8.0%}  (target >= 75%); runtime / full pattern "
                      f"{rate / full:.0%}")
    console.print(_memory_line(procs, agents_per_process))


def _command_started() -> float:
    """Wall-clock time this process started (the command), else now.

    On Linux from the process's start in clock ticks since boot (``/proc/self/stat``) and
    the boot-time clock, to 10 ms: psutil's ``create_time`` adds that start to the boot time
    of ``/proc/stat``, which is rounded down to a whole second, so it reads up to 1 s early
    (0.8 s on the machine where the start-up figures were taken)."""
    import time

    try:
        with open("/proc/self/stat") as f:
            ticks = int(f.read().rsplit(")", 1)[1].split()[19])  # field 22: starttime
        return time.time() - (time.clock_gettime(time.CLOCK_BOOTTIME) - ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError, AttributeError):  # not Linux
        pass
    try:
        import psutil

        return float(psutil.Process().create_time())
    except Exception:  # pragma: no cover
        return time.time()


def _skeleton():
    root = str(Path(__file__).resolve().parents[2])  # benchmarks/ lives next to agents/
    if root not in sys.path:
        sys.path.insert(0, root)
    try:
        from benchmarks.zenoh_skeleton import run_skeleton, sizes_for
    except ImportError:
        raise RSEError("the skeleton benchmark (benchmarks/zenoh_skeleton.py) is not available in this "
                       "installation; run from a source checkout or use --no-skeleton") from None
    return run_skeleton, sizes_for


def _memory_line(procs: dict, per_process: int = 1) -> str:
    """Peak RSS and USS (at the end of the run) of the agent, plant and monitor processes
    (with several agents per process, each agent reports its process's figures)."""
    def fig(recs: list[dict], key: str) -> str:
        vals = [r[key] for r in recs if isinstance(r.get(key), (int, float))]
        if not vals:
            return "n/a"
        return f"{max(vals):.0f}" if len(vals) == 1 else f"max {max(vals):.0f}, median {statistics.median(vals):.0f}"

    agents = [r for who, r in procs.items() if who.startswith("agent")]
    plant, monitor = [procs.get("plant", {})], [procs.get("monitor", {})]
    what = "agent processes" if per_process == 1 else f"agent processes ({per_process} agents each)"
    return (f"{what}: peak RSS {fig(agents, 'maxrss_mb')} MB, USS {fig(agents, 'uss_mb')} MB (target RSS <= 60 MB); "
            f"plant: RSS {fig(plant, 'maxrss_mb')} MB, USS {fig(plant, 'uss_mb')} MB (<= 60); "
            f"monitor: RSS {fig(monitor, 'maxrss_mb')} MB, USS {fig(monitor, 'uss_mb')} MB (<= 120)")
