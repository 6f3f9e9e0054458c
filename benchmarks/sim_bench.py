"""The in-process simulator against team size, and its memory (sections ``simulate`` and ``memory``).

Team: ``scenarios/mitra_cells.toml`` with ``plant.params.K = N / 4`` cells of four
patrolling agents each (``N`` = 16, 64, 256, 1024 agents; the plant has ``20 K`` states),
its cells graph, ``f = 1``, drop probability ``p = 0.32`` and its Byzantine agent 5 (the
cancellation attack); the ``[expect]`` bounds are dropped (their time windows do not fit a
few rounds, and evaluating them is not the simulator's work).

Every team size is measured in a fresh spawned process (:func:`measure_team`): peak RSS
is then that process's own, and one size does not warm the caches of the next. In it the
scenario is built once (timed: the build time), then each repeat runs it through
:func:`agents.simulate.simulate`, the entry point of ``rse simulate`` and
``rse bench simulate``, which builds fresh nodes, plant and monitor from the experiment
(it does not change the experiment: every repeat must end with the same worst error,
else the measurement fails). Its ``elapsed`` is ``time.perf_counter`` around the round
loop only (monitor included, no files, no Rerun output); the node set-up of the call is
reported apart. The best of the repeats is kept (the first one also warms the caches; a
separate warm-up run would cost minutes at 1024 agents). The peak RSS is read after the
build and the first run.
"""

from __future__ import annotations

import math
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from typing import Any

from .report import ROOT, BenchmarkError, Figure

SCENARIO = ROOT / "scenarios" / "mitra_cells.toml"
AGENTS_PER_CELL = 4  # the scenario's per_cell


def fused_values_per_round(exp: Any) -> int:
    """Values the team fuses in one round: ``sum_i |in(i)| * L``.

    Agent ``i`` receives one message per round from each of its in-neighbours
    ``exp.in_neighbours(i)``; an LFRE message is the sender's whole state estimate, of
    length ``L = exp.n``, and the receiver's filter (eqs. 21-22 of Mitra et al.) reads
    every value of every message it gets. The count is *nominal*: taken on the graph, not
    on what the channel delivered (with drop probability ``p`` about ``(1 - p)`` of it
    arrives), and over every agent including the Byzantine ones, so that for a given
    team it is a fixed multiple of its agent-rounds and the cost per fused value
    compares across commits and team sizes.

    Parameters
    ----------
    exp : a built :class:`scenarios.build.Experiment` whose estimator is LFRE

    Returns
    -------
    int
        The number of fused values per round.

    Raises
    ------
    ValueError
        If the experiment's estimator is not LFRE (its message length is not ``exp.n``).
    """
    algorithm = exp.scenario.estimator.algorithm
    if algorithm != "lfre":
        raise ValueError(f"fused values are defined for LFRE messages (length n), not for estimator {algorithm!r}")
    return sum(len(exp.in_neighbours(i)) for i in range(exp.N)) * exp.n


def team_overrides(agents: int, rounds: int) -> tuple[str, ...]:
    """``--set`` overrides of ``mitra_cells.toml`` for a team of ``agents`` (a multiple of 4)."""
    if agents < AGENTS_PER_CELL or agents % AGENTS_PER_CELL:
        raise ValueError(f"team size must be a positive multiple of {AGENTS_PER_CELL}, got {agents}")
    return (f"plant.params.K={agents // AGENTS_PER_CELL}", f"run.rounds={rounds}", "estimator.f=1",
            "network.channel.drop_p=0.32", "expect=[]")


def current_rss_mb() -> float:
    """Resident set size of this process now (MB)."""
    import psutil

    return psutil.Process().memory_info().rss / 2**20


