"""``rse sweep``: a scenario over a grid of overrides and seeds, in parallel worker processes.

A sweep directory holds ``sweep.json`` (the scenario, the grid, the seeds), one folder per
finished point under ``points/`` (its ``summary.json`` and ``point.json``; a point is done
when its ``point.json`` exists, so an interrupted sweep resumes where it stopped) and the
results table ``sweep.parquet`` (one row per run: the grid values, the seed and the worst
regular agent's summary figures for the whole state), plus ``sweep.png``.

Grid syntax (repeat ``--grid`` for more keys; the grid is their product):
``key=v1,v2,...`` (TOML values) or ``key=start:stop:step`` (numbers from start to stop
inclusive, e.g. ``network.channel.drop_p=0:0.9:0.05`` is 19 values).
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from estimation.errors import RSEError, ScenarioError
from scenarios.budget import LIMITS, Cost, check_run
from scenarios.loader import toml_value


def parse_grid(spec: str) -> tuple[str, list[Any]]:
    """``key=v1,v2`` or ``key=start:stop:step`` -> ``(key, values)``."""
    from scenarios.loader import parse_value

    if "=" not in spec:
        raise ScenarioError(f"expected KEY=V1,V2,... or KEY=START:STOP:STEP, got {spec!r}", source="--grid")
    key, text = (x.strip() for x in spec.split("=", 1))
    if not key or not text:
        raise ScenarioError(f"expected KEY=V1,V2,... or KEY=START:STOP:STEP, got {spec!r}", source="--grid")
    if ":" in text and not text.startswith(("[", "{", '"')):
        parts = text.split(":")
        try:
            start, stop, step = (float(p) for p in parts)
        except ValueError:
            raise ScenarioError(f"{key}: range must be START:STOP:STEP numbers, got {text!r}", source="--grid") from None
        if not all(math.isfinite(v) for v in (start, stop, step)) or step <= 0 or stop < start:
            raise ScenarioError(f"{key}: need finite numbers, STEP > 0 and STOP >= START, got {text!r}", source="--grid")
        count_f = math.floor((stop - start) / step + 1e-9) + 1
        if count_f > LIMITS["points"]:
            raise ScenarioError(f"{key}: {count_f:.3g} values exceed the limit of {LIMITS['points']:,} points", source="--grid")
        count = int(count_f)
        values = [round(start + i * step, 12) for i in range(count)]
        if all(float(v).is_integer() for v in (start, stop, step)):
            values = [int(v) for v in values]
        return key, values
    return key, [parse_value(v.strip()) for v in text.split(",") if v.strip()]


@dataclass(frozen=True)
class Point:
    values: tuple[tuple[str, Any], ...]
    seed: int

    @property
    def overrides(self) -> list[str]:
        return [f"{k}={toml_value(v)}" for k, v in self.values] + [f"run.seed={self.seed}"]

    @property
    def id(self) -> str:
        return hashlib.sha1(json.dumps([self.values, self.seed], default=str).encode()).hexdigest()[:12]


def points(grid: list[tuple[str, list[Any]]], seeds: list[int]) -> list[Point]:
    count = math.prod(len(v) for _, v in grid) * len(seeds)
    if count > LIMITS["points"]:
        raise ScenarioError(f"{count:,} points (values x seeds) exceed the limit of {LIMITS['points']:,}", source="--grid")
    keys = [k for k, _ in grid]
    return [Point(tuple(zip(keys, combo)), s) for combo in itertools.product(*(v for _, v in grid)) for s in seeds]


def run_point(scenario: dict[str, Any], source: str, base_overrides: list[str], point: Point,
              record: tuple[str, str] | None = None) -> dict[str, Any]:
    """Run one point in this (worker) process; return ``{"row", "summary", "rrd"}``.

    ``scenario`` is the scenario as data (the worker may not have the file ``source``
    names); ``record`` = ``(application id, sweep id)`` also builds the run's tagged Rerun
    recording (:mod:`agents.sweep_record`). Nothing is written here: the caller writes
    the point's files (:func:`write_point`), so a task that runs twice (its worker died)
    still leaves one set of files.
    """
    from agents import runs

    t0 = time.perf_counter()
    row: dict[str, Any] = {"point": point.id, "seed": point.seed, **{k: v for k, v in point.values}}
    summary = rrd = None
    try:
        exp = runs.load(scenario, set=base_overrides + point.overrides, source=source)
        res = runs.simulate(exp)
        results, summary = res.expectations(), res.summary()
        w = summary["worst_regular"].get("x", {})
        row.update({f"worst_{k}": (None if v is None else float(v)) for k, v in w.items()})
        row["expectations_ok"] = not any(r.failed for r in results)
        row["status"] = "ok"
        if record is not None:
            from .sweep_record import recording_bytes

            rrd = recording_bytes(exp, res.sim, application_id=record[0], recording_id=f"{record[1]}-{point.id}",
                                  values=point.values, seed=point.seed, point=point.id)
    except RSEError as exc:  # a point whose design fails is a result, not a crash
        row["status"] = f"error: {exc}"
    except FloatingPointError as exc:
        row["status"] = f"error: {exc}"
    row["elapsed_s"] = time.perf_counter() - t0
    return {"row": row, "summary": summary, "rrd": rrd}


def write_point(d: Path, result: dict[str, Any]) -> dict[str, Any]:
    """Write one finished point's files into ``d`` (``point.json`` last: the point is done
    once it exists); returns its row. Writing the same result twice leaves the same files."""
    from agents.rundir import write_json

    d.mkdir(parents=True, exist_ok=True)
    if result.get("summary") is not None:
        write_json(d / "summary.json", result["summary"])
    if result.get("rrd"):
        (d / "run.rrd").write_bytes(result["rrd"])
    write_json(d / "point.json", result["row"])
    return result["row"]


def finished_rows(out: Path, pts: list[Point]) -> tuple[list[dict[str, Any]], list[Point]]:
    """The rows of the points of ``pts`` already done in ``out`` and the points still to run."""
    rows, todo = [], []
    for p in pts:
        f = out / "points" / p.id / "point.json"
        if f.exists():
            rows.append(json.loads(f.read_text()))
        else:
            todo.append(p)
    return rows, todo


def run_points(scenario: Path, overrides: list[str], pts: list[Point], out: Path, *, jobs: int,
               cluster: str | None = None, record: bool = True, executor: Any = None,
               on_row: Callable[[dict[str, Any]], None] | None = None) -> list[dict[str, Any]]:
    """Run ``pts`` (none of them done) through an executor, writing each point's files in
    ``out/points/ID`` as it arrives; returns their rows in completion order. ``executor``
    reuses an open executor (a search that submits batch after batch)."""
    from scenarios.loader import read_toml

    from .executor import open_executor

    if not pts:
        return []
    raw = read_toml(scenario)
    tag = (f"rse-sweep-{out.resolve().name}", hashlib.sha1(str(out.resolve()).encode()).hexdigest()[:8]) if record else None
    tasks = [(raw, str(scenario), overrides, p, tag) for p in pts]
    rows = []

    def consume(ex: Any) -> None:
        for i, result in ex.map(run_point, tasks):
            rows.append(write_point(out / "points" / pts[i].id, result))
            if on_row:
                on_row(rows[-1])

    if executor is not None:
        consume(executor)
    else:
        with open_executor(jobs, cluster) as ex:
            consume(ex)
    return rows


def validate_points(scenario: Path, overrides: list[str], pts: list[Point]) -> None:
    """Build every distinct override combination of ``pts`` once (bad keys and values are
    errors before any run); the sum of the runs' estimated times is within the size budget
    (:mod:`scenarios.budget`; ``run.force`` lifts it)."""
    from scenarios.build import build
    from scenarios.loader import load

    memory = seconds = 0.0
    force = False
    for combo in dict.fromkeys(p.values for p in pts):
        sc_p, _ = load(scenario, overrides + Point(combo, 0).overrides)
        cost = build(sc_p, source=str(scenario), check_conditions=False).cost
        runs = sum(p.values == combo for p in pts)
        if cost is not None:
            memory, seconds = max(memory, cost.memory), seconds + runs * cost.seconds
        force = force or sc_p.run.force
    check_run(Cost(memory=memory, seconds=seconds), "--grid", force=force, source=str(scenario),
              what=f"the sweep ({len(pts)} runs)")


def run_sweep(scenario: Path, grid_specs: list[str], *, seeds: int, jobs: int, out: Path,
              overrides: list[str], progress: Callable[[int, int], None] | None = None,
              cluster: str | None = None, record: bool = True) -> list[dict[str, Any]]:
    """Run (or resume) a sweep; returns every point's row. ``cluster``: the Dask scheduler's
    address (:func:`agents.executor.open_executor`); ``record``: a tagged ``run.rrd`` per run."""
    from scenarios.loader import load

    grid = [parse_grid(g) for g in grid_specs]
    if not grid:
        raise ScenarioError("give at least one --grid KEY=VALUES", source="command line")
    sc, _ = load(scenario, overrides)
    base_seed = sc.run.seed
    if seeds > LIMITS["points"]:
        raise ScenarioError(f"{seeds:,} seeds exceed the limit of {LIMITS['points']:,} points", source="--seeds")
    seed_list = [base_seed + i for i in range(seeds)]
    pts = points(grid, seed_list)
    validate_points(scenario, overrides, pts)
    out.mkdir(parents=True, exist_ok=True)
    meta = {"scenario": str(scenario), "grid": grid_specs, "seeds": seed_list, "overrides": overrides}
    meta_path = out / "sweep.json"
    if meta_path.exists():
        old = json.loads(meta_path.read_text())
        if {k: old.get(k) for k in meta} != meta:
            raise ScenarioError(f"{out} holds a different sweep ({old.get('scenario')}, {old.get('grid')}); use another --out",
                                source="--out")
    meta_path.write_text(json.dumps(meta, indent=2) + "\n")
    rows, todo = finished_rows(out, pts)

    def on_row(row: dict[str, Any]) -> None:
        rows.append(row)
        if progress:
            progress(len(rows), len(pts))

    from .executor import open_executor

    try:
        with open_executor(jobs, cluster) as ex:  # a cluster that does not answer fails here, before any progress
            if progress:
                progress(len(rows), len(pts))
            run_points(scenario, overrides, todo, out, jobs=jobs, record=record, executor=ex, on_row=on_row)
    except BaseException:
        # interrupted: the table holds the points finished so far, read back from their
        # point.json (a signal between a point's files and its row must not leave it out);
        # the sweep resumes
        done = finished_rows(out, pts)[0]
        if done:
            from .runs import deferred_signals

            with deferred_signals():
                write_table(out, done, [k for k, _ in grid])
        raise
    order = {p.id: i for i, p in enumerate(pts)}
    rows.sort(key=lambda r: order.get(r.get("point", ""), len(order)))  # grid order, whatever the completion order
    write_table(out, rows, [k for k, _ in grid])
    return rows


def write_table(out: Path, rows: list[dict[str, Any]], keys: list[str], name: str = "sweep.parquet") -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    cols = sorted({c for r in rows for c in r}, key=lambda c: (c not in ("point", "seed", *keys), c))
    data = {c: [r.get(c) for r in rows] for c in cols}
    for c, v in data.items():
        if any(isinstance(x, (list, dict)) for x in v):
            data[c] = [json.dumps(x) for x in v]
    pq.write_table(pa.table(data), out / name)


def mss_curve(scenario: Path, overrides: list[str], p: np.ndarray) -> tuple[np.ndarray, float] | None:
    """Theorem 2's ``rho^2 pbar(p)`` and the largest tolerable ``p`` for an lfre scenario."""
    from estimation.mss import max_erasure_probability, mss_margin, robustness_multiplier
    from estimation.robustness import strong_robustness
    from scenarios.build import build
    from scenarios.loader import load
    from scenarios.plugins.mitra import MitraEstimator

    sc, _ = load(scenario, overrides)
    est = sc.estimator
    if not isinstance(est, MitraEstimator) or est.f < 1:  # the lfre algorithm
        return None
    exp = build(sc, source=str(scenario))
    des = exp.design
    r = min(strong_robustness(des.Adj, des.sources[j]) for j in des.medags)
    m = robustness_multiplier(r, f=est.f)
    rho = float(np.max(np.abs(des.modal.lam)))
    if not math.isfinite(m) or m < 1:
        return None
    return np.array([mss_margin(x, rho=rho, m=int(m), f=est.f) for x in p]), max_erasure_probability(rho=rho, m=int(m), f=est.f)


