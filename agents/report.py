"""``rse report``: the summary table of a run directory, static figures, and comparisons.

Everything is read from the run directory (``manifest.json``, ``summary.json``,
``metrics.parquet``, and ``traces.parquet`` when the scenario declares ``[[output.plots]]``),
so a directory written by ``rse simulate`` and one written by ``rse run`` give the same
report. Figures need the ``plot`` extra (matplotlib).

Figures and the paper figures they correspond to:

* ``errors.png``: error norm of every agent over time, one panel per state block, log
  scale; relative errors for unstable plants; Byzantine agents dashed red; attack start and
  stop marked (Lee, Kim, Shim; Mitra et al. Figs. 8, 9, 11, 12, 13);
* ``state_NAME.png``: a declared linear combination of the state against the agents'
  estimates (Lee, Kim, Shim Fig. 1: theta1 + theta2 + theta3);
* ``compare.png`` (two runs): the worst regular agent's error of each run, per block.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq

from estimation.errors import RSEError, ScenarioError


@dataclass
class RunData:
    path: Path
    manifest: dict
    summary: dict
    metrics: dict[str, np.ndarray]  # column -> array
    traces: dict[str, np.ndarray] | None

    @property
    def name(self) -> str:
        name = self.manifest.get("scenario", {}).get("run", {}).get("name", self.path.name)
        if self.manifest.get("driver") == "replay":  # rse replay: and what it changed (a counterfactual)
            changed = [str(s) for s in self.manifest.get("replay_set", [])]
            name += " replay" + (f" ({', '.join(changed)})" if changed else "")
        return name

    @property
    def blocks(self) -> list[str]:
        return list(dict.fromkeys(self.metrics["block"].tolist()))

    @property
    def agents(self) -> list[int]:
        return sorted(set(int(a) for a in self.metrics["agent"]))

    def unstable(self) -> bool:
        """The whole state grows past 1e3 (use relative errors)."""
        summ = self.summary.get("agents", {})
        for rec in summ.values():
            x = rec["blocks"].get("x", {})
            e = x.get("final_error_2")
            r = x.get("final_relative_error_2")
            if e is not None and r not in (None, 0) and e / r > 1e3:
                return True
        return False


def load_run(path: str | Path) -> RunData:
    """Read a run directory. A run that ended early reads as it is: its ``summary.json``
    says ``complete: false``; a directory whose writer was killed outright (no
    ``metrics.parquet`` yet) is read from its partial metrics stream
    (:func:`agents.recorder.read_partial`), with a summary computed from those metrics."""
    from .recorder import read_partial

    p = Path(path)
    if not p.is_dir():
        raise ScenarioError("not a run directory (no such directory)", source=str(path))
    partial = None
    if not (p / "metrics.parquet").exists():
        try:
            partial = read_partial(p)
        except (OSError, ValueError) as exc:
            raise ScenarioError(f"unreadable run directory: {exc}", source=str(path)) from None
    has_metrics = (p / "metrics.parquet").exists() or partial is not None  # then a summary can be computed
    missing = [f for f in ("manifest.json", "summary.json", "metrics.parquet") if not (p / f).exists()
               and (f == "manifest.json" or not has_metrics)]
    if missing:
        raise ScenarioError(f"not a run directory: missing {', '.join(missing)}", source=str(path))
    try:
        manifest = json.loads((p / "manifest.json").read_text())
        summary = json.loads((p / "summary.json").read_text()) if (p / "summary.json").exists() else None
        table = partial if partial is not None else pq.read_table(p / "metrics.parquet")
    except (json.JSONDecodeError, OSError, ValueError) as exc:
        raise ScenarioError(f"unreadable run directory: {exc}", source=str(path)) from None
    metrics = {c: table.column(c).to_numpy(zero_copy_only=False) for c in table.column_names}
    metrics["block"] = np.asarray([str(b) for b in table.column("block").to_pylist()])
    if summary is None:
        summary = summary_from_metrics(metrics, reason="no summary.json: the run's writer was killed")
    traces = None
    if (p / "traces.parquet").exists():
        t = pq.read_table(p / "traces.parquet")
        traces = {c: np.asarray(t.column(c).to_pylist()) for c in t.column_names}
    return RunData(p, manifest, summary, metrics, traces)


def summary_from_metrics(metrics: dict[str, np.ndarray], *, reason: str) -> dict[str, Any]:
    """The part of ``summary.json`` the report shows, from the metrics alone (a run
    without its summary): per agent and block the errors at the last round recorded and
    the largest over the run (the output window is not known here)."""
    k = metrics["k"]
    last = int(k.max()) if k.size else -1
    agents: dict[str, Any] = {}
    for aid in sorted(set(int(a) for a in metrics["agent"])):
        sel_a = metrics["agent"] == aid
        rec: dict[str, Any] = {"regular": bool(metrics["regular"][sel_a][0]), "blocks": {}}
        for block in dict.fromkeys(metrics["block"][sel_a].tolist()):
            sel = sel_a & (metrics["block"] == block)
            b: dict[str, Any] = {"convergence_round": None}
            for m in ("error_2", "error_inf", "relative_error_2"):
                v = metrics[m][sel].astype(float)
                fin = v[k[sel] == last]
                b[f"final_{m}"] = float(fin[0]) if fin.size else None
                b[f"window_max_{m}"] = float(np.nanmax(v)) if np.isfinite(v).any() else None
            rec["blocks"][block] = b
        agents[str(aid)] = rec
    worst: dict[str, Any] = {}
    return {"complete": False, "reason": reason, "last_round": last, "rounds": last, "window": [None, None],
            "agents": agents, "worst_regular": worst, "links": {}, "rejected": {}}


def _fmt(v: Any) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return "nan" if math.isnan(v) else f"{v:.4g}"
    return str(v)


def table_rows(run: RunData) -> list[list[str]]:
    """Rows of the summary table: per agent and block (the same for both drivers)."""
    metric = "relative_error_2" if run.unstable() else "error_inf"
    links = run.summary.get("links", {})
    rejected = run.summary.get("rejected", {})
    detected = run.summary.get("detected_attacks", {})
    rows = []
    for aid, rec in run.summary["agents"].items():
        into = [c for key, c in links.items() if key.endswith(f"->{aid}")]
        tot = {f: sum(c.get(f, 0) for c in into) for f in ("delivered", "dropped", "late", "rejected")}
        rej = rejected.get(str(aid))
        if isinstance(rej, dict):
            tot["rejected"] += sum(v for v in rej.values() if isinstance(v, (int, float)))
        det = detected.get(str(aid)) if isinstance(detected, dict) else None
        for block, b in rec["blocks"].items():
            rows.append([
                str(aid), "yes" if rec["regular"] else "Byzantine", block,
                _fmt(b.get(f"final_{metric}")), _fmt(b.get(f"window_max_{metric}")),
                _fmt(b.get("convergence_round")), "-" if det is None else _fmt(det),
                f"{tot['delivered']}/{tot['dropped']}/{tot['late']}/{tot['rejected']}",
            ])
    return rows


TABLE_COLUMNS = ("agent", "regular", "block", "final {m}", "window max {m}", "converged at round",
                 "attack detected (round)", "in-links delivered/dropped/late/rejected")


def report_table(run: RunData):
    from rich.table import Table

    m = "|e|_2/|x|_2" if run.unstable() else "|e|_inf"
    w = run.summary.get("window", [None, None])
    status = "" if run.summary.get("complete", True) else (
        f" - INCOMPLETE: {run.summary.get('reason', 'ended early')}, last round recorded {run.summary.get('last_round')}")
    t = Table(title=f"{run.name} ({run.manifest.get('driver', '?')}): {run.summary.get('rounds')} rounds, window [{_fmt(w[0])}, {_fmt(w[1])}]{status}",
              title_justify="left")
    for c in TABLE_COLUMNS:
        t.add_column(c.format(m=m), justify="right")
    for r in table_rows(run):
        t.add_row(*r)
    return t


def compare_table(a: RunData, b: RunData):
    from rich.table import Table

    t = Table(title=f"worst regular agent: {a.name} vs {b.name}", title_justify="left")
    for c in ("block", "metric", a.name + " final", b.name + " final", a.name + " window max", b.name + " window max"):
        t.add_column(c, justify="right")
    blocks = [x for x in a.summary["worst_regular"] if x in b.summary["worst_regular"]]
    for blk in blocks:
        wa, wb = a.summary["worst_regular"][blk], b.summary["worst_regular"][blk]
        for m in ("error_inf", "relative_error_2"):
            t.add_row(blk, m, _fmt(wa.get(f"final_{m}")), _fmt(wb.get(f"final_{m}")),
                      _fmt(wa.get(f"window_max_{m}")), _fmt(wb.get(f"window_max_{m}")))
    return t


def _pyplot():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise RSEError("figures need matplotlib: pip install -e '.[plot]'") from None
    return plt


def _series(run: RunData, metric: str, block: str) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    m = run.metrics
    sel = m["block"] == block
    out = {}
    for aid in run.agents:
        s = sel & (m["agent"] == aid)
        order = np.argsort(m["k"][s])
        out[aid] = (m["t"][s][order], m[metric][s][order])
    return out


def _attack_times(run: RunData) -> list[tuple[float, str]]:
    out = []
    for a in run.manifest.get("scenario", {}).get("attacks", []):
        start = float(a.get("start", 0.0))
        stop = a.get("stop")
        out.append((start, f"{a.get('kind')} start"))
        if stop is not None and math.isfinite(float(stop)):
            out.append((float(stop), f"{a.get('kind')} stop"))
    return out


def figure_errors(run: RunData, out: Path) -> Path:
    plt = _pyplot()
    metric = "relative_error_2" if run.unstable() else "error_2"
    blocks = [b for b in run.blocks if b != "x"] or ["x"]
    cols = min(2, len(blocks))
    rows = math.ceil(len(blocks) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(6.5 * cols, 3.6 * rows), squeeze=False, sharex=True)
    regular = {int(a): r["regular"] for a, r in run.summary["agents"].items()}
    for ax, blk in zip(axes.flat, blocks):
        for aid, (t, v) in _series(run, metric, blk).items():
            v = np.where(v > 0, v, np.nan)
            if regular.get(aid, True):
                ax.semilogy(t, v, lw=1.2, label=f"agent {aid}")
            else:
                ax.semilogy(t, v, "--", color="tab:red", lw=1.0, label=f"agent {aid} (Byzantine)")
        for when, _what in _attack_times(run):
            ax.axvline(when, color="k", ls=":", lw=0.8)
        ax.set_title(f"{blk}: {metric.replace('_', ' ')}")
        ax.grid(True, which="both", alpha=0.3)
    for ax in axes.flat[len(blocks):]:
        ax.set_visible(False)
    for ax in axes[-1]:
        ax.set_xlabel("t")
    handles, labels = axes.flat[0].get_legend_handles_labels()
    if len(labels) <= 20:
        fig.legend(handles, labels, loc="upper right", fontsize=7, ncol=1 if len(labels) <= 10 else 2)
    fig.suptitle(f"{run.name}: error norms per agent" + (" (dotted: attack start/stop)" if _attack_times(run) else ""))
    fig.tight_layout(rect=(0, 0, 0.88 if len(labels) <= 20 else 1, 0.95))
    path = out / "errors.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def figure_states(run: RunData, out: Path) -> list[Path]:
    if run.traces is None:
        return []
    plt = _pyplot()
    tr = run.traces
    paths = []
    for name in dict.fromkeys(tr["plot"].tolist()):
        sel = tr["plot"] == name
        fig, ax = plt.subplots(figsize=(8, 3.8))
        for series in dict.fromkeys(tr["series"][sel].tolist()):
            s = sel & (tr["series"] == series)
            order = np.argsort(tr["t"][s])
            style = dict(color="k", lw=2.0) if series == "truth" else dict(lw=1.0)
            ax.plot(tr["t"][s][order], tr["value"][s][order], label=series, **style)
        for when, _what in _attack_times(run):
            ax.axvline(when, color="k", ls=":", lw=0.8)
        ax.set_xlabel("t")
        ax.set_title(f"{run.name}: {name}, true state (black) and estimates")
        ax.legend(fontsize=7, ncol=3)
        ax.grid(True, alpha=0.3)
        fig.tight_layout()
        path = out / f"state_{name}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        paths.append(path)
    return paths


def figure_compare(a: RunData, b: RunData, out: Path) -> Path:
    plt = _pyplot()
    metric = "relative_error_2" if a.unstable() or b.unstable() else "error_inf"
    blocks = [x for x in a.blocks if x in b.blocks]
    fig, axes = plt.subplots(len(blocks), 1, figsize=(8, 3 * len(blocks)), squeeze=False, sharex=True)
    for ax, blk in zip(axes[:, 0], blocks):
        for run, style in ((a, "-"), (b, "--")):
            regular = {int(k): r["regular"] for k, r in run.summary["agents"].items()}
            ser = _series(run, metric, blk)
            reg = [v for aid, (t, v) in ser.items() if regular.get(aid, True)]
            t = next(iter(ser.values()))[0]
            worst = np.nanmax(np.vstack(reg), axis=0)
            ax.semilogy(t, np.where(worst > 0, worst, np.nan), style, label=run.name)
        ax.set_title(f"{blk}: worst regular agent, {metric.replace('_', ' ')}")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    axes[-1, 0].set_xlabel("t")
    fig.tight_layout()
    path = out / "compare.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# --------------------------------------------------------------------------- sweeps and searches
SWEEP_METRICS = {"worst_final_relative_error_2": "final |e|/|x|", "worst_final_error_2": "final |e|_2"}


def is_sweep_dir(path: str | Path) -> bool:
    """A directory written by ``rse sweep`` (``sweep.json``) or ``rse boundary`` (``boundary.json``)."""
    p = Path(path)
    return (p / "sweep.json").is_file() or (p / "boundary.json").is_file()


def sweep_table(path: str | Path):
    """The table of a sweep (or boundary search) directory, one row per grid point: its
    values, the runs (ok / all), the runs whose ``[expect]`` bounds held, the median and the
    maximum over seeds of the worst regular agent's final relative and absolute errors."""
    from rich.table import Table

    p = Path(path)
    kind = "sweep" if (p / "sweep.json").is_file() else "boundary"
    meta = json.loads((p / f"{kind}.json").read_text())
    table_path = p / f"{kind}.parquet"
    if not table_path.is_file():
        raise ScenarioError(f"no {table_path.name} yet: the {kind} has not finished (run it again to resume)", source=str(p))
    rows = pq.read_table(table_path).to_pylist()
    skip = {"point", "seed", "status", "elapsed_s", "expectations_ok", "step", "search", "above"}
    keys = [c for c in (rows[0] if rows else {}) if c not in skip and not c.startswith("worst_")]
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault(tuple(r.get(k) for k in keys), []).append(r)
    what = ", ".join(meta.get("grid") or meta.get("vary") or [])
    t = Table(title=f"{kind} of {meta.get('scenario')} over {what}: {len(rows)} runs, {len(groups)} points",
              title_justify="left")
    for c in [*(k.rsplit(".", 1)[-1] for k in keys), "runs ok/all", "expect held",
              *(f"{label} {q}" for label in SWEEP_METRICS.values() for q in ("median", "max"))]:
        t.add_column(c, justify="right")
    for vals, rs in sorted(groups.items(), key=lambda kv: [str(type(v)) + str(v) if not isinstance(v, (int, float))
                                                           else v for v in kv[0]]):
        ok = [r for r in rs if r.get("status") == "ok"]
        cells = []
        for m in SWEEP_METRICS:
            v = np.array([r[m] for r in ok if r.get(m) is not None], dtype=float)
            cells += [_fmt(float(np.median(v))), _fmt(float(np.max(v)))] if len(v) else ["-", "-"]
        held = sum(1 for r in ok if r.get("expectations_ok"))
        t.add_row(*(_fmt(v) for v in vals), f"{len(ok)}/{len(rs)}", f"{held}/{len(ok)}", *cells)
    return t


def boundary_lines(path: str | Path) -> list[str]:
    """The result lines of a boundary search directory (empty for a sweep)."""
    f = Path(path) / "boundary.json"
    if not f.is_file():
        return []
    meta = json.loads(f.read_text())
    out = []
    for r in meta.get("results", []):
        where = ", ".join(f"{k}={v}" for k, v in r.get("at", {}).items())
        seeds = "none" if r["ci_low"] is None else f"[{r['ci_low']:.4f}, {r['ci_high']:.4f}]"
        out.append(f"{(where + ': ') if where else ''}boundary {r['estimate']:.4f}, search interval "
                   f"[{r['search_low']:.4f}, {r['search_high']:.4f}], {int(r['level'] * 100)}% interval "
                   f"from the seeds {seeds}, {r['runs']} runs")
    return out
