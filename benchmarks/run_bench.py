"""``rse run`` lockstep rounds/s against the number of agent processes (section ``run``).

Teams of ``scenarios/mitra_cells.toml`` with ``K`` cells of ``per_cell`` agents:

====================  =====  ==========  ==============================================
agent processes       K      per_cell    graph (the scenario's cells graph)
====================  =====  ==========  ==============================================
2                     1      2           one cell: the two agents hear each other
4                     1      4           one cell: complete graph of 4
8                     2      4           each agent hears the 4 of the other cell
16                    4      4           the scenario's own team (Fig. 5)
32                    8      4           a ring of 8 cells, 8 in-neighbours each
====================  =====  ==========  ==============================================

``per_cell = 2`` with ``K >= 2`` is not a valid LFRE design for ``f = 1`` (an agent
outside the sources needs 3 in-neighbours from them), hence ``per_cell = 4`` from 4 agents
on; with one cell every agent measures the whole plant (all are sources). At every size:
``f = 1``, drop probability ``p = 0.32``, every cell's patrol period 14
(``agents.periods = [14]``: the scenario's four periods do not repeat over 1 or 2 cells),
no Byzantine agent (the scenario's agent 5 does not exist below 8 agents; the same team
shape at every size) and no ``[expect]`` bounds. The run is ``rse run``'s
:func:`agents.net.launcher.launch` as ``rse bench run`` calls it (lockstep, deadline 2 s,
no Rerun output), then the bare Zenoh skeleton
(:func:`agents.net.skeleton.run_skeleton`) with the same processes, message sizes and
number of rounds. Each is one run (the plant times its rounds); the peak RSS of every
agent process is read from the run's summary.
"""

from __future__ import annotations

import statistics
import tempfile
from pathlib import Path
from typing import Any

from .report import ROOT, BenchmarkError, Figure

SCENARIO = ROOT / "scenarios" / "mitra_cells.toml"

#: agent processes -> (cells K, agents per cell)
TEAMS: dict[int, tuple[int, int]] = {2: (1, 2), 4: (1, 4), 8: (2, 4), 16: (4, 4), 32: (8, 4)}


def team_overrides(processes: int, rounds: int) -> tuple[str, ...]:
    """``--set`` overrides of ``mitra_cells.toml`` for ``processes`` agent processes (a key of :data:`TEAMS`)."""
    if processes not in TEAMS:
        raise ValueError(f"no team of {processes} agent processes; choose one of {', '.join(map(str, TEAMS))}")
    K, per_cell = TEAMS[processes]
    return (f"plant.params.K={K}", f"agents.per_cell={per_cell}", "agents.periods=[14]", "attacks=[]", "expect=[]",
            "estimator.f=1", "network.channel.drop_p=0.32", f"run.rounds={rounds}")


def measure_run(processes: int, rounds: int, *, deadline: float = 2.0, skeleton: bool = True) -> dict[str, Any]:
    """One ``rse run`` of the team with ``processes`` agent processes, then the skeleton.

    Returns
    -------
    dict
        ``N``, ``rounds``, ``rounds_per_s`` (``rse run``), ``skeleton_rounds_per_s``
        (None without the skeleton), ``rss_mb`` (peak RSS of each agent process), ``plant_rss_mb``,
        ``monitor_rss_mb``, ``deadline_misses``.

    Raises
    ------
    BenchmarkError
        If the run fails or writes no performance figures.
    """
    from agents.api import load_experiment, run_team
    from estimation.errors import RSEError

    overrides = team_overrides(processes, rounds)
    exp, _ = load_experiment(SCENARIO, overrides, None)
    if exp.N != processes:
        raise BenchmarkError(f"mitra_cells.toml with {' '.join(overrides[:2])} has {exp.N} agents, expected {processes}")
    with tempfile.TemporaryDirectory(prefix="rse-benchmarks-") as tmp:
        try:  # Ctrl-C / SIGTERM stops the team and raises KeyboardInterrupt: the suite stops too
            summary = run_team(exp, out=Path(tmp) / "run", deadline=deadline).summary()
        except RSEError as exc:
            raise BenchmarkError(f"rse run with {processes} agent processes failed: {exc}") from None
    perf = summary.get("performance") or {}
    if not perf.get("rounds_per_s"):
        raise BenchmarkError(f"rse run with {processes} agent processes reported no rounds/s")
    procs = summary.get("processes", {})
    rss = [rec["maxrss_mb"] for who, rec in procs.items() if who.startswith("agent") and "maxrss_mb" in rec]
    if len(rss) != processes:
        raise BenchmarkError(f"rse run with {processes} agent processes: peak RSS reported by {len(rss)} of them")
    out = {"N": exp.N, "rounds": int(perf["rounds"]), "rounds_per_s": float(perf["rounds_per_s"]), "rss_mb": rss,
           "plant_rss_mb": procs.get("plant", {}).get("maxrss_mb"), "monitor_rss_mb": procs.get("monitor", {}).get("maxrss_mb"),
           "deadline_misses": perf.get("deadline_misses"), "skeleton_rounds_per_s": None}
    if skeleton:
        from agents.net.skeleton import run_skeleton, sizes_for

        try:
            sk = run_skeleton(sizes_for(exp), rounds=out["rounds"])
        except TimeoutError as exc:
            raise BenchmarkError(f"Zenoh skeleton with {processes} agent processes: {exc}") from None
        out["skeleton_rounds_per_s"] = float(sk["rounds_per_s"])
    return out


def run_figures(m: dict[str, Any]) -> list[Figure]:
    """Figures of section ``run`` from one :func:`measure_run` result."""
    size = f"{m['N']} procs"
    how = f"{m['rounds']} lockstep rounds, {m['N'] + 2} processes"
    rate = m["rounds_per_s"]
    figs = [
        Figure("run", size, "rounds_per_s", "rse run rounds/s", rate, "1/s", True, how),
        Figure("run", size, "agent_rounds_per_s", "rse run agent-rounds/s", rate * m["N"], "1/s", True, how),
    ]
    sk = m.get("skeleton_rounds_per_s")
    if sk:
        figs += [
            Figure("run", size, "skeleton_rounds_per_s", "Zenoh skeleton rounds/s", sk, "1/s", True,
                   "same processes and message sizes, no estimation"),
            Figure("run", size, "runtime_vs_skeleton", "rse run / skeleton", rate / sk, "x", True, "target >= 0.5"),
        ]
    figs += [
        Figure("run", size, "agent_rss_max_mb", "agent peak RSS, max", max(m["rss_mb"]), "MB", False,
               "target <= 60 MB"),
        Figure("run", size, "agent_rss_median_mb", "agent peak RSS, median", statistics.median(m["rss_mb"]), "MB",
               False, f"plant {m['plant_rss_mb']:.0f} MB, monitor {m['monitor_rss_mb']:.0f} MB"
               if m.get("plant_rss_mb") and m.get("monitor_rss_mb") else ""),
    ]
    return figs