#: the per-run figures a sweep figure can draw (the worst regular agent's, columns ``worst_NAME``)
FIGURE_METRICS = ("final_relative_error_2", "final_error_2", "final_error_inf",
                  "window_max_relative_error_2", "window_max_error_2", "window_max_error_inf")


def figure_choice(scenario: Any, metric: str | None, threshold: float | None) -> tuple[str, float | None, str]:
    """The metric and threshold of ``sweep.png``: the user's, else the algorithm's and the scenario's.

    Without ``metric``: the relative error at the horizon for ``lfre`` (a growing state has
    an absolute float64 floor of about 1e-15 |x|), the window's largest infinity-norm error
    otherwise (the quantity of the other papers' bounds). Without ``threshold``: the
    ``max`` of the scenario's ``[[expect]]`` bound on that quantity (regular agents, block
    x or every block: a bound on each block bounds the whole state), else none (no boundary line). Returns ``(metric, threshold, where the threshold
    came from)``; a metric not in :data:`FIGURE_METRICS` is a :class:`ScenarioError`.
    """
    name = (metric or ("final_relative_error_2" if scenario.estimator.algorithm == "lfre"
                       else "window_max_error_inf")).removeprefix("worst_")
    if name not in FIGURE_METRICS:
        raise ScenarioError(f"--metric: unknown metric {name!r}; expected one of {', '.join(FIGURE_METRICS)}",
                            source="command line")
    if threshold is not None:
        return name, float(threshold), "--threshold"
    for e in scenario.expect:
        over = "final" if e.over == "final" else "window_max" if e.over == "window" else None
        if e.max is not None and over and f"{over}_{e.metric}" == name and e.block in ("x", "all") and e.agents == "regular":
            return name, float(e.max), "the scenario's [[expect]] bound"
    return name, None, "none"


