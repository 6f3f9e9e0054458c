"""``rse bench``: benchmarks that print throughput figures (not timed tests)."""

from __future__ import annotations

import os
import platform
import statistics
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
@click.option("--repeat", type=click.IntRange(1, 50), default=1, show_default=True, metavar="N",
              help="Run the team (and the skeletons right after it) N times, interleaved; each ratio is taken "
                   "within one repetition and the median is printed: on a small shared machine single "
                   "figures scatter.")
@click.option("--agents-per-process", type=click.IntRange(min=1), default=1, show_default=True, metavar="N",
              help="Host N agents in each agent process (as rse run --agents-per-process).")
@click.option("--startup-timeout", type=click.FloatRange(min=0.1), default=60.0, show_default=True,
              help="Seconds to wait for the team to assemble.")
@click.option("--secure", type=click.Path(file_okay=False, path_type=Path), default=None, metavar="DIR",
              help="Also run the team as secure peers (rse run --secure DIR: mutual TLS, each peer's access "
                   "control) right after each plain run, and print its rounds/s, start-up and ratio to plain.")
@handle_errors
def bench_run(scenario: Path, overrides: tuple[str, ...], seed: int | None, deadline: float, skeleton: bool,
              repeat: int, agents_per_process: int, startup_timeout: float, secure: Path | None) -> None:
    """Lockstep rounds/s of `rse run` on SCENARIO next to the bare Zenoh skeletons', the
    start-up time (this command to round 0), and peak RSS and USS per process.

    With --repeat N the runtime and the skeletons run N times in turn (runtime, minimal,
    full pattern); a line per repetition, then the medians and the median of the ratios.
    With --secure DIR each repetition also runs the team as secure peers, right after the
    plain one: secure / plain is taken within the repetition.
    """
    import time

    from transport.event_loop import loop_name

    from ..console import out as console
    from ..net.startup import prestart

    t_cmd = _command_started()
    prestart()
    # built once: launch gives every run fresh nodes, channel and slices from it
    exp, _ = load_experiment(scenario, overrides, seed)
    n_proc = -(-exp.N // agents_per_process) + 2
    sizes = run_skeleton = None
    if skeleton:
        run_skeleton, sizes_for = _skeleton()
        sizes = sizes_for(exp)
    rows: list[tuple[float, float | None, float | None]] = []
    secured: list[tuple[float, float]] = []
    procs: dict = {}
    for rep in range(repeat):
        t_launch = t_cmd if rep == 0 else time.time()
        with tempfile.TemporaryDirectory(prefix="rse-bench-") as tmp:
            summary = api.run_team(exp, out=Path(tmp) / "run", deadline=deadline, startup_timeout=startup_timeout,
                                   agents_per_process=agents_per_process).summary()
        perf = summary["performance"]
        rate = perf["rounds_per_s"]
        if rep == 0:
            procs = summary["processes"]
            console.print(f"scenario {exp.scenario.run.name}: {exp.N} agents, {perf['rounds']} rounds, n = {exp.n}, "
                          f"{n_proc} processes" + (f" ({agents_per_process} agents per process)"
                                                   if agents_per_process > 1 else ""))
            console.print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
                          f"Python {platform.python_version()}, {platform.system()} {platform.release()}, "
                          f"load average {os.getloadavg()[0]:.1f}, event loop {loop_name()}")
        mini = full = None
        if run_skeleton is not None:
            mini = run_skeleton(sizes, rounds=perf["rounds"], minimal=True)["rounds_per_s"]
            full = run_skeleton(sizes, rounds=perf["rounds"])["rounds_per_s"]
        rows.append((rate, mini, full))
        start = f"{perf['round0_at'] - t_launch:.2f} s" if perf.get("round0_at") else "n/a"
        if repeat == 1:
            _print_one(console, start, exp.N, rate, mini, full)
        else:
            console.print(f"run {rep + 1} of {repeat}: start-up {start} "
                          f"({'this command' if rep == 0 else 'the launch'} to round 0), "
                          f"rse run {rate:,.1f} rounds/s"
                          + (f", minimal skeleton {mini:,.1f}, full pattern {full:,.1f}, runtime / minimal "
                             f"{rate / mini:.0%}, / full pattern {rate / full:.0%}" if mini and full else ""))
        if secure is not None:
            secured.append(_secure_run(console, exp, secure, deadline,
                                       startup_timeout, rate, rep, repeat))
    if repeat > 1:
        med = statistics.median
        console.print(f"median over {repeat} runs: rse run {med(r[0] for r in rows):,.1f} rounds/s "
                      f"(min {min(r[0] for r in rows):,.1f}, max {max(r[0] for r in rows):,.1f})")
        if run_skeleton is not None:
            minis = [r[1] for r in rows if r[1]]
            fulls = [r[2] for r in rows if r[2]]
            ratios = [r[0] / r[1] for r in rows if r[1]]
            console.print(f"minimal Zenoh skeleton:   median {med(minis):,.1f} rounds/s (min {min(minis):,.1f}, "
                          f"max {max(minis):,.1f}); full pattern median {med(fulls):,.1f}")
            console.print(f"runtime / minimal:        median {med(ratios):.0%} of {len(ratios)} "
                          f"({', '.join(f'{x:.0%}' for x in ratios)}; target >= 75%)")
    if len(secured) > 1:
        med = statistics.median
        console.print(f"secure peers, median over {len(secured)} runs: {med(r[0] for r in secured):,.1f} rounds/s, "
                      f"secure / plain {med(r[1] for r in secured):.0%} ({', '.join(f'{r[1]:.0%}' for r in secured)}; "
                      f"target >= 70%)")
    console.print(_memory_line(procs, agents_per_process))


