"""The outputs of a red-team search: the paper's bound, ``redteam.parquet``, the scenario
files (``worst.toml``, ``shrunk.toml``), the worst run's directory and recording,
``redteam.png``, ``summary.json``, and the live Rerun view of the search."""

from __future__ import annotations

import math
import uuid
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .space import MetricSpec

if TYPE_CHECKING:
    from scenarios.build import Experiment

__all__ = ["paper_bound", "write_table", "write_scenario", "replay", "figure", "LiveView"]

#: a Mitra et al. run "converged" when the final relative error is at most this
MSS_CONVERGED = 1e-6


def _number(detail: str) -> float | None:
    try:
        return float(detail.split()[0])
    except (ValueError, IndexError):
        return None


def paper_bound(exp: Experiment, spec: MetricSpec) -> dict[str, Any] | None:
    """The bound ``rse check`` prints for the scenario that the metric is compared with:
    ``{"name", "value", "applies", "condition"}``; None where the paper gives none for it.

    Lee-Kim-Shim: Theorem 1's ``2 sqrt(N)/(gamma lambda_2)`` (Theorem 3's steady-state bound
    for the Lyapunov variant) on the error norms. Mitra et al.: Theorem 2's mean-square
    stability, i.e. convergence: a final relative error above 1e-6 breaks it. ``applies``
    is False for the non-resilient variants (the bound is the resilient estimator's)."""
    from scenarios.plugins.lee_kim_shim import LeeKimShimEstimator
    from scenarios.plugins.mitra import MitraEstimator

    from .. import runs  # the one-run core (agents.api re-exports it)

    est = exp.scenario.estimator
    conds = runs.check(exp)
    if isinstance(est, LeeKimShimEstimator) and spec.metric in ("error_inf", "error_2"):
        want = "Theorem 3" if est.variant == "lyapunov" else "Theorem 1 bound"
        for c in conds:
            if c.name.startswith(want) and _number(c.detail) is not None:
                value = _number(c.detail)
                if want == "Theorem 1 bound":  # the printed value to 6 digits; the same number, exactly
                    from estimation.median_solver import theorem1_bound

                    value = float(theorem1_bound(exp.Adj, est.gamma))
                return {"name": c.name, "short": want.replace(" bound", "") + " bound", "value": value,
                        "applies": est.variant != "linear", "condition": None}
    if isinstance(est, MitraEstimator) and spec.metric == "relative_error_2" and spec.over == "final":
        mss = next((c for c in conds if c.name.startswith("MSS")), None)
        return {"name": "Theorem 2 (mean-square stability): every regular agent converges; "
                        "a final relative error above this breaks it",
                "short": "Theorem 2 (MSS): converged", "value": MSS_CONVERGED,
                "applies": est.rule != "average" and (mss is None or mss.holds is not False),
                "condition": None if mss is None else f"{mss.name}: {mss.detail} ({'holds' if mss.holds else 'fails'})"}
    return None


def write_table(out: Path, rows: list[dict[str, Any]]) -> Path:
    """``redteam.parquet``: one row per evaluation (parameters ``p_*``, metric, time)."""
    import pandas as pd

    path = out / "redteam.parquet"
    df = pd.DataFrame(rows)
    if "accepted" in df.columns:  # shrinking only: whether the proposal was kept
        df["accepted"] = df["accepted"].astype("boolean")
    for c in df.columns:
        if df[c].dtype == object and c not in ("candidate", "overrides", "status", "phase"):
            df[c] = df[c].map(lambda v: None if v is None or (isinstance(v, float) and math.isnan(v)) else str(v))
    tmp = path.with_suffix(".tmp")
    df.to_parquet(tmp, index=False)
    tmp.replace(path)
    return path


def write_scenario(path: Path, frozen: Mapping[str, Any], *, header: str, spec: MetricSpec, threshold: float | None) -> Path:
    """The scenario as data plus an ``[[expect]]`` that prints the red-team metric, as TOML."""
    import tomli_w

    data = dict(frozen)
    data["expect"] = list(data.get("expect", [])) + [spec.expect_table(threshold)]
    text = "".join(f"# {line}\n" if line else "#\n" for line in header.splitlines())
    path.write_text(text + "\n" + tomli_w.dumps(_plain(data)))
    return path


