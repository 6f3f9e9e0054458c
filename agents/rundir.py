"""The run directory: ``manifest.json``, ``metrics.parquet``, ``summary.json``, ``design.json``."""

from __future__ import annotations

import json
import math
import platform
import sys
import time
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from scenarios.build import Experiment

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


def write_manifest(run_dir: Path, exp: Experiment, frozen: dict, *, driver: str, run_id: str, extra: dict | None = None) -> None:
    write_json(run_dir / "manifest.json", {
        "run_id": run_id,
        "driver": driver,
        "created": datetime.now(timezone.utc).isoformat(),
        "source": exp.source,
        "seed": exp.seed,
        "scenario": frozen,
        "versions": versions(),
        **(extra or {}),
    })


def write_metrics(run_dir: Path, exp: Experiment, mon: Monitor, regular: np.ndarray) -> None:
    """Long format: one row per (round, agent, block)."""
    K = mon.last_round + 1
    N, B = exp.N, len(mon.block_names)
    k = np.repeat(np.arange(K, dtype=np.int64), N * B)
    agent = np.tile(np.repeat(np.array(exp.agent_ids, dtype=np.int32), B), K)
    reg = np.tile(np.repeat(regular.astype(bool), B), K)
    block_idx = np.tile(np.arange(B, dtype=np.int32), K * N)
    block = pa.DictionaryArray.from_arrays(pa.array(block_idx), pa.array(mon.block_names))
    table = pa.table({
        "k": k,
        "t": k * exp.dt,
        "agent": agent,
        "regular": reg,
        "block": block,
        "error_2": mon.error_2[:K].reshape(-1),
        "error_inf": mon.error_inf[:K].reshape(-1),
        "relative_error_2": mon.relative_error_2[:K].reshape(-1),
    })
    pq.write_table(table, run_dir / "metrics.parquet", compression="zstd")


def write_design(run_dir: Path, exp: Experiment) -> None:
    """The offline design, for inspection and reuse (cached per run)."""
    data: dict[str, Any] = {"algorithm": exp.scenario.estimator.algorithm, **exp.plugin.design_json(exp)}
    write_json(run_dir / "design.json", data)
