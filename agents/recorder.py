"""Crash-safe recording: a run's metrics written as the run goes, and a run directory left
consistent on every exit path (DESIGN.md, "Outputs of a run").

While a run goes, the monitor's rows (the columns of ``metrics.parquet`` plus
``truth_norm``, the norm of the true state per block) are appended to an Arrow IPC stream,
``metrics.partial/segment-NNN.arrows``, one record batch per monitor flush (at least once a
second, :attr:`agents.monitor.Monitor.flush_interval`), each written straight to the file.
A writer killed at any moment (SIGKILL included) leaves every batch it completed readable
(:func:`read_partial` stops at a torn last batch). Each monitor instance writes its own
segment, so a restarted monitor appends without rewriting what an earlier one left.

When the run ends, ``metrics.parquet`` and ``summary.json`` are written from the monitor's
arrays and the stream is removed; when it ends early (a signal, a failure), the same files
are written from what was recorded with ``complete: false``, the reason and the last round
recorded (:meth:`Recorder.abort`). A directory whose writer was killed outright is
completed later by :func:`salvage` (the launcher does it for a monitor that died; ``rse
report`` reads such a directory as it is).

:class:`Recorder` has a dashboard's interface (``is_map_frame``, ``log_chunk``), so a driver
streams to it, and through it to a dashboard, without knowing either.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from .columns import column, repeated_strings, to_numpy
from .monitor import Monitor
from .rounds import regular_mask

if TYPE_CHECKING:
    from scenarios.build import Experiment

PARTIAL = "metrics.partial"

SCHEMA = pa.schema([
    ("k", pa.int64()), ("t", pa.float64()), ("agent", pa.int32()), ("regular", pa.bool_()), ("block", pa.string()),
    ("error_2", pa.float64()), ("error_inf", pa.float64()), ("relative_error_2", pa.float64()),
    ("truth_norm", pa.float64()),
])


class MetricsStream:
    """One segment of the partial metrics stream (see the module docstring)."""

    def __init__(self, run_dir: Path, exp: Experiment, regular: np.ndarray) -> None:
        d = Path(run_dir) / PARTIAL
        d.mkdir(parents=True, exist_ok=True)
        n = 0
        while (d / f"segment-{n:03d}.arrows").exists():
            n += 1
        self.path = d / f"segment-{n:03d}.arrows"
        self.exp = exp
        self.regular = np.asarray(regular, dtype=bool)
        self._file = pa.OSFile(str(self.path), "wb")  # unbuffered: each batch is in the file when written
        self._writer = pa.ipc.new_stream(self._file, SCHEMA)

    def write(self, mon: Monitor, rows: np.ndarray) -> None:
        """Append the rounds ``rows`` (already computed by ``mon.flush``)."""
        if self._writer is None or len(rows) == 0:
            return
        rows = np.asarray(rows, dtype=np.int64)
        N, B = self.exp.N, len(mon.block_names)
        c = len(rows)
        k = np.repeat(rows, N * B)
        batch = pa.RecordBatch.from_arrays([
            column(k), column(k * self.exp.dt),
            column(np.tile(np.repeat(np.array(self.exp.agent_ids, dtype=np.int32), B), c)),
            column(np.tile(np.repeat(self.regular.astype(bool), B), c)),
            repeated_strings(mon.block_names, np.tile(np.arange(B, dtype=np.int32), c * N)),
            column(mon.error_2[rows]), column(mon.error_inf[rows]),
            column(mon.relative_rows(rows)),
            column(np.repeat(mon.truth_norm[rows], N, axis=0)),
        ], schema=SCHEMA)
        self._writer.write_batch(batch)

    def close(self) -> None:
        if self._writer is not None:
            try:
                self._writer.close()
            finally:
                self._file.close()
                self._writer = None


def read_partial(run_dir: str | Path) -> pa.Table | None:
    """Every complete batch of every segment under ``RUN_DIR/metrics.partial`` (a torn last
    batch of a killed writer is left out), sorted by round; a round recorded twice keeps its
    later segment's rows. ``None`` when there is no stream."""
    d = Path(run_dir) / PARTIAL
    paths = sorted(d.glob("segment-*.arrows")) if d.is_dir() else []
    if not paths:
        return None
    batches = []
    for path in paths:
        try:
            reader = pa.ipc.open_stream(pa.memory_map(str(path)) if path.stat().st_size else pa.BufferReader(b""))
        except (pa.ArrowInvalid, OSError):
            continue  # killed before its schema was written
        while True:
            try:
                b = reader.read_next_batch()
            except StopIteration:
                break
            except (pa.ArrowInvalid, OSError):
                break  # a torn last batch
            batches.append(b)
    if not batches:
        return pa.Table.from_batches([], schema=SCHEMA)
    table = pa.Table.from_batches(batches)
    # keep, for each (k, agent, block), the row of the latest segment (the last one written):
    # in the order (k, agent, block, position in the streams), the last of each equal key
    k, agent = _np(table, "k"), _np(table, "agent")
    blocks = table.column("block").combine_chunks()  # as an index into its distinct values
    block = to_numpy(pc.index_in(blocks, value_set=pc.unique(blocks)))
    order = np.lexsort((np.arange(len(k)), block, agent, k))
    keys = np.stack([k[order], agent[order], block[order]])
    last = np.ones(len(order), dtype=bool)
    last[:-1] = (keys[:, 1:] != keys[:, :-1]).any(axis=0)
    kept = order[last]
    kept = kept[np.lexsort((kept, k[kept]))]  # by round, then as written
    return table.take(column(kept.astype(np.int64)))


def _np(table: pa.Table, name: str) -> np.ndarray:
    return to_numpy(table.column(name).combine_chunks())


