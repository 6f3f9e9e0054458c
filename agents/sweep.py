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
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from estimation.errors import RSEError, ScenarioError
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
        if step <= 0 or stop < start:
            raise ScenarioError(f"{key}: need STEP > 0 and STOP >= START, got {text!r}", source="--grid")
        count = int(math.floor((stop - start) / step + 1e-9)) + 1
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
    keys = [k for k, _ in grid]
    return [Point(tuple(zip(keys, combo)), s) for combo in itertools.product(*(v for _, v in grid)) for s in seeds]


def run_point(scenario: str, base_overrides: list[str], point: Point, out: str) -> dict[str, Any]:
    """Run one point in this (worker) process; write its files; return its table row."""
    from agents import runs
    from agents.rundir import write_json

    d = Path(out)
    d.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    row: dict[str, Any] = {"point": point.id, "seed": point.seed, **{k: v for k, v in point.values}}
    try:
        res = runs.simulate(runs.load(scenario, set=base_overrides + point.overrides))
        results, summary = res.expectations(), res.summary()
        write_json(d / "summary.json", summary)
        w = summary["worst_regular"].get("x", {})
        row.update({f"worst_{k}": (None if v is None else float(v)) for k, v in w.items()})
        row["expectations_ok"] = not any(r.failed for r in results)
        row["status"] = "ok"
    except RSEError as exc:  # a point whose design fails is a result, not a crash
        row["status"] = f"error: {exc}"
    except FloatingPointError as exc:
        row["status"] = f"error: {exc}"
    row["elapsed_s"] = time.perf_counter() - t0
    write_json(d / "point.json", row)
    return row


def run_sweep(scenario: Path, grid_specs: list[str], *, seeds: int, jobs: int, out: Path,
              overrides: list[str], progress: Callable[[int, int], None] | None = None) -> list[dict[str, Any]]:
    """Run (or resume) a sweep; returns every point's row."""
    from scenarios.build import build
    from scenarios.loader import load

    grid = [parse_grid(g) for g in grid_specs]
    if not grid:
        raise ScenarioError("give at least one --grid KEY=VALUES", source="command line")
    sc, _ = load(scenario, overrides)
    base_seed = sc.run.seed
    seed_list = [base_seed + i for i in range(seeds)]
    pts = points(grid, seed_list)
    # validate every distinct override combination once, before spending time on runs
    for combo in {p.values for p in pts}:
        probe = Point(combo, base_seed)
        sc_p, _ = load(scenario, overrides + probe.overrides)
        build(sc_p, source=str(scenario), check_conditions=False)
    out.mkdir(parents=True, exist_ok=True)
    meta = {"scenario": str(scenario), "grid": grid_specs, "seeds": seed_list, "overrides": overrides}
    meta_path = out / "sweep.json"
    if meta_path.exists():
        old = json.loads(meta_path.read_text())
        if {k: old.get(k) for k in meta} != meta:
            raise ScenarioError(f"{out} holds a different sweep ({old.get('scenario')}, {old.get('grid')}); use another --out",
                                source="--out")
    meta_path.write_text(json.dumps(meta, indent=2) + "\n")
    rows: list[dict[str, Any]] = []
    todo = []
    for p in pts:
        f = out / "points" / p.id / "point.json"
        if f.exists():
            rows.append(json.loads(f.read_text()))
        else:
            todo.append(p)
    done = len(rows)
    if progress:
        progress(done, len(pts))
    if todo:
        from .executor import open_executor

        tasks = [(str(scenario), overrides, p, str(out / "points" / p.id)) for p in todo]
        with open_executor(jobs) as ex:
            for _, row in ex.map(run_point, tasks):
                rows.append(row)
                done += 1
                if progress:
                    progress(done, len(pts))
    write_table(out, rows, [k for k, _ in grid])
    return rows


