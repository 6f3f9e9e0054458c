"""The Rerun recording of one run of a sweep or a search, tagged with its grid values and seed.

Every run of a sweep writes ``points/ID/run.rrd``: one recording whose application id is
the sweep's (``rse-sweep-NAME``), so ``rerun SWEEP_DIR/points/*/run.rrd`` opens all runs
of one sweep together in one viewer, each listed under its recording name
(``drop_p=0.35 seed=7``). The grid values, the seed and the point id are recording
properties (``sweep`` in the viewer's recording properties), queryable from the catalog.

Entities (timeline ``k``, the round):

* ``worst/relative_error_2/{block}``, ``worst/error_2/{block}``: ``log10`` of the worst
  regular agent's error per state block (as the live dashboard, Rerun plots have no log
  axis, so the value is the decade).

The recording is built in memory in the worker and returned as bytes; the caller (the
sweep's client) writes the file, so a run on a remote worker writes nothing there.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from scenarios.build import Experiment


def run_label(values: tuple[tuple[str, Any], ...], seed: int) -> str:
    """``drop_p=0.35 seed=7``: the last part of each key, its value, the seed."""
    return " ".join([f"{k.rsplit('.', 1)[-1]}={v}" for k, v in values] + [f"seed={seed}"])


def _log10(a: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.log10(np.asarray(a, dtype=float))
    return np.where(np.isfinite(out), out, np.nan)


def recording_bytes(exp: Experiment, sim: Any, *, application_id: str, recording_id: str,
                    values: tuple[tuple[str, Any], ...], seed: int, point: str) -> bytes:
    """The ``.rrd`` bytes of one finished in-process run ``sim`` of ``exp``."""
    import rerun as rr

    mon = sim.monitor
    K = mon.last_round + 1
    regular = np.asarray(sim.regular, dtype=bool)
    rec = rr.RecordingStream(application_id, recording_id=recording_id)
    stream = rec.binary_stream()  # type: ignore[misc]  # rerun types the method as a plain function attribute
    try:
        rec.send_recording_name(run_label(values, seed))
        # one arrow type per key across runs (Rerun fixes a property's type at its first use)
        props: dict[str, Any] = {k: (float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else str(v))
                                 for k, v in values}
        rec.send_property("sweep", rr.AnyValues(seed=int(seed), point=point, **props))
        ks = rr.TimeColumn("k", sequence=np.arange(K, dtype=np.int64))
        for name, arr in (("relative_error_2", mon.relative_error_2), ("error_2", mon.error_2)):
            worst = np.asarray(arr[:K])[:, regular, :].max(axis=1) if regular.any() else np.full((K, len(mon.block_names)), np.nan)
            for b, block in enumerate(mon.block_names):
                rec.send_columns(f"worst/{name}/{block}", indexes=[ks],
                                 columns=rr.Scalars.columns(scalars=_log10(worst[:, b])))
        rec.flush()
        return stream.read() or b""
    finally:
        rec.disconnect()
