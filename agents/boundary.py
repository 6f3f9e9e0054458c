"""``rse boundary``: where a metric crosses a threshold as one parameter grows, found adaptively.

The question the papers ask of a grid sweep ("up to which erasure probability does it still
converge?") has one number for an answer; a grid spends most of its runs far from it. This
module finds it by **probabilistic bisection** (Horstein 1963; Waeber, Frazier & Henderson,
"Bisection search with noisy responses", SIAM J. Control Optim. 51(3), 2013), with the
response at each query point given by a sequential sign test over the seeds as in Waeber,
Frazier & Henderson, "A Bayesian approach to stochastic root finding", Proc. Winter
Simulation Conference 2011:

* the boundary ``x*`` in ``[LO, HI]`` is where the median over seeds of ``METRIC`` crosses
  ``T`` (``METRIC`` is taken to be below ``T`` at ``LO`` and above at ``HI``; a run that
  fails, or a non-finite metric, counts as above);
* a posterior density of ``x*`` (uniform prior, ``CELLS`` cells) is queried at its median;
* at the query ``x`` the ``N`` seeds run in batches of 5 (each query starting in the list
  of seeds where the last one stopped, so every seed is seen) until a sequential test
  decides on which side of ``T`` the median over the ``N`` seeds lies (the hypergeometric
  p-value of the least favourable split, at most ``ALPHA``: a unanimous batch of 5 out of
  20 seeds already decides), or all ``N`` ran, when the median of their metric decides
  exactly (as a grid's median over the same seeds);
* the answer updates the density: the side it points to is weighted by ``p_c``, the other
  by ``1 - p_c``, with ``p_c`` one minus the test's p-value (at most ``PC_MAX``), or
  ``PC_EXACT`` when every seed ran;
* the search stops when the central 95% interval of the density (the search interval, a
  Bayesian credible interval for the median's crossing) is narrower than ``2 * tol``, or
  after ``max_runs`` runs. The estimate is the posterior median.

The confidence interval from the seeds is for the population median of the per-seed
crossing points (where the next seeds would put the boundary): each seed's crossing is
bracketed by the runs of that seed (below ``T`` at ``x1``, above at ``x2``), and the
interval is the distribution-free one of order statistics (Conover 1999, sec. 3.2:
``[x_(6), x_(15)]`` for 20 seeds at 95%), its ends taken from the brackets' outer ends,
so it is conservative.

With a second ``--vary KEY2=V1,V2,...`` one search runs per value of ``KEY2``, their batches
submitted together, and the result is a curve ``x*(KEY2)``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from estimation.errors import ScenarioError

from .sweep import Point

CELLS = 2000
ALPHA = 0.05
BATCH = 5  # 0.5 ** 5 < ALPHA: a unanimous batch decides
LEVEL = 0.95
PC_MAX = 0.99     # an early decision of the sequential test: no more sure than this
PC_EXACT = 0.999  # every seed ran: exact for this x, short of certain (a seed's metric need not be monotone in x)

METRIC_COLUMNS = ("final_relative_error_2", "window_max_relative_error_2", "final_error_2", "window_max_error_2",
                  "final_error_inf", "window_max_error_inf", "convergence_round")


def parse_vary(spec: str) -> tuple[str, float, float]:
    """``KEY=LO:HI`` -> ``(key, lo, hi)``."""
    if "=" not in spec:
        raise ScenarioError(f"expected KEY=LO:HI, got {spec!r}", source="--vary")
    key, text = (x.strip() for x in spec.split("=", 1))
    parts = text.split(":")
    try:
        lo, hi = (float(p) for p in parts)
    except ValueError:
        raise ScenarioError(f"{key}: expected LO:HI numbers, got {text!r}", source="--vary") from None
    if not key or not hi > lo:
        raise ScenarioError(f"{key or '(no key)'}: empty range {text!r} (need LO < HI)", source="--vary")
    return key, lo, hi


def metric_column(metric: str) -> str:
    """``relative_error_2`` -> the table column ``worst_final_relative_error_2`` (the worst
    regular agent's figure for the whole state at the horizon)."""
    name = metric.removeprefix("worst_")
    if name in METRIC_COLUMNS:
        return f"worst_{name}"
    if f"final_{name}" in METRIC_COLUMNS:
        return f"worst_final_{name}"
    raise ScenarioError(f"unknown metric {metric!r}; expected one of {', '.join(METRIC_COLUMNS)} "
                        "(relative_error_2 means final_relative_error_2)", source="--metric")


def majority_p_value(k: int, n: int, seeds: int) -> float:
    """The p-value of "the majority of ``seeds`` seeds lies on the side of ``k`` of the ``n``
    sampled so far": ``P(X >= k)`` for ``X`` hypergeometric (``n`` draws from ``seeds``, of
    which ``seeds // 2`` are on that side: the least favourable population). 0 when
    ``n == seeds`` and ``k`` is a strict majority: then the answer is exact."""
    K = seeds // 2
    total = math.comb(seeds, n)
    return sum(math.comb(K, i) * math.comb(seeds - K, n - i) for i in range(k, min(K, n) + 1)) / total


def median_interval(brackets: list[tuple[float, float]], level: float = LEVEL) -> tuple[float, float]:
    """Distribution-free interval for the median over the population of seeds of the
    per-seed crossing point, from each seed's bracket ``(lo, hi)`` (its crossing lies in
    it): the order statistics ``x_(r)``, ``x_(N + 1 - r)`` with ``r`` the largest rank for
    which ``P(r <= Binomial(N, 1/2) <= N - r) >= level`` (Conover, Practical
    Nonparametric Statistics, 3rd ed., sec. 3.2), the lower end from the brackets' lower
    ends and the upper end from their upper ends."""
    N = len(brackets)
    cdf = lambda r: sum(math.comb(N, i) for i in range(r)) / 2.0**N  # P(X < r)
    r = 0
    while r + 1 <= N // 2 and 1 - 2 * cdf(r + 1) >= level:
        r += 1
    if r == 0:
        return -math.inf, math.inf
    los = sorted(b[0] for b in brackets)
    his = sorted(b[1] for b in brackets)
    return los[r - 1], his[N - r]


@dataclass
class Search:
    """One probabilistic bisection of ``key`` over ``[lo, hi]`` (at ``fixed`` other values)."""

    key: str
    lo: float
    hi: float
    seeds: list[int]
    threshold: float
    fixed: tuple[tuple[str, Any], ...] = ()
    tol: float = 0.005
    density: np.ndarray = field(default_factory=lambda: np.full(CELLS, 1.0 / CELLS))
    x: float | None = None          # the current query
    above: int = 0                  # its seeds above the threshold so far
    below: int = 0
    runs: int = 0
    queries: list[dict[str, Any]] = field(default_factory=list)
    observed: list[tuple[float, int, bool]] = field(default_factory=list)  # (x, seed, above) of every run
    values: list[float] = field(default_factory=list)  # the metric of the current query's runs
    offset: int = 0  # each query starts where the last one stopped in the list of seeds
    _batch: list[Point] = field(default_factory=list)

    @property
    def edges(self) -> np.ndarray:
        return np.linspace(self.lo, self.hi, CELLS + 1)

    def quantile(self, q: float) -> float:
        """The ``q`` quantile of the posterior (linear within a cell)."""
        c = np.concatenate([[0.0], np.cumsum(self.density)])
        i = int(np.clip(np.searchsorted(c, q, side="left"), 1, CELLS))
        w = (q - c[i - 1]) / max(c[i] - c[i - 1], 1e-300)
        e = self.edges
        return float(e[i - 1] + np.clip(w, 0.0, 1.0) * (e[i] - e[i - 1]))

    def interval(self) -> tuple[float, float]:
        return self.quantile((1 - LEVEL) / 2), self.quantile((1 + LEVEL) / 2)

    def done(self, max_runs: int) -> bool:
        lo, hi = self.interval()
        return hi - lo <= 2 * self.tol or self.runs >= max_runs

    def next_batch(self) -> list[Point]:
        """The points of the next batch (a new query at the posterior median when the
        current one is decided)."""
        if self.x is None:
            self.x = round(self.quantile(0.5), 6)
            self.above = self.below = 0
            self.values = []
        n = self.above + self.below
        order = self.seeds[self.offset:] + self.seeds[:self.offset]
        seeds = order[n:n + BATCH]
        values = self.fixed + ((self.key, self.x),)
        self._batch = [Point(values, s) for s in seeds]
        return list(self._batch)

    def observe(self, values: list[float]) -> None:
        """The metric of each run of the last batch (``inf`` for a failed run); updates the
        density when the query is decided."""
        x = self.x
        if x is None:
            raise RuntimeError("observe() answers a query: call next_batch() first")
        above = [bool(v > self.threshold) for v in values]
        self.runs += len(above)
        self.observed += [(float(x), p.seed, a) for p, a in zip(self._batch, above)]
        self.values += list(values)
        self.above += sum(above)
        self.below += len(above) - sum(above)
        n = self.above + self.below
        if n >= len(self.seeds):  # every seed ran here: their median decides, exactly
            pc, is_above = PC_EXACT, bool(np.median(self.values) > self.threshold)
        else:
            p_value = majority_p_value(max(self.above, self.below), n, len(self.seeds))
            if p_value > ALPHA:
                return  # undecided: more seeds at the same x
            pc, is_above = min(PC_MAX, 1 - p_value), self.above > self.below
        left = (self.edges[1:] + self.edges[:-1]) / 2 < self.x
        # above at x: the boundary lies left of x (the metric crosses upwards)
        self.density = self.density * np.where(left == is_above, pc, 1 - pc)
        self.density /= self.density.sum()
        self.queries.append({"x": self.x, "above": self.above, "below": self.below, "p_c": pc})
        self.offset = (self.offset + n) % len(self.seeds)
        self.x = None

    def brackets(self) -> list[tuple[float, float]]:
        """Per seed, the interval its own crossing lies in: above the largest ``x`` where it
        was below ``T``, below the smallest where it was above (the range for a seed not run)."""
        out = []
        for seed in self.seeds:
            xs = [(x, a) for x, s, a in self.observed if s == seed]
            lo = max([x for x, a in xs if not a], default=self.lo)
            hi = min([x for x, a in xs if a], default=self.hi)
            out.append((min(lo, hi), max(lo, hi)))  # min/max: a seed whose metric is not monotone in x
        return out

    def result(self) -> dict[str, Any]:
        lo, hi = self.interval()
        s_lo, s_hi = median_interval(self.brackets())
        edge = self.tol
        finite = math.isfinite(s_lo) and math.isfinite(s_hi)  # too few seeds: no interval from them
        return {"at": {k: v for k, v in self.fixed}, "estimate": self.quantile(0.5),
                "ci_low": s_lo if finite else None, "ci_high": s_hi if finite else None,
                "search_low": lo, "search_high": hi,
                "level": LEVEL, "runs": self.runs, "queries": len(self.queries),
                "inside": bool(self.quantile(0.5) > self.lo + edge and self.quantile(0.5) < self.hi - edge)}


def run_boundary(scenario: Path, vary: list[str], *, metric: str, threshold: float, seeds: int, jobs: int,
                 out: Path, overrides: list[str], cluster: str | None = None, tol: float = 0.005,
                 max_runs: int = 90, record: bool = True,
                 progress: Callable[[int, str], None] | None = None) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Find the boundary (one search, or one per value of the second ``--vary``); returns
    ``(every run's row, one result per search)`` and writes ``boundary.parquet`` and
    ``boundary.json`` into ``out`` (each run's files under ``out/points/ID`` as a sweep's)."""
    import json

    from scenarios.loader import load

    from .executor import open_executor
    from .sweep import finished_rows, parse_grid, run_points, validate_points, write_table

    if not vary or len(vary) > 2:
        raise ScenarioError("give --vary KEY=LO:HI once (a value) or twice (a curve over KEY2=V1,V2,...)",
                            source="command line")
    key, lo, hi = parse_vary(vary[0])
    curve: tuple[str, list[Any]] | None = None
    if len(vary) == 2:
        curve = parse_grid(vary[1])
        if not curve[1]:
            raise ScenarioError(f"{curve[0]}: no values", source="--vary")
    col = metric_column(metric)
    if not (threshold > 0 and math.isfinite(threshold)):
        raise ScenarioError(f"must be a positive number, got {threshold!r}", source="--threshold")
    sc, _ = load(scenario, overrides)
    seed_list = [sc.run.seed + i for i in range(seeds)]
    fixed_sets = [((curve[0], v),) for v in curve[1]] if curve else [()]
    searches = [Search(key, lo, hi, seed_list, threshold, fixed=f, tol=tol) for f in fixed_sets]
    validate_points(scenario, overrides, [Point(f + ((key, x),), 0) for f in fixed_sets for x in (lo, hi)])
    out.mkdir(parents=True, exist_ok=True)
    meta = {"scenario": str(scenario), "vary": vary, "metric": col, "threshold": threshold, "seeds": seed_list,
            "overrides": overrides, "tol": tol, "max_runs": max_runs}
    if (out / "boundary.json").exists():
        old = json.loads((out / "boundary.json").read_text())
        if {k: old.get(k) for k in meta} != meta:
            raise ScenarioError(f"{out} holds a different search ({old.get('scenario')}, {old.get('vary')}); "
                                "use another --out", source="--out")
    (out / "boundary.json").write_text(json.dumps(meta, indent=2) + "\n")
    rows: list[dict[str, Any]] = []
    with open_executor(jobs, cluster) as ex:
        step = 0
        while True:
            active = [s for s in searches if not s.done(max_runs)]
            if not active:
                break
            batches = [(s, s.next_batch()) for s in active]
            pts = [p for _, b in batches for p in b]
            fresh = list({p.id: p for p in pts}.values())
            got_rows, todo = finished_rows(out, fresh)  # a search is deterministic: a rerun resumes
            got_rows += run_points(scenario, overrides, todo, out, jobs=jobs, record=record, executor=ex)
            got = {r["point"]: r for r in got_rows}
            for s, batch in batches:
                values = []
                for p in batch:
                    r = dict(got[p.id], step=step, search=searches.index(s))
                    v = r.get(col)
                    values.append(math.inf if r.get("status") != "ok" or v is None or not math.isfinite(v) else v)
                    r["above"] = values[-1] > threshold
                    rows.append(r)
                s.observe(values)
            step += 1
            if progress:
                progress(len(rows), "; ".join(f"{s.quantile(0.5):.4f} [{s.interval()[0]:.4f}, {s.interval()[1]:.4f}]"
                                              for s in searches))
    results = [s.result() for s in searches]
    write_table(out, rows, [key] + ([curve[0]] if curve else []), name="boundary.parquet")
    meta["results"] = results
    meta["queries"] = [s.queries for s in searches]
    (out / "boundary.json").write_text(json.dumps(meta, indent=2) + "\n")
    return rows, results


def figure(out: Path, rows: list[dict[str, Any]], results: list[dict[str, Any]], *, scenario: Path, vary: list[str],
           metric: str, threshold: float, overrides: list[str]) -> Path:
    """``boundary.png``: every run's metric against the varied key, the threshold, the
    estimate and its interval (one search); or the boundary curve over the second key with
    its intervals (two). Theorem 2's largest tolerable ``p`` (:func:`agents.sweep.mss_curve`)
    is drawn when the varied key is ``network.channel.drop_p`` of an lfre scenario."""
    from .report import _pyplot
    from .sweep import mss_curve, parse_grid

    plt = _pyplot()
    key, lo, hi = parse_vary(vary[0])
    col = metric_column(metric)
    theory = key.endswith("drop_p")
    fig, ax = plt.subplots(figsize=(8, 4.5))
    if len(vary) == 1:
        res = results[0]
        ok = [r for r in rows if r.get(col) is not None and math.isfinite(r[col])]
        for above, colour, label in ((False, "tab:blue", f"{col} <= {threshold:g}"), (True, "tab:orange", f"> {threshold:g}")):
            pts = [r for r in ok if bool(r["above"]) == above]
            ax.semilogy([r[key] for r in pts], [max(r[col], 1e-300) for r in pts], "o", ms=4, color=colour, alpha=0.6,
                        label=f"{label} ({len(pts)} runs)")
        ax.axhline(threshold, color="grey", lw=0.8, ls=":")
        ax.axvspan(res["search_low"], res["search_high"], color="tab:green", alpha=0.25,
                   label=f"search interval [{res['search_low']:.4f}, {res['search_high']:.4f}]")
        if res["ci_low"] is not None:
            for x in (res["ci_low"], res["ci_high"]):
                ax.axvline(x, color="tab:green", lw=0.8, ls="--",
                           label=None if x == res["ci_high"] else
                           f"{int(res['level'] * 100)}% interval from the seeds [{res['ci_low']:.4f}, {res['ci_high']:.4f}]")
        ax.axvline(res["estimate"], color="tab:green", lw=1.5, label=f"boundary {res['estimate']:.4f} ({res['runs']} runs)")
        if theory:
            mss = mss_curve(scenario, overrides, np.array([lo]))
            if mss is not None:
                ax.axvline(mss[1], color="tab:red", lw=1.5, label=f"MSS certified for p < {mss[1]:.4f} (Theorem 2)")
        ax.set_xlabel(key)
        ax.set_ylabel(col.replace("worst_", "worst regular agent: "))
        ax.set_xlim(lo, hi)
    else:
        key2, vals = parse_grid(vary[1])
        est = [r["estimate"] for r in results]
        err = [[r["estimate"] - r["search_low"] for r in results], [r["search_high"] - r["estimate"] for r in results]]
        ax.errorbar(vals, est, yerr=err, fmt="o-", color="tab:green", capsize=3,
                    label=f"boundary and search intervals ({sum(r['runs'] for r in results)} runs)")
        if theory:
            bound = []
            for v in vals:
                mss = mss_curve(scenario, overrides + [f"{key2}={v}"], np.array([lo]))
                bound.append(np.nan if mss is None else mss[1])
            if np.isfinite(bound).any():
                ax.plot(vals, bound, "s--", color="tab:red", label="MSS certified bound (Theorem 2)")
        ax.set_xlabel(key2)
        ax.set_ylabel(f"{key.rsplit('.', 1)[-1]} at the boundary")
        ax.set_ylim(lo, hi)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(f"{Path(str(scenario)).stem}: boundary of {col} = {threshold:g}")
    fig.tight_layout()
    path = out / "boundary.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