def load_into(mon: Monitor, table: pa.Table) -> None:
    """Fill ``mon``'s arrays with the rows of a partial stream (a restarted monitor resumes
    from what the earlier ones recorded)."""
    if table is None or table.num_rows == 0:
        return
    exp = mon.exp
    k = _np(table, "k")
    keep = k < mon.error_2.shape[0]
    idx_a = {a: i for i, a in enumerate(exp.agent_ids)}
    idx_b = {b: i for i, b in enumerate(mon.block_names)}
    a = np.array([idx_a.get(int(v), -1) for v in _np(table, "agent")])
    b = np.array([idx_b.get(v, -1) for v in table.column("block").to_pylist()])
    keep &= (a >= 0) & (b >= 0)
    k, a, b = k[keep], a[keep], b[keep]
    for name in ("error_2", "error_inf"):  # relative_error_2 follows from error_2 and truth_norm
        getattr(mon, name)[k, a, b] = _np(table, name)[keep]
    mon.truth_norm[k, b] = _np(table, "truth_norm")[keep]
    if k.size:
        mon.last_round = max(mon.last_round, int(k.max()))


def drop_partial(run_dir: str | Path) -> None:
    shutil.rmtree(Path(run_dir) / PARTIAL, ignore_errors=True)


def write_run(run_dir: Path, exp: Experiment, mon: Monitor, regular: np.ndarray, summary: dict[str, Any]) -> None:
    """``metrics.parquet`` (and the diagnostics and traces), then ``summary.json``; the
    partial stream is removed once both are written."""
    from .rundir import write_json, write_metrics

    write_metrics(run_dir, exp, mon, regular)
    write_json(run_dir / "summary.json", summary)
    drop_partial(run_dir)


def incomplete_summary(exp: Experiment, mon: Monitor | None, regular: np.ndarray, *, reason: str,
                       links: dict | None = None, rejected: dict | None = None) -> dict[str, Any]:
    """``summary.json`` of a run that ended early: the full summary of the rounds recorded
    (none: only the header), ``complete: false``, ``reason``, ``last_round``."""
    from .summary import summarise

    if mon is not None and mon.last_round >= 0:
        return summarise(exp, mon, regular, links or {}, rejected, complete=False, reason=reason)
    return {"scenario": exp.scenario.run.name, "complete": False, "reason": reason, "last_round": -1, "rounds": 0,
            "agents": {}, "worst_regular": {}, "links": links or {}, "rejected": rejected or {}}


def write_incomplete(run_dir: Path, exp: Experiment, mon: Monitor | None, regular: np.ndarray, *, reason: str,
                     links: dict | None = None, rejected: dict | None = None) -> None:
    """The files of a run that ended early: with rounds recorded in ``mon``, as
    :func:`write_run` (``summary.json`` with ``complete: false``); without (``mon`` None or
    empty), the header of a summary only, and the partial stream (no round in it) removed."""
    summary = incomplete_summary(exp, mon, regular, reason=reason, links=links, rejected=rejected)
    if mon is not None and mon.last_round >= 0:
        write_run(run_dir, exp, mon, regular, summary)
    else:
        from .rundir import write_json

        write_json(run_dir / "summary.json", summary)
        drop_partial(run_dir)


class Recorder:
    """The run directory's writer during a run: streams the monitor's flushed rounds to
    the partial stream (and on to ``dashboard`` when given) and, when the run ends early,
    leaves the directory consistent (:meth:`abort`).

    Pass it to a driver where a dashboard goes; after a complete run call :meth:`done`
    (the final files are written by the caller, e.g. :meth:`agents.api.RunResult.save`)."""

    def __init__(self, run_dir: str | Path, exp: Experiment, *, dashboard: Any = None, monitor: Monitor | None = None) -> None:
        self.run_dir = Path(run_dir)
        self.exp = exp
        self.dashboard = dashboard
        self.regular = regular_mask(exp)
        self.mon: Monitor | None = monitor
        self.finished = False
        self.stream = MetricsStream(self.run_dir, exp, self.regular)

    # the dashboard interface the drivers call
    def is_map_frame(self, k: int) -> bool:
        return self.dashboard is not None and self.dashboard.is_map_frame(k)

    def log_chunk(self, rows: np.ndarray, mon: Monitor, **kw: Any) -> None:
        self.mon = mon
        self.stream.write(mon, rows)
        if self.dashboard is not None:
            self.dashboard.log_chunk(rows, mon, **kw)

    def done(self) -> None:
        """The run completed and its final files are written: drop the stream."""
        self.stream.close()
        self.finished = True
        drop_partial(self.run_dir)

    def abort(self, reason: str, *, links: dict | None = None, rejected: dict | None = None) -> None:
        """The run ends early: write ``metrics.parquet`` (the rounds recorded) and a
        ``summary.json`` with ``complete: false``, ``reason`` and the last round recorded.
        Nothing when the run already completed."""
        if self.finished:
            return
        self.finished = True
        self.stream.close()
        mon = self.mon
        if mon is not None:
            mon.flush()
        write_incomplete(self.run_dir, self.exp, mon, self.regular, reason=reason, links=links, rejected=rejected)


def salvage(run_dir: str | Path, exp: Experiment, *, reason: str) -> bool:
    """Complete a run directory whose monitor was killed: ``metrics.parquet`` and
    ``summary.json`` (``complete: false``) from the partial stream. Returns whether there
    was something to salvage (a directory with a ``summary.json`` is left alone)."""
    d = Path(run_dir)
    if (d / "summary.json").exists():
        return False
    table = read_partial(d)
    mon = Monitor(exp)
    load_into(mon, table)
    write_incomplete(d, exp, mon, regular_mask(exp), reason=reason)
    return True