def _plain(o: Any) -> Any:
    if isinstance(o, dict):
        return {k: _plain(v) for k, v in o.items() if v is not None}
    if isinstance(o, (list, tuple)):
        return [_plain(v) for v in o]
    return o


def replay(scenario: Path, run_dir: Path, spec: MetricSpec, *, rerun: bool) -> float:
    """Simulate a written scenario file (as ``rse simulate`` does) into ``run_dir`` with its
    recording; returns the metric, to check it reproduces the search's value exactly."""
    from .. import runs  # the one-run core (agents.api re-exports it)
    from ..rundir import write_manifest
    from .search import metric_value

    exp = runs.load(scenario)
    run_id = uuid.uuid4().hex[:12]
    run_dir.mkdir(parents=True, exist_ok=True)
    write_manifest(run_dir, exp, exp.frozen, driver="simulate", run_id=run_id)
    dash = None
    if rerun:
        from ..dashboard import Dashboard, DashboardOptions

        dash = Dashboard(exp, run_id=run_id, options=DashboardOptions(rrd=run_dir / "recording.rrd"))
    try:
        res = runs.simulate(exp, dashboard=dash)
    finally:
        if dash is not None:
            dash.close()
    res.save(run_dir, run_id=run_id)
    return metric_value(exp, res, spec)


def figure(out: Path, rows: list[dict[str, Any]], *, label: str, bound: float | None, bound_name: str = "bound") -> Path:
    """``redteam.png``: the best metric so far against evaluations (every evaluation as a
    dot), and the distribution of the metric over the search."""
    import numpy as np

    from ..report import _pyplot

    plt = _pyplot()
    search = [r for r in rows if r["phase"] == "search"]
    x = np.array([r["evaluation"] + 1 for r in search])
    v = np.array([r["metric"] for r in search], dtype=float)
    best = np.array([r["best"] for r in search], dtype=float)
    fin = np.isfinite(v) & (v > 0)
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.2))
    a1.semilogy(x[fin], v[fin], ".", color="tab:gray", ms=4, alpha=0.6, label="evaluation")
    a1.semilogy(x, np.where(best > 0, best, np.nan), "-", color="tab:red", lw=2, label="best so far")
    if bound is not None:
        for a in (a1, a2):
            a.axhline(bound, color="k", ls="--", lw=1) if a is a1 else a.axvline(bound, color="k", ls="--", lw=1)
        a1.plot([], [], "k--", lw=1, label=f"{bound_name} = {bound:.4g}")
    a1.set_xlabel("evaluation")
    a1.set_ylabel(label)
    a1.grid(True, which="both", alpha=0.3)
    a1.legend(fontsize=8)
    if fin.any():
        lo, hi = np.log10(v[fin].min()), np.log10(v[fin].max())
        a2.hist(v[fin], bins=np.logspace(lo - 0.05, hi + 0.05, 30), color="tab:blue", alpha=0.8)
        a2.set_xscale("log")
    a2.set_xlabel(label)
    a2.set_ylabel("evaluations")
    a2.grid(True, alpha=0.3)
    fig.suptitle(f"red-team search: {len(search)} evaluations, worst {np.nanmax(v) if fin.any() else float('nan'):.4g}",
                 fontsize=10)
    fig.tight_layout()
    path = out / "redteam.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


class LiveView:
    """The search streamed to Rerun (``recording.rrd`` in the output directory): per
    evaluation the metric and the best so far, and the bound, on the ``evaluation`` timeline."""

    def __init__(self, rrd: Path, *, bound: float | None) -> None:
        import rerun as rr

        self.rr = rr
        self.rec = rr.RecordingStream("rse-redteam", recording_id=uuid.uuid4().hex[:12])
        self.rec.save(str(rrd))
        self.bound = bound

    def log(self, row: dict[str, Any]) -> None:
        rr, rec = self.rr, self.rec
        rec.set_time("evaluation", sequence=int(row["evaluation"]))
        if math.isfinite(row["metric"]):
            rec.log(f"redteam/{row['phase']}/metric", rr.Scalars(float(row["metric"])))
        if row.get("best") is not None and math.isfinite(row["best"]):
            rec.log("redteam/search/best_so_far", rr.Scalars(float(row["best"])))
        if self.bound is not None:
            rec.log("redteam/search/bound", rr.Scalars(float(self.bound)))

    def close(self) -> None:
        try:
            self.rec.flush()
        finally:
            self.rec.disconnect()
