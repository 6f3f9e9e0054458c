"""The run directory: ``manifest.json``, ``metrics.parquet``, ``summary.json``, ``design.json``."""

from __future__ import annotations

import json
import math
import platform
import sys
from collections.abc import Mapping
from datetime import UTC, datetime
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from scenarios.build import Experiment

from .columns import column, strings
from .columns import table as arrow_table
from .monitor import Monitor

PACKAGES = ("resilient-state-estimation", "numpy", "scipy", "pydantic", "pyarrow", "eclipse-zenoh", "rerun-sdk", "msgpack")


def versions() -> dict[str, str]:
    out = {"python": sys.version.split()[0], "platform": platform.platform()}
    for p in PACKAGES:
        try:
            out[p] = metadata.version(p)
        except metadata.PackageNotFoundError:
            out[p] = "not installed"
    return out


def default_run_dir(name: str, root: str | Path = "runs") -> Path:
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    base = Path(root) / f"{name}-{stamp}"
    path, k = base, 1
    while path.exists():
        k += 1
        path = Path(f"{base}-{k}")
    return path


def _clean(o: Any) -> Any:
    """JSON-safe: NaN/inf -> None, numpy scalars -> python."""
    if isinstance(o, dict):
        return {str(k): _clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    if isinstance(o, (np.floating, float)):
        f = float(o)
        return f if math.isfinite(f) else None
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.ndarray):
        return _clean(o.tolist())
    return o


def write_json(path: Path, data: Any) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(_clean(data), indent=2, allow_nan=False) + "\n")
    tmp.replace(path)


def write_manifest(run_dir: Path, exp: Experiment, frozen: Mapping[str, Any], *, driver: str, run_id: str, extra: dict | None = None) -> None:
    write_json(run_dir / "manifest.json", {
        "run_id": run_id,
        "driver": driver,
        "created": datetime.now(UTC).isoformat(),
        "source": exp.source,
        "seed": exp.seed,
        "scenario": dict(frozen),
        "versions": versions(),
        **(extra or {}),
    })


def metrics_table(exp: Experiment, mon: Monitor, regular: np.ndarray) -> pa.Table:
    """The columns of ``metrics.parquet``, long format: one row per (round, agent, block):
    ``k, t, agent, regular, block, error_2, error_inf, relative_error_2``."""
    K = mon.last_round + 1
    N, B = exp.N, len(mon.block_names)
    k = np.repeat(np.arange(K, dtype=np.int64), N * B)
    agent = np.tile(np.repeat(np.array(exp.agent_ids, dtype=np.int32), B), K)
    reg = np.tile(np.repeat(regular.astype(bool), B), K)
    block_idx = np.tile(np.arange(B, dtype=np.int32), K * N)
    block = pa.DictionaryArray.from_arrays(column(block_idx), strings(mon.block_names))
    table = arrow_table({
        "k": k,
        "t": k * exp.dt,
        "agent": agent,
        "regular": reg,
        "block": block,
        "error_2": mon.error_2[:K].reshape(-1),
        "error_inf": mon.error_inf[:K].reshape(-1),
        "relative_error_2": mon.relative_error_2[:K].reshape(-1),
    })
    return table


def write_metrics(run_dir: Path, exp: Experiment, mon: Monitor, regular: np.ndarray) -> None:
    """``metrics.parquet`` (:func:`metrics_table`), ``diagnostics.parquet`` and ``traces.parquet``."""
    pq.write_table(metrics_table(exp, mon, regular), run_dir / "metrics.parquet", compression="zstd")
    write_diagnostics(run_dir, exp, mon)
    write_traces(run_dir, exp, mon)


def write_traces(run_dir: Path, exp: Experiment, mon: Monitor) -> None:
    """``traces.parquet``: the ``[[output.plots]]`` combinations of the true state and of the
    chosen agents' estimates, one row per (round, plot, series): ``k, t, plot, series, value``
    (series ``"truth"`` or ``"agent I"``)."""
    K = mon.last_round + 1
    cols: dict[str, list] = {"k": [], "t": [], "plot": [], "series": [], "value": []}
    ks = np.arange(K, dtype=np.int64)
    for name, _, agents in mon.plots:
        tr = mon.traces[name][:K]
        for s, label in enumerate(["truth"] + [f"agent {a}" for a in agents]):
            cols["k"].append(ks)
            cols["t"].append(ks * exp.dt)
            cols["plot"].append(np.full(K, name, dtype=object))
            cols["series"].append(np.full(K, label, dtype=object))
            cols["value"].append(tr[:, s])
    if not cols["k"]:
        return
    table = arrow_table({c: (np.concatenate(v) if c in ("k", "t", "value") else strings(np.concatenate(v)))
                         for c, v in cols.items()})
    pq.write_table(table, run_dir / "traces.parquet", compression="zstd")


def write_diagnostics(run_dir: Path, exp: Experiment, mon: Monitor) -> None:
    """``diagnostics.parquet``, one row per (round, agent): ``k, t, agent``, ``flagged``
    (null where the estimator has no flag) and one column per estimator diagnostic
    (:mod:`agents.monitor`). Not written when no estimator exposes any."""
    if not mon.diagnostics and mon.flags is None:
        return
    K, N = mon.last_round + 1, exp.N
    k = np.repeat(np.arange(K, dtype=np.int64), N)
    cols: dict[str, Any] = {"k": k, "t": k * exp.dt, "agent": np.tile(np.array(exp.agent_ids, dtype=np.int32), K)}
    if mon.flags is not None:
        f = mon.flags[:K].reshape(-1)
        cols["flagged"] = column(f == 1.0, mask=np.isnan(f))
    for name, arr in mon.diagnostics.items():
        if name in cols:
            name = f"diag_{name}"
        cols[name] = arr[:K].reshape(-1)
    pq.write_table(arrow_table(cols), run_dir / "diagnostics.parquet", compression="zstd")


def write_design(run_dir: Path, exp: Experiment) -> None:
    """The offline design, for inspection and reuse (cached per run)."""
    data: dict[str, Any] = {"algorithm": exp.scenario.estimator.algorithm, **exp.plugin.design_json(exp)}
    write_json(run_dir / "design.json", data)
