"""``python -m benchmarks``: run the benchmark suite, print one table, write the figures as JSON.

Usage::

    python -m benchmarks [--quick] [--only simulate,run,memory,sweep] [--json FILE] [--compare OLD.json]
    python -m benchmarks --load NEW.json [--compare OLD.json]     # print saved figures, no run
    python -m benchmarks --load benchmarks/results.json --markdown docs/benchmarks.md   # the docs page

Run it from a source checkout on a quiet machine (every other process slows the
figures down; the load average at the start and the end is in the JSON). ``--quick`` is
the smoke size of the tests (16 agents, 2 agent processes, a tiny sweep: a few seconds).

Exit status: 0 success; 1 a benchmark failed (the others' figures are still printed and
written); 2 bad input (options, a ``--compare`` / ``--load`` file); 130 interrupted.
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import click
from rich.console import Console

from agents.api import pin_blas_threads
from agents.net.exits import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_INTERRUPTED

from .report import BenchmarkError, Figure, git_info, machine_info, read_document, result_document, table, write_document

# As the rse command does: one BLAS thread per process (tiny matrices, many processes); numpy
# is not imported yet (agents.api and estimation.errors import nothing heavy).
pin_blas_threads()

SECTIONS = ("simulate", "run", "memory", "sweep")

out = Console(highlight=False)
err = Console(stderr=True, highlight=False)


@dataclass(frozen=True)
class Plan:
    """Sizes of one suite run.

    Parameters
    ----------
    sim : simulator team size (agents) -> (``run.rounds``, timed runs; the best is kept)
    run_processes : agent process counts of ``rse run`` (keys of :data:`benchmarks.run_bench.TEAMS`)
    run_rounds : ``run.rounds`` of each ``rse run`` (and the skeleton's rounds)
    sweep_drop_ps, sweep_seeds, sweep_rounds, sweep_jobs : the sweep's grid, seeds per
        point, ``run.rounds`` and worker processes
    sweep_dask : also measure the sweep on a Dask ``LocalCluster`` (when the ``cluster``
        extra is installed; its start alone takes seconds, so not in the smoke plan)
    scenario_repeats : timed runs of each paper scenario (1: their short ``--quick`` form)
    scenarios : which paper scenarios (None: all; ``--quick`` runs Lee-Kim-Shim only, the
        others' designs take seconds to load)
    """

    sim: dict[int, tuple[int, int]]
    run_processes: tuple[int, ...]
    run_rounds: int
    sweep_drop_ps: tuple[float, ...]
    sweep_seeds: int
    sweep_rounds: int
    sweep_jobs: int = field(default_factory=lambda: os.cpu_count() or 1)
    sweep_dask: bool = True
    #: timed runs of each paper scenario (benchmarks/scenario_bench.py; 1: the short --quick runs)
    scenario_repeats: int = 3
    #: the paper scenarios measured (None: every one of scenario_bench.PAPER)
    scenarios: tuple[str, ...] | None = None

    def settings(self) -> dict[str, Any]:
        return {"sim_rounds": {str(k): v[0] for k, v in self.sim.items()},
                "sim_repeats": {str(k): v[1] for k, v in self.sim.items()},
                "run_processes": list(self.run_processes), "run_rounds": self.run_rounds,
                "sweep_drop_ps": list(self.sweep_drop_ps), "sweep_seeds": self.sweep_seeds,
                "sweep_rounds": self.sweep_rounds, "sweep_jobs": self.sweep_jobs, "sweep_dask": self.sweep_dask,
                "scenario_repeats": self.scenario_repeats,
                "scenarios": list(self.scenarios) if self.scenarios is not None else None}

    def limited(self, max_agents: int | None) -> "Plan":
        """This plan without the simulator teams and ``rse run`` teams larger than ``max_agents``."""
        if max_agents is None:
            return self
        return replace(self, sim={k: v for k, v in self.sim.items() if k <= max_agents},
                       run_processes=tuple(p for p in self.run_processes if p <= max_agents))


FULL = Plan(sim={16: (200, 5), 64: (100, 3), 256: (40, 3), 1024: (20, 2)}, run_processes=(2, 4, 8, 16, 32),
            run_rounds=300, sweep_drop_ps=(0.1, 0.2, 0.3, 0.4), sweep_seeds=2, sweep_rounds=100)
QUICK = Plan(sim={16: (10, 2)}, run_processes=(2,), run_rounds=20, sweep_drop_ps=(0.1, 0.3), sweep_seeds=1,
             sweep_rounds=10, sweep_jobs=1, sweep_dask=False, scenario_repeats=1, scenarios=("lee_kim_shim",))


@dataclass
class Step:
    section: str
    label: str
    run: Callable[[], list[Figure]]


def steps(plan: Plan, sections: list[str]) -> list[Step]:
    """The measurements of ``sections`` under ``plan``, in the order they run."""
    from . import run_bench, sim_bench, sweep_bench

    todo: list[Step] = []
    want_sim, want_mem = "simulate" in sections, "memory" in sections
    if want_sim or want_mem:
        ref: dict[str, float] = {}

        def sim_step(agents: int, rounds: int, repeats: int) -> Callable[[], list[Figure]]:
            def go() -> list[Figure]:
                m = sim_bench.measure_team_fresh(agents, rounds, repeats)
                figs: list[Figure] = []
                if want_sim:
                    figs += sim_bench.simulate_figures(m, repeats, ref.get("ns"))
                    if agents == 16:
                        ref["ns"] = next(f.value for f in figs if f.name == "ns_per_fused_value")
                if want_mem:
                    figs += sim_bench.memory_figures(m)
                return figs
            return go

        name = "simulate" if want_sim else "memory"
        for agents, (rounds, repeats) in sorted(plan.sim.items()):
            repeats = repeats if want_sim else 0
            todo.append(Step(name, f"{name}: simulator, {agents} agents, {max(1, repeats)} x {rounds + 1} rounds",
                             sim_step(agents, rounds, repeats)))
    if want_sim:
        from . import scenario_bench

        for stem, full, short in scenario_bench.PAPER:
            if plan.scenarios is not None and stem not in plan.scenarios:
                continue
            ov = short if plan.scenario_repeats <= 1 else full
            todo.append(Step("simulate", f"simulate: {stem}, {plan.scenario_repeats} run(s)",
                             lambda stem=stem, ov=ov: scenario_bench.scenario_figures(
                                 scenario_bench.measure_scenario(stem, ov, plan.scenario_repeats))))
    if "run" in sections:
        for procs in plan.run_processes:
            todo.append(Step("run", f"run: rse run and Zenoh skeleton, {procs} agent processes, {plan.run_rounds} rounds",
                             lambda procs=procs: run_bench.run_figures(run_bench.measure_run(procs, plan.run_rounds))))
    if "sweep" in sections:
        runs = len(plan.sweep_drop_ps) * plan.sweep_seeds
        sweep_pool: dict[str, Any] = {}

        def pool_step() -> list[Figure]:
            sweep_pool.update(sweep_bench.measure_sweep(list(plan.sweep_drop_ps), plan.sweep_seeds, plan.sweep_rounds,
                                                        plan.sweep_jobs))
            return sweep_bench.sweep_figures(sweep_pool)

        todo.append(Step("sweep", f"sweep: {runs} runs, {plan.sweep_jobs} worker process(es)", pool_step))
        if plan.sweep_dask and _have_dask():
            todo.append(Step("sweep", f"sweep: {runs} runs, Dask LocalCluster of {plan.sweep_jobs} worker(s)",
                             lambda: sweep_bench.sweep_figures(sweep_bench.measure_sweep(
                                 list(plan.sweep_drop_ps), plan.sweep_seeds, plan.sweep_rounds, plan.sweep_jobs,
                                 cluster="local"), sweep_pool or None)))
    return todo


def _have_dask() -> bool:
    """Dask distributed is installed (the ``cluster`` extra): the sweep is also measured on it."""
    import importlib.util

    return importlib.util.find_spec("distributed") is not None


#: the table's order of the sections
DISPLAY_ORDER = ("simulate", "memory", "run", "sweep")


def order_figures(figs: list[Figure]) -> list[Figure]:
    """Sections in :data:`DISPLAY_ORDER`, measurement order within a section."""
    return sorted(figs, key=lambda f: DISPLAY_ORDER.index(f.section))


def run_suite(plan: Plan, sections: list[str], *, progress: bool = True
              ) -> tuple[list[Figure], list[str], list[dict[str, Any]]]:
    """Run every step; returns the figures, one message per failed step and each step's wall time."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    todo = steps(plan, sections)
    figs: list[Figure] = []
    errors: list[str] = []
    timings: list[dict[str, Any]] = []
    bar = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                   console=err, disable=not progress)
    with bar:
        task = bar.add_task("benchmarks", total=len(todo))
        for step in todo:
            bar.update(task, description=step.label)
            t0 = time.perf_counter()
            try:
                figs += step.run()
            except BenchmarkError as exc:
                errors.append(f"{step.section}: {exc}")
            except Exception as exc:  # a failed step must not lose the others' figures
                if os.environ.get("RSE_DEBUG"):
                    raise
                errors.append(f"{step.section}: {step.label}: {type(exc).__name__}: {exc}")
            timings.append({"step": step.label, "elapsed_s": round(time.perf_counter() - t0, 3)})
            bar.advance(task)
        bar.update(task, description="benchmarks done")
    return order_figures(figs), errors, timings


def parse_sections(value: str | None) -> list[str]:
    if not value:
        return list(SECTIONS)
    names = [v.strip() for v in value.split(",") if v.strip()]
    bad = [v for v in names if v not in SECTIONS]
    if bad or not names:
        raise click.BadParameter(f"unknown section(s) {', '.join(bad) or '(none)'}; choose from {','.join(SECTIONS)}")
    return [s for s in SECTIONS if s in names]


def default_json_path(git: dict[str, Any]) -> Path:
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    return Path("runs") / "benchmarks" / f"{stamp}-{(git.get('commit') or 'nogit')[:10]}.json"


@click.command(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.option("--quick", is_flag=True, help="Smoke sizes: 16 agents, 2 agent processes, a 2-run sweep (seconds).")
@click.option("--only", "only", default=None, metavar="SECTIONS",
              help=f"Comma-separated sections to run (default: all): {','.join(SECTIONS)}.")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Where to write the figures (default: runs/benchmarks/STAMP-COMMIT.json).")
@click.option("--compare", "compare", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="A result file of an earlier run: print its value and new / old per figure.")
@click.option("--load", "load", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Print the figures of a saved result file instead of running (with --compare: compare them).")
@click.option("--markdown", "markdown", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Also write the figures as a markdown page (docs/benchmarks.md), from --load's file or this run's.")
@click.option("--max-agents", type=click.IntRange(min=2), default=None, metavar="N",
              help="Skip the simulator teams and rse run teams larger than N (e.g. 256: no 1024-agent team).")
@click.option("--progress/--no-progress", default=True, show_default=True, help="Show a progress bar.")
def cli(quick: bool, only: str | None, json_path: Path | None, compare: Path | None, load: Path | None,
        markdown: Path | None, max_agents: int | None, progress: bool) -> None:
    """Benchmark the simulator, rse run, memory and rse sweep; print one table and write JSON."""
    try:
        sections = parse_sections(only)
    except click.BadParameter as exc:
        exc.param_hint = "'--only'"
        raise
    try:
        old = read_document(compare) if compare is not None else None
        if load is not None:
            if quick or only or json_path or max_agents:
                raise BenchmarkError("--load prints a saved file: it takes no --quick, --only, --json or --max-agents")
            doc = read_document(load)
            out.print(table(doc, old))
            _write_markdown(doc, markdown, load)
            return
    except BenchmarkError as exc:
        err.print(f"[red]error:[/red] {exc}", soft_wrap=True)
        sys.exit(EXIT_BAD_INPUT)
    plan = (QUICK if quick else FULL).limited(max_agents)
    machine, git = machine_info(), git_info()
    cores, load0 = machine.get("cores_logical") or 1, (machine.get("loadavg_start") or [0.0])[0]
    if load0 > 0.5 * cores:
        err.print(f"[yellow]warning:[/yellow] the machine is busy (load average {load0:.1f} on {cores} cores): "
                  "the figures will be low", soft_wrap=True)
    try:
        figs, errors, timings = run_suite(plan, sections, progress=progress)
    except KeyboardInterrupt:
        err.print("[red]error:[/red] interrupted")
        sys.exit(EXIT_INTERRUPTED)
    doc = result_document(figs, machine=machine, git=git, quick=quick, sections=sections, errors=errors)
    doc["settings"] = plan.settings()
    doc["steps"] = timings
    path = json_path or default_json_path(git)
    try:
        write_document(doc, path)
    except OSError as exc:
        err.print(f"[red]error:[/red] cannot write {path}: {exc.strerror or exc}", soft_wrap=True)
        sys.exit(EXIT_FAILED)
    out.print(table(doc, old))
    out.print(f"figures: {path}", soft_wrap=True)
    _write_markdown(doc, markdown, path)
    for e in errors:
        err.print(f"[red]error:[/red] {e}", soft_wrap=True)
    if errors:
        sys.exit(EXIT_FAILED)


def _write_markdown(doc: dict[str, Any], markdown: Path | None, source: Path) -> None:
    """Write the page of ``doc`` to ``markdown`` (if given); exit status 1 if it cannot be written."""
    if markdown is None:
        return
    from .markdown import write_markdown

    try:
        write_markdown(doc, markdown, source=str(source), target=str(markdown))
    except OSError as exc:
        err.print(f"[red]error:[/red] cannot write {markdown}: {exc.strerror or exc}", soft_wrap=True)
        sys.exit(EXIT_FAILED)
    out.print(f"page: {markdown}", soft_wrap=True)


def main() -> None:
    cli(prog_name="python -m benchmarks")
