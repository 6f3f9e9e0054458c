"""A recorded run directory replayed into a new run directory (``rse replay``,
:func:`rse.replay`): the driver is :mod:`agents.replay`; this module reads the run's
manifest and record and writes ``manifest.json``, ``design.json``, ``metrics.parquet``,
``summary.json``, ``estimates.npy`` and ``truth.npy`` (and the Rerun recording when a
dashboard is given), as the simulator's run directory."""

from __future__ import annotations

import json
import uuid
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from estimation.errors import ScenarioError

from .runs import RunResult, _override_strings, deferred_signals, ended_by, load

if TYPE_CHECKING:
    from scenarios.build import Experiment


def default_out(run_dir: Path) -> Path:
    """``RUN_DIR-replay`` (``-replay-2``, ... when taken)."""
    base = run_dir.parent / f"{run_dir.name}-replay"
    path, n = base, 1
    while path.exists():
        n += 1
        path = Path(f"{base}-{n}")
    return path


def _read_json(path: Path) -> dict[str, Any] | None:
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        raise ScenarioError(f"{path}: unreadable ({exc})") from None
    if not isinstance(data, dict):
        raise ScenarioError(f"{path}: not a JSON object")
    return data


def check_run_dir(run_dir: Path) -> dict[str, Any]:
    """The manifest of a recorded run directory; a :class:`ScenarioError` (one line) when
    ``run_dir`` is no run directory or holds no delivery record."""
    from .deliveries import record_files

    manifest = _read_json(run_dir / "manifest.json")
    if manifest is None or not isinstance(manifest.get("scenario"), dict):
        raise ScenarioError(f"{run_dir}: not a run directory (no manifest.json with the run's scenario)")
    record_files(run_dir)
    return manifest


def replay_experiment(run_dir: Path, overrides: Iterable[str] = ()) -> Any:
    """The experiment of a recorded run (its frozen scenario and seed from
    ``manifest.json``) with ``overrides`` on top (a counterfactual)."""
    manifest = check_run_dir(run_dir)
    return load(manifest["scenario"], set=list(overrides), seed=manifest.get("seed"),
                source=str(manifest.get("source") or run_dir / "manifest.json"))


def reported(run_dir: Path, exp: Experiment) -> np.ndarray | None:
    """``(rounds, N)`` bool: the agent-rounds whose estimate the run's monitor recorded (a
    finite error in ``metrics.parquet``, else in its partial stream); None: no metrics."""
    import pyarrow.parquet as pq

    from .recorder import read_partial

    try:
        table = pq.read_table(run_dir / "metrics.parquet", columns=["k", "agent", "error_2"]) \
            if (run_dir / "metrics.parquet").exists() else read_partial(run_dir)
    except (OSError, ValueError):
        return None
    if table is None or table.num_rows == 0:
        return None
    k = table.column("k").to_numpy()
    index = {aid: i for i, aid in enumerate(exp.agent_ids)}
    a = np.array([index.get(int(v), -1) for v in table.column("agent").to_numpy()])
    ok = ~np.isnan(table.column("error_2").to_numpy()) & (a >= 0) & (k >= 0)
    out = np.zeros((int(k.max()) + 1, exp.N), dtype=bool)
    out[k[ok], a[ok]] = True
    return out


def replay_run(run_dir: str | Path, *, out: str | Path | None = None,
               set: Mapping[str, Any] | Iterable[str] | None = None, rerun: Any = True,
               progress: Callable[[int, float], None] | None = None) -> RunResult:
    """Replay the recorded run ``run_dir`` in-process (:mod:`agents.replay`) and write the
    run directory ``out`` (default ``RUN_DIR-replay``). ``set``: overrides on top of the
    run's scenario, e.g. ``{"estimator.variant": "linear"}`` for a counterfactual (the team,
    its graph and the number of rounds must stay the run's). ``rerun``: True writes the
    Rerun recording ``out/recording.rrd``; an :class:`agents.dashboard.DashboardOptions`
    sends it where those say; False none. Returns the
    :class:`~agents.runs.RunResult` (``result.sim.estimates``: every replayed estimate)."""
    from .deliveries import read_record
    from .recorder import Recorder
    from .replay import replay
    from .rundir import write_design, write_manifest
    from .summary import summarise_run

    src = Path(run_dir)
    ov = _override_strings(set)
    exp = replay_experiment(src, ov)
    record = read_record(src)
    original = _read_json(src / "summary.json") or {}
    d = Path(out) if out is not None else default_out(src)
    if d.resolve() == src.resolve():
        raise ScenarioError(f"--out {d}: the replay writes a run directory of its own, not the recorded one")
    d.mkdir(parents=True, exist_ok=True)
    (d / "summary.json").unlink(missing_ok=True)
    write_manifest(d, exp, exp.frozen, driver="replay", run_id=uuid.uuid4().hex[:12],
                   extra={"replay_of": str(src.resolve()), "replay_set": ov})
    write_design(d, exp)
    dash = None
    if rerun is not False and rerun is not None:
        from .dashboard import Dashboard, DashboardOptions

        opts = DashboardOptions(rrd=d / "recording.rrd") if rerun is True else rerun
        dash = Dashboard(exp, run_id=json.loads((d / "manifest.json").read_text())["run_id"], options=opts)
    rec = Recorder(d, exp, dashboard=dash)
    try:
        res = replay(exp, record, completed=original.get("complete") is True, links=original.get("links"),
                     reported=reported(src, exp), dashboard=rec, progress=progress)
        summary, results = summarise_run(exp, res.monitor, res.links, complete=res.complete, reason=res.reason)
        summary["replay"] = {"of": str(src), "set": ov, "last_round": res.last_round, "complete": res.complete}
        result = RunResult(exp, summary, results, driver="replay", sim=res)
        result.save(d)
        np.save(d / "estimates.npy", res.estimates)
        np.save(d / "truth.npy", res.truth)
        rec.done()
    except BaseException as exc:
        with deferred_signals():
            rec.abort(ended_by(exc))
        raise
    finally:
        if dash is not None:
            with deferred_signals():
                dash.close()
    return result
