"""The simulator on every paper scenario (section ``simulate``, one row per scenario).

What ``rse bench simulate SCENARIO`` measures, for each scenario that reproduces a paper:
the scenario is loaded afresh for every run (so no run inherits another's state), run once
to warm the caches, then ``repeats`` times through :func:`agents.simulate.simulate`; the
figure is agent-rounds per second of the round loop (``SimResult.elapsed``: monitor
included, no files), the median of the repeats (the best is in the detail). The Lee-Kim-Shim
scenario runs at ``run.dt = 0.001`` (40,001 rounds), the step of its acceptance figure.
"""

from __future__ import annotations

import statistics
from typing import Any

from .report import ROOT, Figure

#: (scenario file stem, overrides of the full run, overrides of the --quick run)
PAPER: tuple[tuple[str, tuple[str, ...], tuple[str, ...]], ...] = (
    ("lee_kim_shim", ("run.dt=0.001",), ("run.duration=1", "expect=[]", "output.window=[0.5, 1.0]")),
    ("mitra_cells", (), ("run.rounds=20", "expect=[]")),
    ("mao_tabuada", (), ("run.rounds=40", "expect=[]")),
    ("ugrinovskii_biasing", (), ("run.duration=0.2", "expect=[]", "output.window=[0.1, 0.2]")),
    ("inverters_median", (), ("run.duration=0.5", "expect=[]", "output.window=[0.1, 0.5]")),
    ("inverters_distributed", (), ("run.duration=0.5", "expect=[]", "output.window=[0.1, 0.5]")),
)


def measure_scenario(stem: str, overrides: tuple[str, ...], repeats: int) -> dict[str, Any]:
    """One warm-up run and ``repeats`` timed runs of ``scenarios/STEM.toml`` (fresh load each)."""
    from agents.api import load_experiment
    from agents.simulate import simulate

    path = ROOT / "scenarios" / f"{stem}.toml"

    def once() -> tuple[float, Any]:
        exp, _ = load_experiment(path, overrides, None)
        res = simulate(exp)
        return res.elapsed, exp

    once()
    times, exp = [], None
    for _ in range(max(1, repeats)):
        t, exp = once()
        times.append(t)
    return {"stem": stem, "N": exp.N, "rounds": exp.n_rounds + 1, "n": exp.n, "overrides": overrides, "loop_s": times}


def scenario_figures(m: dict[str, Any]) -> list[Figure]:
    work = m["N"] * m["rounds"]
    rates = [work / t for t in m["loop_s"]]
    dt = next((o.split("=", 1)[1] for o in m["overrides"] if o.startswith("run.dt=")), None)
    how = (f"{m['N']} x {m['rounds']} rounds{f', dt {dt}' if dt else ''}; median of {len(rates)}, "
           f"best {max(rates):,.0f}")
    return [Figure("simulate", m["stem"], "agent_rounds_per_s", "agent-rounds/s", statistics.median(rates), "1/s", True, how)]