def write_table(out: Path, rows: list[dict[str, Any]], keys: list[str]) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    cols = sorted({c for r in rows for c in r}, key=lambda c: (c not in ("point", "seed", *keys), c))
    data = {c: [r.get(c) for r in rows] for c in cols}
    for c, v in data.items():
        if any(isinstance(x, (list, dict)) for x in v):
            data[c] = [json.dumps(x) for x in v]
    pq.write_table(pa.table(data), out / "sweep.parquet")


def mss_curve(scenario: Path, overrides: list[str], p: np.ndarray) -> tuple[np.ndarray, float] | None:
    """Theorem 2's ``rho^2 pbar(p)`` and the largest tolerable ``p`` for an lfre scenario."""
    from estimation.mss import max_erasure_probability, mss_margin, robustness_multiplier
    from estimation.robustness import strong_robustness
    from scenarios.build import build
    from scenarios.loader import load

    sc, _ = load(scenario, overrides)
    if sc.estimator.algorithm != "lfre" or sc.estimator.f < 1:
        return None
    exp = build(sc, source=str(scenario))
    des = exp.design
    r = min(strong_robustness(des.Adj, des.sources[j]) for j in des.medags)
    m = robustness_multiplier(r, f=sc.estimator.f)
    rho = float(np.max(np.abs(des.modal.lam)))
    if not math.isfinite(m) or m < 1:
        return None
    return np.array([mss_margin(x, rho=rho, m=int(m), f=sc.estimator.f) for x in p]), max_erasure_probability(rho=rho, m=int(m), f=sc.estimator.f)


def figure(out: Path, rows: list[dict[str, Any]], grid_specs: list[str], scenario: Path, overrides: list[str],
           metric: str = "worst_final_relative_error_2", threshold: float = 1e-6) -> Path | None:
    """Mean square of ``metric`` over seeds against the (first) grid key; the MSS bound of
    Theorem 2 drawn on a second axis when the key is the erasure probability.

    The default metric is the worst regular agent's relative error at the horizon: the
    absolute error of a growing state has a float64 floor of about 1e-15 |x|. The empirical
    boundary is the first grid value at which the median over seeds exceeds ``threshold``.
    """
    from .report import _pyplot

    plt = _pyplot()
    key = parse_grid(grid_specs[0])[0]
    ok = [r for r in rows if r.get("status") == "ok" and r.get(metric) is not None]
    if not ok:
        return None
    xs = sorted({r[key] for r in ok})
    mse, lo, hi = [], [], []
    for x in xs:
        v = np.array([r[metric] for r in ok if r[key] == x], dtype=float) ** 2
        v = np.where(np.isfinite(v), v, np.nan)
        mse.append(np.nanmean(v))
        lo.append(np.nanmin(v))
        hi.append(np.nanmax(v))
    fig, ax = plt.subplots(figsize=(8, 4.5))
    ax.semilogy(xs, mse, "o-", label=f"empirical mean over seeds of ({metric.replace('worst_', 'worst regular ')})^2")
    ax.fill_between(xs, lo, hi, alpha=0.2, label="min-max over seeds")
    med = [np.nanmedian([r[metric] for r in ok if r[key] == x]) for x in xs]
    boundary = next((x for x, m in zip(xs, med) if m > threshold), None)
    if boundary is not None:
        ax.axvline(boundary, color="tab:blue", ls="--", lw=1.2,
                   label=f"empirical boundary: median > {threshold:g} from {key.split('.')[-1]} = {boundary:g}")
    ax.set_xlabel(key)
    ax.set_ylabel("mean-square " + ("relative " if "relative" in metric else "") + "error at the horizon")
    ax.grid(True, which="both", alpha=0.3)
    if key.endswith("drop_p"):
        curve = mss_curve(scenario, overrides, np.array(xs, dtype=float))
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
    ax.set_title(f"{Path(name).stem}: {len(ok)} runs")
    fig.tight_layout()
    path = out / "sweep.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