def _secure_run(console, exp, secure: Path, deadline: float, startup_timeout: float, plain: float, rep: int,
                repeat: int) -> tuple[float, float]:
    """One lockstep run of the team as secure peers; prints its line, returns (rounds/s, secure / plain)."""
    import time


    t0 = time.time()
    with tempfile.TemporaryDirectory(prefix="rse-bench-") as tmp:
        try:
            summary = api.run_team(exp, out=Path(tmp) / "run", deadline=deadline, startup_timeout=startup_timeout,
                                   secure=secure).summary()
        except RSEError as exc:
            raise RSEError(f"secure run: {exc}") from None
    perf = summary["performance"]
    rate = perf["rounds_per_s"]
    start = f"{perf['round0_at'] - t0:.2f} s" if perf.get("round0_at") else "n/a"
    console.print(f"{'secure peers' if repeat == 1 else f'run {rep + 1} of {repeat}, secure peers'}: "
                  f"{rate:8,.1f} rounds/s, {rate / plain:.0%} of plain (target >= 70%); start-up, the launch to "
                  f"round 0: {start} (target <= 4 s)")
    return rate, rate / plain


def _print_one(console, start: str, N: int, rate: float, mini: float | None, full: float | None) -> None:
    console.print(f"start-up, this command to round 0: {start:>7}  "
                  f"(targets: <= 4 s for mitra_cells.toml, 18 processes; <= 2 s for lee_kim_shim.toml, 7)")
    console.print(f"rse run lockstep:         {rate:8,.1f} rounds/s  ({rate * N:,.0f} agent-rounds/s)")
    if mini and full:
        console.print(f"minimal Zenoh skeleton:   {mini:8,.1f} rounds/s  (a clock tick, one estimate and one done "
                      f"per agent and round; Zenoh's default threads, callbacks)")
        console.print(f"full-pattern skeleton:    {full:8,.1f} rounds/s  (the runtime's processes and messages)")
        console.print(f"runtime / minimal:        {rate / mini:8.0%}  (target >= 75%); runtime / full pattern "
                      f"{rate / full:.0%}")


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
    from agents.net.skeleton import run_skeleton, sizes_for

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
    io = [r.get("zenoh_io_threads") for r in [*agents, *plant, *monitor]]
    zenoh = ("Zenoh's work on one thread; ZENOH_RUNTIME='()' for its own" if io and all(n == 0 for n in io)
             else "Zenoh's own threads (ZENOH_RUNTIME)")
    return (f"{what}: peak RSS {fig(agents, 'maxrss_mb')} MB, USS {fig(agents, 'uss_mb')} MB (target RSS <= 60 MB); "
            f"plant: RSS {fig(plant, 'maxrss_mb')} MB, USS {fig(plant, 'uss_mb')} MB (<= 60); "
            f"monitor: RSS {fig(monitor, 'maxrss_mb')} MB, USS {fig(monitor, 'uss_mb')} MB (<= 120)\n"
            f"threads per process: agents {fig(agents, 'threads')}, plant {fig(plant, 'threads')}, "
            f"monitor {fig(monitor, 'threads')} ({zenoh})")
