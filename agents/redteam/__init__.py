"""Red-team search: the attack inside (or one step outside) a scenario's threat model that
maximises an error metric, shrunk to a replayable scenario file (docs/redteam.md).

::

    from agents.redteam import redteam
    result = redteam("scenarios/lee_kim_shim_nonresilient.toml", budget=200, jobs=2, out="runs/rt")
    result.summary["worst"]["value"], result.out / "worst.toml"

Modules: :mod:`.space` (the search space and the candidates as scenario overrides),
:mod:`.search` (the Optuna study, evaluations in parallel), :mod:`.shrink` (simplifying a
violating candidate), :mod:`.output` (bound, tables, scenario files, figure, live view).
"""

from __future__ import annotations

import importlib.util
import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .space import METRICS, MetricSpec, Space, active_components, derive

__all__ = ["redteam", "RedteamResult", "derive", "Space", "MetricSpec", "METRICS", "active_components"]


@dataclass
class RedteamResult:
    out: Path
    summary: dict[str, Any]
    rows: list[dict[str, Any]]


def redteam(scenario: str | Path, *, budget: int = 200, jobs: int = 1, cluster: str | None = None,
            beyond: bool = False, metric: str | None = None, over: Any = None, block: str | None = None,
            threshold: float | None = None, out: str | Path | None = None, seed: int = 0,
            overrides: Sequence[str] = (), rerun: bool = True, png: bool = True, shrink_budget: int = 100,
            on_eval: Callable[[dict[str, Any]], None] | None = None,
            say: Callable[[str], None] = lambda m: None) -> RedteamResult:
    """Search ``scenario``'s attacks for the worst ``metric``; write the output directory.

    ``overrides`` are ``KEY=VALUE`` strings applied to the scenario first (``--set``);
    ``seed`` seeds the optimiser (not the scenario). Returns the summary (also
    ``summary.json``) and every evaluation (also ``redteam.parquet``).
    """
    from estimation.errors import RSEError
    from scenarios.loader import read_toml

    from .. import runs  # the one-run core (agents.api re-exports it)
    from ..executor import open_executor

    if importlib.util.find_spec("optuna") is None or importlib.util.find_spec("tomli_w") is None:
        raise RSEError("rse redteam needs optuna and tomli-w: pip install -e '.[redteam]'") from None
    from . import output
    from .search import Evaluator, open_study, search
    from .shrink import shrink

    source = str(scenario)
    base = [str(o) for o in overrides]
    exp = runs.load(source, set=base)
    space, spec = derive(exp, beyond=beyond, metric=metric, over=over, block=block)
    bound = output.paper_bound(exp, spec)
    rt_threshold = exp.scenario.redteam.threshold if exp.scenario.redteam is not None else None
    limit = threshold if threshold is not None else rt_threshold
    if limit is None and bound is not None:
        limit = bound["value"]
    out_dir = Path(out) if out is not None else Path("runs") / f"redteam-{exp.scenario.run.name}"
    out_dir.mkdir(parents=True, exist_ok=True)

    def violates(v: float) -> bool:
        return limit is not None and (math.isinf(v) or (math.isfinite(v) and v > limit))

    live = output.LiveView(out_dir / "recording.rrd", bound=limit) if rerun else None
    rows: list[dict[str, Any]] = []

    def seen(row: dict[str, Any]) -> None:
        if live is not None:
            live.log(row)
        if on_eval is not None:
            on_eval(row)

    t0 = time.perf_counter()
    try:
        with open_executor(jobs, cluster) as ex:
            ev = Evaluator(ex, read_toml(source), source, base, space, spec)
            study = open_study(out_dir, seed, budget)
            resumed = sum(1 for t in study.get_trials(deepcopy=False) if "row" in t.user_attrs)
            rows = search(ev, study, budget=budget, batch=jobs, on_eval=seen)
            output.write_table(out_dir, rows)
            t_search = time.perf_counter() - t0
            ok = [r for r in rows if r["phase"] == "search" and not math.isnan(r["metric"])]
            if not ok:
                raise RSEError("no candidate could be evaluated: " + "; ".join({r['status'] for r in rows})[:300])
            worst = max(ok, key=lambda r: r["metric"])
            worst_cand = json.loads(worst["candidate"])
            shrunk = None
            if violates(worst["metric"]):
                def shrink_seen(c: dict, r: dict, accepted: bool) -> None:
                    row = {"evaluation": len(rows), "phase": "shrink", "trial": None, "metric": r["metric"],
                           "elapsed_s": r["elapsed_s"], "status": r["status"], "components": active_components(c),
                           "candidate": json.dumps(c), "overrides": "\n".join(ev.overrides(c)), "accepted": accepted}
                    rows.append(row)
                    seen(row)

                say(f"shrinking the worst candidate ({worst['metric']:.6g} > {limit:g})")
                c, v, n = shrink(worst_cand, worst["metric"], space, ev, violates, batch=jobs,
                                 max_evals=shrink_budget, on_eval=shrink_seen)
                shrunk = {"candidate": c, "value": v, "evaluations": n}
                output.write_table(out_dir, rows)
    finally:
        if live is not None:
            live.close()

    # the scenario files and the worst run (replayed exactly as `rse simulate` would)
    scen_name = Path(source).name
    files: dict[str, Any] = {}
    for name, cand, value in [("worst", worst_cand, worst["metric"])] + (
            [("shrunk", shrunk["candidate"], shrunk["value"])] if shrunk else []):
        ov = ev.overrides(cand)
        e = runs.load(source, set=ov)
        header = (f"rse redteam: the {name} attack found on {scen_name} ({spec.label()} = {value!r})\n"
                  f"that is {scen_name} with these overrides:\n" + "\n".join(f"  --set {o}" for o in ov) +
                  f"\nreproduce: rse simulate {name}.toml")
        path = output.write_scenario(out_dir / f"{name}.toml", e.frozen, header=header, spec=spec, threshold=limit)
        files[name] = {"file": str(path), "value": value, "components": active_components(cand), "candidate": cand,
                       "overrides": ov}
    replayed = output.replay(out_dir / "worst.toml", out_dir / "worst", spec, rerun=rerun)
    files["worst"].update(run_dir=str(out_dir / "worst"), replayed=replayed,
                          reproduced=replayed == worst["metric"] or (math.isnan(replayed) and math.isnan(worst["metric"])))
    if shrunk:
        files["shrunk"]["evaluations"] = shrunk["evaluations"]
    n_search = sum(1 for r in rows if r["phase"] == "search")
    new = n_search - resumed
    summary = {
        "scenario": source, "algorithm": space.algorithm, "overrides": base, "metric": spec.label(),
        "metric_spec": {"metric": spec.metric, "over": spec.over, "block": spec.block},
        "budget": budget, "evaluations": n_search, "resumed": resumed, "jobs": jobs, "seed": seed,
        "search_s": t_search, "evaluations_per_s": new / t_search if t_search > 0 and new else None,
        "space": space.describe(),
        "bound": bound, "threshold": limit,
        "held": None if limit is None else not violates(worst["metric"]),
        "worst": files["worst"], "shrunk": files.get("shrunk"),
        "failed_evaluations": sum(1 for r in rows if r["phase"] == "search" and math.isnan(r["metric"])),
    }
    from ..rundir import write_json

    write_json(out_dir / "summary.json", summary)
    if png:
        output.figure(out_dir, rows, label=spec.label(), bound=limit,
                      bound_name="threshold" if bound is None or limit != bound["value"] else bound["short"])
    return RedteamResult(out_dir, summary, rows)