def figure_curve(rows: list[dict[str, Any]], key: str, metric: str, threshold: float | None) -> dict[str, Any] | None:
    """Median and min-max over seeds of ``worst_METRIC`` per value of ``key``, and the first
    value whose median exceeds ``threshold`` (``crossing``, None if none or no threshold)."""
    col = f"worst_{metric}"
    ok = [r for r in rows if r.get("status") == "ok" and r.get(col) is not None]
    if not ok:
        return None
    xs = sorted({r[key] for r in ok})
    vals = [np.array([r[col] for r in ok if r[key] == x], dtype=float) for x in xs]
    vals = [np.where(np.isfinite(v), v, np.nan) for v in vals]
    med = [float(np.nanmedian(v)) for v in vals]
    crossing = None if threshold is None else next((x for x, m in zip(xs, med) if m > threshold), None)
    return {"x": xs, "median": med, "low": [float(np.nanmin(v)) for v in vals],
            "high": [float(np.nanmax(v)) for v in vals], "runs": len(ok), "crossing": crossing}


def figure(out: Path, rows: list[dict[str, Any]], grid_specs: list[str], scenario: Path, overrides: list[str],
           metric: str, threshold: float | None) -> tuple[Path, dict[str, Any]] | None:
    """``sweep.png``: the median over seeds of the worst regular agent's ``metric`` against
    the (first) grid key, the min-max band, ``threshold`` and where the median first
    exceeds it; Theorem 2's MSS condition on a second axis when the key is the erasure
    probability of an lfre scenario. Returns the path and the curve (:func:`figure_curve`)."""
    from .report import _pyplot

    key = parse_grid(grid_specs[0])[0]
    c = figure_curve(rows, key, metric, threshold)
    if c is None:
        return None
    plt = _pyplot()
    xs = c["x"]
    fig, ax = plt.subplots(figsize=(8, 4.5))
    ax.semilogy(xs, c["median"], "o-", label=f"median over seeds of the worst regular agent's {metric}")
    ax.fill_between(xs, c["low"], c["high"], alpha=0.2, label="min-max over seeds")
    if threshold is not None:
        ax.axhline(threshold, color="tab:gray", lw=0.8, ls=":", label=f"threshold {threshold:g}")
    if c["crossing"] is not None:
        ax.axvline(c["crossing"], color="tab:blue", ls="--", lw=1.2,
                   label=f"median > {threshold:g} from {key.split('.')[-1]} = {c['crossing']:g}")
    ax.set_xlabel(key)
    ax.set_ylabel(metric)
    ax.grid(True, which="both", alpha=0.3)
    curve = mss_curve(scenario, overrides, np.array(xs, dtype=float)) if key.endswith("drop_p") else None
    if curve is not None:
        margin, pstar = curve
        ax2 = ax.twinx()
        ax2.plot(xs, margin, "--", color="tab:red", label="rho^2 pbar(p) (Theorem 2, eqs. 23-24)")
        ax2.axhline(1.0, color="tab:red", lw=0.8, ls=":")
        ax2.set_ylabel("rho^2 pbar", color="tab:red")
        ax.axvline(pstar, color="tab:red", lw=1.2, label=f"MSS certified for p < {pstar:.4f}")
        h1, l1 = ax.get_legend_handles_labels()
        h2, l2 = ax2.get_legend_handles_labels()
        ax.legend(h1 + h2, l1 + l2, fontsize=8, loc="upper left")
    else:
        ax.legend(fontsize=8)
    name = json.loads((out / "sweep.json").read_text())["scenario"]
    ax.set_title(f"{Path(name).stem}: {c['runs']} runs")
    fig.tight_layout()
    path = out / "sweep.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path, c