def measure_team(agents: int, rounds: int, repeats: int) -> dict[str, Any]:
    """Build and run one team in this process (the body of the spawned worker).

    Parameters
    ----------
    agents : team size (16, 64, 256, 1024, ...)
    rounds : ``run.rounds`` (the loop runs ``rounds + 1`` rounds, ``k = 0 .. rounds``)
    repeats : timed runs (0: one run, for the memory figures only)

    Returns
    -------
    dict
        ``N``, ``n``, ``rounds`` (simulated per run), ``fused_per_round``, ``build_s``,
        ``loop_s`` and ``setup_s`` (one per timed run), ``rss_imports_mb`` (RSS
        after the imports, before building), ``rss_peak_mb`` (peak after the build and
        the first run).

    Raises
    ------
    BenchmarkError
        If the scenario does not give ``agents`` agents, or two runs end differently.
    """
    from agents.api import load_experiment  # also pins BLAS to one thread, as rse does
    from agents.net.figures import maxrss_mb
    from agents.simulate import simulate

    rss0 = current_rss_mb()
    t0 = time.perf_counter()
    exp, _ = load_experiment(SCENARIO, team_overrides(agents, rounds), None)
    build_s = time.perf_counter() - t0
    if exp.N != agents:
        raise BenchmarkError(f"mitra_cells.toml with K = {agents // AGENTS_PER_CELL} has {exp.N} agents, expected {agents}")
    out: dict[str, Any] = {"N": exp.N, "n": exp.n, "fused_per_round": fused_values_per_round(exp), "build_s": build_s,
                           "rss_imports_mb": rss0, "loop_s": [], "setup_s": []}
    first = None
    for r in range(max(1, repeats)):
        t = time.perf_counter()
        res = simulate(exp)
        total = time.perf_counter() - t
        worst = res.monitor.current_worst()
        if r == 0:
            out["rss_peak_mb"] = maxrss_mb()
            out["rounds"] = res.rounds
            first = worst
        elif not (worst == first or (math.isnan(worst) and math.isnan(first))):
            raise BenchmarkError(f"{agents} agents: run {r + 1} ended with worst error {worst!r}, run 1 with {first!r}; "
                                 "the simulator is not repeatable on one built experiment")
        if repeats:
            out["loop_s"].append(res.elapsed)
            out["setup_s"].append(max(0.0, total - res.elapsed))
        del res
    return out


def measure_team_fresh(agents: int, rounds: int, repeats: int) -> dict[str, Any]:
    """:func:`measure_team` in a fresh spawned process."""
    with ProcessPoolExecutor(max_workers=1, mp_context=get_context("spawn")) as pool:
        return pool.submit(measure_team, agents, rounds, repeats).result()


def simulate_figures(m: dict[str, Any], repeats: int, ref_ns: float | None) -> list[Figure]:
    """Figures of section ``simulate`` from one :func:`measure_team` result.

    ``ref_ns``: the 16-agent cost per fused value (None: no ratio row).
    """
    size = f"{m['N']} agents"
    loop = min(m["loop_s"])
    agent_rounds = m["N"] * m["rounds"]
    fused = m["fused_per_round"] * m["rounds"]
    ns = 1e9 * loop / fused
    how = f"{m['rounds']} rounds, n = {m['n']}, best of {repeats}"
    figs = [
        Figure("simulate", size, "build_s", "scenario build", m["build_s"], "s", False, "load + build + conditions, once"),
        Figure("simulate", size, "setup_s", "node set-up per run", min(m["setup_s"]), "s", False,
               "simulate() call minus its round loop"),
        Figure("simulate", size, "loop_s", "round loop", loop, "s", False, how),
        Figure("simulate", size, "agent_rounds_per_s", "agent-rounds/s", agent_rounds / loop, "1/s", True, how),
        Figure("simulate", size, "fused_values_per_s", "fused values/s", fused / loop, "1/s", True,
               f"{m['fused_per_round']:,} per round"),
        Figure("simulate", size, "ns_per_fused_value", "cost per fused value", ns, "ns", False, how),
    ]
    if ref_ns is not None and math.isfinite(ref_ns) and ref_ns > 0:
        figs.append(Figure("simulate", size, "ns_per_fused_value_vs_16", "cost per fused value / 16 agents'",
                           ns / ref_ns, "x", False, "1 = linear scaling in fused values"))
    return figs


def memory_figures(m: dict[str, Any]) -> list[Figure]:
    """Figures of section ``memory`` from one :func:`measure_team` result."""
    size = f"{m['N']} agents"
    grown = max(0.0, m["rss_peak_mb"] - m["rss_imports_mb"])
    how = f"fresh process, build + one run of {m['rounds']} rounds"
    return [
        Figure("memory", size, "rss_peak_mb", "simulator peak RSS", m["rss_peak_mb"], "MB", False, how),
        Figure("memory", size, "rss_team_mb", "peak RSS above the imports", grown, "MB", False,
               f"imports alone: {m['rss_imports_mb']:.0f} MB"),
        Figure("memory", size, "rss_per_agent_kb", "per agent", 1024 * grown / m["N"], "kB", False,
               f"n = {m['n']} states"),
    ]

